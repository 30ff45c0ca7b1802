"""Training S independent runs as one: an optimizer and a target update that move only the runs asked.

S runs batched in one process keep every network's parameters with a leading run dimension ``S``
(the runs of K-member ensembles are ``S * K`` members). At a step, only some runs' agents acted (a
run in its forward phase updates its forward agent, not its reset agent), so one update call must
change exactly those runs and leave every other run's parameters, target parameters and optimizer
state (its moment estimates and its step count) as they were, bit for bit. A gradient of zero is
not enough: Adam would still move a parameter by its momentum and count a step.

:class:`RunMaskedAdam` is Adam with per-run step counts and a mask; :class:`RunMaskedSoftUpdate` is
the soft target update with a mask. For one run, the sequence of its masked updates computes what
``torch.optim.Adam(foreach=False)`` and torchrl's ``SoftUpdate`` compute on that run alone, with the
same operations in the same order (``tests/test_runs.py`` checks it bit for bit).
"""
from __future__ import annotations

from collections.abc import Iterable, Sequence

import torch

__all__ = ["RunMaskedAdam", "RunMaskedSoftUpdate"]


def _check_mask(mask: torch.Tensor, runs: int) -> torch.Tensor:
    if not isinstance(mask, torch.Tensor) or mask.dtype != torch.bool or mask.shape != (runs,):
        shape = tuple(mask.shape) if isinstance(mask, torch.Tensor) else type(mask).__name__
        raise ValueError(f"mask must be a boolean tensor of shape ({runs},), one entry per run; got {shape}.")
    return mask


def _per_run(values: Sequence[float], like: torch.Tensor) -> torch.Tensor:
    """``values[s]`` broadcast along ``like``'s run dimension, in ``like``'s dtype and device."""
    return torch.tensor(values, dtype=like.dtype, device=like.device).reshape(-1, *([1] * (like.dim() - 1)))


