"""The stochastic reset actor in the library's losses (SACLoss's conventions): RCELoss, EntropyDDPGLoss and
EnsembleDDPGLoss with a tanh-Gaussian actor. Values are worked out from the formulas (the tanh-Gaussian's
entropy by quadrature, the temperature's gradient by hand), not read from the code's output."""
from __future__ import annotations

import math

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModuleBase
from torch import nn
from torchrl.data import Bounded
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import ValueOperator
from torchrl.objectives import DDPGLoss

from torchrl_reset import EnsembleValueOperator, RCELoss, accel
from torchrl_reset.actor_heads import TanhHead, TanhNormalHead
from torchrl_reset.ensemble_ddpg import EnsembleDDPGLoss
from torchrl_reset.stochastic_actor import EntropyDDPGLoss

LOC = 0.3  # the Gaussian's location at every state (scale 1)


def constant_gaussian_actor(head=None, act_dim=1):
    """A tanh-Gaussian actor on [-1, 1]^act_dim whose Gaussian is N(LOC, 1) at every state: its network's weights
    are 0, its biases LOC for the location and 0 for the scale (NormalParamExtractor maps 0 to a scale of 1)."""
    net = nn.Linear(1, 2 * act_dim)
    with torch.no_grad():
        net.weight.zero_()
        net.bias.copy_(torch.tensor([LOC] * act_dim + [0.0] * act_dim))
    spec = Bounded(-torch.ones(act_dim), torch.ones(act_dim), shape=(act_dim,))
    return (head or TanhNormalHead()).build(net, spec)


class ConstantLogits(TensorDictModuleBase):
    """K classifier members whose logit is ``value`` plus 0 * the action (so the actor's loss has a graph)."""

    in_keys, out_keys = ["observation", "action"], ["state_action_logit"]

    def __init__(self, value: float, members: int = 2) -> None:
        super().__init__()
        self.value = nn.Parameter(torch.tensor(value))
        self.members = members

    def forward(self, td):
        action = td["action"]
        logits = self.value + 0.0 * action.sum(-1, keepdim=True).expand(*action.shape[:-1], self.members)
        return td.set("state_action_logit", logits)


def rce_batch(n: int, act_dim: int = 1) -> TensorDict:
    state = lambda: TensorDict(observation=torch.randn(n, 1), batch_size=[n])  # noqa: E731
    return TensorDict(observation=torch.randn(n, 1), action=torch.rand(n, act_dim) * 2 - 1, next=state(),
                      nstep=state(), example=state(), batch_size=[n])


def tanh_gaussian_entropy(loc: float) -> float:
    """The differential entropy of tanh(x), x ~ N(loc, 1): H(N) + E[log(1 - tanh(x)^2)], by quadrature."""
    x = torch.linspace(loc - 12, loc + 12, 200_001, dtype=torch.float64)
    density = torch.exp(-0.5 * (x - loc) ** 2) / math.sqrt(2 * math.pi)
    log_jacobian = 2 * (math.log(2.0) - x - torch.nn.functional.softplus(-2 * x))  # log(1 - tanh(x)^2)
    dx = float(x[1] - x[0])
    return 0.5 * math.log(2 * math.pi * math.e) + float((density * log_jacobian).sum()) * dx


@pytest.mark.parametrize("entropy_sample", ["own", "shared"])
def test_the_actor_loss_scores_samples_and_adds_alpha_times_log_pi(entropy_sample):
    torch.manual_seed(0)
    loss = RCELoss(constant_gaussian_actor(), ConstantLogits(-1.0), n_steps=4, alpha_init=0.5,
                   entropy_sample=entropy_sample)
    value, meta = loss.loss_actor(rce_batch(40_000))
    value_now = float(value.detach())
    # -mean min_i sigmoid(-1) + alpha * mean(log pi): the value term is the same whatever the sample
    assert value_now == pytest.approx(-1 / (1 + math.e) + 0.5 * float(meta["log_prob"].mean()), rel=1e-5)
    # the samples' -mean(log pi) estimates the tanh-Gaussian's entropy (Monte Carlo over 40,000 states)
    assert float(meta["entropy"]) == pytest.approx(tanh_gaussian_entropy(LOC), abs=0.02)
    assert float(meta["alpha"]) == pytest.approx(0.5)
    # the actor's term reaches the actor only: alpha is held fixed in it
    value.backward()
    assert loss.temperature.log_alpha.grad is None
    assert loss.actor_network_params.get(("module", "0", "module", "0", "module", "0", "bias")).grad is not None


