"""What explains a run over time: the trigger's scores, the reset classifier on examples, replay and
forward states, and how far each reset episode ended from the start (``diagnostics.csv``, ``resets.csv``).

The paper's claim to check is that the trigger fires early in training, while the reset agent is not
yet capable, because the ensemble with randomized priors is uncertain there. These columns show
whether the classifier is optimistic or pessimistic where the trigger looks, and whether failed resets
end near or far from the initial state.
"""
from __future__ import annotations

import math

import torch
from tensordict import TensorDict

from torchrl_reset_recipes.training.reset_agents import ResetAgentKind
from torchrl_reset import reduce_members

DIAGNOSTIC_FIELDS = [
    "frames", "trigger_score_mean", "trigger_score_min", "trigger_below_share", "trigger_scored_steps",
    "examples", "example_c", "example_p", "reset_replay_c", "reset_replay_p", "forward_p", "forward_p_min_member",
    "forward_p_member_std", "forward_below_share", "sampler_fallbacks",
]
RESET_FIELDS = ["frames", "outcome", "steps", "distance_to_start", "distance_to_examples", "started_by", "irrecoverable"]


class TriggerScores:
    """Accumulates the trigger's score of every forward action between two log rows: the executed ones
    and the ones it stopped (or scored after H_f), so its minimum and its share below the threshold
    show the triggers too."""

    def __init__(self, score_key, threshold: float):
        self.score_key, self.threshold = score_key, float(threshold)
        self._scores: list[torch.Tensor] = []

    def add(self, batch) -> None:
        score = batch.get(("next", self.score_key), None)
        if score is not None:
            self._scores.append(score.reshape(-1).detach().cpu())

    def add_event(self, event: dict) -> None:
        """The score of an action that was scored but not executed (a trigger, or the action after H_f)."""
        if event.get("scores"):
            self._scores.append(torch.tensor(event["scores"][:1]))

    def row(self) -> dict:
        scores = torch.cat(self._scores) if self._scores else torch.zeros(0)
        self._scores = []
        scores = scores[torch.isfinite(scores)]
        if not len(scores):
            return {"trigger_score_mean": math.nan, "trigger_score_min": math.nan, "trigger_below_share": math.nan,
                    "trigger_scored_steps": 0}
        return {"trigger_score_mean": float(scores.mean()), "trigger_score_min": float(scores.min()),
                "trigger_below_share": float((scores < self.threshold).float().mean()),
                "trigger_scored_steps": len(scores)}


@torch.no_grad()
def probe_classifier(kind: ResetAgentKind, model, reset_actor, examples, forward_rb, reset_rb, threshold: float) -> dict:
    """The reset agent's model on examples (with the reset policy's action), reset replay (the taken
    action) and forward replay (the forward agent's taken action, as the trigger sees it).

    Ours: ``*_c`` the ensemble-mean classifier value C, ``*_p`` the ensemble-mean success probability
    p = C / (1 - C) with C clipped to [0, 0.5]. LNT: the ``*_p`` columns hold the ensemble minimum of the
    reset Q (its trigger score) and the ``*_c`` columns are left empty.
    """
    out = {"examples": len(examples)}
    device = next(model.parameters()).device  # the buffers are on the CPU, the networks on cfg.device

    def scores(data: TensorDict) -> tuple[torch.Tensor, torch.Tensor]:
        return kind.member_scores(model(data.select(*model.in_keys).clone(False)).get(model.out_keys[0]))

    def reduce(p: torch.Tensor) -> torch.Tensor:  # as the trigger reduces its members
        return reduce_members(p, kind.reduction)

    if len(examples):
        sample = examples.sample(reset_rb.batch_size if len(reset_rb) else 256).to(device)
        sample = reset_actor(sample.select(*reset_actor.in_keys))
        c, p = scores(sample)
        out.update(example_c=float(c.mean()), example_p=float(reduce(p).mean()))
    if len(reset_rb):
        c, p = scores(reset_rb.sample().to(device))
        out.update(reset_replay_c=float(c.mean()), reset_replay_p=float(reduce(p).mean()))
    if len(forward_rb):
        _, p = scores(forward_rb.sample().to(device))
        trigger = reduce(p)
        out.update(forward_p=float(trigger.mean()), forward_p_min_member=float(p.amin(-1).mean()),
                   forward_p_member_std=float(p.std(-1).mean()) if p.shape[-1] > 1 else 0.0,
                   forward_below_share=float((trigger < threshold).float().mean()))
    return out


class ResetDistances:
    """How far each reset episode ended from the first start state and from the nearest example."""

    def __init__(self, examples, key="observation"):
        self.examples, self.key = examples, key
        self._start = None

    def row(self, event: dict) -> dict:
        states = self.examples.states().get(self.key).reshape(len(self.examples), -1).float()
        if self._start is None:
            self._start = states[0].clone()
        last = event["state"].get(self.key).reshape(-1).float().cpu()  # the examples are on the CPU
        return {"frames": event["frame"], "outcome": event["outcome"], "steps": event["steps"],
                "distance_to_start": float((last - self._start).norm()),
                "distance_to_examples": float((states - last).norm(dim=-1).min())}
