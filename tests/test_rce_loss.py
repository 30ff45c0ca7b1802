"""RCELoss against numbers worked out by hand from docs/method.md section 3."""
from __future__ import annotations

import math

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.objectives import SoftUpdate

from helpers import constant_actor, linear_logit_ensemble
from torchrl_reset import EnsembleValueOperator, RCELoss


def sigmoid(x: float) -> float:
    return 1.0 / (1.0 + math.exp(-x))


def ratio(logit: float) -> float:
    c = min(sigmoid(logit), 0.5)
    return c / (1.0 - c)


def bce(logit: float, target: float) -> float:
    c = sigmoid(logit)
    return -(target * math.log(c) + (1.0 - target) * math.log(1.0 - c))


def batch(obs, nxt, nstep=None, example=None, action=0.0):
    n = len(obs)
    col = lambda v: torch.tensor(v, dtype=torch.float32).view(n, 1)  # noqa: E731
    data = {
        "observation": col(obs),
        "action": torch.full((n, 1), action),
        "next": TensorDict(observation=col(nxt), batch_size=[n]),
        "example": TensorDict(observation=col(example if example is not None else [0.0] * n), batch_size=[n]),
    }
    if nstep is not None:
        data["nstep"] = TensorDict(observation=col(nstep), batch_size=[n])
    return TensorDict(data, batch_size=[n])


SLOPES = [1.0, 2.0]  # member i: logit = -SLOPES[i] * x


def test_label_is_one_step_rce_label_with_ensemble_minimum_when_n_is_1():
    gamma = 0.9
    loss = RCELoss(constant_actor(0.0), linear_logit_ensemble(SLOPES), gamma=gamma, n_steps=1)
    label, weight = loss.labels(batch(obs=[0.0, 0.0], nxt=[0.5, 2.0]))
    for j, x in enumerate([0.5, 2.0]):
        per_member = []
        for s in SLOPES:
            w = math.exp(-s * x)  # C/(1-C) = exp(logit) for logit <= 0
            per_member.append(gamma * w / (1 + gamma * w))
        y = min(per_member)
        w_min = math.exp(-max(SLOPES) * x)  # the minimal label belongs to the steepest member
        assert label[j].item() == pytest.approx(y, rel=1e-6)
        assert weight[j].item() == pytest.approx(1 + gamma * w_min, rel=1e-6)


def test_label_reduces_to_one_step_rce_when_n_is_1_even_with_an_nstep_entry():
    gamma = 0.95
    data = batch(obs=[0.0, 0.0, 0.0], nxt=[0.1, 0.7, 3.0], nstep=[5.0, 5.0, 5.0])
    one = RCELoss(constant_actor(0.0), linear_logit_ensemble(SLOPES), gamma=gamma, n_steps=1)
    label, weight = one.labels(data)
    expected = [gamma * math.exp(-2 * x) / (1 + gamma * math.exp(-2 * x)) for x in [0.1, 0.7, 3.0]]
    torch.testing.assert_close(label, torch.tensor(expected), rtol=1e-6, atol=0)
    # For n = 1 the weight's ratio w_y equals the next-state ratio exactly.
    torch.testing.assert_close(weight, 1 + gamma * torch.exp(-2 * torch.tensor([0.1, 0.7, 3.0])), rtol=1e-6, atol=0)


def test_nstep_label_mixes_one_step_and_n_step_terms_then_takes_member_minimum():
    gamma, n = 0.9, 3
    loss = RCELoss(constant_actor(0.0), linear_logit_ensemble(SLOPES), gamma=gamma, n_steps=n)
    x1, xn = 0.4, 1.5
    label, weight = loss.labels(batch(obs=[0.0], nxt=[x1], nstep=[xn]))
    ys = []
    for s in SLOPES:
        w1, wn = math.exp(-s * x1), math.exp(-s * xn)
        ys.append(0.5 * (gamma * w1 / (1 + gamma * w1) + gamma**n * wn / (1 + gamma**n * wn)))
    y = min(ys)
    c_y = min(y / (y + gamma * (1 - y)), 0.5)
    assert label.item() == pytest.approx(y, rel=1e-6)
    assert weight.item() == pytest.approx(1 + gamma * c_y / (1 - c_y), rel=1e-6)


def test_target_values_above_half_enter_the_label_unclipped_and_the_label_is_clipped_at_half():
    # The release (docs/method.md section 9): logit 2 everywhere, C = sigmoid(2) = 0.8808 enters the label
    # unclipped, gamma C / (1 + (gamma - 1) C) = 0.869, which is clipped to 0.5; the weight's classifier
    # value is clipped to 0.5, so the weight is 1 + gamma.
    gamma = 0.9
    loss = RCELoss(constant_actor(0.0), linear_logit_ensemble([0.0], biases=[2.0]), gamma=gamma, n_steps=1)
    c = sigmoid(2.0)
    assert gamma * c / (1 + (gamma - 1) * c) > 0.5
    label, weight = loss.labels(batch(obs=[0.0], nxt=[1.0]))
    assert label.item() == pytest.approx(0.5, rel=1e-6)
    assert weight.item() == pytest.approx(1 + gamma, rel=1e-6)