def test_the_temperatures_loss_moves_alpha_towards_the_target_entropy():
    torch.manual_seed(0)
    loss = RCELoss(constant_gaussian_actor(act_dim=2), ConstantLogits(0.0), n_steps=4)
    assert loss.temperature.target_entropy == -2.0  # "auto": -dim(A), read from the actor's spec
    assert any(p is loss.temperature.log_alpha for p in loss.parameters())  # an optimizer of the loss gets it
    out = loss(rce_batch(20_000, act_dim=2))
    assert set(out.keys()) >= {"loss_classifier", "loss_actor", "loss_alpha", "alpha", "entropy"}
    out["loss_alpha"].backward()
    # d/d log_alpha of -mean(log alpha (log pi + target)) = -(mean log pi - 2) = entropy + 2: positive, as the
    # two independent components' entropy (2 H, about -0.42) is above the target -2: alpha goes down
    expected = 2 * tanh_gaussian_entropy(LOC) + 2.0
    assert float(loss.temperature.log_alpha.grad) == pytest.approx(expected, abs=0.03)
    assert float(out["alpha"]) == pytest.approx(0.01)  # the default first value


def test_a_fixed_temperature_is_no_parameter_and_a_deterministic_actor_changes_nothing():
    fixed = RCELoss(constant_gaussian_actor(), ConstantLogits(0.0), n_steps=4, alpha_init=1e-4, fixed_alpha=True)
    assert not any(p is fixed.temperature.log_alpha for p in fixed.parameters())
    assert float(fixed.loss_alpha(torch.tensor([-1.0, 2.0]))) == 0.0
    deterministic = RCELoss(constant_gaussian_actor(TanhHead()), ConstantLogits(0.0), n_steps=4)
    assert not deterministic.stochastic and deterministic.temperature is None
    out = deterministic(rce_batch(8))
    assert "loss_alpha" not in out.keys() and "alpha" not in out.keys()
    with pytest.raises(RuntimeError, match="needs a stochastic actor"):
        deterministic.loss_alpha(torch.zeros(3))
    with pytest.raises(ValueError, match="label_action must be one of"):
        RCELoss(constant_gaussian_actor(), ConstantLogits(0.0), label_action="mean")
    with pytest.raises(ValueError, match="entropy_sample must be one of"):
        RCELoss(constant_gaussian_actor(), ConstantLogits(0.0), entropy_sample="both")


def test_labels_take_the_deterministic_action_or_a_sample_as_asked():
    torch.manual_seed(0)
    ensemble = EnsembleValueOperator(1, 1, num_members=2, hidden_sizes=(8,))
    data = rce_batch(64)
    deterministic = RCELoss(constant_gaussian_actor(), ensemble, n_steps=4)
    first, _ = deterministic.labels(data)
    torch.manual_seed(123)  # another generator state: the same labels (tanh(loc), no draw)
    assert torch.equal(first, deterministic.labels(data)[0])
    # the deterministic action is tanh(LOC) at every state: the labels of a tanh actor fixed there
    tanh_net = nn.Linear(1, 1)
    with torch.no_grad():
        tanh_net.weight.zero_()
        tanh_net.bias.fill_(LOC)
    fixed = TanhHead().build(tanh_net, Bounded(-1.0, 1.0, shape=(1,)))
    same = RCELoss(fixed, ensemble, n_steps=4)
    assert torch.allclose(same.labels(data)[0], first, atol=1e-6)
    sampled = RCELoss(constant_gaussian_actor(), ensemble, n_steps=4, label_action="sample")
    assert not torch.equal(sampled.labels(data)[0], sampled.labels(data)[0])  # a draw each time


def test_the_fast_loss_agrees_with_the_reference_for_a_stochastic_actor():
    obs_dim, act_dim = 3, 2
    spec = Bounded(-torch.ones(act_dim), torch.ones(act_dim), shape=(act_dim,))
    torch.manual_seed(0)
    actor = TanhNormalHead().make_actor(obs_dim, spec, (16,))
    plain = EnsembleValueOperator(obs_dim, act_dim, num_members=3, hidden_sizes=(16, 16))
    fast = accel.FastEnsembleValueOperator(obs_dim, act_dim, num_members=3, hidden_sizes=(16, 16))
    fast.load_state_dict(plain.state_dict())
    data = TensorDict(observation=torch.randn(32, obs_dim), action=torch.rand(32, act_dim) * 2 - 1,
                      next=TensorDict(observation=torch.randn(32, obs_dim), batch_size=[32]),
                      nstep=TensorDict(observation=torch.randn(32, obs_dim), batch_size=[32]),
                      example=TensorDict(observation=torch.randn(32, obs_dim), batch_size=[32]), batch_size=[32])
    outs = []
    for loss in (RCELoss(actor, plain, n_steps=4), accel.FastRCELoss(actor, fast, n_steps=4)):
        torch.manual_seed(7)  # the same draws for both
        outs.append(loss(data))
    for key in ("loss_classifier", "loss_actor", "loss_alpha", "entropy"):
        assert torch.allclose(outs[0][key], outs[1][key], atol=1e-5), key


