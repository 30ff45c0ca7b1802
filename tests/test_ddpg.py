"""The recipe's DDPG agents (torchrl's DDPGLoss on the paper's critic layout): the losses by hand, and LNT's
bounded-target option."""
import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torchrl.modules import ValueOperator
from torchrl.objectives import DDPGLoss
from torchrl.objectives.utils import ValueEstimators

from torchrl_reset import EnsembleValueOperator


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
        from torchrl_reset.td_bounds import bound_td0_targets
        bound_td0_targets(loss, reward_bounds)
    with torch.no_grad():
        loss.actor_network_params["module", "weight"].fill_(2.0)
        loss.value_network_params["module", "net", "weight"].copy_(torch.tensor([[1.0, 3.0]]))
        loss.value_network_params["module", "net", "bias"].fill_(0.5)
        loss.target_actor_network_params["module", "weight"].fill_(1.0)
        loss.target_value_network_params["module", "net", "weight"].copy_(torch.tensor([[2.0, 1.0]]))
        loss.target_value_network_params["module", "net", "bias"].fill_(0.0)
    return loss


def test_losses_and_gradients_by_hand():
    loss = hand_worked_loss(DDPGLoss)
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


def test_an_ensemble_critic_gets_one_reward_column_per_member():
    """LNT's reset agent: K members, one TD target per member (the recipe expands the reward to K columns);
    a single reward column for three members is refused by torchrl's estimator."""
    actor, critic = recipe_networks(3, 0.0)
    loss = DDPGLoss(actor, critic, delay_actor=True, delay_value=True)
    loss.make_value_estimator(gamma=0.9)
    loss(random_batch(4, 3, torch.Generator().manual_seed(0)))
    with pytest.raises(RuntimeError):
        loss(random_batch(4, 1, torch.Generator().manual_seed(0)))


def test_bounded_targets_are_clipped_to_the_values_the_rewards_allow():
    from torchrl_reset.td_bounds import BoundedTD0Estimator

    # the hand-worked losses above, with rewards in [0, 1] and gamma = 0.9: values lie in [0, 10]
    loss = hand_worked_loss(DDPGLoss, reward_bounds=(0.0, 1.0))
    assert isinstance(loss.value_estimator, BoundedTD0Estimator)
    assert loss.value_estimator.bounds == pytest.approx((0.0, 10.0))
    # next states 3, -1, 6 (none terminal); a' = s'; Q'(s', a') = 3 s' = 9, -3, 18
    td = batch(obs=[1.0, 2.0, 0.0], action=[0.5, -1.0, 0.0], next_obs=[3.0, -1.0, 6.0], reward=[1.0, 0.0, 1.0],
               terminated=[False, False, False])
    out = loss(td)
    # y = r + 0.9 Q' = 9.1, -2.7, 17.2, clipped to [0, 10]: 9.1 (inside), 0, 10
    torch.testing.assert_close(out["target_value"], torch.tensor([9.1, 0.0, 10.0]))
    # Q(s, a) = 3, -0.5, 0.5
    assert float(out["loss_value"].detach()) == pytest.approx(((3 - 9.1) ** 2 + 0.5**2 + 9.5**2) / 3)


def test_bounded_targets_refuse_bad_bounds_and_other_estimators():
    from torchrl_reset.td_bounds import BoundedTD0Estimator, bound_td0_targets

    with pytest.raises(ValueError, match="low < high"):
        BoundedTD0Estimator(reward_bounds=(1.0, 0.0), gamma=0.9, value_network=None)
    with pytest.raises(ValueError, match="pair of numbers"):
        BoundedTD0Estimator(reward_bounds=1.0, gamma=0.9, value_network=None)
    with pytest.raises(ValueError, match=r"discount in \[0, 1\)"):
        BoundedTD0Estimator(reward_bounds=(0.0, 1.0), gamma=1.0, value_network=None)
    actor = TensorDictModule(torch.nn.Linear(1, 1, bias=False), ["observation"], ["action"])
    loss = DDPGLoss(actor, ValueOperator(LinearCritic(1, 1), in_keys=["observation", "action"]))
    loss.make_value_estimator(ValueEstimators.TDLambda, gamma=0.9, lmbda=0.5)
    with pytest.raises(TypeError, match="TD\\(0\\) estimator"):
        bound_td0_targets(loss, (0.0, 1.0))
