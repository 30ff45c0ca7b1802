"""DirectDDPGLoss: torchrl's DDPG losses by hand, and the same results as torchrl's DDPGLoss."""
import copy

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torchrl.modules import ValueOperator
from torchrl.objectives import DDPGLoss, SoftUpdate
from torchrl.objectives.utils import ValueEstimators

from torchrl_reset import EnsembleValueOperator
from torchrl_reset.accel import DirectDDPGLoss


class LinearCritic(torch.nn.Module):
    def __init__(self, obs_dim: int, act_dim: int):
        super().__init__()
        self.net = torch.nn.Linear(obs_dim + act_dim, 1)

    def forward(self, observation, action):
        return self.net(torch.cat([observation, action], -1))


def batch(obs, action, next_obs, reward, terminated) -> TensorDict:
    n = len(obs)
    col = lambda values, dtype=torch.float32: torch.tensor(values, dtype=dtype).reshape(n, -1)  # noqa: E731
    return TensorDict(
        observation=col(obs), action=col(action),
        next=TensorDict(observation=col(next_obs), reward=col(reward), done=col(terminated, torch.bool),
                        terminated=col(terminated, torch.bool), batch_size=[n]),
        batch_size=[n],
    )


def hand_worked_loss(loss_cls, reward_bounds=None):
    """actor a = 2 s, critic Q(s, a) = s + 3 a + 0.5; targets a' = s', Q'(s', a') = 2 s' + a'; gamma = 0.9."""
    actor = TensorDictModule(torch.nn.Linear(1, 1, bias=False), ["observation"], ["action"])
    critic = ValueOperator(LinearCritic(1, 1), in_keys=["observation", "action"])
    loss = loss_cls(actor, critic, delay_actor=True, delay_value=True)
    loss.make_value_estimator(gamma=0.9)
    if reward_bounds is not None:
        from torchrl_reset import bound_td0_targets
        bound_td0_targets(loss, reward_bounds)
    with torch.no_grad():
        loss.actor_network_params["module", "weight"].fill_(2.0)
        loss.value_network_params["module", "net", "weight"].copy_(torch.tensor([[1.0, 3.0]]))
        loss.value_network_params["module", "net", "bias"].fill_(0.5)
        loss.target_actor_network_params["module", "weight"].fill_(1.0)
        loss.target_value_network_params["module", "net", "weight"].copy_(torch.tensor([[2.0, 1.0]]))
        loss.target_value_network_params["module", "net", "bias"].fill_(0.0)
    return loss


@pytest.mark.parametrize("loss_cls", [DDPGLoss, DirectDDPGLoss])
def test_losses_and_gradients_by_hand(loss_cls):
    loss = hand_worked_loss(loss_cls)
    td = batch(obs=[1.0, 2.0], action=[0.5, -1.0], next_obs=[3.0, -1.0], reward=[1.0, 0.0], terminated=[False, True])
    out = loss(td)
    # Q(s, a) = [3, -0.5]; target a' = [3, -1], Q'(s', a') = [9, -3], y = r + 0.9 (1 - term) Q' = [9.1, 0]
    assert float(out["loss_value"].detach()) == pytest.approx(((3 - 9.1) ** 2 + 0.5**2) / 2)  # 18.73
    torch.testing.assert_close(out["target_value"], torch.tensor([9.1, 0.0]))
    torch.testing.assert_close(td["td_error"], torch.tensor([(3 - 9.1) ** 2, 0.25]))
    # the actor's actions [2, 4]: Q = [7.5, 14.5]
    assert float(out["loss_actor"].detach()) == pytest.approx(-11.0)
    (out["loss_actor"] + out["loss_value"]).backward()
    assert float(loss.actor_network_params["module", "weight"].grad) == pytest.approx(-4.5)  # -mean(c2 s)
    # the critic's gradient comes from the value loss only: mean(2 (Q - y) [s, a]), mean(2 (Q - y))
    torch.testing.assert_close(loss.value_network_params["module", "net", "weight"].grad, torch.tensor([[-7.1, -2.55]]))
    assert float(loss.value_network_params["module", "net", "bias"].grad) == pytest.approx(-6.6)


