"""EnsembleDDPGLoss: the release's K-critic DDPG semantics, checked on values worked out by hand."""
from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torch import nn

from torchrl_reset import EnsembleValueOperator
from torchrl_reset.ensemble_ddpg import EnsembleDDPGLoss


def _actor():
    torch.manual_seed(0)
    return TensorDictModule(nn.Sequential(nn.Linear(3, 2), nn.Tanh()), ["observation"], ["action"])


def _critics(k=2):
    return EnsembleValueOperator(3, 2, num_members=k, hidden_sizes=(4,), prior_scale=0.0,
                                 out_keys=["state_action_value"])


def _constant(params, values):
    """Every member's output a constant: zero weights, the last bias the member's value."""
    with torch.no_grad():
        for key, tensor in params.items(True, True):
            tensor.zero_()
        params.get("bias_1").copy_(torch.tensor(values).unsqueeze(-1))


def _batch(shape, reward=0.5, terminated=None):
    terminated = torch.zeros(*shape, 1, dtype=torch.bool) if terminated is None else terminated
    nxt = TensorDict(observation=torch.randn(*shape, 3), reward=torch.full((*shape, 1), reward),
                     terminated=terminated, done=terminated.clone(), batch_size=shape)
    return TensorDict(observation=torch.randn(*shape, 3), action=torch.rand(*shape, 2) * 2 - 1, next=nxt,
                      batch_size=shape)


def test_each_members_td_target_and_the_value_loss_by_hand():
    loss = EnsembleDDPGLoss(_actor(), _critics(), gamma=0.9)
    _constant(loss.target_value_network_params, [1.0, 2.0])  # Q'_0 = 1, Q'_1 = 2
    _constant(loss.value_network_params, [0.0, 0.0])  # Q_0 = Q_1 = 0
    batch = _batch([2], terminated=torch.tensor([[False], [True]]))
    # y_k = 0.5 + 0.9 * (1 - terminated) * Q'_k: member 0 (1.4, 0.5), member 1 (2.3, 0.5)
    assert loss.targets(batch).flatten().tolist() == pytest.approx([1.4, 0.5, 2.3, 0.5])
    value, _ = loss.loss_value(batch)
    assert float(value) == pytest.approx((1.4 ** 2 + 0.25 + 2.3 ** 2 + 0.25) / 4)
    # rewards in [0, 0.1] with gamma 0.9: values in [0, 1], the targets clipped there
    bounded = EnsembleDDPGLoss(_actor(), _critics(), gamma=0.9, reward_bounds=(0.0, 0.1))
    _constant(bounded.target_value_network_params, [1.0, 2.0])
    _constant(bounded.value_network_params, [0.0, 0.0])
    assert bounded.targets(batch).flatten().tolist() == pytest.approx([1.0, 0.5, 1.0, 0.5])


def test_independent_batches_give_identical_members_different_gradients():
    loss = EnsembleDDPGLoss(_actor(), _critics(), independent_batches=True)
    params = loss.value_network_params
    with torch.no_grad():  # member 1 a copy of member 0, its target too
        for tensors in (params, loss.target_value_network_params):
            for key, tensor in tensors.items(True, True):
                tensor[1].copy_(tensor[0])
    batch = _batch([2, 8])
    loss.loss_value(batch)[0].backward()
    grad = params.get("weight_0").grad
    assert not torch.allclose(grad[0], grad[1])  # each member on its own rows
    params.get("weight_0").grad = None
    same = batch.clone()
    same[1] = batch[0]  # both members given the same rows
    loss.loss_value(same)[0].backward()
    grad = params.get("weight_0").grad
    assert torch.allclose(grad[0], grad[1])
    with pytest.raises(ValueError, match=r"\[K, B\]"):
        loss.loss_value(_batch([8]))


def test_an_actor_rows_gradient_comes_from_its_member_alone():
    loss = EnsembleDDPGLoss(_actor(), _critics(), independent_batches=True, member_actor_gradient=True)
    with torch.no_grad():  # member 1's value does not depend on the action; member 0's does
        loss.value_network_params.get("action_weight")[1].zero_()
    batch = _batch([2, 1])  # one row per member: the actor's one row is drawn from these two
    seen = set()
    for seed in range(12):
        torch.manual_seed(seed)
        member = int(torch.randint(2, (1,)))  # the row the loss draws next: flat index = member (B = 1)
        torch.manual_seed(seed)
        for p in loss.actor_network_params.values(True, True):
            p.grad = None
        loss.loss_actor(batch)[0].backward()
        grad = loss.actor_network_params.get(("module", "0", "weight")).grad
        assert (grad.abs().sum() == 0) == (member == 1)
        seen.add(member)
    assert seen == {0, 1}


