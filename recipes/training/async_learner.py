"""``learner.mode=async``: the learner in a process of its own, beside the robot's control loop.

The actor process (the run's own: the environment with its safety filter, the dual collector, the trigger, the
exploration, the example buffer) acts; the learner process holds both replay buffers and both agents' losses
and optimizers, and makes Algorithm 1's updates. What passes between them:

- actor -> learner, a ``torch.multiprocessing`` queue: each collected step with its phase, and the initial
  states added to the example buffer since the last one (the learner keeps a mirror of it, so that its
  examples are the actor's); checkpoint and stop requests;
- learner -> actor, shared memory (:class:`SharedWeights`): the weights of the forward actor, the reset actor
  and the reset model (its trained members and its fixed priors: one publication, so the trigger and the reset
  policy always come from the same update), versioned by the number of steps the learner has processed; the
  priors' digest is checked once at the start. A queue carries the learner's losses, update counts, errors and
  acknowledgements.

The two weight schemes of ``torchrl.weight_update`` move one policy's weights; here three modules must change
together with a version the actor can wait for, so the weights live in one block of shared tensors under a lock.

Algorithm 1's update count is kept, late: the learner takes the steps in the order they were collected and makes,
for each, the updates that step owes (one per step of its phase past heat-up), sampling its buffers as they stood
after that step, as the single process does. Only the weights the actor acts with lag behind. ``learner.max_lag``
bounds the lag (steps the learner has not processed): past it, the actor waits at the next episode boundary
(the arm still) until the learner catches up; ``max_lag: 0`` is lockstep (the actor waits after every step), which
gives exactly the counters and losses of ``learner.mode=sync`` with ``learner.streams=separate``.
"""
from __future__ import annotations

import hashlib
import logging
import queue as queue_module
import signal
import time
import traceback
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace

import torch
import torch.multiprocessing as mp
from omegaconf import DictConfig, OmegaConf

from torchrl_reset import DualCollector, InitialStateBuffer
from torchrl_reset_recipes.training.learner import updates_achieved

__all__ = ["LearnerFailed", "SharedWeights", "AsyncLearner", "learner_main", "next_message", "LEARNER_FILE"]

log = logging.getLogger("torchrl_reset.train")

#: the learner's part of a checkpoint (its losses, optimizers, example mirror and counts; the buffers beside it)
LEARNER_FILE = "learner.pt"
POLL = 0.0005  # seconds between two looks at the learner while the actor waits for it
ACTOR_CHECK = 1.0  # seconds the idle learner waits for a message before it looks whether its actor still lives


class LearnerFailed(RuntimeError):
    """The learner process crashed, hung or refused the actor's weights; the last checkpoint stands."""


def weight_modules(forward, reset) -> dict[str, torch.nn.Module]:
    """The modules whose weights the learner publishes: the forward actor, the reset actor, the reset model."""
    return {"forward_actor": forward.actor, "reset_actor": reset.actor, "reset_model": reset.model}


def _priors(state: dict) -> dict:
    return {k: v for k, v in state.items() if "prior" in k}


def digest(tensors: dict) -> str:
    """A digest of named tensors (their names, shapes and bytes)."""
    h = hashlib.sha256()
    for name in sorted(tensors):
        value = tensors[name].detach().cpu().contiguous()
        h.update(name.encode())
        h.update(str(tuple(value.shape)).encode())
        h.update(value.numpy().tobytes())
    return h.hexdigest()


