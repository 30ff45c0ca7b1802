"""learner.mode=async: the learner in a process of its own. Lockstep equals the single process exactly; a lagging
learner still makes every update Algorithm 1 owes; a crashed or hung learner stops the run with a clear error and
the last checkpoint; bad weights are refused. (Ctrl-C and an exact lockstep resume: test_recipes.py.)"""
from __future__ import annotations

import csv
import multiprocessing

import pytest
import torch
from torch import nn

from helpers import quick_config
from torchrl_reset_recipes import train
from torchrl_reset_recipes.training.async_learner import AsyncLearner, LearnerFailed, SharedWeights
from torchrl_reset_recipes.training.config_checks import ConfigError, validate

SEPARATE = ["learner.streams=separate", "total_steps=200"]


def rows(path):
    with open(path, newline="") as f:
        return [{k: v for k, v in row.items() if k != "steps_per_second"} for row in csv.DictReader(f)]


def test_lockstep_gives_exactly_the_single_process_runs_counters_and_losses(tmp_path):
    sync = train.train(quick_config(tmp_path / "sync", *SEPARATE))
    lockstep = train.train(quick_config(tmp_path / "async", *SEPARATE, "learner.mode=async", "learner.max_lag=0"))
    assert rows(tmp_path / "sync" / "progress.csv") == rows(tmp_path / "async" / "progress.csv")
    for name in ("resets.csv", "triggers.csv", "diagnostics.csv", "eval.csv"):
        a, b = tmp_path / "sync" / name, tmp_path / "async" / name
        assert a.exists() == b.exists(), name  # a table is written with its first row (triggers.csv: a trigger)
        assert not a.exists() or rows(a) == rows(b), name
    same = ("manual_resets", "episodic_resets", "successful_resets", "forward_share", "updates_achieved")
    assert {k: sync[k] for k in same} == {k: lockstep[k] for k in same}
    assert lockstep["learner"]["mode"] == "async" and lockstep["learner"]["lag_steps"]["max"] == 0


def test_a_lagging_learner_still_makes_every_update_algorithm_1_owes(tmp_path):
    summary = train.train(quick_config(tmp_path, *SEPARATE, "learner.mode=async", "learner.max_lag=30"))
    assert summary["finished"] and summary["steps"] == 200
    assert summary["updates_achieved"] == {"forward": 1.0, "reset": 1.0}  # late, but kept
    stats = summary["learner"]
    assert stats["max_lag"] == 30 and stats["lag_steps"]["mean"] >= 0
    assert set(stats["updates_achieved_when_acting_ended"]) == {"forward", "reset"}


@pytest.mark.parametrize("fault, message", [(("fail",), "the learner process failed"), (("hang", 60.0), "hung")])
def test_a_crashed_or_hung_learner_stops_the_run_with_a_clear_error_and_the_last_checkpoint(tmp_path, monkeypatch,
                                                                                          fault, message):
    original = AsyncLearner.send

    def send(self, batch, phase):
        original(self, batch, phase)
        if self.sent == 120:  # after the checkpoint at 100
            self.inbox.put(fault)

    monkeypatch.setattr(AsyncLearner, "send", send)
    cfg = quick_config(tmp_path, *SEPARATE, "learner.mode=async", "learner.max_lag=0", "learner.timeout=3")
    with pytest.raises(train.LearnerStopped, match=message):
        train.train(cfg)
    assert (tmp_path / "checkpoints" / "step_0000000100" / "learner.pt").exists()
    if fault[0] == "hang":
        return  # resuming after either is the same (a lockstep run resumed exactly: test_recipes' Ctrl-C test)
    monkeypatch.setattr(AsyncLearner, "send", original)
    resumed = train.train(quick_config(tmp_path, *SEPARATE, "learner.mode=async", "learner.max_lag=0",
                                       "resume=auto"))
    assert resumed["finished"] and resumed["steps"] == 200


def test_weights_of_another_layout_are_refused():
    ctx = multiprocessing.get_context("spawn")
    weights = SharedWeights(ctx, {"reset_model": nn.Linear(3, 2)})
    weights.publish({"reset_model": nn.Linear(3, 2)}, 1)
    assert weights.version.value == 1
    with pytest.raises(LearnerFailed, match="refused"):
        weights.publish({"reset_model": nn.Sequential(nn.Linear(3, 2))}, 2)
    target = nn.Linear(3, 2)
    source = nn.Linear(3, 2)
    weights.publish({"reset_model": source}, 3)
    assert weights.load({"reset_model": target}) == 3 and torch.equal(target.weight, source.weight)


@pytest.mark.parametrize("overrides, text", [
    (["learner.mode=async"], "set learner.streams=separate"),
    (["learner.max_lag=-1"], "learner.max_lag must be a whole number"),
    (["learner.timeout=0"], "learner.timeout must be a number of seconds > 0"),
    (["learner.mode=threads"], "learner.mode"),
])
def test_bad_learner_settings_are_refused(tmp_path, overrides, text):
    with pytest.raises(ConfigError, match=text):
        validate(quick_config(tmp_path, *overrides))
