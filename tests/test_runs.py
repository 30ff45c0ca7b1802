"""Run-masked Adam and soft update: each run as if trained alone, the others untouched bit for bit."""
from __future__ import annotations

import pytest
import torch

from torchrl_reset.many import RunMaskedAdam, RunMaskedSoftUpdate

S = 4


def masks(steps: int, gen: torch.Generator) -> list[torch.Tensor]:
    out = [torch.rand(S, generator=gen) < 0.6 for _ in range(steps)]
    out[3] = torch.zeros(S, dtype=torch.bool)  # a step where no run acted
    out[4] = torch.ones(S, dtype=torch.bool)
    return out


def test_each_run_follows_torch_adam_alone_and_runs_that_did_not_act_are_untouched():
    gen = torch.Generator().manual_seed(0)
    weight = torch.nn.Parameter(torch.randn(S, 5, 3, generator=gen))
    bias = torch.nn.Parameter(torch.randn(S, 3, generator=gen))
    batched = RunMaskedAdam([{"params": [weight], "lr": 1e-2}, {"params": [bias], "lr": 3e-3, "betas": (0.8, 0.99)}],
                            runs=S)
    alone = [(torch.nn.Parameter(weight[s].detach().clone()), torch.nn.Parameter(bias[s].detach().clone()))
             for s in range(S)]
    optimizers = [torch.optim.Adam([{"params": [w], "lr": 1e-2}, {"params": [b], "lr": 3e-3, "betas": (0.8, 0.99)}],
                                   foreach=False) for w, b in alone]
    schedule = masks(12, gen)
    for mask in schedule:
        grad_w, grad_b = torch.randn(S, 5, 3, generator=gen), torch.randn(S, 3, generator=gen)
        before = weight.detach().clone(), bias.detach().clone(), {k: v.clone() for k, v in batched.state[weight].items()}
        weight.grad, bias.grad = grad_w.clone(), grad_b.clone()
        batched.step(mask)
        for s in range(S):
            if mask[s]:
                (w, b), opt = alone[s], optimizers[s]
                w.grad, b.grad = grad_w[s].clone(), grad_b[s].clone()
                opt.step()
            else:  # not touched: parameters, moments
                assert torch.equal(weight[s], before[0][s]) and torch.equal(bias[s], before[1][s])
                assert all(torch.equal(batched.state[weight][k][s], before[2][k][s]) for k in before[2])
        for s in range(S):
            assert torch.equal(weight[s], alone[s][0]) and torch.equal(bias[s], alone[s][1]), s  # bit for bit
    # each run counted the steps it acted in, as its own optimizer did
    assert batched.steps.tolist() == torch.stack(schedule).sum(0).tolist()
    assert batched.steps.tolist() == [int(optimizers[s].state[alone[s][0]]["step"]) for s in range(S)]


def test_a_second_step_of_the_same_count_is_torch_adam_stepping_another_set_of_parameters():
    """A critic step, then an actor step (the release's update order): torch's Adam skips the parameters
    without a gradient and counts per parameter, so each parameter steps once per update at the same
    count; ``same_step=True`` does the same with one count per run."""
    gen = torch.Generator().manual_seed(1)
    critic = torch.nn.Parameter(torch.randn(S, 4, generator=gen))
    actor = torch.nn.Parameter(torch.randn(S, 2, generator=gen))
    batched = RunMaskedAdam([{"params": [actor], "lr": 1e-2}, {"params": [critic], "lr": 3e-3}], runs=S)
    alone = [(torch.nn.Parameter(actor[s].detach().clone()), torch.nn.Parameter(critic[s].detach().clone()))
             for s in range(S)]
    optimizers = [torch.optim.Adam([{"params": [a], "lr": 1e-2}, {"params": [c], "lr": 3e-3}], foreach=False)
                  for a, c in alone]
    with pytest.raises(ValueError, match="has taken none"):
        batched.step(torch.ones(S, dtype=torch.bool), same_step=True)
    schedule = masks(10, gen)
    for mask in schedule:
        grad_c, grad_a = torch.randn(S, 4, generator=gen), torch.randn(S, 2, generator=gen)
        batched.zero_grad()
        critic.grad = grad_c.clone()
        batched.step(mask)  # the actor has no gradient: untouched
        batched.zero_grad()
        actor.grad = grad_a.clone()
        batched.step(mask, same_step=True)
        for s in range(S):
            if mask[s]:
                (a, c), opt = alone[s], optimizers[s]
                opt.zero_grad()
                c.grad = grad_c[s].clone()
                opt.step()
                opt.zero_grad()
                a.grad = grad_a[s].clone()
                opt.step()
        for s in range(S):
            assert torch.equal(actor[s], alone[s][0]) and torch.equal(critic[s], alone[s][1]), s  # bit for bit
    counts = torch.stack(schedule).sum(0).tolist()
    assert batched.steps.tolist() == counts
    assert [int(optimizers[s].state[alone[s][0]]["step"]) for s in range(S)] == counts  # once per update each
    assert [int(optimizers[s].state[alone[s][1]]["step"]) for s in range(S)] == counts


def test_state_dict_resumes_exactly():
    gen = torch.Generator().manual_seed(1)
    p = torch.nn.Parameter(torch.randn(S, 6, generator=gen))
    q = torch.nn.Parameter(p.detach().clone())
    a, b = RunMaskedAdam([p], runs=S), RunMaskedAdam([q], runs=S)
    grads = [torch.randn(S, 6, generator=gen) for _ in range(6)]
    steps = masks(6, gen)
    for i in range(3):
        p.grad = grads[i].clone()
        a.step(steps[i])
    q.data.copy_(p.data)
    b.load_state_dict(a.state_dict())
    for i in range(3, 6):
        p.grad, q.grad = grads[i].clone(), grads[i].clone()
        a.step(steps[i])
        b.step(steps[i])
    assert torch.equal(p, q) and torch.equal(a.steps, b.steps)


@pytest.mark.parametrize("mask", [[True, False, True, False], [True] * S, [False] * S])
def test_masked_soft_update_is_softupdates_lerp_for_the_masked_runs_only(mask):
    gen = torch.Generator().manual_seed(2)
    source, target = torch.randn(S, 7, generator=gen), torch.randn(S, 7, generator=gen)
    expected = target.clone()
    update = RunMaskedSoftUpdate([source], [target], runs=S, tau=1e-3)
    mask = torch.tensor(mask)
    update.step(mask)
    for s in range(S):
        if mask[s]:
            expected[s].lerp_(source[s], 1 - (1 - 1e-3))  # torchrl SoftUpdate: lerp_(source, 1 - eps)
    assert torch.equal(target, expected)


@pytest.mark.parametrize("mask", [torch.ones(S + 1, dtype=torch.bool), torch.ones(S), [True] * S])
def test_bad_masks_and_parameters_are_refused(mask):
    p = torch.nn.Parameter(torch.zeros(S, 2))
    p.grad = torch.ones(S, 2)
    with pytest.raises(ValueError, match="boolean tensor of shape"):
        RunMaskedAdam([p], runs=S).step(mask)
    with pytest.raises(ValueError, match="run dimension"):
        RunMaskedAdam([torch.nn.Parameter(torch.zeros(S + 1, 2))], runs=S)
    with pytest.raises(ValueError, match="tau"):
        RunMaskedSoftUpdate([p.detach()], [p.detach().clone()], runs=S, tau=0.0)
