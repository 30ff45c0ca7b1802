"""learner.mode=async: the learner in a process of its own. A lagging learner still makes every update Algorithm 1
owes; a crashed or hung learner stops the run with a clear error and the last checkpoint; bad weights and other
priors are refused; on the real arm's backend (the fake ur_rtde) a protective stop while the learner is busy is the
actor's alone. (Lockstep equals the single process exactly, through a Ctrl-C and its resume: test_recipes.py.)"""
from __future__ import annotations

import copy
import csv
import gc
import multiprocessing
import sys
import threading
import time
from types import SimpleNamespace

import pytest
import torch
from torch import nn

from fake_ur_rtde import PROTECTIVE_STOP, FakeURController
from helpers import quick_config
from torchrl_reset_recipes import train
from torchrl_reset_recipes.training.async_learner import AsyncLearner, LearnerFailed, SharedWeights, next_message
from torchrl_reset_recipes.training.config_checks import ConfigError, validate

SEPARATE = ["learner.streams=separate", "total_steps=200"]


def rows(path):
    with open(path, newline="") as f:
        return [{k: v for k, v in row.items() if k != "steps_per_second"} for row in csv.DictReader(f)]


def test_a_lagging_learner_still_makes_every_update_algorithm_1_owes(tmp_path):
    summary = train.train(quick_config(tmp_path, *SEPARATE, "learner.mode=async", "learner.max_lag=30"))
    assert summary["finished"] and summary["steps"] == 200
    assert summary["updates_achieved"] == {"forward": 1.0, "reset": 1.0}  # late, but kept
    stats = summary["learner"]
    assert stats["max_lag"] == 30 and stats["lag_steps"]["mean"] >= 0
    assert set(stats["updates_achieved_when_acting_ended"]) == {"forward", "reset"}
    # progress.csv, per log window: the lag and the weights' age; the windows together hold every sample of the
    # summary's, so the largest window maximum is the run's
    table = rows(tmp_path / "progress.csv")
    lag_mean, lag_max, age = ([float(r[k]) for r in table] for k in ("learner_lag_mean", "learner_lag_max",
                                                                     "weight_age_mean"))
    assert all(0 <= m <= x for m, x in zip(lag_mean, lag_max)) and min(age) >= 0 and max(lag_max) > 0
    assert max(lag_max) == stats["lag_steps"]["max"]


@pytest.mark.parametrize("fault, message", [(("fail",), "the learner process failed"), (("hang", 60.0), "hung")])
def test_a_crashed_or_hung_learner_stops_the_run_with_a_clear_error_and_the_last_checkpoint(tmp_path, monkeypatch,
                                                                                          fault, message):
    original = AsyncLearner.send
    learners = []

    def send(self, batch, phase):
        learners.append(self)
        original(self, batch, phase)
        if self.sent == 120:  # after the checkpoint at 100
            self.inbox.put(fault)

    waits = []  # what the actor waited for, each time it waited for a message
    next_message = AsyncLearner._next_message

    def recorded_next_message(self, timeout, *, waiting_for):
        waits.append(waiting_for)
        return next_message(self, timeout, waiting_for=waiting_for)

    monkeypatch.setattr(AsyncLearner, "send", send)
    monkeypatch.setattr(AsyncLearner, "_next_message", recorded_next_message)
    cfg = quick_config(tmp_path, *SEPARATE, "learner.mode=async", "learner.max_lag=0", "learner.timeout=3")
    with pytest.raises(train.LearnerStopped, match=message):
        train.train(cfg)
    assert (tmp_path / "checkpoints" / "step_0000000100" / "learner.pt").exists()
    assert "the learner's checkpoint" in waits
    assert not learners[-1].process.is_alive()  # ended with the run: the hung one killed (it ignores SIGTERM)
    if fault[0] == "hang":
        assert "the learner to stop" not in waits  # a hung learner is ended at once, not asked and waited for again
        return  # resuming after either is the same (a lockstep run resumed exactly: test_recipes' Ctrl-C test)
    monkeypatch.setattr(AsyncLearner, "send", original)
    resumed = train.train(quick_config(tmp_path, *SEPARATE, "learner.mode=async", "learner.max_lag=0",
                                       "resume=auto"))
    assert resumed["finished"] and resumed["steps"] == 200


