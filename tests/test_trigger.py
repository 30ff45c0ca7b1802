"""ResetTriggerTransform: when it fires, what it writes, and that a fired action is never executed."""
from __future__ import annotations

import math

import pytest
import torch
from tensordict.nn import TensorDictModule
from torchrl.envs import TransformedEnv
from torchrl.envs.utils import check_env_specs, step_mdp

from torchrl_reset import EnsembleValueOperator, ResetTriggerTransform
from torchrl_reset_envs import ChainEnv

N = 6


def constant_ensemble(logits):
    """An ensemble over ChainEnv observations returning fixed per-member logits."""
    ens = EnsembleValueOperator(N, 1, num_members=len(logits), hidden_sizes=(1, 1), prior_scale=0.0)
    with torch.no_grad():
        for p in ens.parameters():
            p.zero_()
        ens.bias_2.copy_(torch.tensor(logits).view(-1, 1))
    return ens


def step_right(env, td=None):
    td = env.reset() if td is None else td
    td["action"] = torch.ones(1)
    return env.step(td)


LOGITS = [-1.0, -2.0, 0.5]
MEAN_P = (math.exp(-1.0) + math.exp(-2.0) + 1.0) / 3  # member 3 is clipped at C = 0.5: p = 1


@pytest.mark.parametrize("threshold, fires", [(MEAN_P + 1e-4, True), (MEAN_P - 1e-4, False)])
def test_fires_exactly_when_the_mean_success_probability_is_below_the_threshold(threshold, fires):
    env = TransformedEnv(ChainEnv(num_states=N), ResetTriggerTransform(constant_ensemble(LOGITS), threshold))
    out = step_right(env)
    assert bool(out["next", "reset_trigger"]) is fires
    assert out["next", "success_probability"].item() == pytest.approx(MEAN_P, rel=1e-6)


def test_min_reduction_uses_the_least_confident_member():
    env = TransformedEnv(
        ChainEnv(num_states=N), ResetTriggerTransform(constant_ensemble(LOGITS), 0.2, reduction="min")
    )
    out = step_right(env)
    assert out["next", "success_probability"].item() == pytest.approx(math.exp(-2.0), rel=1e-6)
    assert bool(out["next", "reset_trigger"])  # e^-2 = 0.135 < 0.2, though the mean 0.50 is not


def test_a_fired_step_executes_nothing_and_ends_truncated_not_terminated():
    env = TransformedEnv(ChainEnv(num_states=N), ResetTriggerTransform(constant_ensemble([-5.0]), 0.1))
    td = env.reset()
    env.base_env.set_simulator_state({"position": 2})
    td["observation"] = torch.nn.functional.one_hot(torch.tensor(2), N).float()
    out = step_right(env, td)
    assert env.base_env.position == 2  # the action (a step right) was not executed
    assert torch.equal(out["next", "observation"], td["observation"])
    assert out["next", "reward"].item() == 0.0
    assert bool(out["next", "truncated"]) and bool(out["next", "done"]) and not bool(out["next", "terminated"])


def test_a_step_that_does_not_fire_is_executed_normally():
    env = TransformedEnv(ChainEnv(num_states=N), ResetTriggerTransform(constant_ensemble([-5.0]), 1e-3))
    out = step_right(env)
    assert env.base_env.position == 1
    assert not bool(out["next", "reset_trigger"]) and not bool(out["next", "done"])


def _action_sensitive_model():
    # logit -5 for actions to the right, 0 otherwise: p = e^-5 or 1
    def logits(action):
        return torch.where(action > 0, -5.0, 0.0).expand(*action.shape[:-1], 2)

    return TensorDictModule(logits, in_keys=["action"], out_keys=["state_action_logit"])


def test_the_trigger_scores_the_action_about_to_be_executed():
    env = TransformedEnv(ChainEnv(num_states=N), ResetTriggerTransform(_action_sensitive_model(), 0.1))
    td = env.reset()
    td["action"] = -torch.ones(1)
    assert not bool(env.step(td.clone())["next", "reset_trigger"])
    td["action"] = torch.ones(1)
    assert bool(env.step(td.clone())["next", "reset_trigger"])


