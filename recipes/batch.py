"""Several runs in one process: ``python recipes/train.py task=... algo=... seeds=5``.

S runs (seeds) of one task and algorithm advance in lockstep, one environment step each per
iteration, and their agents are updated together: one batched update call per agent type serves
every run whose agent updates at that step (:mod:`torchrl_reset.many`). Everything else is
each run's own, built exactly as for the run alone (:func:`single_run.build_run`): its environment and
collector (so its own phase, forward or reset, its own episode counters, trigger decisions, H_f / H_r
clocks, manual resets and success examples), its replay buffers, its random streams, its records
and its checkpoints in its own ``runs/<task>/<algo>/seed<k>`` folder. A run of the batch therefore
computes what the same seed computes alone, up to float32 rounding in the batched products
(``tests/test_batch.py``), and each run's folder is a complete single run: ``report.py`` reads it,
``resume`` continues it (alone or in a batch).
"""
from __future__ import annotations

import contextlib
import logging
import random
import signal
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf
from tensordict.utils import expand_as_right, expand_right
from torchrl.envs.utils import ExplorationType, exploration_type

from agents import reset_tau
from config_checks import ConfigError, validate
from learner import NonFiniteLoss, event_keys, restart_option
from reset_agents import reset_kind
from run_files import RunInterrupted, run_folder_lock, stop_on_signals
from single_run import TrainingDiverged, build_run, seed_process, set_up_process
from torchrl_reset import DualCollector
from torchrl_reset.accel import matmul_products
from torchrl_reset.many import RunDDPGUpdate

__all__ = ["batch_seeds", "batch_runs", "run_configs", "RunRNG", "BatchedUpdates", "train_batch"]

log = logging.getLogger("torchrl_reset.train")


def batch_seeds(cfg: DictConfig) -> list[int] | None:
    """``seeds``: null (one run, ``seed``), a count N (seeds ``seed .. seed + N - 1``) or a list of seeds."""
    seeds = OmegaConf.select(cfg, "seeds", default=None)
    if seeds is None:
        return None
    if isinstance(seeds, bool):
        raise ConfigError(f"seeds must be a count or a list of seeds, got {seeds!r}")
    if isinstance(seeds, int):
        if seeds < 1:
            raise ConfigError(f"seeds (a count) must be >= 1, got {seeds}")
        return list(range(int(cfg.seed), int(cfg.seed) + seeds))
    if OmegaConf.is_list(seeds) and seeds and all(isinstance(s, int) and not isinstance(s, bool) for s in seeds):
        if len(set(seeds)) != len(seeds):
            raise ConfigError(f"seeds lists a seed twice: {list(seeds)}")
        return [int(s) for s in seeds]
    raise ConfigError(f"seeds must be a count or a non-empty list of integer seeds, got {seeds!r}")


# what the batched updates share: runs of one batch must agree on these (any other setting may differ)
BATCHED_SETTINGS = ("task.name", "algo.name", "hidden_sizes", "gamma", "tau", "reset.tau", "forward.actor_lr",
                    "forward.critic_lr", "reset.actor_lr", "reset.critic_lr", "forward.batch_size", "reset.batch_size",
                    "algo.num_members", "algo.prior_scale", "algo.n_steps", "algo.clip_target_values", "device",
                    "threads", "speed")


# with speed.batched_acting the runs also share one collector over one env of S copies (and one noise process kind)
ACTING_SETTINGS = ("task.forward_horizon", "reset.max_steps", "reset.min_steps", "env", "exploration", "algo.threshold")


def batched_acting(cfg: DictConfig) -> bool:
    return bool(OmegaConf.select(cfg, "speed.batched_acting", default=False))