def test_an_idle_learner_whose_actor_has_ended_stops_waiting_and_one_whose_actor_lives_gets_its_message():
    """A killed actor sends nothing more: the learner's wait ends (None) instead of holding the buffers forever."""
    ctx = multiprocessing.get_context("spawn")
    inbox = ctx.Queue()
    gone = ctx.Process(target=int)  # a real process that has ended
    gone.start()
    gone.join()
    start = time.monotonic()
    assert next_message(inbox, gone.is_alive, wait=0.1) is None
    assert time.monotonic() - start >= 0.1  # it waited for a message first
    inbox.put(("stop",))
    assert next_message(inbox, gone.is_alive, wait=5.0) == ("stop",)  # what was sent is still taken
    threading.Timer(0.3, inbox.put, args=(("step", 1),)).start()  # a live actor, slow to send: waited for
    assert next_message(inbox, lambda: True, wait=0.05) == ("step", 1)


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


class WithPriors(nn.Module):
    """A reset model in miniature: trained weights and fixed priors (named as the ensemble names them)."""

    def __init__(self):
        super().__init__()
        self.weight_0 = nn.Parameter(torch.randn(3, 2))
        self.prior_weight_0 = nn.Parameter(torch.randn(3, 2), requires_grad=False)


def test_a_learner_with_other_priors_is_refused_and_no_publication_changes_the_actors_priors():
    ctx = multiprocessing.get_context("spawn")
    actor = WithPriors()
    weights = SharedWeights(ctx, {"reset_model": actor})
    learner = copy.deepcopy(actor)
    weights.check_priors({"reset_model": learner})  # the same priors: accepted
    with pytest.raises(LearnerFailed, match="other priors"):
        weights.check_priors({"reset_model": WithPriors()})  # drawn again: refused
    priors = actor.prior_weight_0.detach().clone()
    with torch.no_grad():
        learner.weight_0.add_(1.0)
        learner.prior_weight_0.add_(1.0)  # a learner that changed its priors cannot pass them on
    weights.publish({"reset_model": learner}, 1)
    assert weights.load({"reset_model": actor}) == 1
    assert torch.equal(actor.weight_0, learner.weight_0) and torch.equal(actor.prior_weight_0, priors)


@pytest.fixture
def fake_arm(monkeypatch):
    """ur_rtde's three modules, faked (tests/fake_ur_rtde.py) on the real clock: the recipe's rtde path as on an arm."""
    controller = FakeURController(time.monotonic)
    monkeypatch.setitem(sys.modules, "rtde_control", SimpleNamespace(RTDEControlInterface=controller.control))
    monkeypatch.setitem(sys.modules, "rtde_receive", SimpleNamespace(RTDEReceiveInterface=controller.receive))
    monkeypatch.setitem(sys.modules, "dashboard_client", SimpleNamespace(DashboardClient=controller.dashboard))
    return controller


