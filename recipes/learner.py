"""The recipe's collector and learner: Algorithm 1's "save transition and update" for both agents.

``make_collector`` builds the :class:`~torchrl_reset.DualCollector` (Algorithm 1's two inner loops);
:class:`Learner` stores each collected step in its phase's replay buffer and runs that agent's
update once it is past its heat-up (lines 16 and 23).
"""
from __future__ import annotations

import time
from functools import partial

import torch
from omegaconf import DictConfig, OmegaConf

from agents import Agent, lnt_batch, with_exploration
from buffers import buffer_keys, sampler_fallbacks
from config_checks import arm_count, reset_horizon
from task_envs import UpdateBudget
from torchrl_reset import DualCollector
from torchrl_reset.many import BatchedDualCollector, PooledCollector
from torchrl_reset.accel import matmul_products

__all__ = ["make_collector", "Learner", "NonFiniteLoss", "update_agent"]


def make_collector(cfg: DictConfig, env, forward: Agent, reset: Agent) -> DualCollector | PooledCollector:
    """Forward and reset episodes over ``env``, with the paper's OU exploration on both policies.

    With ``arms``: one :class:`~torchrl_reset.BatchedDualCollector` over the N copies, each in its own
    phase, one example buffer for all, seen as one run's collector (its ``pooled()`` view); copy ``i``
    is seeded ``seed + i``."""
    arms = arm_count(cfg)
    loop = DualCollector if arms is None else partial(BatchedDualCollector, shared_examples=True)
    collector = loop(
        env,
        with_exploration(forward.actor, env.action_spec, cfg),
        with_exploration(reset.actor, env.action_spec, cfg),
        max_forward_steps=int(cfg.task.forward_horizon),   # H_f
        max_reset_steps=reset_horizon(cfg),                 # H_r
        min_reset_steps=int(cfg.reset.min_steps),
        total_frames=int(cfg.total_steps),
        **restart_option(cfg),
    )
    collector.set_seed(int(cfg.seed))
    return collector if arms is None else collector.pooled()


def restart_option(cfg: DictConfig) -> dict:
    """The collector's ``restart_exploration`` from ``exploration.restart`` (configs without it: ``episode``)."""
    restart = OmegaConf.select(cfg, "exploration.restart", default="episode")
    return {} if restart == "episode" else {"restart_exploration": False}


class NonFiniteLoss(RuntimeError):
    """A loss came out NaN or infinite; no parameter was changed by it."""


def update_agent(agent: Agent, sample, names: tuple[str, str], *, release_order: bool, loss=None) -> dict[str, float]:
    """One update of ``agent`` on ``sample``, then its soft target update; returns the losses (``names``: the
    actor's entry, then the critic's: ``loss_value`` or ``loss_classifier``).

    ``release_order`` (``update_order: release``, the authors' release, docs/method.md section 9): a step of
    the critic (classifiers) on its loss, then a step of the actor on its loss computed with the updated
    critic, on as many rows drawn with replacement from the critic's batch. Otherwise one step on the sum of
    both losses computed together by ``loss`` (the agent's loss module, or its compiled form)."""
    actor_name, critic_name = names
    if release_order:
        critic = _step(agent, critic_name, getattr(agent.loss, critic_name)(sample)[0])
        rows = torch.randint(sample.shape[0], (sample.shape[0],), device=sample.device)
        actor = _step(agent, actor_name, agent.loss.loss_actor(sample[rows])[0])
        values = {actor_name: actor, critic_name: critic}
    else:
        losses = (loss or agent.loss)(sample)
        total = sum(losses[n] for n in names)
        if not torch.isfinite(total):
            raise NonFiniteLoss(", ".join(f"{n}={float(losses[n].detach())}" for n in names))
        agent.optimizer.zero_grad()
        total.backward()
        agent.optimizer.step()
        values = {n: float(losses[n].detach()) for n in names}
    agent.targets.step()
    return values


def _step(agent: Agent, name: str, loss: torch.Tensor) -> float:
    """One optimizer step on ``loss``: only the parameters it reaches have gradients (the others' are None
    after ``zero_grad``), so Adam moves only those."""
    if not torch.isfinite(loss):
        raise NonFiniteLoss(f"{name}={float(loss.detach())}")
    agent.optimizer.zero_grad()
    loss.backward()
    agent.optimizer.step()
    return float(loss.detach())