def batch_runs(cfg: DictConfig) -> list[tuple[int, object]] | None:
    """The runs of a batch as ``(seed, value)`` pairs, or None for one run.

    ``seeds`` (a count or a list) and ``vary`` with ``vary_values`` (a setting and its values, such as
    ``vary=task.p_thresh vary_values=[0.1,0.3]`` for Fig. 4): every value with every seed."""
    seeds = batch_seeds(cfg)
    key, values = OmegaConf.select(cfg, "vary", default=None), OmegaConf.select(cfg, "vary_values", default=None)
    if key is None:
        if values:
            raise ConfigError("vary_values needs vary=<the setting they are values of>")
        return None if seeds is None else [(seed, None) for seed in seeds]
    if OmegaConf.select(cfg, str(key), default="__missing__") == "__missing__":
        raise ConfigError(f"vary={key}: no such setting")
    if key in BATCHED_SETTINGS or str(key).split(".")[0] in ("speed", "seed", "seeds", "run_dir", "sweep_dir"):
        raise ConfigError(f"vary={key}: the runs of a batch share it; run separate batches (or a -m grid) over it")
    if not OmegaConf.is_list(values) or not values or len(set(map(str, values))) != len(values):
        raise ConfigError(f"vary_values must be a non-empty list of distinct values, got {values!r}")
    return [(seed, value) for value in values for seed in (seeds or [int(cfg.seed)])]


def run_configs(cfg: DictConfig, runs: list, *, check: bool = True) -> list[DictConfig]:
    """One configuration per run (``(seed, value)`` pairs, or seeds), each validated as a run alone (unless
    ``check=False``), with its own ``run_dir``."""
    key = OmegaConf.select(cfg, "vary", default=None)
    configs = []
    for run in runs:
        seed, value = run if isinstance(run, tuple) else (run, None)
        run_cfg = OmegaConf.create(OmegaConf.to_container(cfg, resolve=False))
        run_cfg.seed = seed
        run_cfg.seeds, run_cfg.vary, run_cfg.vary_values = None, None, None
        if value is not None:
            OmegaConf.update(run_cfg, str(key), value, merge=False)
        run_cfg.progress_bar = bool(cfg.progress_bar) and not configs  # one bar: the batch moves as one
        OmegaConf.resolve(run_cfg)
        configs.append(run_cfg)
    if not check:
        return configs
    folders = [str(Path(c.run_dir).resolve()) for c in configs]
    if len(set(folders)) != len(folders):
        varied = f" and ${{{key}}}" if key else ""
        raise ConfigError(f"the runs of a batch need one run_dir each; run_dir must contain ${{seed}}{varied} "
                          f"(it is {cfg._get_node('run_dir')._value()!r}).")
    problems = []
    if OmegaConf.select(cfg, "speed.compile", default=[]):
        problems.append("speed.compile is not available for a batch (its updates are batched functions)")
    if (cfg.get("env") or {}).get("backend", "sim") != "sim":
        problems.append("a batch runs simulated tasks only (one robot is one run)")
    for setting in BATCHED_SETTINGS:
        seen = {str(OmegaConf.select(c, setting, default=None)) for c in configs}
        if len(seen) > 1:
            problems.append(f"{setting} differs between the runs ({', '.join(sorted(seen))}): the batched updates share it")
    for setting in ACTING_SETTINGS if batched_acting(cfg) else ():
        seen = {str(OmegaConf.select(c, setting, default=None)) for c in configs}
        if len(seen) > 1:
            problems.append(f"{setting} differs between the runs ({', '.join(sorted(seen))}): with speed.batched_acting "
                            "the runs share one collector (speed.batched_acting=false lets it differ)")
    if problems:
        raise ConfigError("invalid configuration for a batch of runs:\n  - " + "\n  - ".join(problems))
    for run_cfg in configs:
        validate(run_cfg)
    return configs


class RunRNG:
    """A run's own random streams (torch's, numpy's and Python's global generators, and the current
    CUDA device's once CUDA is in use), swapped in while that run acts so that each run draws exactly
    the numbers it would draw alone."""

    def __init__(self) -> None:
        self.capture()

    def capture(self) -> None:
        self.torch, self.numpy, self.python = torch.get_rng_state(), np.random.get_state(), random.getstate()
        self.cuda = torch.cuda.get_rng_state() if torch.cuda.is_available() and torch.cuda.is_initialized() else None

    @contextlib.contextmanager
    def active(self) -> Iterator[None]:
        torch.set_rng_state(self.torch)
        np.random.set_state(self.numpy)
        random.setstate(self.python)
        if self.cuda is not None:
            torch.cuda.set_rng_state(self.cuda)
        try:
            yield
        finally:
            self.capture()