def test_unclipped_nstep_label_reaches_half_where_clipping_first_caps_it():
    # n = 10, both target values C = sigmoid(3) = 0.9526: unclipped, the 1-step part is 0.9521 and the
    # n-step part (gamma^10 = 0.9044) 0.9478; their mean is above 0.5, so y = 0.5. Clipping C to 0.5
    # first gives the cap 0.5 (gamma / (1 + gamma) + gamma^n / (1 + gamma^n)) = 0.4862.
    gamma, n = 0.99, 10
    ensemble = linear_logit_ensemble([0.0], biases=[3.0])
    data = batch(obs=[0.0], nxt=[1.0], nstep=[1.0])
    c, gn = sigmoid(3.0), gamma**n
    unclipped = 0.5 * (gamma * c / (1 + (gamma - 1) * c) + gn * c / (1 + (gn - 1) * c))
    assert unclipped > 0.5
    release = RCELoss(constant_actor(0.0), ensemble, gamma=gamma, n_steps=n)
    assert release.labels(data)[0].item() == pytest.approx(0.5, rel=1e-6)
    clipped = RCELoss(constant_actor(0.0), ensemble, gamma=gamma, n_steps=n, clip_target_values=True)
    cap = 0.5 * (gamma / (1 + gamma) + gn / (1 + gn))
    assert cap == pytest.approx(0.4862, abs=1e-4)  # 0.5 (0.99 / 1.99 + 0.9044 / 1.9044)
    assert clipped.labels(data)[0].item() == pytest.approx(cap, rel=1e-6)


def test_labels_use_the_policy_without_noise_like_forward():
    # An actor with additive Gaussian exploration: labels() must see its deterministic action (0),
    # as forward does, even when called inside a RANDOM exploration context.
    from tensordict.nn import TensorDictSequential
    from torchrl.data import Bounded
    from torchrl.envs.utils import ExplorationType, set_exploration_type
    from torchrl.modules import AdditiveGaussianModule

    spec = Bounded(-1.0, 1.0, shape=(1,))
    noisy = TensorDictSequential(constant_actor(0.0), AdditiveGaussianModule(spec, sigma_init=1.0, sigma_end=1.0))
    # member logit = -x - 4 a: the label depends on the action taken at s_{t+1}
    ensemble = linear_logit_ensemble([1.0], action_slopes=[4.0])
    data = batch(obs=[0.0, 0.0, 0.0], nxt=[0.2, 0.5, 1.0])
    gamma = 0.9
    expected = [gamma * math.exp(-x) / (1 + gamma * math.exp(-x)) for x in [0.2, 0.5, 1.0]]
    loss = RCELoss(noisy, ensemble, gamma=gamma, n_steps=1)
    with set_exploration_type(ExplorationType.RANDOM):
        label, _ = loss.labels(data)
        with torch.no_grad():
            assert not torch.equal(noisy(data["next"].clone())["action"], torch.zeros(3, 1))  # the noise is on
    torch.testing.assert_close(label, torch.tensor(expected), rtol=1e-5, atol=0)
    assert loss(data)["label"].item() == pytest.approx(sum(expected) / 3, rel=1e-5)


def test_classifier_loss_matches_hand_computed_cross_entropies():
    gamma = 0.9
    slopes = [1.0, 2.0]
    loss = RCELoss(constant_actor(0.0), linear_logit_ensemble(slopes), gamma=gamma, n_steps=1)
    obs, nxt, example = [0.3, 1.2], [0.5, 2.0], [0.0, 0.25]
    out = loss(batch(obs=obs, nxt=nxt, example=example))
    # labels: minimum over members of gamma w / (1 + gamma w), w = exp(-s x_next)
    labels = [min(gamma * math.exp(-s * x) / (1 + gamma * math.exp(-s * x)) for s in slopes) for x in nxt]
    weights = [1 + gamma * math.exp(-max(slopes) * x) for x in nxt]
    total = 0.0
    for s in slopes:
        examples_term = (1 - gamma) * sum(bce(-s * e, 0.5) for e in example) / len(example)
        replay_term = sum(w * bce(-s * o, y) for o, y, w in zip(obs, labels, weights)) / len(obs)
        total += examples_term + replay_term
    assert out["loss_classifier"].item() == pytest.approx(total, rel=1e-5)


