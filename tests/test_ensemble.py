"""EnsembleValueOperator: architecture, priors, batched evaluation and the ratio helpers."""
from __future__ import annotations

import math

import pytest
import torch
from tensordict import TensorDict

from torchrl_reset import EnsembleValueOperator, reduce_members, success_classifier, success_probability
from torchrl_reset.accel import FastEnsembleValueOperator

BOTH = pytest.mark.parametrize("cls", [EnsembleValueOperator, FastEnsembleValueOperator])


def member_reference(ens: EnsembleValueOperator, i: int, obs: torch.Tensor, act: torch.Tensor, prefix: str = ""):
    """Member i written as plain per-member layers (state in, action joined after the first layer)."""
    w = lambda name: getattr(ens, f"{prefix}{name}")[i]  # noqa: E731
    h = torch.relu(obs @ w("weight_0") + w("bias_0"))
    h = torch.relu(torch.cat([h, act], -1) @ torch.cat([w("weight_1"), w("action_weight")], 0) + w("bias_1"))
    return (h @ w("weight_2") + w("bias_2")).squeeze(-1)


@BOTH
@pytest.mark.parametrize("grad", [True, False])
def test_every_member_matches_a_plain_per_member_network_plus_beta_times_its_prior(cls, grad):
    ens = cls(5, 2, num_members=4, hidden_sizes=(8, 6), prior_scale=3.0)
    obs, act = torch.randn(7, 5), torch.rand(7, 2)
    with torch.set_grad_enabled(grad):
        logits = ens.logits(obs, act)
    assert logits.shape == (7, 4)
    for i in range(4):
        expected = member_reference(ens, i, obs, act) + 3.0 * member_reference(ens, i, obs, act, "prior_")
        torch.testing.assert_close(logits[:, i], expected, rtol=1e-5, atol=1e-5)


def test_grad_free_fused_path_equals_the_separate_prior_path():
    ens = FastEnsembleValueOperator(5, 2, num_members=3, hidden_sizes=(8, 6))
    obs, act = torch.randn(9, 5), torch.rand(9, 2)
    with torch.no_grad():
        fused = ens.logits(obs, act)
    separate = ens.logits(obs, act).detach()
    torch.testing.assert_close(fused, separate, rtol=1e-6, atol=1e-6)


def test_default_architecture_is_the_papers_400_300_with_five_members_and_beta_3():
    ens = EnsembleValueOperator(18, 6)
    assert ens.num_members == 5 and ens.hidden_sizes == (400, 300) and ens.prior_scale == 3.0
    assert ens.weight_0.shape == (5, 18, 400)  # state at the input
    assert ens.weight_1.shape == (5, 400, 300) and ens.action_weight.shape == (5, 6, 300)  # action joins layer 1
    assert ens.weight_2.shape == (5, 300, 1)
    per_member = 18 * 400 + 400 + (400 + 6) * 300 + 300 + 300 + 1
    assert sum(p.numel() for p in ens.parameters()) == 5 * per_member


def test_trained_part_starts_with_zero_biases_and_xavier_bounds_while_prior_biases_are_random():
    ens = EnsembleValueOperator(18, 6, num_members=2)
    assert all((getattr(ens, f"bias_{i}") == 0).all() for i in range(3))
    assert all((getattr(ens, f"prior_bias_{i}") != 0).any() for i in range(3))
    bound = math.sqrt(6 / (18 + 400))
    assert ens.weight_0.abs().max() <= bound and ens.weight_0.abs().max() > 0.9 * bound
    # members differ from each other and from their priors
    assert not torch.equal(ens.weight_0[0], ens.weight_0[1])
    assert not torch.equal(ens.weight_0[0], ens.prior_weight_0[0])


def test_priors_are_buffers_in_state_dict_and_not_parameters():
    ens = EnsembleValueOperator(3, 1, num_members=2, hidden_sizes=(4, 4))
    names = {n for n, _ in ens.named_parameters()}
    assert not any(n.startswith("prior_") for n in names)
    assert {"prior_weight_0", "prior_bias_2", "prior_action_weight"} <= set(ens.state_dict())


def test_tensordict_forward_handles_extra_batch_dims_and_several_observation_keys():
    ens = EnsembleValueOperator(5, 2, num_members=3, hidden_sizes=(8, 8), in_keys=["a", ("nested", "b"), "action"])
    td = TensorDict({"a": torch.randn(4, 2, 3), "nested": {"b": torch.randn(4, 2, 2)}, "action": torch.rand(4, 2, 2)}, [4, 2])
    out = ens(td)["state_action_logit"]
    assert out.shape == (4, 2, 3)
    flat = ens.logits(torch.cat([td["a"], td["nested", "b"]], -1).reshape(8, 5), td["action"].reshape(8, 2))
    torch.testing.assert_close(out.reshape(8, 3), flat)


def test_success_probability_is_the_clipped_classifier_ratio():
    logits = torch.tensor([-3.0, -0.5, 0.0, 0.7, 5.0])
    c = [1 / (1 + math.exp(-x)) for x in logits.tolist()]
    expected = [min(ci, 0.5) / (1 - min(ci, 0.5)) for ci in c]
    torch.testing.assert_close(success_probability(logits), torch.tensor(expected))
    torch.testing.assert_close(success_classifier(logits), torch.tensor(c))


