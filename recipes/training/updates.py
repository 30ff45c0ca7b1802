"""One update of an agent, as Algorithm 1 runs it after each step of its phase: the losses, backward, the
optimizer step and the soft target update (``recipes/train.py``'s loop and the analysis both call it)."""
from __future__ import annotations

import torch
from torchrl.envs.utils import ExplorationType, set_exploration_type

from torchrl_reset_recipes.training.agents import Agent
from torchrl_reset_recipes.training.learner import NonFiniteLoss

__all__ = ["learn_step", "update", "optimizer_step"]


def learn_step(learner, batch, phase: str) -> None:
    """Algorithm 1's lines 16 / 23 and the updates after them: stores the collected step in its phase's buffer,
    then updates that agent once per step taken, past its heat-up (the run's process with ``learner.mode=sync``,
    the learner's process with ``async``)."""
    learner.store(batch, phase)
    agent = learner.agents[phase]  # pi_f and Q, or pi_r and the C_i (LNT: the Q_i)
    for _ in range(batch.numel() if learner.updating(phase) else 0):
        sample = learner.sample(phase)  # replay rows (ours: + success examples; LNT: + reward)
        with learner.timed(phase):
            losses = update(agent, sample, learner.losses[phase], release_order=learner.release_order)
        learner.record_losses(phase, losses)


def update(agent: Agent, sample, loss_module, *, release_order: bool) -> dict[str, float]:
    """One update of ``agent`` (DDPG, or RCE / LNT for the reset agent) on ``sample``; returns its losses
    (``loss_actor`` and the critic's, ``agent.critic_loss``: ``loss_value`` or ``loss_classifier``).

    ``release_order`` (``update_order: release``, the authors' release, docs/method.md section 9): a step of
    the critic (classifiers) on its loss, then a step of the actor on its loss computed with the updated
    critic, on as many rows drawn with replacement from the critic's batch. Otherwise one step on the sum of
    both losses computed together by ``loss_module`` (the agent's loss, or its compiled form)."""
    stochastic = bool(getattr(agent.loss, "stochastic", False))  # a tanh-Gaussian actor: the loss samples itself
    if release_order:
        critic_loss, _ = getattr(agent.loss, agent.critic_loss)(sample)
        optimizer_step(agent, critic_loss, agent.critic_loss)
        if getattr(agent.loss, "draws_actor_rows", False):  # it draws its rows from the members' own batches
            actor_batch = sample
        else:
            rows = torch.randint(sample.shape[0], (sample.shape[0],), device=sample.device)
            actor_batch = sample[rows]
        with set_exploration_type(ExplorationType.DETERMINISTIC):  # (a stochastic actor's loss samples anyway)
            actor_loss, actor_meta = agent.loss.loss_actor(actor_batch)
        if stochastic:  # the temperature steps with the actor (0 when it is fixed)
            actor_loss = actor_loss + agent.loss.loss_alpha(actor_meta["log_prob"])
        penalty = agent.head.penalty(agent.actor, actor_batch)
        if penalty is not None:
            actor_loss = actor_loss + penalty
        optimizer_step(agent, actor_loss, "loss_actor")
        losses = {"loss_actor": actor_loss, agent.critic_loss: critic_loss}
    else:
        out = loss_module(sample)
        losses = {"loss_actor": out["loss_actor"], agent.critic_loss: out[agent.critic_loss]}
        if stochastic:  # the temperature's loss steps with the actor's
            losses["loss_actor"] = losses["loss_actor"] + out["loss_alpha"]
        penalty = agent.head.penalty(agent.actor, sample)
        if penalty is not None:
            losses["loss_actor"] = losses["loss_actor"] + penalty
        optimizer_step(agent, losses["loss_actor"] + losses[agent.critic_loss], *losses, values=losses)
    agent.targets.step()  # the soft target update: target <- (1 - tau) target + tau network
    return {name: float(value.detach()) for name, value in losses.items()}


def optimizer_step(agent: Agent, loss: torch.Tensor, *names: str, values: dict | None = None) -> None:
    """Backward and one optimizer step on ``loss``: only the parameters it reaches have gradients (the
    others' are None after ``zero_grad``), so Adam moves only those. A non-finite loss changes nothing."""
    if not torch.isfinite(loss):
        raise NonFiniteLoss(", ".join(f"{n}={float((values or {n: loss})[n].detach())}" for n in names))
    agent.optimizer.zero_grad()
    loss.backward()
    agent.optimizer.step()
