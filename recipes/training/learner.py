"""The recipe's collector and learner: Algorithm 1's "save transition and update" for both agents.

``make_collector`` builds the :class:`~torchrl_reset.DualCollector` (Algorithm 1's two inner loops);
:class:`Learner` holds each phase's replay buffer and what an update needs around it (lines 16 and 23);
the update itself, loss, backward, optimizer step and target update, is written out in ``recipes/train.py``.
"""
from __future__ import annotations

import contextlib
import time

import torch

from torchrl_reset_recipes.training.agents import Agent, with_exploration
from torchrl_reset_recipes.training.buffers import buffer_keys
from torchrl_reset_recipes.training.run_spec import RunSpec
from torchrl_reset_recipes.training.task_envs import UpdateBudget
from torchrl_reset import DualCollector
from torchrl_reset.accel import matmul_products

__all__ = ["make_collector", "Learner", "NonFiniteLoss", "updates_achieved", "LEARNER_FIELDS", "learner_fields"]


def make_collector(spec: RunSpec, env, forward: Agent, reset: Agent) -> DualCollector:
    """Forward and reset episodes over ``env``, with the paper's OU exploration on both policies."""
    cfg = spec.cfg
    collector = DualCollector(
        env,
        with_exploration(forward.actor, env.action_spec, spec, forward.head),
        with_exploration(reset.actor, env.action_spec, spec, reset.head),
        max_forward_steps=spec.forward_horizon,   # H_f
        max_reset_steps=spec.reset_horizon,       # H_r
        min_reset_steps=int(cfg.reset.min_steps),
        total_frames=int(cfg.total_steps),
        event_keys=event_keys(env),
        **restart_option(spec),
    )
    collector.set_seed(int(cfg.seed))
    return collector


def event_keys(env) -> list[str]:
    """What each episode record copies beside the observation, where the env has it: its latched ``irrecoverable``
    flag (the records say whether a triggered state, or the state a reset episode ended in, was already lost)
    and its at-initial-state check ``reset_success`` (whether a triggered state already counted as the start)."""
    return [key for key in ("irrecoverable", "reset_success") if key in env.full_observation_spec.keys(True, True)]


def restart_option(spec: RunSpec) -> dict:
    """The collector's ``restart_exploration`` from ``exploration.restart`` (configs without it: ``episode``)."""
    return {} if spec["exploration.restart"] == "episode" else {"restart_exploration": False}


#: ``progress.csv``'s learner columns, over each log window: the lag (steps sent, not yet learnt from), the age of the
#: weights in use (steps), the queue's deepest and the seconds the actor waited at episode boundaries; all 0 in sync
LEARNER_FIELDS = ("learner_lag_mean", "learner_lag_max", "weight_age_mean", "queue_depth_max", "boundary_wait_seconds")


def learner_fields(learner) -> dict:
    """The learner columns of a ``progress.csv`` row since the last: the async learner's window, else zeros."""
    window = getattr(learner, "take_window", None)
    if window is not None:
        return window()
    return {"learner_lag_mean": 0.0, "learner_lag_max": 0, "weight_age_mean": 0.0, "queue_depth_max": 0,
            "boundary_wait_seconds": 0.0}  # one process: never behind, the weights always the newest


def updates_achieved(updates: dict, counters: dict, heat_up: int) -> dict[str, float | None]:
    """Per agent, its ``updates`` as a fraction of Algorithm 1's count, one update per step of its phase past
    ``heat_up`` (``counters``: the collector's); None while none is owed."""
    owed = {phase: max(0, int(counters[f"{phase}_steps"]) - heat_up) for phase in ("forward", "reset")}
    return {phase: (updates[phase] / owed[phase] if owed[phase] else None) for phase in owed}


class NonFiniteLoss(RuntimeError):
    """A loss came out NaN or infinite; no parameter was changed by it."""