def test_old_state_dicts_with_the_entropy_bonus_key_load():
    loss = RCELoss(constant_gaussian_actor(), ConstantLogits(0.0), n_steps=4)
    state = loss.state_dict()
    state["entropy_bonus.log_alpha"] = torch.tensor(math.log(0.25))
    del state["temperature.log_alpha"]
    loss.load_state_dict(state)
    assert float(loss.alpha) == pytest.approx(0.25)


class Critic(nn.Module):
    def __init__(self, width: int) -> None:
        super().__init__()
        self.net = nn.Sequential(nn.Linear(width, 16), nn.ReLU(), nn.Linear(16, 1))

    def forward(self, observation, action):
        return self.net(torch.cat([observation, action], -1))


def ddpg_batch(n: int, obs_dim: int, act_dim: int) -> TensorDict:
    nxt = TensorDict(observation=torch.randn(n, obs_dim), reward=torch.rand(n, 1),
                     done=torch.zeros(n, 1, dtype=torch.bool), terminated=torch.zeros(n, 1, dtype=torch.bool),
                     batch_size=[n])
    return TensorDict(observation=torch.randn(n, obs_dim), action=torch.rand(n, act_dim) * 2 - 1, next=nxt,
                      batch_size=[n])


def test_entropy_ddpg_loss_is_ddpg_loss_for_a_deterministic_actor_and_adds_the_temperature_otherwise():
    obs_dim, act_dim = 3, 2
    spec = Bounded(-torch.ones(act_dim), torch.ones(act_dim), shape=(act_dim,))
    torch.manual_seed(0)
    actor = TanhHead().make_actor(obs_dim, spec, (16,))
    critic = ValueOperator(Critic(obs_dim + act_dim), in_keys=["observation", "action"])
    data = ddpg_batch(16, obs_dim, act_dim)
    ours, stock = EntropyDDPGLoss(actor, critic), DDPGLoss(actor, critic)
    for loss in (ours, stock):
        loss.make_value_estimator(gamma=0.99)
    a, b = ours(data), stock(data)
    assert set(a.keys()) == set(b.keys())
    for key in ("loss_actor", "loss_value"):
        assert torch.equal(a[key], b[key])
    stochastic = EntropyDDPGLoss(TanhNormalHead().make_actor(obs_dim, spec, (16,)), critic, alpha_init=0.2)
    stochastic.make_value_estimator(gamma=0.99)
    out = stochastic(data)
    assert {"loss_alpha", "alpha", "entropy"} <= set(out.keys()) and float(out["alpha"]) == pytest.approx(0.2)
    # its actor loss is -mean Q at a sample plus alpha * mean(log pi) of a sample of its own
    torch.manual_seed(3)
    value, meta = stochastic.loss_actor(data)
    torch.manual_seed(3)
    with set_exploration_type(ExplorationType.RANDOM):
        q_term, _ = DDPGLoss.loss_actor(stochastic, data)  # the same draw for the critic's term
    assert float(value.detach()) == pytest.approx(float(q_term.detach()) + 0.2 * float(meta["log_prob"].mean()),
                                                  rel=1e-5)


def test_the_ensemble_ddpg_loss_takes_the_stochastic_actor_too():
    obs_dim, act_dim, k, b = 3, 2, 4, 5
    spec = Bounded(-torch.ones(act_dim), torch.ones(act_dim), shape=(act_dim,))
    torch.manual_seed(0)
    q = EnsembleValueOperator(obs_dim, act_dim, num_members=k, hidden_sizes=(8, 8), prior_scale=0.0,
                              out_keys=["state_action_value"])
    loss = EnsembleDDPGLoss(TanhNormalHead().make_actor(obs_dim, spec, (8,)), q, independent_batches=True,
                            member_actor_gradient=True)
    data = ddpg_batch(k * b, obs_dim, act_dim).reshape(k, b)
    out = loss(data)
    assert {"loss_actor", "loss_value", "loss_alpha", "alpha", "entropy"} <= set(out.keys())
    (out["loss_actor"] + out["loss_value"] + out["loss_alpha"]).backward()
    assert loss.temperature.log_alpha.grad is not None
