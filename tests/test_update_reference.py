"""The optimized reset update against a plain implementation written straight from docs/method.md section 3.

The plain version loops over members with one small network per member, evaluates each prior
separately, runs the actor loss on its own pass through the classifier, steps torch's default
(unfused) Adam and applies the soft target update by hand. Several whole updates (loss, backward,
optimizer step, target step) must give the same losses and the same parameters as
``RCELoss`` + ``EnsembleValueOperator`` (the reference path) and ``FastRCELoss`` +
``FastEnsembleValueOperator`` (the accelerator), with fused Adam and ``SoftUpdate``.
"""
from __future__ import annotations

import copy

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.objectives import SoftUpdate

from torchrl_reset import EnsembleValueOperator, RCELoss
from torchrl_reset.accel import FastEnsembleValueOperator, FastRCELoss
from torchrl_reset.accel import ensemble as fast_ensemble

OBS, ACT, K, HIDDEN, BATCH = 3, 2, 3, (16, 12), 64
GAMMA, N_STEPS, BETA, TAU = 0.99, 4, 3.0, 0.05


def plain_member(params: dict, i: int, obs: torch.Tensor, act: torch.Tensor, prefix: str = "") -> torch.Tensor:
    """Member i as one network: state in, action joined to the first hidden layer's output."""
    w = lambda name: params[prefix + name][i]  # noqa: E731
    h = torch.relu(obs @ w("weight_0") + w("bias_0"))
    h = torch.relu(h @ w("weight_1") + act @ w("action_weight") + w("bias_1"))
    return (h @ w("weight_2") + w("bias_2")).squeeze(-1)


def plain_logits(params: dict, priors: dict, obs: torch.Tensor, act: torch.Tensor) -> torch.Tensor:
    """[N, K]: for each member separately, f_i(s, a) + beta * g_i(s, a)."""
    return torch.stack(
        [plain_member(params, i, obs, act) + BETA * plain_member(priors, i, obs, act, "prior_") for i in range(K)], -1
    )


def plain_losses(actor: nn.Module, params: dict, target: dict, priors: dict, batch: TensorDict):
    """The RCE classifier loss and the actor loss, one term at a time (docs/method.md section 3)."""
    s, a = batch["observation"], batch["action"]
    s1, sn, se = batch["next", "observation"], batch["nstep", "observation"], batch["example", "observation"]
    with torch.no_grad():
        # the release (docs/method.md section 9): unclipped target values C, label c2l(C) = g C / (1 + (g - 1) C)
        c1 = torch.sigmoid(plain_logits(target, priors, s1, actor(s1)))
        cn = torch.sigmoid(plain_logits(target, priors, sn, actor(sn)))
        g, gn = GAMMA, GAMMA**N_STEPS
        per_member = 0.5 * (g * c1 / (1 + (g - 1) * c1) + gn * cn / (1 + (gn - 1) * cn))
        y = per_member.min(-1).values.clamp(max=0.5)
        c_y = (y / (y + g * (1 - y))).clamp(0, 0.5)
        weight = 1 + g * c_y / (1 - c_y)
        example_action = actor(se)
    loss_classifier = 0.0
    for i in range(K):
        example_logit = plain_member(params, i, se, example_action) + BETA * plain_member(priors, i, se, example_action, "prior_")
        replay_logit = plain_member(params, i, s, a) + BETA * plain_member(priors, i, s, a, "prior_")
        ce_example = -(0.5 * torch.log(torch.sigmoid(example_logit)) + 0.5 * torch.log(1 - torch.sigmoid(example_logit)))
        ce_replay = -(y * torch.log(torch.sigmoid(replay_logit)) + (1 - y) * torch.log(1 - torch.sigmoid(replay_logit)))
        loss_classifier = loss_classifier + (1 - g) * ce_example.mean() + (weight * ce_replay).mean()
    frozen = {k: v.detach() for k, v in params.items()}
    pi = actor(s)
    values = torch.stack([torch.sigmoid(plain_member(frozen, i, s, pi) + BETA * plain_member(priors, i, s, pi, "prior_"))
                          for i in range(K)], -1)
    loss_actor = -values.min(-1).values.mean()
    return loss_classifier, loss_actor