class Learner:
    """Each phase's replay buffer and what its agent's update needs around it (the update itself is written
    out in ``recipes/train.py``): storing a collected step, whether the agent updates at this step, a
    completed sample, the update's timing and its losses.

    Each agent updates once per step of its own phase, after ``heat_up`` steps of it; on a real-time
    robot only when the update fits in what is left of the control period (:class:`UpdateBudget`).
    The updates run with the CPU product precision the run chose (``speed.matmul_precision``) and,
    for the agents named in ``speed.compile``, through ``torch.compile`` (``losses``).
    """

    def __init__(self, spec: RunSpec, forward: Agent, reset: Agent, forward_rb, reset_rb, collector: DualCollector,
                 matmul_precision: str, robot=None, *, last_losses: dict | None = None,
                 updates: dict | None = None) -> None:
        cfg = spec.cfg
        self.spec, self.cfg, self.forward, self.reset = spec, cfg, forward, reset
        self.forward_rb, self.reset_rb, self.collector = forward_rb, reset_rb, collector
        self.agents = {"forward": forward, "reset": reset}
        self.keys = dict(zip(("forward", "reset"), buffer_keys(spec, forward, reset)))
        self.kind = spec.kind
        self.matmul_precision, self.robot = matmul_precision, robot
        self.heat_up = int(cfg.heat_up)
        #: ``update_order: release``: a critic step, then an actor step (else one joint step on both losses)
        self.release_order = spec["update_order"] == "release"
        #: ``reset.learn_from_forward``: the forward steps go to the reset agent's buffer as well
        self.learn_from_forward = bool(spec["reset.learn_from_forward"])
        compiled = set(spec["speed.compile"])
        self.losses = {name: torch.compile(agent.loss) if name in compiled else agent.loss
                       for name, agent in self.agents.items()}
        self.budget = UpdateBudget()
        self.last_losses: dict[str, float] = {} if last_losses is None else last_losses  # the latest of each loss
        #: the updates each agent made (the run's history keeps them across a resume)
        self.updates: dict[str, int] = {"forward": 0, "reset": 0} if updates is None else updates

    def buffer(self, phase: str):
        return self.forward_rb if phase == "forward" else self.reset_rb

    def store(self, batch, phase: str) -> None:
        """Lines 16 / 23: stores the step(s) in the phase's replay buffer, the entries its agent reads
        (the buffers live on the CPU; the reset buffer's n-step transform runs here). With
        ``reset.learn_from_forward`` a forward step goes to the reset agent's buffer too (each forward episode
        its own trajectory there, so its n-step states stay inside it)."""
        self.buffer(phase).extend(batch.select(*self.keys[phase], strict=False).cpu())
        if phase == "forward" and self.learn_from_forward:
            self.reset_rb.extend(batch.select(*self.keys["reset"], strict=False).cpu())

    def updating(self, phase: str) -> bool:
        """Whether agent ``phase`` updates at this step: past its heat-up (and, on a robot, in time)."""
        return self.collector.counters[f"{phase}_steps"] > self.heat_up and self._fits(phase)

    def sample(self, phase: str):
        """A batch for agent ``phase``'s update, on the run's device: replay rows, completed by the reset
        agent's kind (ours: the one-step flag when the sampler says it fell back, and as many success
        examples; LNT: its reward, one column per member)."""
        if phase == "forward":
            return self.forward_rb.sample().to(self.cfg.device)
        sample, info = self.reset_rb.sample(return_info=True)
        return self.kind.prepare(sample.to(self.cfg.device), info, self.collector.example_buffer, self.spec)

    @contextlib.contextmanager
    def timed(self, phase: str):
        """An update of agent ``phase``: in the run's product precision, its duration kept for the robot's budget."""
        started = time.perf_counter()
        with matmul_products(self.matmul_precision):
            yield
        self.budget.record(phase, time.perf_counter() - started)

    def updates_achieved(self) -> dict[str, float | None]:
        """Per agent, the updates it made as a fraction of Algorithm 1's count (:func:`updates_achieved`)."""
        return updates_achieved(self.updates, self.collector.counters, self.heat_up)

    def record_losses(self, phase: str, losses: dict[str, float]) -> None:
        """After an update of agent ``phase``: its losses, and one more update counted."""
        self.updates[phase] += 1
        agent = self.agents[phase]
        self.last_losses.update({f"loss_{phase}_actor": losses["loss_actor"],
                                 f"loss_{phase}_critic": losses[agent.critic_loss]})

    def _fits(self, name: str) -> bool:
        """On a real-time robot, whether the update fits in what is left of the control period."""
        return self.robot is None or self.budget.fits(name, self.robot.time_left())