class SharedWeights:
    """Versioned weights in shared memory: :meth:`publish` (the learner) and :meth:`load` (the actor, between
    steps) copy whole modules' states under one lock, so a load never mixes two publications. The reset model's
    fixed priors are the actor's, shared once: a publication leaves them out, and a learner whose priors differ is
    refused (:meth:`check_priors`)."""

    def __init__(self, ctx, modules: dict[str, torch.nn.Module]) -> None:
        self.tensors = {name: {k: v.detach().clone().share_memory_() for k, v in module.state_dict().items()}
                        for name, module in modules.items()}
        self.version = ctx.Value("q", -1, lock=False)
        self.lock = ctx.Lock()

    def layout(self) -> dict:
        return {name: {k: tuple(v.shape) for k, v in state.items()} for name, state in self.tensors.items()}

    def publish(self, modules: dict[str, torch.nn.Module], version: int) -> None:
        with self.lock:
            for name, module in modules.items():
                state = module.state_dict()
                if set(state) != set(self.tensors[name]):
                    raise LearnerFailed(f"the learner's {name} has entries {sorted(set(state) ^ set(self.tensors[name]))} "
                                        "that the actor's layout does not: refused")
                for key, value in state.items():
                    if not (name == "reset_model" and "prior" in key):  # fixed priors: shared once, by the actor
                        self.tensors[name][key].copy_(value)
            self.version.value = version

    def load(self, modules: dict[str, torch.nn.Module]) -> int:
        with self.lock, torch.no_grad():
            for name, module in modules.items():
                module.load_state_dict(self.tensors[name])
            return int(self.version.value)

    def prior_digest(self) -> str:
        return digest(_priors(self.tensors["reset_model"]))

    def check_priors(self, modules: dict[str, torch.nn.Module]) -> None:
        """Refuses a learner whose reset model has other fixed priors than the actor's (by digest)."""
        if self.prior_digest() != digest(_priors(modules["reset_model"].state_dict())):
            raise LearnerFailed("the learner's reset model has other priors than the actor's: refused")


# ------------------------------------------------------------------------------------------------ learner
def learner_main(cfg_yaml: str, weights: SharedWeights, inbox, outbox, resume_from: str | None,
                 example_keys: list, example_size: int) -> None:
    """The learner process: builds both agents and buffers as the run does, then serves the actor's messages."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the actor stops the run: it checkpoints, then sends "stop"
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    try:
        _serve(OmegaConf.create(cfg_yaml), weights, inbox, outbox, resume_from, example_keys, example_size)
    except BaseException as err:  # noqa: BLE001: every failure goes back to the actor, then the process ends
        outbox.put(("error", f"{type(err).__name__}: {err}\n{traceback.format_exc()}"))
        raise


def _serve(cfg: DictConfig, weights, inbox, outbox, resume_from, example_keys, example_size) -> None:
    from torchrl_reset_recipes.training.agents import make_forward_agent, make_reset_agent
    from torchrl_reset_recipes.training.buffers import make_buffers
    from torchrl_reset_recipes.training.learner import Learner
    from torchrl_reset_recipes.training.run_spec import run_spec
    from torchrl_reset_recipes.training.single_run import set_up_process
    from torchrl_reset_recipes.training.streams import RandomStreams
    from torchrl_reset_recipes.training.task_envs import task_dimensions
    from torchrl_reset_recipes.training.updates import learn_step
    from torchrl_reset_recipes.training.records import diagnostic_probe
    from torchrl_reset_recipes.training.checkpoints import dump_buffer, owned_state

    spec = run_spec(cfg, check=False)
    precision = set_up_process(spec)  # the seeds as the actor's process had them: the same initial networks
    obs_dim, action_spec = task_dimensions(cfg)
    forward = make_forward_agent(spec, obs_dim, action_spec)
    reset = make_reset_agent(spec, obs_dim, action_spec)
    forward_rb, reset_rb = make_buffers(spec)
    examples = InitialStateBuffer(state_keys=example_keys, max_size=example_size)  # the actor's, mirrored
    collector = SimpleNamespace(counters={"forward_steps": 0, "reset_steps": 0}, example_buffer=examples)
    learner = Learner(spec, forward, reset, forward_rb, reset_rb, collector, precision)
    streams = RandomStreams("separate", int(cfg.seed))
    modules = weight_modules(forward, reset)
    processed = 0
    if resume_from is not None:
        state = torch.load(Path(resume_from) / LEARNER_FILE, weights_only=False)
        forward.loss.load_state_dict(state["forward_loss"])
        reset.loss.load_state_dict(state["reset_loss"])
        forward.optimizer.load_state_dict(state["forward_optimizer"])
        reset.optimizer.load_state_dict(state["reset_optimizer"])
        examples.load_state_dict(state["examples"])
        collector.counters.update(state["counters"])
        learner.updates.update(state["updates"])
        learner.last_losses.update(state["last_losses"])
        streams.load_state_dict(state["streams"])
        processed = int(state["processed"])
        for name, rb in (("forward_buffer", forward_rb), ("reset_buffer", reset_rb)):
            if (Path(resume_from) / name).exists():
                rb.loads(Path(resume_from) / name)
    weights.check_priors(modules)
    weights.publish(modules, processed)
    outbox.put(("ready", processed))
    actor = mp.parent_process()
    with streams.use("learner"):
        while True:
            message = next_message(inbox, actor.is_alive)
            if message is None:  # the actor is gone (killed, crashed): nothing will come, nothing to save
                return
            kind = message[0]
            if kind == "step":
                _, batch, phase, new_examples = message
                for state in new_examples:
                    examples.add(state)
                collector.counters[f"{phase}_steps"] += batch.numel()
                learn_step(learner, batch, phase)
                processed += 1
                weights.publish(modules, processed)  # then its progress: the actor waits for that message
                outbox.put(("progress", processed, dict(learner.last_losses), dict(learner.updates)))
            elif kind == "probe":  # diagnostics.csv's probe, on the buffers as they stand after the steps before it
                outbox.put(("probe", processed, diagnostic_probe(spec, learner, examples, spec.trigger_threshold,
                                                                 processed)))
            elif kind == "checkpoint":
                folder = Path(message[1])
                torch.save({"forward_loss": owned_state(forward.loss.state_dict()), "reset_loss": owned_state(reset.loss.state_dict()),
                            "forward_optimizer": forward.optimizer.state_dict(),
                            "reset_optimizer": reset.optimizer.state_dict(), "examples": examples.state_dict(),
                            "counters": dict(collector.counters), "updates": dict(learner.updates),
                            "last_losses": dict(learner.last_losses), "streams": streams.state_dict(),
                            "processed": processed}, folder / LEARNER_FILE)
                for name, rb in (("forward_buffer", forward_rb), ("reset_buffer", reset_rb)):
                    if len(rb):
                        dump_buffer(rb, folder / name)
                outbox.put(("checkpointed", processed))
            elif kind == "stop":
                outbox.put(("stopped", processed))
                return
            elif kind == "fail":  # tests: a learner that crashes in the middle of a run
                raise RuntimeError("the learner was asked to fail (a test)")
            elif kind == "hang":  # tests: a learner that stops answering
                time.sleep(float(message[1]))


def next_message(inbox, actor_alive, wait: float = ACTOR_CHECK):
    """The actor's next message, or None once the actor process has ended without a word (kill -9, a crash):
    the learner does not outlive it, holding the buffers and the shared weights' memory."""
    while True:
        try:
            return inbox.get(timeout=wait)
        except queue_module.Empty:
            if not actor_alive():
                return None