class BatchTiming:
    """Where a batch's wall time goes once every run's agents both update (after their heat-up and
    ``WARM_UP_UPDATES`` more steps of each phase, as a run's own ``step_seconds``): the aggregate rate
    and the cost per run-step outside the updates (env steps, policies, triggers, buffers, records)."""

    def __init__(self, runs: list, heat_up: int) -> None:
        from records import WARM_UP_UPDATES

        self.runs, self.after = runs, heat_up + WARM_UP_UPDATES
        self.iterations = self.run_steps = 0
        self.seconds = self.update_seconds = 0.0

    def steady(self) -> bool:
        return all(min(r.collector.counters["forward_steps"], r.collector.counters["reset_steps"]) > self.after
                   for r in self.runs)

    def add(self, seconds: float, update_seconds: float, run_steps: int) -> None:
        self.iterations += 1
        self.run_steps += run_steps
        self.seconds += seconds
        self.update_seconds += update_seconds

    def row(self) -> dict:
        measured = self.run_steps > 0
        return {
            "runs": len(self.runs), "seeds": [int(r.cfg.seed) for r in self.runs],
            "acting": "batched" if batched_acting(self.runs[0].cfg) else "per run",
            "steady_iterations": self.iterations,
            "run_steps_per_second": self.run_steps / self.seconds if measured else None,
            "update_ms_per_iteration": 1e3 * self.update_seconds / self.iterations if measured else None,
            "outside_updates_ms_per_run_step": 1e3 * (self.seconds - self.update_seconds) / self.run_steps if measured else None,
        }


class BatchedUpdates:
    """The S runs' forward agents and reset agents, each kind updated by one call per step."""

    def __init__(self, runs: list) -> None:
        cfg = runs[0].cfg
        self.runs = runs
        self.forward = RunDDPGUpdate([r.forward.loss for r in runs], [r.forward.optimizer for r in runs],
                                     gamma=float(cfg.gamma), tau=float(cfg.tau))
        self.reset = reset_kind(cfg).batched_update([r.reset.loss for r in runs], [r.reset.optimizer for r in runs],
                                                    cfg, reset_tau(cfg))
        self.precision = runs[0].matmul_precision
        self.release_order = runs[0].learner.release_order  # update_order: release (a batch's runs agree on it)
        self.seconds = 0.0  # spent in update calls (read by the loop's timing)
        for s, run in enumerate(runs):  # a checkpoint holds the run's own optimizer state, as a run alone's
            run.state.before_save = (lambda s=s: self.export(s))

    def export(self, run: int) -> None:
        self.forward.export(run)
        self.reset.export(run)

    def request(self, learner, phase: str) -> tuple:
        """A run's sample for its update of agent ``phase``, and with ``update_order: release`` the rows of it
        the actor's step uses (drawn with replacement), in the order a run alone draws them: call it in the
        run's own random stream."""
        sample = learner.sample(phase)  # replay rows (ours: + success examples; LNT: + reward)
        if not self.release_order:
            return sample, None
        return sample, torch.randint(sample.shape[0], (sample.shape[0],), device=sample.device)

    def apply(self, phase: str, requests: dict[int, tuple]) -> None:
        """One update of agent ``phase`` for the runs in ``requests`` (run index -> :meth:`request`'s pair)."""
        if not requests:
            return
        update = self.forward if phase == "forward" else self.reset
        runs = sorted(requests)
        started = time.perf_counter()
        with matmul_products(self.precision):
            try:
                losses = update.update([requests[s][0] for s in runs], runs,
                                       actor_rows=[requests[s][1] for s in runs] if self.release_order else None)
            except FloatingPointError as err:
                raise NonFiniteLoss(f"{phase} agent, {err}") from err
            if torch.cuda.is_available() and torch.cuda.is_initialized():
                torch.cuda.synchronize()  # the backward pass and the optimizer step are queued, not done
        self.seconds += time.perf_counter() - started
        values = {n: v.tolist() for n, v in losses.items()}  # one device-to-host copy per loss, not one per run
        for j, s in enumerate(runs):
            learner = self.runs[s].learner
            learner.record_losses(phase, {n: v[j] for n, v in values.items()})