def test_value_scores_with_a_q_threshold_for_the_lnt_baselines():
    q_values = TensorDictModule(
        lambda obs: torch.stack([obs.argmax(-1).float() * 10, torch.full(obs.shape[:-1], 50.0)], -1),
        in_keys=["observation"],
        out_keys=["q_ensemble"],
    )
    trigger = ResetTriggerTransform(q_values, 20.0, score="value", reduction="min", score_key="reset_q")
    env = TransformedEnv(ChainEnv(num_states=N), trigger)
    td = env.reset()  # cell 0: Q = (0, 50), min 0 < 20
    td["action"] = torch.ones(1)
    out = env.step(td)
    assert bool(out["next", "reset_trigger"]) and out["next", "reset_q"].item() == 0.0
    env.base_env.set_simulator_state({"position": 3})
    td["observation"] = torch.nn.functional.one_hot(torch.tensor(3), N).float()
    out = env.step(td)  # Q = (30, 50): min 30 >= 20
    assert not bool(out["next", "reset_trigger"]) and out["next", "reset_q"].item() == 30.0


def test_smoothing_is_an_exponential_moving_average_restarted_on_reset():
    # p at cell x is exp(-x): the ensemble's logit is -x (one-hot observation times a ramp)
    ens = EnsembleValueOperator(N, 1, num_members=1, hidden_sizes=(N, 1), prior_scale=0.0)
    with torch.no_grad():
        for p in ens.parameters():
            p.zero_()
        ens.weight_0[0].copy_(torch.eye(N))
        ens.weight_1[0].copy_(torch.arange(N, dtype=torch.float).view(N, 1))
        ens.weight_2.fill_(-1.0)
    alpha = 0.5
    trigger = ResetTriggerTransform(ens, 1e-6, smoothing=alpha)
    env = TransformedEnv(ChainEnv(num_states=N), trigger)
    td = env.reset()
    smoothed = None
    for cell in range(4):  # scores at cells 0, 1, 2, 3
        td["action"] = torch.ones(1)
        td = env.step(td)
        score = math.exp(-cell)
        smoothed = score if smoothed is None else alpha * smoothed + (1 - alpha) * score
        assert td["next", "success_probability"].item() == pytest.approx(smoothed, rel=1e-5)
        td = step_mdp(td)
    env.reset()
    assert trigger.smoothed is None


def test_disabled_trigger_never_fires_and_evaluates_nothing():
    trigger = ResetTriggerTransform(constant_ensemble([-9.0]), 0.5)
    env = TransformedEnv(ChainEnv(num_states=N), trigger)
    trigger.set_enabled(False)
    out = step_right(env)
    assert not bool(out["next", "reset_trigger"]) and env.base_env.position == 1
    assert math.isnan(out["next", "success_probability"].item())


def test_check_env_specs_passes_with_the_trigger_firing_and_not():
    for logit in (-9.0, 0.0):
        env = TransformedEnv(ChainEnv(num_states=N), ResetTriggerTransform(constant_ensemble([logit]), 0.5))
        check_env_specs(env)


@pytest.mark.parametrize("threshold", [0.0, 1.0, -0.1, 1.5])
def test_probability_thresholds_outside_0_1_are_rejected(threshold):
    with pytest.raises(ValueError, match=r"\(0, 1\)"):
        ResetTriggerTransform(constant_ensemble([0.0]), threshold)


def test_other_bad_arguments_are_rejected():
    with pytest.raises(ValueError, match="smoothing"):
        ResetTriggerTransform(constant_ensemble([0.0]), 0.1, smoothing=1.0)
    with pytest.raises(ValueError, match="reduction"):
        ResetTriggerTransform(constant_ensemble([0.0]), 0.1, reduction="median")
    with pytest.raises(ValueError, match="score"):
        ResetTriggerTransform(constant_ensemble([0.0]), 0.1, score="q")
    with pytest.raises(TypeError, match="TensorDictModuleBase"):
        ResetTriggerTransform(lambda td: td, 0.1)


def test_a_model_input_missing_from_the_step_gets_a_clear_error():
    env = TransformedEnv(ChainEnv(num_states=N), ResetTriggerTransform(constant_ensemble([0.0]), 0.1))
    td = env.reset()
    with pytest.raises(KeyError, match="action"):
        env.transform._inv_call(td.exclude("action"))


def test_the_trigger_takes_one_threshold_and_one_switch_for_the_whole_env():
    with pytest.raises(TypeError, match="threshold is one number"):
        ResetTriggerTransform(constant_ensemble([0.0]), [0.1, 0.2])
    trigger = ResetTriggerTransform(constant_ensemble([0.0]), 0.1)
    with pytest.raises(TypeError, match="set_enabled takes a bool"):
        trigger.set_enabled(torch.tensor([True, False]))