# ------------------------------------------------------------------------------------------------ actor side
@dataclass
class LagStats:
    """The lag in steps (sent, not yet processed by the learner) and the age of the weights in use (steps since
    the step they were published after), sampled at every step; the queue's depth."""

    count: int = 0
    lag_sum: float = 0.0
    lag_max: int = 0
    age_sum: float = 0.0
    age_max: int = 0
    depth_sum: float = 0.0
    depth_max: int = 0
    waits: int = 0
    wait_seconds: float = 0.0

    def add(self, lag: int, age: int, depth: int) -> None:
        self.count += 1
        self.lag_sum += lag
        self.lag_max = max(self.lag_max, lag)
        self.age_sum += age
        self.age_max = max(self.age_max, age)
        self.depth_sum += depth
        self.depth_max = max(self.depth_max, depth)

    def summary(self) -> dict:
        n = max(self.count, 1)
        return {"lag_steps": {"mean": self.lag_sum / n, "max": self.lag_max},
                "weight_age_steps": {"mean": self.age_sum / n, "max": self.age_max},
                "queue_depth": {"mean": self.depth_sum / n, "max": self.depth_max},
                "boundary_waits": self.waits, "boundary_wait_seconds": round(self.wait_seconds, 3)}

    def fields(self) -> dict:
        """``progress.csv``'s learner columns (:data:`~.learner.LEARNER_FIELDS`) over these samples."""
        n = max(self.count, 1)
        return {"learner_lag_mean": self.lag_sum / n, "learner_lag_max": self.lag_max,
                "weight_age_mean": self.age_sum / n, "queue_depth_max": self.depth_max,
                "boundary_wait_seconds": round(self.wait_seconds, 3)}