class RunMaskedAdam:
    """Adam over parameters whose first dimension indexes S independent runs.

    ``step(mask)`` updates the runs where ``mask`` is True, each with its own step count (so its own
    bias corrections), and leaves the others exactly as they were. Hyper-parameters are per parameter
    group as in ``torch.optim.Adam`` (``lr``, ``betas``, ``eps``); no weight decay or amsgrad.

    Args:
        params: tensors with the run dimension first, or a list of parameter groups (dicts with
            ``"params"`` and optionally ``"lr"``, ``"betas"``, ``"eps"``).
        runs (int): S.

    Keyword Args:
        lr (float): defaults to 1e-3.
        betas (tuple of float): defaults to (0.9, 0.999).
        eps (float): defaults to 1e-8.

    Examples:
        >>> import torch
        >>> weight = torch.nn.Parameter(torch.zeros(3, 2))  # 3 runs of a 2-parameter model
        >>> opt = RunMaskedAdam([weight], runs=3, lr=0.1)
        >>> weight.grad = torch.ones(3, 2)
        >>> opt.step(torch.tensor([True, False, True]))
        >>> weight.data  # Adam's first step moves by lr; run 1 did not act
        tensor([[-0.1000, -0.1000],
                [ 0.0000,  0.0000],
                [-0.1000, -0.1000]])
        >>> opt.steps
        tensor([1, 0, 1])
    """

    def __init__(self, params: Iterable, runs: int, *, lr: float = 1e-3, betas: tuple[float, float] = (0.9, 0.999),
                 eps: float = 1e-8) -> None:
        if isinstance(runs, bool) or not isinstance(runs, int) or runs < 1:
            raise ValueError(f"runs must be a positive integer, got {runs!r}.")
        params = list(params)
        groups = params if params and isinstance(params[0], dict) else [{"params": params}]
        self.runs = runs
        self.param_groups = []
        for group in groups:
            group = {"lr": lr, "betas": tuple(betas), "eps": eps, **group, "params": list(group["params"])}
            for p in group["params"]:
                if p.dim() == 0 or p.shape[0] != runs:
                    raise ValueError(f"every parameter needs the run dimension ({runs}) first; got shape {tuple(p.shape)}.")
            self.param_groups.append(group)
        self.state = {p: {"exp_avg": torch.zeros_like(p, memory_format=torch.preserve_format),
                          "exp_avg_sq": torch.zeros_like(p, memory_format=torch.preserve_format)}
                      for g in self.param_groups for p in g["params"]}
        self.steps = torch.zeros(runs, dtype=torch.long)

    def zero_grad(self, set_to_none: bool = True) -> None:
        for group in self.param_groups:
            for p in group["params"]:
                if p.grad is not None:
                    if set_to_none:
                        p.grad = None
                    else:
                        p.grad.zero_()

    @torch.no_grad()
    def step(self, mask: torch.Tensor, *, same_step: bool = False) -> None:
        """One Adam step for the runs where ``mask`` holds; the other runs are not touched. Parameters
        without a gradient are skipped, as torch's Adam skips them.

        ``same_step=True``: a further step of the same count, on other parameters (those with a gradient
        now): the runs' counts are not advanced again, and the bias corrections use the current counts.
        Two losses that step disjoint parameters one after the other (a critic, then an actor) so count
        once per run, as torch's per-parameter step counts do.

        With every run in the mask the update runs in place on the whole stacks; otherwise on the
        selected runs' rows only (gathered, updated, written back), so its cost follows the runs that
        acted. Either way each run gets torch's arithmetic on its own rows."""
        mask = _check_mask(mask, self.runs).cpu()
        if not bool(mask.any()):
            return
        if same_step and bool((self.steps[mask] == 0).any()):
            raise ValueError("same_step=True continues a step already taken; a run in the mask has taken none.")
        steps = self.steps if same_step else self.steps + mask.long()
        everyone = bool(mask.all())
        index = mask.nonzero().squeeze(1)
        counts = steps[index].tolist()
        for group in self.param_groups:
            beta1, beta2 = group["betas"]
            lr, eps = group["lr"], group["eps"]
            # torch's bias corrections, in Python floats, per run that steps
            bias1 = [1 - beta1 ** float(n) for n in counts]
            bias2 = [1 - beta2 ** float(n) for n in counts]
            neg_step_size = [-(lr / b) for b in bias1]
            bias2_sqrt = [b**0.5 for b in bias2]
            for p in group["params"]:
                if p.grad is None:
                    continue
                state = self.state[p]
                step_size, root = _per_run(neg_step_size, p), _per_run(bias2_sqrt, p)
                if everyone:
                    exp_avg = state["exp_avg"].lerp_(p.grad, 1 - beta1)
                    exp_avg_sq = state["exp_avg_sq"].mul_(beta2).addcmul_(p.grad, p.grad, value=1 - beta2)
                    denom = (exp_avg_sq.sqrt() / root).add_(eps)
                    # param.addcdiv_(exp_avg, denom, value=-step_size) computes p + (value * exp_avg) / denom
                    p.add_(step_size * exp_avg / denom)
                    continue
                rows = index.to(p.device)
                grad = p.grad.index_select(0, rows)
                exp_avg = state["exp_avg"].index_select(0, rows).lerp_(grad, 1 - beta1)
                exp_avg_sq = state["exp_avg_sq"].index_select(0, rows).mul_(beta2).addcmul_(grad, grad, value=1 - beta2)
                denom = (exp_avg_sq.sqrt() / root).add_(eps)
                updated = p.index_select(0, rows).add_(step_size * exp_avg / denom)
                state["exp_avg"].index_copy_(0, rows, exp_avg)
                state["exp_avg_sq"].index_copy_(0, rows, exp_avg_sq)
                p.index_copy_(0, rows, updated)
        self.steps = steps

    def state_dict(self) -> dict:
        order = [p for g in self.param_groups for p in g["params"]]
        return {"steps": self.steps.clone(),
                "state": [{k: v.clone() for k, v in self.state[p].items()} for p in order],
                "groups": [{k: v for k, v in g.items() if k != "params"} for g in self.param_groups]}

    def load_state_dict(self, state: dict) -> None:
        order = [p for g in self.param_groups for p in g["params"]]
        if len(state["state"]) != len(order) or state["steps"].shape != (self.runs,):
            raise ValueError("the state dict belongs to another set of parameters or another number of runs.")
        self.steps = state["steps"].clone()
        for p, saved in zip(order, state["state"]):
            self.state[p] = {k: v.to(p.device).clone() for k, v in saved.items()}
        for group, saved in zip(self.param_groups, state["groups"]):
            group.update(saved)


class RunMaskedSoftUpdate:
    """``target <- (1 - tau) target + tau source`` for the runs in a mask, as torchrl's ``SoftUpdate``
    computes it (``target.lerp_(source, 1 - eps)`` with ``eps = 1 - tau``); the other runs are not touched.

    Args:
        sources, targets: matching sequences of tensors with the run dimension first.
        runs (int): S.
        tau (float): the update rate, in (0, 1].
    """

    def __init__(self, sources: Sequence[torch.Tensor], targets: Sequence[torch.Tensor], runs: int, tau: float) -> None:
        sources, targets = list(sources), list(targets)
        if len(sources) != len(targets):
            raise ValueError(f"got {len(sources)} sources for {len(targets)} targets.")
        for s, t in zip(sources, targets):
            if s.shape != t.shape or s.dim() == 0 or s.shape[0] != runs:
                raise ValueError(f"sources and targets must match, with the run dimension ({runs}) first: "
                                 f"{tuple(s.shape)} and {tuple(t.shape)}.")
        if not 0.0 < float(tau) <= 1.0:
            raise ValueError(f"tau must lie in (0, 1], got {tau!r}.")
        self.sources, self.targets, self.runs = sources, targets, runs
        self.weight = 1.0 - (1.0 - float(tau))  # what SoftUpdate passes to lerp_

    @torch.no_grad()
    def step(self, mask: torch.Tensor) -> None:
        mask = _check_mask(mask, self.runs)
        if bool(mask.all()):
            torch._foreach_lerp_(self.targets, self.sources, self.weight)
            return
        index = mask.cpu().nonzero().squeeze(1)
        if index.numel() == 0:
            return
        for source, target in zip(self.sources, self.targets):
            rows = index.to(target.device)
            target.index_copy_(0, rows, target.index_select(0, rows).lerp_(source.index_select(0, rows), self.weight))