def train_batch(cfg: DictConfig, runs: list) -> list[dict]:
    """Trains (or resumes) the runs (seeds, or :func:`batch_runs`'s pairs) together; returns their summaries. A
    signal that stops the batch (Ctrl-C, SIGTERM) raises :class:`RunInterrupted` once every run is checkpointed."""
    configs = run_configs(cfg, runs)
    with contextlib.ExitStack() as locks:
        for run_cfg in configs:
            Path(run_cfg.run_dir).mkdir(parents=True, exist_ok=True)
            locks.enter_context(run_folder_lock(Path(run_cfg.run_dir)))
        return _train_batch(configs)


class RowExploration:
    """The S runs' exploration on one batch of S rows: row ``s`` gets run ``s``'s own noise module (its
    Ornstein-Uhlenbeck process), drawn from run ``s``'s random stream, for the rows the policy acts for
    (the collector's ``"_acting"`` mask) only; so each run draws the numbers it draws alone.

    When every run's noise is a torchrl ``OrnsteinUhlenbeckProcessModule`` with the same process settings
    (a batch's runs agree on ``exploration``), the acting rows advance as one vector step of that module's
    update (``prev + theta (mu - prev) dt + sigma_t sqrt(dt) N(0, 1)``, the action moved by ``eps`` times
    it and clamped into the action's box as the module's safe mode does), each row's normal draws taken
    from its run's stream: the same numbers, bit for bit, as each module called on its own row
    (``tests/test_batch.py``), without one module call per row. Otherwise each row calls its run's module."""

    def __init__(self, policy, noises: list, streams: list[RunRNG]) -> None:
        self.policy, self.noises, self.streams = policy, noises, streams
        self.process = _shared_ou(noises)  # None: one module call per row

    def __call__(self, td):
        td = self.policy(td)
        rows = td.get("_acting").nonzero().flatten().tolist()
        if not rows:
            return td
        if self.process is not None:
            return self._vector(td, rows)
        outputs = []
        for s in rows:
            with self.streams[s].active():
                outputs.append(self.noises[s](td[s]))
        for key in outputs[0].keys(True, True):
            if key == "_acting":
                continue
            _merge(td, key, rows, torch.stack([out.get(key) for out in outputs]))
        return td

    def _vector(self, td, rows: list[int]):
        if exploration_type() not in (ExplorationType.RANDOM, None):
            return td  # the module adds noise only when exploring
        module = self.noises[0]
        ou, low, high = module.ou, *self.process
        index = torch.tensor(rows)
        action = td.get(ou.key)
        if ou.steps_key in td.keys():
            prev, steps = td.get(ou.noise_key)[index], td.get(ou.steps_key)[index]
        else:  # the module's first call: a zero process at step 0
            prev = torch.zeros((len(rows), *action.shape[1:]), device=action.device)
            steps = torch.zeros(len(rows), dtype=torch.long, device=action.device)
        is_init = td.get(module.is_init_key, None)
        if is_init is not None:
            is_init = is_init[index]
            if is_init.ndim > 1 and is_init.shape[-1] == 1:
                is_init = is_init.squeeze(-1)
            prev = torch.masked_fill(prev, expand_right(is_init, prev.shape), 0)
            steps = torch.masked_fill(steps, expand_right(is_init, steps.shape), 0)
        draws = []
        for j, s in enumerate(rows):
            with self.streams[s].active():
                draws.append(torch.randn_like(prev[j]))
        prev = prev + ou.x0
        noise = (prev + ou.theta * (ou.mu - prev) * ou.dt
                 + ou.current_sigma(expand_as_right(steps, prev)) * np.sqrt(ou.dt) * torch.stack(draws))
        eps = torch.stack([self.noises[s].eps for s in rows]).to(noise.device).reshape(-1, *([1] * (noise.ndim - 1)))
        moved = action[index] + eps * noise
        if low is not None:
            moved = torch.clamp(moved, low.expand_as(moved), high.expand_as(moved))
        _merge(td, ou.noise_key, rows, noise - ou.x0)
        _merge(td, ou.key, rows, moved)
        _merge(td, ou.steps_key, rows, steps + 1)
        return td