def test_on_the_arm_a_protective_stop_while_the_learner_is_busy_is_handled_by_the_actor_alone(tmp_path, monkeypatch,
                                                                                              fake_arm):
    """The stop ends the episode at once; from the stop until the arm is unlocked and home the actor neither waits for
    the learner nor loads weights (the collector's manual reset comes before the actor's next call to the learner);
    then training goes on and every owed update is made."""
    events = []  # ("stop", home moves so far, lag) at the stop; ("halted", _, moves) when the actor learns of it; ...
    frozen = []  # the objects kept out of the garbage collector's passes, every 30th step (a real-time arm: the
    # set-up's); every 30th only: gc.get_freeze_count() walks every frozen object (CPython), about 0.08 s here, so that
    # counting at each step made each step about three control periods long
    send, load, wait_until, after_step = (AsyncLearner.send, AsyncLearner._load, AsyncLearner._wait_until,
                                          AsyncLearner.after_step)

    def busy_then_stop(self, batch, phase):
        send(self, batch, phase)
        if self.sent == 50:  # past heat-up: the learner sleeps 1.5 s on its next message ...
            self.inbox.put(("hang", 1.5))

    def recorded_load(self):
        events.append(("load", fake_arm.names().count("moveJ"), fake_arm.safety_mode, fake_arm.program_running))
        load(self)

    def recorded_wait(self, processed, why):
        events.append(("wait", fake_arm.safety_mode))
        wait_until(self, processed, why)

    steps = [0]

    def recorded_after_step(self, episode_ended, halted=False):
        steps[0] += 1
        if steps[0] % 30 == 1:
            frozen.append(gc.get_freeze_count())
        if halted:
            events.append(("halted", None, fake_arm.names().count("moveJ")))
        after_step(self, episode_ended, halted)
        if self.sent == 60:  # ... and while it is busy the arm stops, between two steps (the next one sees it)
            fake_arm.protective_stop()
            self._drain_outbox()  # the learner's progress as it stands
            events.append(("stop", fake_arm.names().count("moveJ"), self.sent - self.processed))

    for name, method in (("send", busy_then_stop), ("_load", recorded_load), ("_wait_until", recorded_wait),
                         ("after_step", recorded_after_step)):
        monkeypatch.setattr(AsyncLearner, name, method)
    cfg = quick_config(tmp_path, "learner.streams=separate", "learner.mode=async", "learner.max_lag=5",
                       "task=ur3_peg", "task.forward_horizon=20", "env.backend=rtde", "env.host=ur3.fake",
                       "total_steps=120")
    summary = train.train(cfg)
    assert summary["finished"] and summary["steps"] == 120
    assert summary["protective_stops"] == 1 and fake_arm.protective_stops == 1
    stop = next(i for i, e in enumerate(events) if e[0] == "stop")
    _, moves_at_stop, lag_at_stop = events[stop]
    assert lag_at_stop >= 5  # the learner was busy, steps behind the actor, when the arm stopped
    halts = [i for i, e in enumerate(events) if e[0] == "halted"]
    # On a loaded host a step can outlast the controller's watchdog, which stops the control script: that ends an
    # episode too (as on an arm; a trip during a manual reset ends none). Every other halt is the stop's: on an idle
    # host, exactly one.
    assert 1 <= len(halts) <= 1 + fake_arm.watchdog_trips
    after = [i for i in halts if i > stop]
    assert after and events[after[0]][2] > moves_at_stop  # the collector's manual reset (unlock, home) came first
    first_load = next(i for i in range(stop, len(events)) if events[i][0] == "load")
    assert all(e[0] != "wait" for e in events[stop:first_load])  # the actor never waited on the learner meanwhile
    _, moves, mode, running = events[first_load]
    assert moves > moves_at_stop and mode != PROTECTIVE_STOP and running  # the next weights: unlocked and home
    assert summary["updates_achieved"]["reset"] == 1.0  # late, but kept (the forward agent may still be heating up)
    assert len(frozen) >= 4 and min(frozen) > 100_000  # frozen while acting (120 steps and more: the manual reset's)
    assert gc.get_freeze_count() == 0  # returned afterwards
    assert summary["updates_achieved"]["forward"] in (None, 1.0)


@pytest.mark.parametrize("overrides, text", [
    (["learner.mode=async"], "set learner.streams=separate"),
    (["learner.max_lag=-1"], "learner.max_lag must be a whole number"),
    (["learner.timeout=0"], "learner.timeout must be a number of seconds > 0"),
    (["learner.mode=threads"], "learner.mode"),
])
def test_bad_learner_settings_are_refused(tmp_path, overrides, text):
    with pytest.raises(ConfigError, match=text):
        validate(quick_config(tmp_path, *overrides))
