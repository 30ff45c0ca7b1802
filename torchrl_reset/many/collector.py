"""Algorithm 1 on N copies of a task at once, each copy in its own phase (docs/method.md section 2)."""
from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable, Iterator, Sequence

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.utils import NestedKey
from torchrl.collectors import BaseCollector
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType, set_exploration_type, step_mdp

from .._validation import check_int
from ..collector import (COUNTERS, FORWARD, PHASE_NAMES, RESET, _private_keys, _state_owner, check_state_keys,
                        set_up_loop, stopped_scores)
from ..example_buffer import InitialStateBuffer
from .trigger import RowResetTriggerTransform

__all__ = ["BatchedDualCollector", "CopyView", "PooledCollector", "split_phases"]


def split_phases(batch: TensorDictBase) -> dict[str, TensorDictBase]:
    """The rows of a :class:`BatchedDualCollector` batch by phase: ``{"forward": ..., "reset": ...}``
    (a phase with no executed step this iteration is left out)."""
    phase = batch.get(("collector", "phase")).reshape(-1)
    out = {}
    for code, name in PHASE_NAMES.items():
        rows = (phase == code).nonzero().flatten()
        if rows.numel():
            out[name] = batch[rows]
    return out


def _per_copy_budget(budget, n: int) -> np.ndarray | None:
    if budget is None:
        return None
    values = [budget] * n if isinstance(budget, int) and not isinstance(budget, bool) else list(budget)
    if len(values) != n:
        raise ValueError(f"max_frames_per_env gives {len(values)} budgets for {n} copies.")
    return np.array([check_int("max_frames_per_env", v) for v in values], dtype=np.int64)


def _rows_mask(mask: np.ndarray, like: torch.Tensor) -> torch.Tensor:
    return torch.from_numpy(mask).to(like.device).reshape(-1, *([1] * (like.dim() - 1)))