def _merge(td, key, rows: list[int], value: torch.Tensor) -> None:
    """Sets ``value`` (one row per acting row) into ``td[key]``; the other rows keep theirs (zeros if new)."""
    full = td.get(key, None)
    full = (torch.zeros((td.shape[0], *value.shape[1:]), dtype=value.dtype, device=value.device)
            if full is None else full.clone())
    full[rows] = value.to(full.dtype)
    td.set(key, full)


def _shared_ou(noises: list):
    """``(low, high)`` of the action box (``(None, None)`` if unsafe) when all ``noises`` are torchrl OU modules
    with one process setting and one action box, else None."""
    from torchrl.data import Bounded
    from torchrl.modules import OrnsteinUhlenbeckProcessModule

    if not noises or not all(type(n) is OrnsteinUhlenbeckProcessModule for n in noises):
        return None

    def setting(n):
        ou = n.ou
        return (ou.theta, ou.mu, ou.sigma, ou.dt, ou.x0, ou.m, ou.c, ou.sigma_min, ou.key, n.is_init_key,
                ou.noise_key, ou.steps_key, bool(n.safe))

    first = noises[0]
    if any(not isinstance(v, float) for v in setting(first)[:8]) or any(setting(n) != setting(first) for n in noises):
        return None
    if not first.safe:
        return None, None
    spec = first.spec[first.ou.key]
    if not isinstance(spec, Bounded) or spec.dtype != torch.float32:
        return None
    low, high = spec.space.low, spec.space.high
    for n in noises[1:]:
        other = n.spec[first.ou.key]
        if not isinstance(other, Bounded) or not (torch.equal(other.space.low, low) and torch.equal(other.space.high, high)):
            return None
    return low, high


def batched_collector(runs: list, updates: BatchedUpdates, streams: list[RunRNG]):
    """One :class:`~torchrl_reset.many.BatchedDualCollector` for the S runs (``speed.batched_acting``): one env of S
    copies, row ``s`` seeded as run ``s``'s env, the runs' policies and trigger ensembles acting as one (the
    batched updates' own parameter stacks), each run's exploration on its row. Each run then collects through
    its copy, loaded from its own collector (fresh, or resumed from its checkpoint)."""
    from agents import make_trigger
    from config_checks import reset_horizon
    from torchrl.envs import TransformedEnv
    from torchrl_reset.many import BatchedDualCollector
    from torchrl_reset_envs import BatchedTaskEnv

    cfg = runs[0].cfg
    env = BatchedTaskEnv(cfg.task.name, seeds=[int(r.cfg.seed) for r in runs], device=cfg.device,
                         **(OmegaConf.to_container(cfg.env, resolve=True) if cfg.get("env") else {}))
    thresholds = [float(r.trigger.threshold) for r in runs]
    trigger = make_trigger(cfg, runs[0].reset, model=updates.reset.ensembles.module(),
                           threshold=thresholds[0] if len(set(thresholds)) == 1 else thresholds, rows=True)
    env = TransformedEnv(env, trigger)

    def policy(agent_updates, phase: str):
        noises = [getattr(r.collector, f"{phase}_policy")[-1] for r in runs]  # each run's OU module
        return RowExploration(agent_updates.policies.module(), noises, streams)

    collector = BatchedDualCollector(
        env, policy(updates.forward, "forward"), policy(updates.reset, "reset"),
        max_forward_steps=int(cfg.task.forward_horizon), max_reset_steps=reset_horizon(cfg),
        min_reset_steps=int(cfg.reset.min_steps), max_frames_per_env=[int(r.cfg.total_steps) for r in runs],
        example_buffers=[r.collector.example_buffer for r in runs], event_keys=event_keys(env), **restart_option(cfg))
    for s, run in enumerate(runs):
        with streams[s].active():
            collector.view(s).load_state_dict(run.collector.state_dict())
        run.adopt(collector.view(s))
    return collector