def recipe_networks(members: int, prior_scale: float):
    """The recipe's layout on small sizes: an MLP actor with tanh onto the action box, an ensemble critic."""
    from tensordict.nn import TensorDictSequential
    from torchrl.data import Bounded
    from torchrl.modules import TanhModule

    net = torch.nn.Sequential(torch.nn.Linear(5, 16), torch.nn.ReLU(), torch.nn.Linear(16, 12), torch.nn.ReLU(),
                              torch.nn.Linear(12, 3))
    actor = TensorDictSequential(
        TensorDictModule(net, ["observation"], ["action_preactivation"]),
        TanhModule(["action_preactivation"], ["action"], spec=Bounded(-2.0, 2.0, shape=(3,))),
    )
    critic = EnsembleValueOperator(5, 3, num_members=members, hidden_sizes=(16, 12), prior_scale=prior_scale,
                                   out_keys=["state_action_value"])
    return actor, critic


def random_batch(n: int, columns: int, gen: torch.Generator) -> TensorDict:
    terminated = torch.rand(n, 1, generator=gen) < 0.2
    return TensorDict(
        observation=torch.randn(n, 5, generator=gen), action=torch.rand(n, 3, generator=gen) * 4 - 2,
        next=TensorDict(observation=torch.randn(n, 5, generator=gen), reward=torch.randn(n, columns, generator=gen),
                        done=terminated.expand(n, columns), terminated=terminated.expand(n, columns), batch_size=[n]),
        batch_size=[n],
    )


@pytest.mark.parametrize("members,prior_scale", [(1, 0.0), (3, 1.5)])
def test_training_matches_torchrl_ddpg_loss_step_for_step(members, prior_scale):
    """Five Adam steps with soft target updates, from the same start: the same losses, metadata and parameters."""
    torch.manual_seed(0)
    actor, critic = recipe_networks(members, prior_scale)
    runs = []
    for cls in (DDPGLoss, DirectDDPGLoss):
        loss = cls(copy.deepcopy(actor), copy.deepcopy(critic), delay_actor=True, delay_value=True)
        loss.make_value_estimator(gamma=0.95)
        optim = torch.optim.Adam(loss.parameters(), lr=1e-2)
        targets = SoftUpdate(loss, tau=0.2)
        gen = torch.Generator().manual_seed(1)
        outputs = []
        for _ in range(5):
            data = random_batch(32, members, gen)
            out = loss(data)
            optim.zero_grad()
            (out["loss_actor"] + out["loss_value"]).backward()
            optim.step()
            targets.step()
            outputs.append((out.detach(), data["td_error"]))
        runs.append((outputs, loss.state_dict()))
    (stock, stock_state), (direct, direct_state) = runs
    for (a, a_err), (b, b_err) in zip(stock, direct):
        assert sorted(a.keys()) == sorted(b.keys())
        for key in a.keys():
            torch.testing.assert_close(b[key], a[key], rtol=1e-5, atol=1e-6)
        torch.testing.assert_close(b_err, a_err, rtol=1e-5, atol=1e-6)
    assert stock_state.keys() == direct_state.keys()
    for key in stock_state:
        torch.testing.assert_close(direct_state[key], stock_state[key], rtol=1e-5, atol=1e-6)


def stock_and_direct() -> tuple[DDPGLoss, DirectDDPGLoss]:
    """Both losses on copies of the same small networks."""
    torch.manual_seed(0)
    actor, critic = recipe_networks(1, 0.0)
    return tuple(cls(copy.deepcopy(actor), copy.deepcopy(critic), delay_actor=True, delay_value=True)
                 for cls in (DDPGLoss, DirectDDPGLoss))


def test_other_estimators_and_priority_weights_go_through_torchrl_forward():
    stock, direct = stock_and_direct()
    data = random_batch(8, 1, torch.Generator().manual_seed(2))
    for loss in (stock, direct):
        loss.make_value_estimator(ValueEstimators.TD0, gamma=0.9)
        loss.value_estimator.average_rewards = True  # standardised rewards: not the direct path
    torch.testing.assert_close(direct(data.clone())["loss_value"], stock(data.clone())["loss_value"])
    assert not direct._direct(data)

    weighted = data.clone()
    weighted.set("priority_weight", torch.rand(8))
    for loss in (stock, direct):
        loss.make_value_estimator(ValueEstimators.TD0, gamma=0.9)
    assert direct._direct(data) and not direct._direct(weighted)
    torch.testing.assert_close(direct(weighted.clone())["loss_value"], stock(weighted.clone())["loss_value"])


