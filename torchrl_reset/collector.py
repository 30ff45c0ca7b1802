"""Forward and reset episodes interleaved without free resets (paper, Algorithm 1; docs/method.md section 2)."""
from __future__ import annotations

import warnings
from collections import OrderedDict
from collections.abc import Callable, Iterator, Sequence

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey
from torchrl.collectors import BaseCollector
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType, set_exploration_type, step_mdp

from ._validation import check_int
from .example_buffer import InitialStateBuffer
from .collector_env import (private_keys, own_time_limit, truncation_warning, termination_warning, set_up_loop, stopped_scores, check_state_keys, state_owner)

__all__ = ["DualCollector"]

FORWARD = 0
RESET = 1
PHASE_NAMES = {FORWARD: "forward", RESET: "reset"}
# a warning from the loop points at the user's ``for batch in collector`` line, 7 frames up from
# _check_own_episode_end (_executed, _forward_step or _reset_step, _step, iterator, BaseCollector.__iter__)
LOOP_DEPTH = 7
COUNTERS = (
    "forward_steps",
    "reset_steps",
    "forward_episodes",
    "reset_episodes",
    "triggered_resets",
    "requested_resets",
    "successful_resets",
    "manual_resets",
    "terminations",
)


class DualCollector(BaseCollector):
    """Runs a forward and a reset agent in turn on one environment that is never reset for free.

    The loop of the paper's Algorithm 1 over tensordicts:

    1. the first ``env.reset()`` gives the first state; it is added to the example buffer;
    2. forward episode: the forward policy acts until a :class:`ResetTriggerTransform` in the env
       fires (a *triggered* reset: the action is not executed and the step is not yielded) or
       ``max_forward_steps`` (H_f) steps were taken (a *requested* reset). As in Algorithm 1, the
       trigger is checked first: after the H_f-th step the policy's next action is scored, and
       a trigger there counts as triggered (that action is not executed either way);
    3. reset episode, from that very state: the reset policy acts until the env's
       ``reset_success_key`` holds after at least ``min_reset_steps`` steps (a *successful*
       reset) or ``max_reset_steps`` (H_r) steps were taken, after which the collector calls
       ``env.reset()`` (a *manual* reset, the only other ``env.reset()`` call);
    4. the state that starts the next forward episode is added to the example buffer.

    Every yielded batch holds consecutive executed steps of **one** phase, tagged with
    ``("collector", "phase")`` (0 forward, 1 reset; see :meth:`phase_of`) and
    ``("collector", "traj_ids")`` (one id per episode), so each agent's replay buffer receives only
    its own transitions. The last step of an episode that ends by request, success or manual reset
    carries ``("next", "truncated")`` and ``("next", "done")``. The trigger is enabled during forward
    episodes only. With ``restart_exploration=True``, ``init_key`` is set on the first step of every
    episode so that torchrl's exploration modules (Ornstein-Uhlenbeck) restart their noise; with
    ``False`` (the authors' release) each policy's exploration state carries over from one of its
    episodes to its next, across the other policy's episodes and manual resets.

    The env must write ``reset_success_key`` (a bool of shape ``(1,)``) in every step's ``"next"``
    tensordict, computed on the state after the step, and must not end episodes by itself
    (docs/environment-contract.md). If it *terminates* (``("next", "terminated")``; the paper's tasks
    never do), the episode ends and the collector calls ``env.reset()``, counted under
    ``terminations``: no reset episode follows, so if every forward episode ends this way the reset
    agent never acts. If it *truncates* (a time limit, such as gymnasium's ``TimeLimit``), the
    collector carries on from that state, but the flag stays on the step and cuts the episode in the
    replay buffers. Either one is warned about once per collector (a ``UserWarning`` naming the fix;
    a ``TimeLimit`` or ``StepCounter(max_steps=...)`` found in the env already at construction).

    Args:
        create_env_fn (EnvBase or callable): an unbatched env, or a function returning one.
        forward_policy (TensorDictModuleBase or callable): the forward policy with its exploration.
        reset_policy (TensorDictModuleBase or callable): the reset policy with its exploration.

    Keyword Args:
        max_forward_steps (int): H_f.
        max_reset_steps (int, optional): H_r; defaults to ``2 * max_forward_steps``.
        min_reset_steps (int): reset steps before ``reset_success`` may end a reset episode. Defaults to 5.
        frames_per_batch (int): at most this many steps per batch (a batch also ends with its
            phase). Defaults to 1: one update per environment step, as in the paper.
        total_frames (int): executed steps (forward and reset) after which iteration stops; -1 (default) never.
        example_buffer (InitialStateBuffer, optional): where initial states go; one is created if omitted.
        example_keys (sequence of NestedKey): the state entries stored as examples. Defaults to
            ``("observation",)`` (or the given buffer's ``state_keys``).
        reset_success_key (NestedKey): the env's at-initial-state flag in the next tensordict.
            Defaults to ``"reset_success"``.
        trigger_key (NestedKey): the trigger flag in the next tensordict. Defaults to the trigger
            transform's ``trigger_key``, else ``"reset_trigger"``.
        init_key (NestedKey): the flag written on the first step of each episode. Defaults to ``"is_init"``.
        restart_exploration (bool): ``True`` (default): ``init_key`` is True on the first step of every
            episode. ``False``: it is never True, and the private entries (names starting with ``_``,
            such as Ornstein-Uhlenbeck's ``_ou_prev_noise`` and ``_ou_steps``) that a policy's
            exploration writes into the root tensordict are kept per phase: a forward episode continues
            the forward policy's noise where its last episode left it, a reset episode the reset
            policy's, whatever happened in between (docs/method.md section 9: the release never restarts
            its noise). They are saved by :meth:`state_dict`.
        exploration_type (ExplorationType): mode the policies run in. Defaults to ``RANDOM``.
        max_events (int): episode records kept until :meth:`pop_events` drains them. Defaults to 100_000.
        event_keys (sequence of NestedKey): entries of the env's observation copied into each episode
            record's ``state`` beside ``example_keys``, for instance an env's latched ``irrecoverable`` flag
            (was the triggered state, or the state a reset episode ended in, already lost?). Defaults to none.

    Examples:
        >>> import torch
        >>> from tensordict.nn import TensorDictModule
        >>> from torchrl_reset import DualCollector
        >>> from torchrl_reset_envs import ChainEnv
        >>> right = TensorDictModule(lambda obs: torch.ones(1), in_keys=["observation"], out_keys=["action"])
        >>> left = TensorDictModule(lambda obs: -torch.ones(1), in_keys=["observation"], out_keys=["action"])
        >>> collector = DualCollector(ChainEnv(num_states=10), right, left, max_forward_steps=4,
        ...                           min_reset_steps=1, total_frames=16)
        >>> [DualCollector.phase_of(batch) for batch in collector][:5]
        ['forward', 'forward', 'forward', 'forward', 'reset']
        >>> collector.counters["successful_resets"], collector.forward_share, collector.reset_success_rate
        (2, 0.5, 1.0)
    """

    FORWARD = FORWARD
    RESET = RESET

    def __init__(
        self,
        create_env_fn: EnvBase | Callable[[], EnvBase],
        forward_policy: TensorDictModuleBase | Callable[[TensorDictBase], TensorDictBase],
        reset_policy: TensorDictModuleBase | Callable[[TensorDictBase], TensorDictBase],
        *,
        max_forward_steps: int,
        max_reset_steps: int | None = None,
        min_reset_steps: int = 5,
        frames_per_batch: int = 1,
        total_frames: int = -1,
        example_buffer: InitialStateBuffer | None = None,
        example_keys: Sequence[NestedKey] | None = None,
        reset_success_key: NestedKey = "reset_success",
        trigger_key: NestedKey | None = None,
        init_key: NestedKey = "is_init",
        exploration_type: ExplorationType = ExplorationType.RANDOM,
        max_events: int = 100_000,
        restart_exploration: bool = True,
        event_keys: Sequence[NestedKey] = (),
    ) -> None:
        super().__init__()
        if not isinstance(restart_exploration, bool):
            raise TypeError(f"restart_exploration must be a bool, got {restart_exploration!r}.")
        self.restart_exploration = restart_exploration
        self._exploration: dict[int, dict[str, torch.Tensor]] = {FORWARD: {}, RESET: {}}

        self.frames_per_batch = self.requested_frames_per_batch = check_int("frames_per_batch", frames_per_batch)
        env = set_up_loop(self, create_env_fn, forward_policy, reset_policy, max_forward_steps=max_forward_steps,
                          max_reset_steps=max_reset_steps, min_reset_steps=min_reset_steps, total_frames=total_frames,
                          max_events=max_events, trigger_key=trigger_key, reset_success_key=reset_success_key,
                          init_key=init_key, exploration_type=exploration_type, event_keys=event_keys)
        if env.batch_size != torch.Size([]):
            raise ValueError(
                f"DualCollector runs one unbatched environment (batch_size []), got batch_size {tuple(env.batch_size)}."
            )
        if example_buffer is None:
            example_buffer = InitialStateBuffer(state_keys=example_keys or ("observation",))
        elif example_keys is not None and list(example_keys) != example_buffer.state_keys:
            raise ValueError(
                f"example_keys {list(example_keys)} differ from the example buffer's state_keys {example_buffer.state_keys}."
            )
        self.example_buffer = example_buffer
        self._state_owner = state_owner(env)
        # the env's own episode ends already warned about ("truncated", "terminated"), each once per collector
        self._warned: set[str] = set()
        limit = own_time_limit(env)
        if limit is not None:
            self._warn_once("truncated", truncation_warning(type(env).__name__, f"it has {limit}"), stacklevel=2)
        self.counters: dict[str, int] = dict.fromkeys(COUNTERS, 0)
        self._events: list[dict] = []
        self._td: TensorDictBase | None = None
        self._phase = FORWARD
        self._phase_steps = 0
        self._traj_id = 0
        self._frames = 0

    # ----------------------------------------------------------------- metrics
    @property
    def frames(self) -> int:
        """Executed environment steps so far (forward and reset)."""
        return self._frames

    @property
    def phase(self) -> str:
        """The phase of the next step: ``"forward"`` or ``"reset"``."""
        return PHASE_NAMES[self._phase]

    @property
    def forward_share(self) -> float:
        """Forward steps / (forward + reset steps); NaN before any step."""
        total = self.counters["forward_steps"] + self.counters["reset_steps"]
        return self.counters["forward_steps"] / total if total else float("nan")

    @property
    def reset_success_rate(self) -> float:
        """Successful reset episodes / finished reset episodes; NaN before the first one ends."""
        finished = self.counters["successful_resets"] + self.counters["manual_resets"]
        return self.counters["successful_resets"] / finished if finished else float("nan")

    def metrics(self) -> dict[str, float]:
        """Counters plus forward share and reset success rate, ready for a logger."""
        return {**self.counters, "forward_share": self.forward_share, "reset_success_rate": self.reset_success_rate}

    @staticmethod
    def phase_of(batch: TensorDictBase) -> str:
        """``"forward"`` or ``"reset"``: the phase of a batch yielded by this collector."""
        phase = batch.get(("collector", "phase"), None)
        if phase is None:
            raise KeyError("the batch has no ('collector', 'phase') entry: it was not yielded by a DualCollector.")
        return PHASE_NAMES[int(phase.reshape(-1)[0])]

    def pop_events(self) -> list[dict]:
        """Returns and clears the records of the episodes finished since the last call.

        Each record: ``phase``, ``outcome`` (``triggered``, ``requested``, ``success``, ``manual``,
        ``terminated``), ``steps``, ``frame`` (executed steps when it ended) and ``state`` (for a
        triggered episode the state just before the trigger, else the episode's last state); a
        forward episode ended by the trigger or at H_f also has ``scores``, the triggers' scores of
        the action that was not executed.
        """
        events, self._events = self._events, []
        return events

    # --------------------------------------------------------------- the loop
    def _record(self, outcome: str, state: TensorDictBase, scored: TensorDictBase | None = None) -> None:
        if len(self._events) < self.max_events:
            event = {
                "phase": PHASE_NAMES[self._phase],
                "outcome": outcome,
                "steps": self._phase_steps,
                "frame": self._frames,
                "state": state.select(*self.example_buffer.state_keys, *self.event_keys).clone(),
            }
            if scored is not None and self.triggers:
                event["scores"] = stopped_scores(self.triggers, scored)
            self._events.append(event)

    def _begin(self, phase: int, td: TensorDictBase) -> None:
        """Starts an episode of ``phase`` from the state in ``td`` (a root tensordict); a forward
        episode first saves that state as an example of an initial state (Algorithm 1, line 6)."""
        self._phase = phase
        self._phase_steps = 0
        self._traj_id += 1
        for trigger in self.triggers:
            trigger.set_enabled(phase == FORWARD)
        if phase == FORWARD:
            self.example_buffer.add(td)
        if not self.restart_exploration:  # the phase's own exploration state, where its last episode left it
            for key in private_keys(td):
                del td[key]
            td.update(self._exploration[phase])
        self._td = td

    def _clear_flags(self, root: TensorDictBase) -> TensorDictBase:
        """Sets every done flag (and ``truncated``) of a root tensordict to False: no episode end pending."""
        done = root.get("done", None)
        template = torch.zeros(1, dtype=torch.bool, device=root.device) if done is None else torch.zeros_like(done)
        for key in {*self.env.done_keys, "truncated"}:
            value = root.get(key, None)
            root.set(key, template if value is None else torch.zeros_like(value))
        return root

    def _continue_from(self, td: TensorDictBase) -> TensorDictBase:
        """The root tensordict of the state reached by ``td``'s step."""
        root = step_mdp(td, exclude_action=True, exclude_reward=True, exclude_done=False, keep_other=True)
        return self._clear_flags(root)

    def _manual_reset(self) -> TensorDictBase:
        return self._clear_flags(self.env.reset())

    def _start(self) -> None:
        self._begin(FORWARD, self._manual_reset())

    # Algorithm 1 of the paper, one action per call; "line n" refers to its numbered lines.
    def _step(self) -> tuple[TensorDictBase | None, bool]:
        """Runs one policy action; returns (the executed step or None, whether the episode ended)."""
        return self._forward_step() if self._phase == FORWARD else self._reset_step()

    def _act(self, policy) -> TensorDictBase:
        """``a_t <- pi(s_t)`` (lines 8 and 20), with exploration, then ``env.step``: for a forward action the
        env's trigger scores it first (lines 9-11) and skips the step when it fires."""
        td = self._td
        td.set(self.init_key, torch.tensor([self.restart_exploration and self._phase_steps == 0], device=td.device))
        with torch.no_grad(), set_exploration_type(self.exploration_type):
            td = policy(td)
        if not self.restart_exploration:
            self._exploration[self._phase] = {key: td.get(key) for key in private_keys(td)}
        return self.env.step(td)

    def _executed(self, td: TensorDictBase, phase: int) -> TensorDictBase:
        """Books an executed step and returns it as yielded (phase and episode tags, a truncated flag)."""
        self._phase_steps += 1
        self._frames += 1
        self.counters[f"{PHASE_NAMES[phase]}_steps"] += 1
        if len(self._warned) < 2:
            self._check_own_episode_end(td.get("next"), phase)
        step = td.exclude(*private_keys(td))
        step.set(("collector", "phase"), torch.tensor(phase, device=td.device))
        step.set(("collector", "traj_ids"), torch.tensor(self._traj_id, device=td.device))
        if step.get(("next", "truncated"), None) is None:
            # every yielded step carries the flag that marks an episode's last step
            step.set(("next", "truncated"), torch.zeros_like(td.get("next").get("done")))
        return step

    def _warn_once(self, kind: str, message: str, stacklevel: int) -> None:
        if kind not in self._warned:
            self._warned.add(kind)
            warnings.warn(message, UserWarning, stacklevel=stacklevel + 1)

    def _check_own_episode_end(self, next_td: TensorDictBase, phase: int) -> None:
        """Warns (once per collector and kind) when an executed step comes back terminated or truncated by
        the env itself: the collector's own episode ends (trigger, H_f, success, H_r) are booked after this
        check, and a triggered step is never executed."""
        flags = [next_td.get(key, None) for key in ("terminated", "truncated", "done")]
        raised = [flag is not None and bool(flag.any()) for flag in flags]
        if not any(raised):
            return
        name = type(self.env).__name__
        where = f"at frame {self._frames}, step {self._phase_steps} of a {PHASE_NAMES[phase]} episode"
        if raised[0]:
            self._warn_once("terminated", termination_warning(name, f"('next', 'terminated') = True {where}"),
                            stacklevel=LOOP_DEPTH)
        else:
            key = "truncated" if raised[1] else "done"
            self._warn_once("truncated", truncation_warning(
                name, f"('next', {key!r}) = True {where}, which the collector did not cause"), stacklevel=LOOP_DEPTH)

    def _forward_step(self) -> tuple[TensorDictBase | None, bool]:
        """One pass of the forward episode's loop (lines 7-18)."""
        td = self._act(self.forward_policy)  # lines 8-9
        next_td = td.get("next")
        if bool(next_td.get(self.trigger_key, torch.zeros(1, dtype=torch.bool)).any()):
            # lines 10-11: trigger reset; the action was not executed, no transition to store
            self.counters["triggered_resets"] += 1
            self.counters["forward_episodes"] += 1
            self._record("triggered", td, next_td)
            self._begin(RESET, self._continue_from(td))
            return None, True
        step = self._executed(td, FORWARD)  # lines 14-16: env.step, store (the caller updates)
        if bool(next_td.get("terminated", torch.zeros(1, dtype=torch.bool)).any()):
            # not in the paper (its tasks never terminate): the env ended the episode, e.g. a robot stop
            self.counters["forward_episodes"] += 1
            self.counters["terminations"] += 1
            self._mark_end(step)
            self._record("terminated", next_td)
            self._begin(FORWARD, self._manual_reset())
            return step, True
        if self._phase_steps < self.max_forward_steps:
            self._td = self._continue_from(td)
            return step, False
        # Lines 10-13 for the next action: the algorithm scores it before it checks "reached max
        # forward episode steps", so a trigger there is a triggered reset, else the reset is requested.
        # That action is not executed either way.
        root = self._continue_from(td)
        fired, scored = self._would_trigger(root)
        outcome = "triggered" if fired else "requested"
        self.counters["forward_episodes"] += 1
        self.counters[f"{outcome}_resets"] += 1
        self._mark_end(step)
        self._record(outcome, root, scored)
        self._begin(RESET, root)
        return step, True

    def _reset_step(self) -> tuple[TensorDictBase | None, bool]:
        """One pass of the reset episode's loop (lines 19-27), from the state the forward episode ended in."""
        td = self._act(self.reset_policy)  # lines 20-22
        next_td = td.get("next")
        step = self._executed(td, RESET)  # line 23: store (the caller updates)
        at_initial_state = next_td.get(self.reset_success_key, None)
        if at_initial_state is None:
            raise KeyError(
                f"the env's step output has no {self.reset_success_key!r} entry (the at-initial-state check); "
                f"got {sorted(map(str, next_td.keys(True, True)))}. Pass reset_success_key=... to DualCollector."
            )
        terminated = bool(next_td.get("terminated", torch.zeros(1, dtype=torch.bool)).any())
        # line 19: "at initial state", after at least min_reset_steps steps (the release's rule)
        success = bool(at_initial_state.any()) and self._phase_steps >= self.min_reset_steps
        if not (success or terminated or self._phase_steps >= self.max_reset_steps):  # line 21
            self._td = self._continue_from(td)
            return step, False
        self.counters["reset_episodes"] += 1
        self._mark_end(step)
        if success:  # back at the initial state: the next forward episode starts here (lines 5-6)
            self.counters["successful_resets"] += 1
            self._record("success", next_td)
            self._begin(FORWARD, self._continue_from(td))
        else:  # lines 24-25: manual reset with env.reset() (or the env terminated)
            outcome = "terminated" if terminated else "manual"
            self.counters["terminations" if terminated else "manual_resets"] += 1
            self._record(outcome, next_td)
            self._begin(FORWARD, self._manual_reset())
        return step, True

    def _would_trigger(self, root: TensorDictBase) -> tuple[bool, TensorDictBase | None]:
        """Whether the trigger fires on the action the forward policy would take in ``root`` (which is
        not executed either way), and the tensordict it scored; without a trigger transform no action
        is drawn. The policy's output is scored as it is: a transform that changes actions must not
        sit between the trigger and the policy (the trigger is the env's outermost transform)."""
        if not self.triggers:
            return False, None
        root.set(self.init_key, torch.tensor([False], device=root.device))
        with torch.no_grad(), set_exploration_type(self.exploration_type):
            scored = self.forward_policy(root.clone(False))  # a shallow copy: root keeps no action
        fired = [bool(trigger.score_step(scored).any()) for trigger in self.triggers if trigger.enabled]
        return any(fired), scored

    @staticmethod
    def _mark_end(step: TensorDictBase) -> None:
        # every yielded step carries both flags (see _step)
        for key in ("truncated", "done"):
            step.set(("next", key), torch.ones_like(step.get(("next", key))))

    def iterator(self) -> Iterator[TensorDictBase]:
        if self._td is None:
            self._start()
        pending: list[TensorDictBase] = []
        while self.total_frames < 0 or self._frames < self.total_frames:
            step, ended = self._step()
            if step is not None:
                pending.append(step)
            done = self.total_frames >= 0 and self._frames >= self.total_frames
            if pending and (ended or done or len(pending) >= self.frames_per_batch):
                yield torch.stack(pending, 0)
                pending = []

    # --------------------------------------------------------- state / seeding
    def set_seed(self, seed: int, static_seed: bool = False) -> int:
        """Seeds torch's global generator and the env; call it before the first iteration.

        ``torch.manual_seed(seed)`` covers what the loop draws through torch's global generator: the
        policies' exploration noise (torchrl's Ornstein-Uhlenbeck and Gaussian modules), the example
        buffer's samples, and replay buffers whose samplers use it (torchrl's ``RandomSampler``,
        :class:`~torchrl_reset.EpisodeWindowSampler`). ``env.set_seed(seed, static_seed=static_seed)``
        seeds the env's own generator (its start states and noise); torchrl seeds a gymnasium env with
        ``reset(seed=seed)``, which also resets it, so a call during the loop would move the system
        behind the collector's back. Not seeded here: parameters initialised before this call (seed
        torch before building the networks), numpy's and Python's global generators, a replay buffer
        given its own ``generator``, and every other env (an evaluation env). See
        docs/environment-contract.md. Returns the env's next seed (torchrl's convention).
        """
        torch.manual_seed(seed)
        return self.env.set_seed(seed, static_seed=static_seed)

    def state_dict(self) -> OrderedDict:
        """Everything needed to continue identically: counters, the current episode and state,
        the env's simulator state (when the env offers ``get_simulator_state``), the example buffer, the
        trigger smoothing and torch's global RNG state."""
        if self._state_owner is None:
            warnings.warn(
                f"{type(self.env).__name__} has no get_simulator_state/set_simulator_state: a resumed DualCollector will "
                "start from env.reset() instead of the saved state.",
                stacklevel=2,
            )
        return OrderedDict(
            counters=dict(self.counters),
            phase=self._phase,
            phase_steps=self._phase_steps,
            traj_id=self._traj_id,
            frames=self._frames,
            td=None if self._td is None else self._td.to_dict(),
            env_state=None if self._state_owner is None or self._td is None else self._state_owner.get_simulator_state(),
            example_buffer=self.example_buffer.state_dict(),
            trigger_smoothing=[t.smoothed for t in self.triggers],
            exploration={PHASE_NAMES[p]: {k: v.clone() for k, v in state.items()} for p, state in self._exploration.items()},
            events=[{**event, "state": event["state"].to_dict()} for event in self._events],
            rng_state=torch.get_rng_state(),
        )

    def load_state_dict(self, state_dict: OrderedDict) -> None:
        check_state_keys(state_dict)
        self.counters = dict.fromkeys(COUNTERS, 0) | dict(state_dict["counters"])
        self._frames = int(state_dict["frames"])
        self.example_buffer.load_state_dict(state_dict["example_buffer"])
        saved = state_dict.get("exploration") or {}
        self._exploration = {p: dict(saved.get(PHASE_NAMES[p], {})) for p in (FORWARD, RESET)}
        self._events = [
            {**event, "state": TensorDict.from_dict(event["state"], batch_size=[])} for event in state_dict.get("events", [])
        ]
        if state_dict.get("rng_state") is not None:
            torch.set_rng_state(state_dict["rng_state"])
        td = state_dict["td"]
        if td is None:
            self._td = None
            return
        if state_dict.get("env_state") is not None and self._state_owner is not None:
            self._state_owner.set_simulator_state(state_dict["env_state"])
            self._phase = int(state_dict["phase"])
            self._phase_steps = int(state_dict["phase_steps"])
            self._traj_id = int(state_dict["traj_id"])
            self._td = TensorDict.from_dict(td, batch_size=[])
            for trigger, smoothed in zip(self.triggers, state_dict.get("trigger_smoothing", [])):
                trigger.set_enabled(self._phase == FORWARD)
                trigger.smoothed = smoothed
        else:
            warnings.warn("no saved env state to restore: continuing from env.reset().", stacklevel=2)
            self._traj_id = int(state_dict["traj_id"])
            self._begin(FORWARD, self._manual_reset())

    def shutdown(self, timeout: float | None = None, close_env: bool = True, raise_on_error: bool = True) -> None:
        if close_env and not self.env.is_closed:
            self.env.close(raise_if_closed=False)

    def update_policy_weights_(self, *args, **kwargs) -> None:
        """The policies are used in place: trained parameters are seen at the next step."""

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(env={type(self.env).__name__}, H_f={self.max_forward_steps}, "
            f"H_r={self.max_reset_steps}, frames={self._frames}, counters={self.counters})"
        )