def test_actor_loss_is_minus_the_mean_ensemble_minimum_of_c():
    slopes = [1.0, 3.0, 2.0]
    loss = RCELoss(constant_actor(0.0), linear_logit_ensemble(slopes), gamma=0.99, n_steps=1)
    obs = [0.2, 0.9]
    out = loss(batch(obs=obs, nxt=[0.0, 0.0]))
    expected = -sum(min(sigmoid(-s * x) for s in slopes) for x in obs) / len(obs)
    assert out["loss_actor"].item() == pytest.approx(expected, rel=1e-6)


def _random_setup(n_steps=4, k=3, obs_dim=4, act_dim=2, b=16, prior_scale=3.0):
    actor = TensorDictModule(
        nn.Sequential(nn.Linear(obs_dim, 16), nn.ReLU(), nn.Linear(16, act_dim), nn.Tanh()),
        in_keys=["observation"],
        out_keys=["action"],
    )
    ens = EnsembleValueOperator(obs_dim, act_dim, num_members=k, hidden_sizes=(16, 16), prior_scale=prior_scale)
    loss = RCELoss(actor, ens, gamma=0.99, n_steps=n_steps)

    def sample():
        state = lambda: TensorDict(observation=torch.randn(b, obs_dim), batch_size=[b])  # noqa: E731
        return TensorDict(
            observation=torch.randn(b, obs_dim),
            action=torch.rand(b, act_dim) * 2 - 1,
            next=state(),
            nstep=state(),
            example=state(),
            batch_size=[b],
        )

    return loss, actor, ens, sample


def test_classifier_loss_gradients_reach_only_trainable_classifier_parameters():
    loss, actor, ens, sample = _random_setup()
    out = loss(sample())
    out["loss_classifier"].backward()
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in ens.parameters())
    assert all(p.grad is None or p.grad.abs().sum() == 0 for p in actor.parameters())
    assert all(not b.requires_grad for name, b in ens.named_buffers() if name.startswith("prior_"))


def test_actor_loss_gradients_reach_only_the_actor():
    loss, actor, ens, sample = _random_setup()
    out = loss(sample())
    out["loss_actor"].backward()
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in actor.parameters())
    assert all(p.grad is None or p.grad.abs().sum() == 0 for p in ens.parameters())


def test_labels_and_weights_carry_no_gradient():
    loss, _, _, sample = _random_setup()
    label, weight = loss.labels(sample())
    assert not label.requires_grad and not weight.requires_grad


def test_priors_never_change_after_many_optimizer_and_target_steps():
    loss, actor, ens, sample = _random_setup()
    priors = {name: b.clone() for name, b in ens.named_buffers() if name.startswith("prior_")}
    assert priors, "the ensemble should hold prior buffers"
    optimizer = torch.optim.Adam(loss.parameters(), lr=1e-2)
    updater = SoftUpdate(loss, tau=0.1)
    trainable_before = [p.detach().clone() for p in ens.parameters()]
    for _ in range(60):
        optimizer.zero_grad()
        out = loss(sample())
        (out["loss_classifier"] + out["loss_actor"]).backward()
        optimizer.step()
        updater.step()
    for name, before in priors.items():
        assert torch.equal(getattr(ens, name), before), name
        target = loss.target_classifier_network_params.get(name)
        assert torch.equal(target, before), name
        # the target network uses the very same prior tensors
        assert target.data_ptr() == loss.classifier_network_params.get(name).data_ptr()
    assert any(not torch.equal(p, q) for p, q in zip(ens.parameters(), trainable_before))
    assert not any(id(b) in {id(p) for g in optimizer.param_groups for p in g["params"]} for b in ens.buffers())


def test_soft_update_moves_targets_towards_trained_parameters_by_tau():
    loss, _, ens, sample = _random_setup()
    tau = 0.25
    updater = SoftUpdate(loss, tau=tau)
    optimizer = torch.optim.SGD(loss.parameters(), lr=0.5)
    target_before = loss.target_classifier_network_params.get("weight_1").clone()
    optimizer.zero_grad()
    loss(sample())["loss_classifier"].backward()
    optimizer.step()
    updater.step()
    source = loss.classifier_network_params.get("weight_1")
    expected = target_before + tau * (source.detach() - target_before)
    torch.testing.assert_close(loss.target_classifier_network_params.get("weight_1"), expected)


def test_all_members_see_the_same_batch_and_share_one_label():
    loss, _, ens, sample = _random_setup(k=4)
    data = sample()
    label, _ = loss.labels(data)
    assert label.shape == (16,)


def test_missing_keys_get_a_clear_error():
    loss, _, _, sample = _random_setup()
    data = sample()
    with pytest.raises(KeyError, match="example"):
        loss(data.exclude("example"))
    with pytest.raises(KeyError, match="nstep"):
        loss(data.exclude("nstep"))
    with pytest.raises(KeyError, match="action"):
        loss(data.exclude("action"))
    with pytest.raises(KeyError, match="observation"):
        loss(data.exclude(("next", "observation")))