def test_networks_not_holding_the_trained_parameters_go_through_torchrl_forward():
    stock, direct = stock_and_direct()
    data = random_batch(8, 1, torch.Generator().manual_seed(3))
    assert direct._direct(data)
    # the critic now holds other tensors than the loss's trained parameters: torchrl swaps those in
    direct.value_network.weight_0 = torch.nn.Parameter(torch.zeros_like(direct.value_network.weight_0))
    assert not direct._direct(data)
    for key in ("loss_value", "loss_actor"):
        torch.testing.assert_close(direct(data.clone())[key], stock(data.clone())[key])


def test_mismatched_reward_columns_are_an_error():
    actor, critic = recipe_networks(3, 0.0)
    loss = DirectDDPGLoss(actor, critic, delay_actor=True, delay_value=True)
    loss.make_value_estimator(gamma=0.9)
    data = random_batch(4, 1, torch.Generator().manual_seed(0))  # one reward column for three members
    with pytest.raises(RuntimeError, match="same shape"):
        loss(data)


@pytest.mark.parametrize("loss_cls", [DDPGLoss, DirectDDPGLoss])
def test_bounded_targets_are_clipped_to_the_values_the_rewards_allow(loss_cls):
    from torchrl_reset import BoundedTD0Estimator

    # the hand-worked losses above, with rewards in [0, 1] and gamma = 0.9: values lie in [0, 10]
    loss = hand_worked_loss(loss_cls, reward_bounds=(0.0, 1.0))
    assert isinstance(loss.value_estimator, BoundedTD0Estimator)
    assert loss.value_estimator.bounds == pytest.approx((0.0, 10.0))
    # next states 3, -1, 6 (none terminal); a' = s'; Q'(s', a') = 3 s' = 9, -3, 18
    td = batch(obs=[1.0, 2.0, 0.0], action=[0.5, -1.0, 0.0], next_obs=[3.0, -1.0, 6.0], reward=[1.0, 0.0, 1.0],
               terminated=[False, False, False])
    if loss_cls is DirectDDPGLoss:
        assert loss._direct(td)  # its own fast path clips, not torchrl's forward
    out = loss(td)
    # y = r + 0.9 Q' = 9.1, -2.7, 17.2, clipped to [0, 10]: 9.1 (inside), 0, 10
    torch.testing.assert_close(out["target_value"], torch.tensor([9.1, 0.0, 10.0]))
    # Q(s, a) = 3, -0.5, 0.5
    assert float(out["loss_value"].detach()) == pytest.approx(((3 - 9.1) ** 2 + 0.5**2 + 9.5**2) / 3)


def test_bounded_targets_refuse_bad_bounds_and_other_estimators():
    from torchrl_reset import BoundedTD0Estimator, bound_td0_targets

    with pytest.raises(ValueError, match="low < high"):
        BoundedTD0Estimator(reward_bounds=(1.0, 0.0), gamma=0.9, value_network=None)
    with pytest.raises(ValueError, match="pair of numbers"):
        BoundedTD0Estimator(reward_bounds=1.0, gamma=0.9, value_network=None)
    with pytest.raises(ValueError, match=r"discount in \[0, 1\)"):
        BoundedTD0Estimator(reward_bounds=(0.0, 1.0), gamma=1.0, value_network=None)
    actor = TensorDictModule(torch.nn.Linear(1, 1, bias=False), ["observation"], ["action"])
    loss = DirectDDPGLoss(actor, ValueOperator(LinearCritic(1, 1), in_keys=["observation", "action"]))
    loss.make_value_estimator(ValueEstimators.TDLambda, gamma=0.9, lmbda=0.5)
    with pytest.raises(TypeError, match="TD\\(0\\) estimator"):
        bound_td0_targets(loss, (0.0, 1.0))