def make_batch(gen: torch.Generator, example_pool: torch.Tensor | None = None) -> TensorDict:
    """A replay batch; with ``example_pool``, the examples are drawn from that fixed set of states
    with their slots under ``("example", "index")``, as InitialStateBuffer.sample gives them."""
    state = lambda: TensorDict(observation=torch.randn(BATCH, OBS, generator=gen, dtype=torch.float64), batch_size=[BATCH])  # noqa: E731
    batch = TensorDict(
        observation=torch.randn(BATCH, OBS, generator=gen, dtype=torch.float64),
        action=torch.rand(BATCH, ACT, generator=gen, dtype=torch.float64) * 2 - 1,
        next=state(), nstep=state(), example=state(), batch_size=[BATCH],
    )
    if example_pool is not None:
        slots = torch.randint(len(example_pool), (BATCH,), generator=gen)
        batch["example"] = TensorDict(observation=example_pool[slots], index=slots, batch_size=[BATCH])
    return batch


@pytest.mark.parametrize("threads, examples_with_slots, fast", [
    (1, False, False), (2, True, False), (1, False, True), (2, False, True), (2, True, True)])
def test_update_matches_a_plain_per_member_reference_over_several_updates(threads, examples_with_slots, fast):
    """The library's reference path and its accelerator, each against the per-member loops above."""
    ensemble_cls, loss_cls = (FastEnsembleValueOperator, FastRCELoss) if fast else (EnsembleValueOperator, RCELoss)
    old_threads = torch.get_num_threads()
    # the thread count itself, also where the suite's workers hold one thread each (tests/conftest.py)
    set_threads = getattr(torch.set_num_threads, "__wrapped__", torch.set_num_threads)
    set_threads(threads)
    try:
        if threads == 2 and fast:  # K = 3 members on 2 threads: the classifier's rows are cut in blocks
            assert fast_ensemble._row_split(K, 2 * BATCH, torch.device("cpu")) == 2
        torch.manual_seed(0)
        net = nn.Sequential(nn.Linear(OBS, 8), nn.ReLU(), nn.Linear(8, ACT), nn.Tanh()).double()
        ensemble = ensemble_cls(OBS, ACT, num_members=K, hidden_sizes=HIDDEN, prior_scale=BETA, dtype=torch.float64)
        with torch.no_grad():  # non-zero biases, so that every term of the update is exercised
            for name, p in ensemble.named_parameters():
                if name.startswith("bias"):
                    p.uniform_(-0.3, 0.3)
        plain_actor = copy.deepcopy(net)
        params = {n: p.detach().clone().requires_grad_(True) for n, p in ensemble.named_parameters()}
        target = {n: p.detach().clone() for n, p in params.items()}
        priors = {n: b.clone() for n, b in ensemble.named_buffers()}

        actor = TensorDictModule(net, in_keys=["observation"], out_keys=["action"])
        loss = loss_cls(actor, ensemble, gamma=GAMMA, n_steps=N_STEPS)
        updater = SoftUpdate(loss, tau=TAU)
        optimizer = torch.optim.Adam([{"params": list(net.parameters()), "lr": 1e-2},
                                      {"params": list(ensemble.parameters()), "lr": 3e-2}], fused=True)
        plain_optimizer = torch.optim.Adam([{"params": list(plain_actor.parameters()), "lr": 1e-2},
                                            {"params": list(params.values()), "lr": 3e-2}], foreach=False)
        gen = torch.Generator().manual_seed(1)
        # 20 example states for 64 rows: later updates read the priors' part of most examples from
        # the kept copy (FastEnsembleValueOperator.paired_logits with slots)
        pool = torch.randn(20, OBS, generator=gen, dtype=torch.float64) if examples_with_slots else None
        for _ in range(4):
            batch = make_batch(gen, pool)
            out = loss(batch)
            ref_classifier, ref_actor = plain_losses(plain_actor, params, target, priors, batch)
            torch.testing.assert_close(out["loss_classifier"], ref_classifier, rtol=1e-10, atol=1e-12)
            torch.testing.assert_close(out["loss_actor"], ref_actor, rtol=1e-10, atol=1e-12)

            optimizer.zero_grad()
            (out["loss_classifier"] + out["loss_actor"]).backward()
            optimizer.step()
            updater.step()

            plain_optimizer.zero_grad()
            (ref_classifier + ref_actor).backward()
            plain_optimizer.step()
            with torch.no_grad():
                for name, p in params.items():
                    target[name].mul_(1 - TAU).add_(TAU * p)

            for (name, p), q in zip(net.named_parameters(), plain_actor.parameters()):
                torch.testing.assert_close(p, q, rtol=1e-9, atol=1e-10, msg=f"actor {name}")
            for name, p in ensemble.named_parameters():
                torch.testing.assert_close(p, params[name], rtol=1e-9, atol=1e-10, msg=f"classifier {name}")
                torch.testing.assert_close(loss.target_classifier_network_params[name], target[name], rtol=1e-9,
                                           atol=1e-10, msg=f"target {name}")
            for name, b in ensemble.named_buffers():
                assert torch.equal(b, priors[name])
    finally:
        set_threads(old_threads)