class AsyncLearner:
    """The actor's side of ``learner.mode=async``: it starts the learner process, sends each step and the new
    success examples, loads the newest weights between steps, waits where ``learner.max_lag`` says, and watches
    the learner (its exit, its progress). It offers what the run's records read of a learner (``updates``,
    ``last_losses``, ``budget``, :meth:`updates_achieved`)."""

    def __init__(self, spec, forward, reset, collector: DualCollector, resume_from: str | None, *,
                 updates: dict, last_losses: dict, robot=None) -> None:
        cfg = spec.cfg
        self.spec, self.collector, self.robot = spec, collector, robot
        self.max_lag = int(spec["learner.max_lag"])
        self.timeout = float(spec["learner.timeout"])
        self.heat_up = int(cfg.heat_up)
        self.modules = weight_modules(forward, reset)
        ctx = mp.get_context("spawn")
        self.weights = SharedWeights(ctx, self.modules)
        self.inbox, self.outbox = ctx.Queue(), ctx.Queue()
        self.process = ctx.Process(target=learner_main, name="learner", daemon=True,
                                   args=(OmegaConf.to_yaml(cfg, resolve=True), self.weights, self.inbox, self.outbox,
                                         resume_from, list(collector.example_buffer.state_keys),
                                         int(collector.example_buffer.max_size)))
        self.sent = 0
        self.unresponsive = False  # the learner let a wait for it time out: close() ends it without asking
        self.processed = 0  # the steps the learner reported processed (its progress messages)
        self.loaded = -1
        self.updates, self.last_losses = updates, last_losses  # the run's history's: kept across a resume
        self.budget = SimpleNamespace(skipped=0)
        self.stats = LagStats()
        self.window = LagStats()  # since the last progress.csv row
        self.achieved_at_end: dict | None = None
        self._pending_examples: list = []
        self._probe_callbacks: list = []  # the diagnostics rows waiting for the learner's probe, in order
        original_add = collector.example_buffer.add

        def add(state, _original=original_add):
            self._pending_examples.append(state.clone())
            _original(state)

        collector.example_buffer.add = add
        self.process.start()
        kind, processed = self._next_message(self.timeout + 120, waiting_for="the learner to start")
        if kind != "ready":
            raise LearnerFailed(f"the learner answered {kind!r} instead of starting")
        self.sent = self.processed = processed
        self._load()

    # -- what the records read --------------------------------------------------------------------
    def updates_achieved(self) -> dict[str, float | None]:
        return updates_achieved(self.updates, self.collector.counters, self.heat_up)

    # -- the loop ---------------------------------------------------------------------------------
    def send(self, batch, phase: str) -> None:
        """Sends a collected step (and the examples added since the last) to the learner."""
        examples, self._pending_examples = self._pending_examples, []
        self.inbox.put(("step", batch.detach().cpu(), phase, examples))
        self.sent += 1

    def after_step(self, episode_ended: bool, halted: bool = False) -> None:
        """Between steps: the newest weights; with ``max_lag: 0`` after the learner processed this very step; else
        at an episode's end once the lag is within ``max_lag``. After a step the robot halted in (a protective stop)
        the actor handles the stop alone: no wait and no weights until the arm is home again (the next step)."""
        self._drain_outbox()
        if halted and self.max_lag > 0:
            self._check_alive()
            self._sample()
            return
        if self.max_lag == 0:
            self._wait_until(self.sent, "lockstep")
        elif episode_ended and self.sent - self.processed > self.max_lag:
            started = time.monotonic()
            if self.robot is not None:  # the arm held still while the actor waits: no overrun
                self.robot.hold()
            self._wait_until(self.sent - self.max_lag, "the lag to come back within learner.max_lag")
            for stats in (self.stats, self.window):
                stats.waits += 1
                stats.wait_seconds += time.monotonic() - started
        self._check_alive()
        if int(self.weights.version.value) > self.loaded:
            self._load()
        self._sample()

    def request_probe(self, callback) -> None:
        """``diagnostics.csv``'s probe at this step, computed by the learner on its buffers as they stand after
        this step; ``callback(probe)`` writes the row when the answer comes (in order; every one by :meth:`drain`)."""
        self._probe_callbacks.append(callback)
        self.inbox.put(("probe",))

    def drain(self) -> None:
        """Waits until the learner has processed every step sent (its late updates included)."""
        self._wait_until(self.sent, "the learner to work off its updates")
        self._drain_outbox()
        self._load()

    def checkpoint(self, folder: Path) -> None:
        """The learner's part of a checkpoint, written into ``folder`` once it has caught up."""
        self.drain()
        self.inbox.put(("checkpoint", str(folder)))
        kind, _ = self._next_message(self.timeout, waiting_for="the learner's checkpoint")
        if kind != "checkpointed":
            raise LearnerFailed(f"the learner answered {kind!r} to a checkpoint")

    def close(self) -> None:
        """Stops the learner (after its last message) and waits for the process to end; a learner that already let a
        wait time out (hung) is ended at once, not asked and waited for again. Ended means killed: the learner
        ignores SIGTERM (the actor stops the run, checkpointing first), so ``terminate`` would not end it."""
        if self.process.is_alive() and not self.unresponsive:
            self.inbox.put(("stop",))
            try:
                self._next_message(self.timeout, waiting_for="the learner to stop")
            except LearnerFailed:  # hung or gone: it is ended below
                pass
            self.process.join(timeout=2)
        if self.process.is_alive():
            self.process.kill()
            self.process.join(timeout=5)

    def stats_summary(self) -> dict:
        return {"mode": "async", "max_lag": self.max_lag, **self.stats.summary(),
                "updates_achieved_when_acting_ended": self.achieved_at_end}

    def take_window(self) -> dict:
        """The learner columns of ``progress.csv`` since the last call (:data:`~.learner.LEARNER_FIELDS`); a new
        window starts."""
        fields, self.window = self.window.fields(), LagStats()
        return fields

    # -- internals --------------------------------------------------------------------------------
    def _sample(self) -> None:
        lag, age, depth = self.sent - self.processed, self.sent - self.loaded, self._depth()
        self.stats.add(lag, age, depth)
        self.window.add(lag, age, depth)

    def _depth(self) -> int:
        try:
            return int(self.inbox.qsize())
        except NotImplementedError:  # macOS
            return -1

    def _load(self) -> None:
        self.loaded = self.weights.load(self.modules)

    def _drain_outbox(self) -> None:
        while True:
            try:
                message = self.outbox.get_nowait()
            except queue_module.Empty:
                return
            self._handle(message)

    def _handle(self, message) -> tuple[str, int]:
        kind = message[0]
        if kind == "error":
            raise LearnerFailed(f"the learner process failed:\n{message[1]}")
        if kind == "probe":
            self._probe_callbacks.pop(0)(message[2])
            return kind, message[1]
        if kind == "progress":
            _, processed, losses, updates = message
            self.processed = processed
            self.last_losses.update(losses)
            self.updates.update(updates)
            return kind, processed
        return kind, message[1]

    def _next_message(self, timeout: float, *, waiting_for: str) -> tuple[str, int]:
        deadline = time.monotonic() + timeout
        while True:
            try:
                message = self.outbox.get(timeout=0.05)
            except queue_module.Empty:
                self._check_alive()
                self._idle()
                if time.monotonic() > deadline:
                    self.unresponsive = True
                    raise LearnerFailed(f"no answer from the learner in {timeout:.0f} s while waiting for {waiting_for}")
                continue
            kind, value = self._handle(message)
            if kind not in ("progress", "probe"):
                return kind, value

    def _wait_until(self, processed: int, why: str) -> None:
        """Until the learner reports ``processed`` steps done (its progress message follows its weights); a learner
        that reports nothing for ``learner.timeout`` seconds meanwhile counts as hung."""
        last_change = time.monotonic()
        while self.processed < processed:
            try:
                message = self.outbox.get(timeout=0.05)
            except queue_module.Empty:
                self._check_alive()
                self._idle()
                if time.monotonic() - last_change > self.timeout:
                    self.unresponsive = True
                    raise LearnerFailed(f"the learner made no progress for {self.timeout:g} s while the actor waited "
                                        f"for {why} (processed {self.processed} of {self.sent} steps): hung")
                continue
            self._handle(message)
            last_change = time.monotonic()

    def _idle(self) -> None:
        if self.robot is not None:  # the wall-clock twin simulates the (held) arm as the wait goes
            self.robot.idle()

    def _check_alive(self) -> None:
        if not self.process.is_alive():
            self._drain_outbox()  # its error message, if it sent one
            raise LearnerFailed(f"the learner process ended (exit code {self.process.exitcode}) with "
                                f"{self.sent - self.processed} steps not processed")