def test_in_keys_name_every_entry_the_loss_reads_and_follow_set_keys():
    """As torchrl's losses: what a replay buffer must keep. The actor and the classifier read "observation"
    (and the classifier the action), so the loss reads it at the root and in next, nstep and example."""
    loss, _, _, sample = _random_setup()
    assert loss.in_keys == ["observation", "action", ("next", "observation"), ("nstep", "observation"),
                            ("example", "observation"), "one_step"]
    data = sample()
    data.set("unread", torch.zeros(data.shape[0]))
    kept = data.select(*loss.in_keys, strict=False)  # one_step is optional: absent here
    assert "unread" not in kept.keys()
    torch.testing.assert_close(loss(kept)["loss_classifier"], loss(data)["loss_classifier"])
    loss.set_keys(example_state="success_examples", one_step="short_window")
    assert ("success_examples", "observation") in loss.in_keys and "short_window" in loss.in_keys
    assert ("example", "observation") not in loss.in_keys


def test_set_keys_renames_the_example_entry():
    loss, _, _, sample = _random_setup()
    data = sample()
    data.rename_key_("example", "success_examples")
    loss.set_keys(example_state="success_examples")
    out = loss(data)
    assert torch.isfinite(out["loss_classifier"])
    with pytest.raises(ValueError, match="not an accepted"):
        loss.set_keys(not_a_key="x")


@pytest.mark.parametrize(
    "kwargs, message",
    [({"gamma": 1.0}, "gamma"), ({"gamma": 0.0}, "gamma"), ({"n_steps": 0}, "n_steps"), ({"n_steps": 2.5}, "n_steps")],
)
def test_bad_hyper_parameters_are_rejected(kwargs, message):
    with pytest.raises(ValueError, match=message):
        RCELoss(constant_actor(0.0), linear_logit_ensemble([1.0]), **kwargs)


def test_actor_that_does_not_write_the_action_is_rejected():
    actor = TensorDictModule(nn.Linear(1, 1), in_keys=["observation"], out_keys=["act"])
    with pytest.raises(ValueError, match="action"):
        RCELoss(actor, linear_logit_ensemble([1.0]))


def test_a_batch_marked_one_step_gets_the_one_step_label_and_needs_no_nstep_entry():
    # the release's fallback while no reset episode has n transitions: n = 10, but the one-step label
    gamma = 0.9
    loss = RCELoss(constant_actor(0.0), linear_logit_ensemble(SLOPES), gamma=gamma, n_steps=10)
    data = batch(obs=[0.0, 0.0], nxt=[0.5, 2.0])  # no "nstep" entry
    with pytest.raises(KeyError, match="nstep"):
        loss.labels(data)
    data.set("one_step", torch.ones(2, dtype=torch.bool))
    label, weight = loss.labels(data)
    expected = [gamma * math.exp(-2 * x) / (1 + gamma * math.exp(-2 * x)) for x in (0.5, 2.0)]  # steepest member
    torch.testing.assert_close(label, torch.tensor(expected), rtol=1e-6, atol=0)
    torch.testing.assert_close(weight, 1 + gamma * torch.exp(-2 * torch.tensor([0.5, 2.0])), rtol=1e-6, atol=0)
    assert torch.isfinite(loss(data)["loss_classifier"])


@pytest.mark.parametrize("fast", [False, True])
def test_loss_classifier_and_loss_actor_are_forwards_two_losses(fast):
    """The separate losses (for the release's update order) are the joint forward's entries on the same
    parameters, with the same gradients, on the reference and the accelerated path."""
    from torchrl_reset import accel

    torch.manual_seed(0)
    loss, actor, ens, sample = _random_setup()
    if fast:
        fast_ens = accel.FastEnsembleValueOperator(4, 2, num_members=3, hidden_sizes=(16, 16))
        fast_ens.load_state_dict(ens.state_dict())
        loss = accel.FastRCELoss(actor, fast_ens, gamma=0.99, n_steps=4)
    batch = sample()
    joint = loss(batch.clone())
    classifier, meta = loss.loss_classifier(batch.clone())
    actor_loss, _ = loss.loss_actor(batch.clone())
    torch.testing.assert_close(classifier, joint["loss_classifier"])
    torch.testing.assert_close(actor_loss, joint["loss_actor"])
    for key in ("label", "weight", "success_probability", "example_classifier"):
        torch.testing.assert_close(meta[key], joint[key])
    params = list(loss.parameters())
    both = torch.autograd.grad(joint["loss_classifier"] + joint["loss_actor"], params, allow_unused=True)
    apart = torch.autograd.grad(classifier + actor_loss, params, allow_unused=True)
    for a, b in zip(both, apart):
        assert (a is None) == (b is None)
        if a is not None:
            torch.testing.assert_close(a, b)