def test_member_reductions():
    x = torch.tensor([[0.2, 0.5, 0.1], [1.0, 0.0, 0.5]])
    torch.testing.assert_close(reduce_members(x, "mean"), torch.tensor([0.8 / 3, 0.5]))
    torch.testing.assert_close(reduce_members(x, "min"), torch.tensor([0.1, 0.0]))
    with pytest.raises(ValueError, match="reduction"):
        reduce_members(x, "median")


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"num_members": 0}, "K"),
        ({"num_members": -2}, "K"),
        ({"hidden_sizes": ()}, "hidden_sizes"),
        ({"prior_scale": -1.0}, "prior_scale"),
        ({"in_keys": ["action"]}, "in_keys"),
    ],
)
def test_bad_construction_arguments_are_rejected(kwargs, message):
    with pytest.raises(ValueError, match=message):
        EnsembleValueOperator(3, 1, **kwargs)


def test_mismatched_shapes_and_missing_keys_get_clear_errors():
    ens = EnsembleValueOperator(3, 2, num_members=2, hidden_sizes=(4, 4))
    with pytest.raises(ValueError, match="observations of size 3"):
        ens.logits(torch.randn(5, 4), torch.randn(5, 2))
    with pytest.raises(ValueError, match="actions of size 2"):
        ens.logits(torch.randn(5, 3), torch.randn(5, 1))
    with pytest.raises(ValueError, match="batch shapes differ"):
        ens.logits(torch.randn(5, 3), torch.randn(4, 2))
    with pytest.raises(KeyError, match="action"):
        ens(TensorDict(observation=torch.randn(5, 3), batch_size=[5]))


def _reference_logits(ens: EnsembleValueOperator, obs: torch.Tensor, act: torch.Tensor) -> torch.Tensor:
    return torch.stack(
        [member_reference(ens, i, obs, act) + ens.prior_scale * member_reference(ens, i, obs, act, "prior_")
         for i in range(ens.num_members)], -1)


def test_kept_prior_part_of_slotted_states_gives_the_same_logits_and_follows_changed_states_and_priors():
    torch.manual_seed(0)
    ens = FastEnsembleValueOperator(3, 2, num_members=3, hidden_sizes=(8, 6), dtype=torch.float64)
    pool = torch.randn(5, 3, dtype=torch.float64)
    replay_obs, replay_act = torch.randn(4, 3, dtype=torch.float64), torch.rand(4, 2, dtype=torch.float64)
    policy_act = torch.rand(4, 2, dtype=torch.float64)

    def check(slots: torch.Tensor, states: torch.Tensor) -> None:
        example_act = torch.rand(len(slots), 2, dtype=torch.float64)
        obs = torch.cat([states[slots], replay_obs])
        act = torch.cat([example_act, replay_act])
        out, policy = ens.paired_logits(obs, act, policy_act, len(slots), slots=slots)
        torch.testing.assert_close(out, _reference_logits(ens, obs, act), rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(policy, _reference_logits(ens, replay_obs, policy_act), rtol=1e-12, atol=1e-12)

    check(torch.tensor([0, 1, 1, 4, 0]), pool)  # filled on first use
    check(torch.tensor([4, 4, 0, 2]), pool)  # read back (slot 2 new)
    changed = pool.clone()
    changed[4] += 1.0  # a buffer overwrote slot 4 with another state
    check(torch.tensor([4, 1, 4]), changed)
    with torch.no_grad():  # priors reloaded in place (load_state_dict): everything kept is recomputed
        ens.prior_weight_1.mul_(-2.0)
    check(torch.tensor([1, 0, 4]), changed)
    check(torch.tensor([1, 0, 4]), changed)
    with pytest.raises(ValueError, match="one per row"):
        ens.paired_logits(torch.cat([pool[:2], replay_obs]), torch.rand(6, 2, dtype=torch.float64), policy_act, 2,
                          slots=torch.tensor([0]))


@pytest.mark.parametrize("draw", ["xavier", "fan_in"])
def test_prior_biases_follow_the_chosen_draw(draw):
    """The release's Xavier initializer reads a bias of n units as fan_in = fan_out = n: U(+-sqrt(6 / 2n)),
    so sqrt(3 / 1) = 1.732 on the one-unit output and sqrt(3 / 300) = 0.1 on 300 units; the fan_in draw is
    U(+-1 / sqrt(fan_in)). A uniform draw on [-b, b] has standard deviation b / sqrt(3)."""
    members, obs, act = 4000, 3, 2
    ens = EnsembleValueOperator(obs, act, num_members=members, hidden_sizes=(8, 300), prior_bias_draw=draw)
    if draw == "xavier":
        bounds = [math.sqrt(3 / 8), math.sqrt(3 / 300), math.sqrt(3.0)]
    else:  # fan_in of layer 1 counts the action joined to it
        bounds = [1 / math.sqrt(obs), 1 / math.sqrt(8 + act), 1 / math.sqrt(300)]
    for i, bound in enumerate(bounds):
        bias = getattr(ens, f"prior_bias_{i}")
        assert bias.abs().max() <= bound and bias.abs().max() > 0.99 * bound
        assert bias.std().item() == pytest.approx(bound / math.sqrt(3), rel=0.05)
    assert all((getattr(ens, f"bias_{i}") == 0).all() for i in range(3))  # the trained biases stay zero
    # beta = 3 turns the output bias into a constant logit offset of up to 3 * bound per member
    assert (3 * ens.prior_bias_2).abs().max() <= 3 * bounds[2]


def test_an_unknown_prior_bias_draw_is_refused():
    with pytest.raises(ValueError, match="prior_bias_draw must be one of"):
        EnsembleValueOperator(3, 2, prior_bias_draw="uniform")