def test_without_member_gradients_the_actor_ascends_the_members_mean():
    loss = EnsembleDDPGLoss(_actor(), _critics())
    with torch.no_grad():
        loss.value_network_params.get("action_weight")[1].zero_()
    batch = _batch([4])
    loss.loss_actor(batch)[0].backward()
    mean_grad = loss.actor_network_params.get(("module", "0", "weight")).grad.clone()
    # the mean of members 0 and 1 is half of member 0's value plus a term without the action
    one = EnsembleDDPGLoss(_actor(), EnsembleValueOperator(3, 2, num_members=1, hidden_sizes=(4,), prior_scale=0.0,
                                                           out_keys=["state_action_value"]))
    with torch.no_grad():
        for key, tensor in one.value_network_params.items(True, True):
            tensor.copy_(loss.value_network_params.get(key)[:1])
    one.loss_actor(batch)[0].backward()
    assert torch.allclose(mean_grad, 0.5 * one.actor_network_params.get(("module", "0", "weight")).grad, atol=1e-7)


# -- the recipe's keys and presets ---------------------------------------------------------------------------

from pathlib import Path  # noqa: E402

from helpers import quick_config  # noqa: E402

RECIPES = Path(__file__).resolve().parents[1] / "recipes"

from torchrl_reset_recipes import train
from torchrl_reset_recipes.training.agents import make_reset_agent
from torchrl_reset_recipes.training.buffers import make_buffers
from torchrl_reset_recipes.training.run_spec import run_spec
from torchrl_reset_recipes.training.task_envs import task_dimensions

KEYS = ("independent_batches", "member_actor_gradient", "target_draws", "sampling")


def _config(tmp_path, *overrides):
    return quick_config(tmp_path, "reset.batch_size=8", "forward.batch_size=8", *overrides)


@pytest.mark.parametrize("algo, reward", [("lnt_release", "shaped"), ("lnt_sparse_release", "sparse")])
def test_the_release_presets_turn_every_option_on_and_keep_their_baselines_reward(tmp_path, algo, reward):
    cfg = _config(tmp_path, f"algo={algo}")
    assert [cfg.algo[k] for k in KEYS] == [True, True, True, "episode"]
    assert cfg.algo.name == algo and cfg.algo.reset_reward == reward and cfg.algo.num_members == 20
    plain = _config(tmp_path, f"algo={algo.replace('_release', '')}")
    assert [plain.algo[k] for k in KEYS] == [False, False, False, "transition"]


def test_the_release_ensemble_draws_its_targets_and_samples_k_batches(tmp_path):
    cfg = _config(tmp_path, "algo=lnt_sparse_release", "algo.num_members=3")
    torch.manual_seed(0)
    obs_dim, spec = task_dimensions(cfg)
    agent = make_reset_agent(run_spec(cfg, check=False), obs_dim, spec)
    loss = agent.loss
    assert isinstance(loss, EnsembleDDPGLoss) and loss.draws_actor_rows
    live, target = loss.value_network_params.get("weight_0"), loss.target_value_network_params.get("weight_0")
    # members 0 and 1 start from targets of their own; the last member's target is its copy
    assert not torch.equal(live[0], target[0]) and not torch.equal(live[1], target[1])
    assert torch.equal(live[2], target[2])
    actor_live = list(loss.actor_network_params.values(True, True))
    actor_target = list(loss.target_actor_network_params.values(True, True))
    assert any(not torch.equal(a, b) for a, b in zip(actor_live, actor_target) if a.dim() > 1)
    _, reset_rb = make_buffers(run_spec(cfg, check=False))
    assert reset_rb.batch_size == 3 * 8  # K batches of reset.batch_size, split by prepare()
    with pytest.raises(ValueError, match=r"\[K, B\]"):  # a [B] batch is refused by the K-batch loss
        loss.loss_value(_batch([8]))


@pytest.mark.parametrize("algo", ["lnt_release", "lnt_sparse_release"])
def test_a_short_run_with_the_release_ensemble_trains(tmp_path, algo):
    summary = train.train(_config(tmp_path, f"algo={algo}", "algo.num_members=4"))
    assert summary["finished"] and summary["algo"] == algo
    assert run_spec(_config(tmp_path, f"algo={algo}"), check=False).kind.name == algo