class Learner:
    """Stores every collected step in its phase's buffer and updates that phase's agent.

    Each agent updates once per step of its own phase, after ``heat_up`` steps of it; on a real-time
    robot only when the update fits in what is left of the control period (:class:`UpdateBudget`).
    The updates run with the CPU product precision the run chose (``speed.matmul_precision``) and,
    for the agents named in ``speed.compile``, through ``torch.compile``.
    """

    def __init__(self, cfg: DictConfig, forward: Agent, reset: Agent, forward_rb, reset_rb, collector: DualCollector,
                 matmul_precision: str, robot=None, *, last_losses: dict | None = None) -> None:
        self.cfg, self.forward, self.reset = cfg, forward, reset
        self.forward_rb, self.reset_rb, self.collector = forward_rb, reset_rb, collector
        self.forward_keys, self.reset_keys = buffer_keys(cfg, forward, reset)
        self.matmul_precision, self.robot = matmul_precision, robot
        self.heat_up = int(cfg.heat_up)
        self.ours = cfg.algo.name == "ours"
        self.release_order = OmegaConf.select(cfg, "update_order", default="joint") == "release"
        compiled = set(cfg.speed.compile)
        self._losses = {name: torch.compile(agent.loss) if name in compiled else agent.loss
                        for name, agent in (("forward", forward), ("reset", reset))}
        self.budget = UpdateBudget()
        self.last_losses: dict[str, float] = {} if last_losses is None else last_losses  # the latest of each loss

    def observe(self, batch, phase: str) -> None:
        """Lines 16 (forward) and 23 (reset): store the transition, then update that agent. A batch of
        several steps (N arms, each stepped once) is stored at once and updates the agent once per step,
        each update on a sample of its own."""
        sample = self.store(batch, phase)
        if sample is None:
            return
        for update in range(batch.numel()):
            if update:
                sample = self._sample(phase)
            self.record_losses(phase, self._update(phase, sample, self.loss_names(phase)))

    def store(self, batch, phase: str):
        """Stores the transition in its phase's buffer; returns that agent's update batch when it updates
        at this step (past its heat-up, and in time on a robot), else None."""
        updating = self.collector.counters[f"{phase}_steps"] > self.heat_up
        if phase == "forward":
            self.forward_rb.extend(batch.select(*self.forward_keys, strict=False).cpu())  # the buffers live on the CPU
        else:
            self.reset_rb.extend(batch.select(*self.reset_keys, strict=False).cpu())  # (the n-step transform too)
        return self._sample(phase) if updating and self._fits(phase) else None

    def _sample(self, phase: str):
        return self.forward_rb.sample().to(self.cfg.device) if phase == "forward" else self._reset_sample()

    def loss_names(self, phase: str) -> tuple[str, str]:
        """The loss entries that agent ``phase`` sums and minimises (the actor's first)."""
        if phase == "reset" and self.ours:
            return ("loss_actor", "loss_classifier")
        return ("loss_actor", "loss_value")

    def record_losses(self, phase: str, losses: dict[str, float]) -> None:
        actor, critic = self.loss_names(phase)
        self.last_losses.update({f"loss_{phase}_actor": losses[actor], f"loss_{phase}_critic": losses[critic]})

    def _reset_sample(self):
        """The reset agent's batch: ours, replay rows and as many success examples; LNT, its rewards."""
        fallbacks = sampler_fallbacks(self.reset_rb)
        sample = self.reset_rb.sample().to(self.cfg.device)
        if fallbacks is not None and sampler_fallbacks(self.reset_rb) > fallbacks:
            # no reset episode has n transitions yet: the release uses the one-step label
            sample.set("one_step", torch.ones(sample.shape[0], dtype=torch.bool, device=sample.device))
        if self.ours:
            sample.set("example", self.collector.example_buffer.sample(sample.shape[0]).to(self.cfg.device))
            return sample
        return lnt_batch(sample, self.cfg.algo, int(self.cfg.algo.num_members))

    def _fits(self, name: str) -> bool:
        """On a real-time robot, whether the update fits in what is left of the control period."""
        return self.robot is None or self.budget.fits(name, self.robot.time_left())

    def _update(self, name: str, sample, names) -> dict[str, float]:
        """One update of agent ``name`` on ``sample`` (:func:`update_agent`), timed, in the run's product precision."""
        agent = self.forward if name == "forward" else self.reset
        started = time.perf_counter()
        with matmul_products(self.matmul_precision):
            values = update_agent(agent, sample, names, release_order=self.release_order, loss=self._losses[name])
        self.budget.record(name, time.perf_counter() - started)
        return values