class BatchedDualCollector(BaseCollector):
    """:class:`~torchrl_reset.DualCollector`'s loop on an env of batch size ``[N]``: N copies of a task,
    each in its own phase.

    Every copy follows Algorithm 1 on its own, as :class:`~torchrl_reset.DualCollector` runs it on one
    env: its own phase (forward or reset), H_f / H_r clocks, trigger decisions, successful and manual
    resets, counters and (unless shared) example buffer. One iteration takes one action in every
    copy: the forward policy acts for the copies in a forward episode and the reset policy for the
    others, each called once on the whole batch (its outputs, its exploration state included, are
    kept on its own rows), and one ``env.step`` steps them all. A copy whose action the trigger
    stops is not stepped while the others are (torchrl's partial steps: the env must honour
    ``"_step"``, as :class:`~torchrl_reset_envs.BatchedTaskEnv` and ``SerialEnv`` do); a manual reset
    resets that copy only (``"_reset"``). After a copy's H_f-th step its next action is drawn and
    scored in the same iteration, and not executed (Algorithm 1's order: trigger first, then the
    horizon), as :class:`~torchrl_reset.DualCollector` does: each copy draws its random numbers in
    the order a single collector draws them. Each policy's input carries ``"_acting"``, the boolean
    mask ``[N]`` of the rows it acts for (the other rows' outputs are discarded), so that a policy
    may draw noise for its own rows only.

    Each iteration yields the steps it executed, batch ``[M]`` (M <= N), each row tagged with
    ``("collector", "phase")``, ``("collector", "env_ids")`` (its copy) and ``("collector", "traj_ids")``
    (for independent runs counted per copy, as each copy's own :class:`~torchrl_reset.DualCollector`
    counts them; with a shared example buffer unique over all copies): :func:`split_phases` sorts
    them for the two agents' buffers. :meth:`view` gives one copy's live view with a single collector's
    interface (counters, frames, example buffer, events, and its state in
    :class:`~torchrl_reset.DualCollector`'s ``state_dict`` format), for the code that keeps one run's
    records and checkpoints.

    The same collector serves both uses, by configuration:

    - **independent runs** (``shared_examples=False``, the default): copy ``i`` is run ``i``, with its
      own example buffer (``example_buffers[i]``) and metrics (:meth:`env_metrics`); the policies
      and the trigger's model compute row ``i`` with run ``i``'s networks (for example
      :class:`~torchrl_reset.many.RunPolicies` and ``RunEnsembles``), and ``max_frames_per_env``
      stops each run at its own budget;
    - **one agent pair over N environments** (``shared_examples=True``; N arms in one cell): one
      example buffer receives every copy's initial states, the policies are ordinary modules over
      the batch, and :meth:`metrics` sums the copies.

    Args:
        create_env_fn (EnvBase or callable): an env of batch size ``[N]`` with the trigger transform
            outermost (its model sees the batch), or a function returning one.
        forward_policy, reset_policy (callable): tensordict modules over the batch, with their exploration.

    Keyword Args:
        max_forward_steps, max_reset_steps, min_reset_steps, reset_success_key, trigger_key, init_key,
        exploration_type, max_events, event_keys: as :class:`~torchrl_reset.DualCollector`.
        restart_exploration (bool): as :class:`~torchrl_reset.DualCollector`'s, per copy: ``True`` (default):
            ``init_key`` is True on each copy's first step of every episode. ``False`` (the authors'
            release): it is never True, and the private root entries a policy's exploration writes
            (Ornstein-Uhlenbeck's ``_ou_prev_noise`` and ``_ou_steps``) are kept per copy and per phase:
            a copy's forward episode continues that copy's forward noise where its last forward episode
            left it, its reset episode the reset noise; a phase that never acted in a copy starts from
            zeros (a process at its start, as torchrl's OU module starts one). Saved by :meth:`state_dict`
            and, per copy, in a single collector's format by :meth:`view`.
        total_frames (int): executed steps of all copies together after which iteration stops; -1 (default) never.
            The iteration that reaches it is completed (up to N - 1 steps past it), so that a run
            continued from there takes the same iterations as one that never stopped.
        max_frames_per_env (int or sequence of int, optional): a copy that executed this many steps (its
            own budget, when one per copy is given) stops: its row is neither stepped nor scored;
            iteration ends when every copy stopped.
        example_buffers (InitialStateBuffer or sequence of them, optional): one shared buffer, or one per copy.
        shared_examples (bool): when no buffers are given, one shared buffer (True) or one per copy (False, default).
        example_keys (sequence of NestedKey): the state entries stored as examples. Defaults to ``("observation",)``.

    Examples:
        >>> import torch
        >>> from tensordict.nn import TensorDictModule
        >>> from torchrl_reset.many import BatchedDualCollector
        >>> from torchrl_reset_envs import BatchedTaskEnv
        >>> env = BatchedTaskEnv("peg_insertion_insert", seeds=[0, 1])
        >>> still = TensorDictModule(lambda obs: torch.zeros(*obs.shape[:-1], 7), in_keys=["observation"], out_keys=["action"])
        >>> collector = BatchedDualCollector(env, still, still, max_forward_steps=4, min_reset_steps=1, total_frames=16)
        >>> sum(batch.shape[0] for batch in collector)
        16
        >>> [m["successful_resets"] for m in collector.env_metrics()]
        [1, 1]
    """

    FORWARD = FORWARD
    RESET = RESET

    def __init__(
        self,
        create_env_fn: EnvBase | Callable[[], EnvBase],
        forward_policy: Callable[[TensorDictBase], TensorDictBase],
        reset_policy: Callable[[TensorDictBase], TensorDictBase],
        *,
        max_forward_steps: int,
        max_reset_steps: int | None = None,
        min_reset_steps: int = 5,
        total_frames: int = -1,
        max_frames_per_env: int | None = None,
        example_buffers: InitialStateBuffer | Sequence[InitialStateBuffer] | None = None,
        shared_examples: bool = False,
        example_keys: Sequence[NestedKey] = ("observation",),
        reset_success_key: NestedKey = "reset_success",
        trigger_key: NestedKey | None = None,
        init_key: NestedKey = "is_init",
        exploration_type: ExplorationType = ExplorationType.RANDOM,
        max_events: int = 100_000,
        event_keys: Sequence[NestedKey] = (),
        restart_exploration: bool = True,
    ) -> None:
        super().__init__()
        if not isinstance(restart_exploration, bool):
            raise TypeError(f"restart_exploration must be a bool, got {restart_exploration!r}.")
        self.restart_exploration = restart_exploration
        env = set_up_loop(self, create_env_fn, forward_policy, reset_policy, max_forward_steps=max_forward_steps,
                          max_reset_steps=max_reset_steps, min_reset_steps=min_reset_steps, total_frames=total_frames,
                          max_events=max_events, trigger_key=trigger_key, reset_success_key=reset_success_key,
                          init_key=init_key, exploration_type=exploration_type, event_keys=event_keys)
        if env.batch_dims != 1:
            raise ValueError(f"BatchedDualCollector runs an env of batch size [N] (N copies of a task), got "
                             f"{tuple(env.batch_size)}; for one unbatched env use DualCollector.")
        wrong = [type(t).__name__ for t in self.triggers if not isinstance(t, RowResetTriggerTransform)]
        if wrong:
            raise TypeError(f"BatchedDualCollector runs each copy in its own phase, so its trigger works row by row: "
                            f"use torchrl_reset.many.RowResetTriggerTransform instead of {', '.join(wrong)}.")
        self.num_envs = int(env.batch_size[0])
        self.max_frames_per_env = _per_copy_budget(max_frames_per_env, int(env.batch_size[0]))
        if example_buffers is None:
            make = lambda: InitialStateBuffer(state_keys=example_keys)  # noqa: E731
            example_buffers = make() if shared_examples else [make() for _ in range(self.num_envs)]
        if isinstance(example_buffers, InitialStateBuffer):
            self.shared_examples, self.example_buffers = True, [example_buffers]
        else:
            self.shared_examples, self.example_buffers = False, list(example_buffers)
            if len(self.example_buffers) != self.num_envs:
                raise ValueError(f"example_buffers holds {len(self.example_buffers)} buffers for {self.num_envs} copies: "
                                 "pass one buffer (shared) or one per copy.")
        self._state_owner = _state_owner(env)
        n = self.num_envs
        self.counters = {name: np.zeros(n, dtype=np.int64) for name in COUNTERS}
        self._phase = np.full(n, FORWARD, dtype=np.int64)
        self._phase_steps = np.zeros(n, dtype=np.int64)
        self._traj_ids = np.zeros(n, dtype=np.int64)
        self._next_traj_id = 0
        self._restart = np.zeros(n, dtype=bool)
        # restart_exploration=False: each phase's exploration entries per copy, where its last episode left them
        self._exploration: dict[int, dict[str, torch.Tensor]] = {FORWARD: {}, RESET: {}}
        self._explored = {FORWARD: np.zeros(n, dtype=bool), RESET: np.zeros(n, dtype=bool)}
        self._events: list[dict] = []
        self._pending: dict[int, tuple[dict, list]] = {}  # copies' saved states, restored at the first iteration
        self._td: TensorDictBase | None = None
        self._frames = 0

    # ----------------------------------------------------------------- metrics
    @property
    def frames(self) -> int:
        """Executed steps of all copies together."""
        return self._frames

    @property
    def frames_per_env(self) -> np.ndarray:
        return self.counters["forward_steps"] + self.counters["reset_steps"]

    @property
    def phases(self) -> list[str]:
        """Each copy's phase for its next step."""
        return [PHASE_NAMES[int(p)] for p in self._phase]

    @staticmethod
    def _with_rates(counters: dict[str, int]) -> dict[str, float]:
        total = counters["forward_steps"] + counters["reset_steps"]
        finished = counters["successful_resets"] + counters["manual_resets"]
        return {**counters, "forward_share": counters["forward_steps"] / total if total else float("nan"),
                "reset_success_rate": counters["successful_resets"] / finished if finished else float("nan")}

    def env_metrics(self) -> list[dict[str, float]]:
        """Each copy's counters, forward share and reset success rate (a run's metrics)."""
        return [self._with_rates({k: int(v[i]) for k, v in self.counters.items()}) for i in range(self.num_envs)]

    def metrics(self) -> dict[str, float]:
        """The copies' counters summed, with the forward share and reset success rate of the sums."""
        return self._with_rates({k: int(v.sum()) for k, v in self.counters.items()})

    def pop_events(self) -> list[dict]:
        """As :meth:`DualCollector.pop_events`, each record with its copy under ``env``."""
        events, self._events = self._events, []
        return events

    # --------------------------------------------------------------- the loop
    def _record(self, i: int, outcome: str, state: TensorDictBase, scored: TensorDictBase | None = None) -> None:
        if len(self._events) < self.max_events:
            keys = self.example_buffers[0].state_keys
            event = {"env": i, "phase": PHASE_NAMES[int(self._phase[i])], "outcome": outcome,
                     "steps": int(self._phase_steps[i]),
                     # one run's step count: the copy's own, or every copy's together when they are one run
                     "frame": self._frames if self.shared_examples else int(self.frames_per_env[i]),
                     "state": state.select(*keys, *self.event_keys).clone()}
            if scored is not None and self.triggers:
                event["scores"] = stopped_scores(self.triggers, scored)
            self._events.append(event)

    def _begin(self, rows: np.ndarray, phase: int, root: TensorDictBase) -> None:
        """Copies ``rows`` (indices) start an episode of ``phase`` from their state in ``root``; a forward
        episode first saves that state as an example (Algorithm 1, line 6)."""
        if not len(rows):
            return
        self._phase[rows], self._phase_steps[rows] = phase, 0
        if self.shared_examples:  # one buffer: episode ids unique over the copies
            self._traj_ids[rows] = self._next_traj_id + 1 + np.arange(len(rows))
            self._next_traj_id += len(rows)
        else:  # a run per copy: each copy counts its episodes as its single collector does
            self._traj_ids[rows] += 1
        self._restart[rows] = True
        if not self.restart_exploration:
            self._continue_exploration(rows, phase, root)
        if phase == FORWARD:
            states = root[torch.as_tensor(rows)]
            if self.shared_examples:
                self.example_buffers[0].add(states)
            else:
                for j, i in enumerate(rows):
                    self.example_buffers[i].add(states[j])

    def _continue_exploration(self, rows: np.ndarray, phase: int, root: TensorDictBase) -> None:
        """Copies ``rows`` take up ``phase``'s exploration entries where that phase's last episode in each of
        them left them (zeros, a process at its start, where the phase never acted in that copy)."""
        chosen = np.zeros(self.num_envs, dtype=bool)
        chosen[rows] = True
        for key in _private_keys(root):
            value = root.get(key)
            saved = self._exploration[phase].get(key)
            root.set(key, torch.where(_rows_mask(chosen, value),
                                      torch.zeros_like(value) if saved is None else saved.to(value.device), value))

    def _keep_exploration(self, td: TensorDictBase, forward: np.ndarray, reset: np.ndarray) -> None:
        """Saves each acting copy's exploration entries (after its policy's call) as its phase's."""
        for phase, rows in ((FORWARD, forward), (RESET, reset)):
            if not rows.any():
                continue
            store = self._exploration[phase]
            for key in _private_keys(td):
                value = td.get(key)
                before = store.get(key)
                store[key] = torch.where(_rows_mask(rows, value), value,
                                         torch.zeros_like(value) if before is None else before.to(value.device))
            self._explored[phase] |= rows

    def _clear_flags(self, root: TensorDictBase) -> TensorDictBase:
        for key in {*self.env.done_keys, "truncated"}:
            value = root.get(key, None)
            if value is not None:
                root.set(key, torch.zeros_like(value))
        return root

    def _start(self) -> None:
        """The first ``env.reset()``; the copies given a saved state (:meth:`view`) continue from it."""
        root = self._clear_flags(self.env.reset())
        fresh = np.ones(self.num_envs, dtype=bool)
        for i, (state, smoothing) in sorted(self._pending.items()):
            self._state_owner.set_copy_state(i, state["env_state"], state["td"])
            row = TensorDict.from_dict(state["td"], batch_size=[])
            for key in row.keys(True, True):
                target = root.get(key, None)
                value = row.get(key)
                if target is None:  # an entry the first reset has not written yet (the exploration's state)
                    target = torch.zeros((self.num_envs, *value.shape), dtype=value.dtype, device=root.device)
                    root.set(key, target)
                target[i] = value.to(target.device)
            for trigger, smoothed in zip(self.triggers, smoothing):
                trigger.restore_row(i, smoothed, self.num_envs)
            fresh[i] = False
        self._pending = {}
        self._td = root
        self._begin(np.flatnonzero(fresh), FORWARD, root)

    def _mask(self, rows: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(rows.copy()).to(self._td.device)

    def _act(self, td: TensorDictBase, forward: np.ndarray, reset: np.ndarray) -> TensorDictBase:
        """Each policy on the whole batch, its outputs kept on its own rows (lines 8 and 20)."""
        outputs = []
        with torch.no_grad(), set_exploration_type(self.exploration_type):
            for rows, policy in ((forward, self.forward_policy), (reset, self.reset_policy)):
                if rows.any():
                    inputs = td.clone(False)
                    inputs.set("_acting", self._mask(rows))
                    outputs.append((rows, policy(inputs)))
        for rows, out in outputs:
            for key in out.keys(True, True):
                if key == "_acting":
                    continue
                value, before = out.get(key), td.get(key, None)
                if value is before:
                    continue
                td.set(key, value if before is None or len(outputs) == 1 and rows.all()
                       else torch.where(_rows_mask(rows, value), value, before))
        if not self.restart_exploration:
            self._keep_exploration(td, forward, reset)
        return td

    def _score_next(self, root: TensorDictBase, rows: np.ndarray) -> tuple[np.ndarray, TensorDictBase]:
        """Lines 9-11 for the action after the H_f-th step of copies ``rows``: drawn, scored (smoothing
        included) and never executed; ``root`` keeps no action. The other rows' trigger state is untouched."""
        n = self.num_envs
        root.set(self.init_key, torch.zeros(n, 1, dtype=torch.bool, device=root.device))
        with torch.no_grad(), set_exploration_type(self.exploration_type):
            inputs = root.clone(False)
            inputs.set("_acting", self._mask(rows))
            scored = self.forward_policy(inputs)
        fired = np.zeros(n, dtype=bool)
        mask = torch.from_numpy(rows.copy())
        for trigger in self.triggers:
            fired |= trigger.score_rows(scored, mask).reshape(n).cpu().numpy()
        return fired & rows, scored

    def _iterate(self) -> TensorDictBase | None:
        """One action in every active copy; returns the executed steps (or None when none executed)."""
        td, n = self._td, self.num_envs
        active = np.ones(n, dtype=bool) if self.max_frames_per_env is None else self.frames_per_env < self.max_frames_per_env
        forward, reset = active & (self._phase == FORWARD), active & (self._phase == RESET)
        td.set(self.init_key, torch.from_numpy((self._phase_steps == 0) & self.restart_exploration).reshape(n, 1).to(td.device))
        for trigger in self.triggers:
            trigger.set_enabled(torch.from_numpy(forward), restart=torch.from_numpy(self._restart))
        self._restart[:] = False
        td = self._act(td, forward, reset)
        if not active.all():  # a copy past its budget is neither stepped nor scored
            td.set("_step", self._mask(active))
        stepped = self.env.step(td)
        td.pop("_step", None)
        flag = stepped.get(("next", self.trigger_key), None)
        fired = np.zeros(n, dtype=bool) if flag is None else flag.reshape(n).cpu().numpy() & forward
        executed = active & ~fired
        nxt = stepped.get("next")
        root = step_mdp(stepped, exclude_action=True, exclude_reward=True, exclude_done=False, keep_other=True)
        terminated = nxt.get("terminated", None)
        terminated = np.zeros(n, dtype=bool) if terminated is None else terminated.reshape(n).cpu().numpy()

        # book the executed steps (lines 14-16 and 23)
        self._phase_steps[executed] += 1
        self.counters["forward_steps"] += executed & forward
        self.counters["reset_steps"] += executed & reset
        self._frames += int(executed.sum())
        success_flag = nxt.get(self.reset_success_key, None)
        if success_flag is None:
            raise KeyError(f"the env's step output has no {self.reset_success_key!r} entry (the at-initial-state check); "
                           f"pass reset_success_key=... to BatchedDualCollector.")
        at_initial = success_flag.reshape(n).cpu().numpy()
        fwd_exec, rst_exec = executed & forward, executed & reset
        fwd_term = fwd_exec & terminated
        fwd_last = fwd_exec & ~terminated & (self._phase_steps >= self.max_forward_steps)
        success = rst_exec & at_initial & (self._phase_steps >= self.min_reset_steps)
        rst_term = rst_exec & ~success & terminated
        manual = rst_exec & ~success & ~terminated & (self._phase_steps >= self.max_reset_steps)
        ends = fwd_term | fwd_last | success | rst_term | manual  # executed steps that end their episode
        batch = None
        if executed.any():
            rows = torch.from_numpy(np.flatnonzero(executed))
            batch = stepped[rows].exclude(*[k for k in stepped.keys() if isinstance(k, str) and k.startswith("_")])
            if batch.get(("next", "truncated"), None) is None:
                batch.set(("next", "truncated"), torch.zeros_like(batch.get(("next", "done"))))
            end_rows = torch.from_numpy(ends[executed]).reshape(-1, 1).to(batch.device)
            for key in ("truncated", "done"):
                value = batch.get(("next", key))
                batch.set(("next", key), value | end_rows.reshape(value.shape))
            batch.set(("collector", "phase"), torch.from_numpy(self._phase[executed]).to(batch.device))
            batch.set(("collector", "env_ids"), rows.to(batch.device))
            batch.set(("collector", "traj_ids"), torch.from_numpy(self._traj_ids[executed]).to(batch.device))

        # the episodes that end (lines 10-13, 17-19, 24-25); triggered rows keep their state
        root = self._clear_flags(root)
        horizon_fired, scored = (self._score_next(root, fwd_last) if fwd_last.any() and self.triggers
                                 else (np.zeros(n, dtype=bool), None))
        for i in np.flatnonzero(fired):
            self.counters["triggered_resets"][i] += 1
            self.counters["forward_episodes"][i] += 1
            self._record(i, "triggered", root[int(i)], nxt[int(i)])
        for i in np.flatnonzero(fwd_last):
            outcome = "triggered" if horizon_fired[i] else "requested"
            self.counters[f"{outcome}_resets"][i] += 1
            self.counters["forward_episodes"][i] += 1
            self._record(i, outcome, root[int(i)], None if scored is None else scored[int(i)])
        for i in np.flatnonzero(fwd_term):
            self.counters["forward_episodes"][i] += 1
            self.counters["terminations"][i] += 1
            self._record(i, "terminated", nxt[int(i)])
        for i in np.flatnonzero(success | rst_term | manual):
            self.counters["reset_episodes"][i] += 1
            outcome = "success" if success[i] else "terminated" if rst_term[i] else "manual"
            self.counters["successful_resets" if success[i] else "terminations" if rst_term[i] else "manual_resets"][i] += 1
            self._record(i, outcome, nxt[int(i)])
        hard = fwd_term | rst_term | manual
        if hard.any():  # a manual reset of those copies only (env.reset with "_reset")
            mask = torch.from_numpy(hard).reshape(n, 1).to(root.device)
            fresh = self.env.reset(TensorDict({"_reset": mask}, batch_size=self.env.batch_size, device=root.device))
            rows = torch.from_numpy(np.flatnonzero(hard))
            for key in fresh.keys(True, True):
                target = root.get(key, None)
                if target is not None and not (isinstance(key, str) and key.startswith("_")):
                    target[rows] = fresh.get(key)[rows].to(target.dtype)
            root = self._clear_flags(root)
        self._begin(np.flatnonzero(fired | fwd_last), RESET, root)
        self._begin(np.flatnonzero(success | hard), FORWARD, root)
        self._td = root
        return batch

    def _finished(self) -> bool:
        if self.total_frames >= 0 and self._frames >= self.total_frames:
            return True
        return self.max_frames_per_env is not None and bool((self.frames_per_env >= self.max_frames_per_env).all())

    def __len__(self) -> int:
        raise TypeError("a BatchedDualCollector yields one batch per iteration with at least one executed step: "
                        "its number of batches is not known in advance.")

    def iterator(self) -> Iterator[TensorDictBase]:
        if self._td is None:
            self._start()
        while not self._finished():
            batch = self._iterate()
            if batch is not None:
                yield batch

    # ------------------------------------------------------------- one copy
    def view(self, i: int) -> CopyView:
        """Copy ``i`` seen as one run's collector: a live view (it reads and steps this collector), with a single
        collector's interface (independent runs only)."""
        if self.shared_examples:
            raise ValueError("view() gives one run's view; with a shared example buffer the copies are one run.")
        if not (isinstance(i, int) and 0 <= i < self.num_envs):
            raise IndexError(f"copy index {i!r} out of range for {self.num_envs} copies.")
        return CopyView(self, i)

    def pooled(self) -> PooledCollector:
        """The copies seen as one run's collector (one agent pair over N environments, shared examples only)."""
        if not self.shared_examples:
            raise ValueError("pooled() views the copies as one run; with an example buffer per copy they are "
                             "independent runs: use view(i).")
        return PooledCollector(self)

    # --------------------------------------------------------- state / seeding
    def set_seed(self, seed: int, static_seed: bool = False) -> int:
        torch.manual_seed(seed)
        return self.env.set_seed(seed, static_seed=static_seed)

    def state_dict(self) -> OrderedDict:
        """Everything needed to continue identically (as :meth:`DualCollector.state_dict`, per copy)."""
        return OrderedDict(
            counters={k: v.copy() for k, v in self.counters.items()},
            phase=self._phase.copy(), phase_steps=self._phase_steps.copy(), traj_ids=self._traj_ids.copy(),
            next_traj_id=self._next_traj_id, restart=self._restart.copy(), frames=self._frames,
            td=None if self._td is None else self._td.to_dict(),
            env_state=None if self._state_owner is None or self._td is None else self._state_owner.get_simulator_state(),
            example_buffers=[b.state_dict() for b in self.example_buffers],
            trigger_state=[(t.smoothed, t.enabled_rows) for t in self.triggers],
            exploration={PHASE_NAMES[p]: {k: v.clone() for k, v in store.items()} for p, store in self._exploration.items()},
            explored={PHASE_NAMES[p]: rows.copy() for p, rows in self._explored.items()},
            events=[{**e, "state": e["state"].to_dict()} for e in self._events],
            pending=dict(self._pending),
            rng_state=torch.get_rng_state(),
        )

    def load_state_dict(self, state_dict: OrderedDict) -> None:
        missing = {"counters", "phase", "phase_steps", "traj_ids", "frames", "td", "example_buffers"} - set(state_dict)
        if missing:
            raise KeyError(f"not a BatchedDualCollector state_dict: missing {sorted(missing)}.")
        if len(state_dict["phase"]) != self.num_envs:
            raise ValueError(f"the state holds {len(state_dict['phase'])} copies; this collector runs {self.num_envs}.")
        if state_dict["td"] is not None and (state_dict.get("env_state") is None or self._state_owner is None):
            raise ValueError("the saved state has no simulator state to restore (or this env cannot restore one): "
                             "a batch resumes exactly or not at all.")
        self.counters = {k: np.array(v, dtype=np.int64) for k, v in state_dict["counters"].items()}
        self._phase, self._phase_steps = np.array(state_dict["phase"]), np.array(state_dict["phase_steps"])
        self._traj_ids, self._next_traj_id = np.array(state_dict["traj_ids"]), int(state_dict["next_traj_id"])
        self._restart, self._frames = np.array(state_dict["restart"]), int(state_dict["frames"])
        for buffer, saved in zip(self.example_buffers, state_dict["example_buffers"]):
            buffer.load_state_dict(saved)
        for trigger, (smoothed, rows) in zip(self.triggers, state_dict.get("trigger_state", [])):
            trigger.set_enabled(True if rows is None else rows)
            trigger.smoothed = smoothed
        saved, explored = state_dict.get("exploration") or {}, state_dict.get("explored") or {}
        self._exploration = {p: dict(saved.get(PHASE_NAMES[p], {})) for p in (FORWARD, RESET)}
        self._explored = {p: np.array(explored.get(PHASE_NAMES[p], np.zeros(self.num_envs, dtype=bool)), dtype=bool)
                          for p in (FORWARD, RESET)}
        self._events = [{**e, "state": TensorDict.from_dict(e["state"])} for e in state_dict.get("events", [])]
        torch.set_rng_state(state_dict["rng_state"])
        self._pending = dict(state_dict.get("pending", {}))
        if state_dict["td"] is None:
            self._td = None
            return
        self._state_owner.set_simulator_state(state_dict["env_state"])
        self._td = TensorDict.from_dict(state_dict["td"], batch_size=self.env.batch_size)

    def shutdown(self, timeout: float | None = None, close_env: bool = True, raise_on_error: bool = True) -> None:
        if close_env and not self.env.is_closed:
            self.env.close(raise_if_closed=False)

    def update_policy_weights_(self, *args, **kwargs) -> None:
        """The policies are used in place: trained parameters are seen at the next step."""

    def __repr__(self) -> str:
        return (f"{type(self).__name__}(env={type(self.env).__name__}, N={self.num_envs}, H_f={self.max_forward_steps}, "
                f"H_r={self.max_reset_steps}, frames={self._frames}, phases={self.phases})")


class _RunView:
    """What a one-run view of a :class:`BatchedDualCollector` derives from its ``counters``."""

    def __init__(self, collector: BatchedDualCollector) -> None:
        self.collector = collector

    @property
    def counters(self) -> dict[str, int]:
        raise NotImplementedError

    def metrics(self) -> dict[str, float]:
        return self.collector._with_rates(self.counters)

    @property
    def forward_share(self) -> float:
        return self.metrics()["forward_share"]

    @property
    def reset_success_rate(self) -> float:
        return self.metrics()["reset_success_rate"]

    @property
    def triggers(self) -> list:
        return self.collector.triggers


class CopyView(_RunView):
    """One copy of a :class:`BatchedDualCollector` seen as a single run's collector.

    It reads like :class:`~torchrl_reset.DualCollector` for the code that keeps one run's records
    and checkpoints: ``counters``, ``frames``, ``phase``, ``forward_share``, ``reset_success_rate``,
    :meth:`metrics`, ``example_buffer``, :meth:`pop_events` (this copy's events), and
    :meth:`state_dict` / :meth:`load_state_dict` in :class:`~torchrl_reset.DualCollector`'s format,
    so a run checkpointed alone continues in a batch and the other way round. A saved state is
    loaded before the batch's first iteration (the env is reset then, and the copy continues from
    its saved simulator state); ``rng_state`` is torch's global generator state, saved from and
    loaded into whatever stream is current when the call is made (the caller's run's own)."""

    def __init__(self, collector: BatchedDualCollector, index: int) -> None:
        super().__init__(collector)
        self.index = index

    @property
    def counters(self) -> dict[str, int]:
        return {k: int(v[self.index]) for k, v in self.collector.counters.items()}

    @property
    def frames(self) -> int:
        return int(self.collector.frames_per_env[self.index])

    @property
    def phase(self) -> str:
        return PHASE_NAMES[int(self.collector._phase[self.index])]

    @property
    def example_buffer(self) -> InitialStateBuffer:
        return self.collector.example_buffers[self.index]

    def shutdown(self, *args, **kwargs) -> None:
        """A copy closes nothing: the batch's env is closed with the batch (:meth:`BatchedDualCollector.shutdown`)."""

    def _own_events(self) -> list[dict]:
        return [e for e in self.collector._events if e["env"] == self.index]

    def pop_events(self) -> list[dict]:
        """This copy's events since the last call, as :meth:`DualCollector.pop_events` gives them."""
        mine = self._own_events()
        if mine:
            self.collector._events = [e for e in self.collector._events if e["env"] != self.index]
        return [{k: v for k, v in e.items() if k != "env"} for e in mine]

    def state_dict(self) -> OrderedDict:
        """This copy's state in :meth:`DualCollector.state_dict`'s format."""
        c, i = self.collector, self.index
        if c._td is not None:
            td = c._td[i].to_dict()
            env_state = c._state_owner.get_copy_state(i)
            smoothing = [t.row_smoothing(i) for t in c.triggers]
        elif i in c._pending:
            saved, smoothing = c._pending[i]
            td, env_state = saved["td"], saved["env_state"]
        else:
            td, env_state, smoothing = None, None, [None for _ in c.triggers]
        return OrderedDict(
            counters=self.counters, phase=int(c._phase[i]), phase_steps=int(c._phase_steps[i]),
            traj_id=int(c._traj_ids[i]), frames=self.frames, td=td, env_state=env_state,
            example_buffer=self.example_buffer.state_dict(), trigger_smoothing=smoothing,
            exploration={PHASE_NAMES[p]: {k: v[i].clone() for k, v in store.items()} if c._explored[p][i] else {}
                         for p, store in c._exploration.items()},
            events=[{**{k: v for k, v in e.items() if k != "env"}, "state": e["state"].to_dict()}
                    for e in self._own_events()],
            rng_state=torch.get_rng_state(),
        )

    def load_state_dict(self, state_dict: OrderedDict) -> None:
        c, i = self.collector, self.index
        check_state_keys(state_dict)
        if c._td is not None:
            raise RuntimeError("a copy's state is loaded before the batch's first iteration.")
        if state_dict["td"] is not None and (state_dict.get("env_state") is None
                                             or not callable(getattr(c._state_owner, "set_copy_state", None))):
            raise ValueError("the saved state has no simulator state to restore (or this env cannot restore one "
                             "copy): a copy resumes exactly or not at all.")
        counters = dict.fromkeys(COUNTERS, 0) | dict(state_dict["counters"])
        for key, value in counters.items():
            c.counters[key][i] = int(value)
        c._phase[i], c._phase_steps[i] = int(state_dict["phase"]), int(state_dict["phase_steps"])
        c._traj_ids[i] = int(state_dict["traj_id"])
        c._frames = int(c.frames_per_env.sum())
        self.example_buffer.load_state_dict(state_dict["example_buffer"])
        saved = state_dict.get("exploration") or {}
        for p in (FORWARD, RESET):  # the copy's row of each phase's exploration entries (zeros: none saved)
            entries = saved.get(PHASE_NAMES[p]) or {}
            store = c._exploration[p]
            for key, value in entries.items():
                if key not in store:
                    store[key] = torch.zeros((c.num_envs, *value.shape), dtype=value.dtype, device=value.device)
            for key, value in store.items():
                value[i] = entries[key].to(value.device) if key in entries else 0
            c._explored[p][i] = bool(entries)
        c._events = [e for e in c._events if e["env"] != i] + [
            {**e, "env": i, "state": TensorDict.from_dict(e["state"], batch_size=[])} for e in state_dict.get("events", [])]
        if state_dict.get("rng_state") is not None:
            torch.set_rng_state(state_dict["rng_state"])
        if state_dict["td"] is None:
            c._pending.pop(i, None)
            return
        smoothing = list(state_dict.get("trigger_smoothing") or [])
        c._pending[i] = ({"td": state_dict["td"], "env_state": state_dict["env_state"]},
                         smoothing + [None] * (len(c.triggers) - len(smoothing)))


class PooledCollector(_RunView):
    """All copies of a :class:`BatchedDualCollector` with a shared example buffer seen as one run's collector.

    One agent pair over N environments (N arms in one cell) is one run: its ``counters`` are the
    copies' sums, ``frames`` counts every copy's executed steps, ``example_buffer`` is the shared one
    and :meth:`pop_events` gives every copy's events (each with its copy under ``env`` and ``frame``
    the run's step count). It reads like :class:`~torchrl_reset.DualCollector` for the code that keeps
    one run's records and checkpoints; iterating it iterates the batched collector (each batch holds
    the executed steps of one iteration, tagged with their copy). :meth:`state_dict` is the batched
    collector's."""

    def __iter__(self) -> Iterator[TensorDictBase]:
        return iter(self.collector)

    @property
    def counters(self) -> dict[str, int]:
        return {k: int(v.sum()) for k, v in self.collector.counters.items()}

    @property
    def frames(self) -> int:
        return self.collector.frames

    @property
    def example_buffer(self) -> InitialStateBuffer:
        return self.collector.example_buffers[0]

    def pop_events(self) -> list[dict]:
        return self.collector.pop_events()

    def state_dict(self) -> OrderedDict:
        return self.collector.state_dict()

    def load_state_dict(self, state_dict: OrderedDict) -> None:
        self.collector.load_state_dict(state_dict)

    def set_seed(self, seed: int, static_seed: bool = False) -> int:
        return self.collector.set_seed(seed, static_seed=static_seed)

    def shutdown(self, *args, **kwargs) -> None:
        self.collector.shutdown(*args, **kwargs)