def _per_run_steps(runs: list, streams: list[RunRNG]):
    """Each iteration, one step of every run still going, from its own collector: ``[(run, step, phase)]``."""
    steps = [iter(run.collector) for run in runs]
    done = [False] * len(runs)
    while not all(done):
        stepped = []
        for s, run in enumerate(runs):
            if done[s]:
                continue
            with streams[s].active():
                batch = next(steps[s], None)
            if batch is None:
                done[s] = True
                continue
            stepped.append((s, batch.to(run.cfg.device), DualCollector.phase_of(batch)))
        if stepped:
            yield stepped


def _batched_steps(collector, runs: list):
    """Each iteration of the batch's one collector, its executed steps split by run: ``[(run, step, phase)]``."""
    for batch in collector:
        stepped = []
        for j, s in enumerate(batch.get(("collector", "env_ids")).tolist()):
            step = batch[j:j + 1].to(runs[s].cfg.device)  # as a run's own collector yields it: batch [1]
            stepped.append((s, step, DualCollector.phase_of(step)))
        yield stepped


def _train_batch(configs: list[DictConfig]) -> list[dict]:

    precision = set_up_process(configs[0])
    runs, streams = [], []
    for run_cfg in configs:
        # each run is built from its own seed, in the order a run alone draws its random numbers
        seed_process(int(run_cfg.seed))
        runs.append(build_run(run_cfg, precision))
        streams.append(RunRNG())
    updates = BatchedUpdates(runs)
    shared = batched_collector(runs, updates, streams) if batched_acting(configs[0]) else None
    timing = BatchTiming(runs, int(configs[0].heat_up))
    # lines 5-15 / 17-22 of each run: its own env step (from its own collector, or its row of the shared one)
    iterations = _per_run_steps(runs, streams) if shared is None else _batched_steps(shared, runs)
    stopped_by = None  # the signal (SIGINT, SIGTERM) that ends the batch after its current iteration
    try:
        with stop_on_signals() as stop_requested:
            started = time.perf_counter()
            for stepped in iterations:
                steady, in_updates = timing.steady(), updates.seconds
                requests = {"forward": {}, "reset": {}}
                for s, batch, phase in stepped:
                    with streams[s].active():
                        learner = runs[s].learner
                        learner.store(batch, phase)
                        if learner.updating(phase):
                            requests[phase][s] = updates.request(learner, phase)  # from its own stream
                for phase in ("forward", "reset"):  # lines 16 / 23 of every run, one call per agent type
                    updates.apply(phase, requests[phase])
                for s, batch, phase in stepped:
                    with streams[s].active():
                        runs[s].after_step(batch, phase)
                now = time.perf_counter()
                if steady:  # the iteration's time from the end of the previous one (its env steps included)
                    timing.add(now - started, updates.seconds - in_updates, len(stepped))
                started = now
                if stop_requested:
                    stopped_by = stop_requested[0]
                    log.warning("%s at step %d: checkpointing the batch", signal.Signals(stopped_by).name,
                                max(r.collector.frames for r in runs))
                    break
    except KeyboardInterrupt:  # a second Ctrl-C: the iteration under way was cut short, its state is not saved
        raise RunInterrupted(signal.SIGINT, [], "stopped at once, without a checkpoint of the iteration under way; "
                                                "each run's last checkpoint stands") from None
    except NonFiniteLoss as err:
        paths = [str(run.state.save()) for run in runs]  # the update stopped before it changed anything
        raise TrainingDiverged(f"non-finite loss ({err}); every run's last good state is checkpointed "
                                     f"({', '.join(paths)}). Lower the learning rates or check the inputs.") from err
    finally:
        for run in runs:
            run.record.close()
    summaries = []
    for s, run in enumerate(runs):
        with streams[s].active():
            summaries.append(run.finish(stopped_by is not None, extra={"batch": timing.row()}))
    if shared is not None:
        shared.shutdown()
    if stopped_by is not None:
        steps = ", ".join(str(summary["steps"]) for summary in summaries)
        raise RunInterrupted(stopped_by, summaries, f"{signal.Signals(stopped_by).name} stopped the batch at steps "
                                                    f"{steps}, each run checkpointed there")
    return summaries
