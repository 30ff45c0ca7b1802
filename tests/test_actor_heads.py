"""The reset actor's remedies for a saturating tanh (torchrl_reset.actor_heads and reset.actor.*): every value
below is worked out by hand from the formulas in the docstrings."""
from __future__ import annotations

import csv
import json
import math

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import Bounded
from torchrl.envs.utils import ExplorationType, set_exploration_type

from torchrl_reset.actor_heads import (InvertingGradientHead, InvertingGradients, InvertingHead, TanhHead,
                                       TanhNormalHead, Temperature, actor_penalties, head_from_settings, saturation)


from torchrl_reset_recipes import train
from torchrl_reset_recipes.training.agents import make_actor
from torchrl_reset_recipes.training.config_checks import ConfigError, validate
from torchrl_reset_recipes.training.records import Saturation
from helpers import quick_config  # noqa: E402


def test_inverting_gradients_scale_by_the_distance_to_the_bound_pushed_towards():
    u = torch.tensor([0.5, -0.5, 1.5], requires_grad=True)
    a = InvertingGradients.apply(u)
    assert a.tolist() == [0.5, -0.5, 1.0]  # clipped forward
    # a loss falling as a grows (dL/da = -1, a push up): factors (1 - u) / 2 = 0.25, 0.75, -0.25
    (-a.sum()).backward()
    assert u.grad.tolist() == pytest.approx([-0.25, -0.75, 0.25])
    # beyond the bound the factor is negative: a descent step moves u = 1.5 down, back towards the box
    u.grad = None
    a = InvertingGradients.apply(u)
    a.sum().backward()  # dL/da = +1, a push down: factors (u + 1) / 2 = 0.75, 0.25, 1.25
    assert u.grad.tolist() == pytest.approx([0.75, 0.25, 1.25])


def test_the_inverting_head_maps_normalised_outputs_onto_the_box():
    head = InvertingGradientHead(low=torch.tensor([-2.0, 0.0]), high=torch.tensor([2.0, 1.0]))
    u = torch.tensor([[0.5, -0.5], [-3.0, 0.2]], requires_grad=True)
    td = head(TensorDict(action_preactivation=u, batch_size=[2]))
    # mid + half * clamp(u): (0 + 2 * 0.5, 0.5 + 0.5 * -0.5), (0 + 2 * -1, 0.5 + 0.5 * 0.2)
    assert td["action"].flatten().tolist() == pytest.approx([1.0, 0.25, -2.0, 0.6])
    td["action"].sum().backward()  # pushes down everywhere: half * (u + 1) / 2
    assert u.grad.flatten().tolist() == pytest.approx([2 * 0.75, 0.5 * 0.25, 2 * -1.0, 0.5 * 0.6])
    with pytest.raises(ValueError, match="high bound must exceed"):
        InvertingGradientHead(low=torch.tensor([1.0]), high=torch.tensor([1.0]))


def test_penalties_are_the_mean_squares_and_their_gradient_pulls_towards_zero():
    u = torch.tensor([[1.0, 2.0], [3.0, 0.0]], requires_grad=True)
    a = torch.tanh(u)
    value = actor_penalties(u, a, preact_penalty=0.1)
    assert float(value) == pytest.approx(0.1 * (1 + 4 + 9 + 0) / 4)
    value.backward()
    assert u.grad.flatten().tolist() == pytest.approx([0.05, 0.1, 0.15, 0.0])  # 2 c u / 4
    assert float(actor_penalties(u, torch.tensor([[0.5, -1.0]]), action_l2=2.0)) == pytest.approx(2.0 * 1.25 / 2)
    assert float(actor_penalties(u, a)) == 0.0


def test_temperature_fixed_and_learned():
    log_prob = torch.tensor([-1.0, -3.0])
    fixed = Temperature(1e-4, fixed_alpha=True)
    assert float(fixed.actor_term(log_prob)) == pytest.approx(1e-4 * -2.0)  # alpha * mean(log pi)
    assert float(fixed.loss(log_prob)) == 0.0 and not list(fixed.parameters())  # a fixed alpha is no parameter
    learned = Temperature(0.5, target_entropy=-2.0)
    assert float(learned.actor_term(log_prob)) == pytest.approx(0.5 * -2.0)
    value = learned.loss(log_prob)
    # -mean(log alpha * (log pi + target)) = -log(0.5) * (-2 - 2)
    assert float(value) == pytest.approx(4 * math.log(0.5))
    value.backward()
    # d/d log_alpha = -mean(log pi + target) = 4 > 0: the entropy (2) is above the target (-2), alpha goes down
    assert float(learned.log_alpha.grad) == pytest.approx(4.0)
    # "auto" is -dim(A); bounds clamp log alpha where it is used
    assert Temperature(1.0, action_dim=3).target_entropy == -3.0
    bounded = Temperature(1.0, target_entropy=0.0, max_alpha=0.5)
    assert float(bounded.alpha) == pytest.approx(0.5)
    for bad, message in ((dict(alpha_init=0.0), "alpha_init must be positive"),
                         (dict(alpha_init=1.0), "pass action_dim"),
                         (dict(alpha_init=1.0, min_alpha=2.0, max_alpha=1.0, target_entropy=0.0), "must not exceed")):
        with pytest.raises(ValueError, match=message):
            Temperature(**bad)


def test_saturation_counts_components_beyond_099_of_the_bound():
    u = torch.tensor([[3.0, 0.1], [-2.0, -4.0]])
    a = torch.tanh(u)  # tanh(3) = 0.9951, tanh(2) = 0.9640, tanh(4) = 0.9993
    assert saturation(a, u) == (2, 4, pytest.approx(9.1))
    window = Saturation.empty()
    Saturation.add(window["reset"], saturation(a, u))
    fields = Saturation.fields(window)
    assert fields["reset_saturation"] == 0.5 and fields["reset_preact_abs"] == pytest.approx(9.1 / 4)
    assert math.isnan(fields["forward_saturation"])  # no forward step in this window
    # the inverting head's normalised action is its clipped output; the tanh heads' is tanh(u)
    assert InvertingHead().normalised_action(torch.tensor([1.5, -0.2])).tolist() == pytest.approx([1.0, -0.2])
    assert TanhHead().saturation(u) == TanhNormalHead().saturation(u) == (2, 4, pytest.approx(9.1))


def _spec(low=-1.0, high=1.0):
    return Bounded(torch.full((2,), low), torch.full((2,), high), shape=(2,))


def test_the_tanh_normal_head_samples_when_exploring_and_acts_tanh_loc_otherwise():
    torch.manual_seed(0)
    actor = make_actor(3, _spec(0.0, 2.0), [8], head="tanh_normal")
    td = TensorDict(observation=torch.randn(4000, 3), batch_size=[4000])
    plain = actor(td.clone())
    # the deterministic action: tanh(loc) onto [0, 2], i.e. 1 + tanh(loc)
    assert torch.allclose(plain["action"], 1.0 + torch.tanh(plain["action_preactivation"]), atol=1e-6)
    with set_exploration_type(ExplorationType.RANDOM):
        drawn = actor(td.clone())
    assert not torch.allclose(drawn["action"], plain["action"])
    assert bool(((drawn["action"] > 0) & (drawn["action"] < 2)).all())
    # a sample's log-density is the Gaussian's minus log|d a / d x| = log(1 - tanh(x)^2) (the box's half-width is 1)
    x = torch.atanh((drawn["action"] - 1.0).clamp(-1 + 1e-6, 1 - 1e-6))
    loc, scale = drawn["action_preactivation"], drawn["action_scale"]
    gauss = torch.distributions.Normal(loc, scale).log_prob(x) - torch.log1p(-torch.tanh(x).pow(2))
    close = (x.abs() < 3).all(-1)  # away from the float edge of the box
    assert torch.allclose(drawn["action_log_prob"][close], gauss.sum(-1)[close], atol=1e-3)


def test_a_heads_penalty_is_on_the_actors_own_noiseless_preactivation():
    torch.manual_seed(0)
    sample = TensorDict(observation=torch.randn(16, 3), batch_size=[16])
    head = TanhHead(preact_penalty=0.5)
    actor = head.make_actor(3, _spec(), [8])
    u = actor(sample.clone())["action_preactivation"]
    assert float(head.penalty(actor, sample)) == pytest.approx(0.5 * float(u.pow(2).mean()), rel=1e-6)
    assert TanhHead().penalty(actor, sample) is None  # no penalty, no term
    # the tanh-Gaussian's: its pre-activation is the Gaussian's location, the same with or without sampling
    head = TanhNormalHead(action_l2=2.0)
    actor = head.make_actor(3, _spec(), [8])
    u = actor(sample.clone())["action_preactivation"]
    with set_exploration_type(ExplorationType.RANDOM):
        value = head.penalty(actor, sample)
    assert float(value) == pytest.approx(2.0 * float(torch.tanh(u).pow(2).mean()), rel=1e-6)


def test_heads_from_settings_and_what_each_asks_of_its_loss():
    assert head_from_settings("tanh", preact_penalty=0.1, action_l2=0.0, entropy="auto").loss_kwargs() == {}
    assert not head_from_settings("inverting").stochastic
    learned = head_from_settings("tanh_normal", entropy="auto")
    assert learned.stochastic and learned.loss_kwargs() == {"alpha_init": 0.01, "fixed_alpha": False,
                                                            "target_entropy": "auto"}
    assert head_from_settings("tanh_normal", entropy=1e-4).loss_kwargs()["fixed_alpha"] is True
    with pytest.raises(ValueError, match="unknown actor head 'sigmoid'"):
        head_from_settings("sigmoid")
    with pytest.raises(ValueError, match="preact_penalty must be a number >= 0"):
        TanhHead(preact_penalty=-1.0)


def _config(tmp_path, *overrides):
    return quick_config(tmp_path, *overrides)


@pytest.mark.parametrize("algo, remedy", [
    ("ours", ["reset_actor=release", "reset.actor.head=inverting"]),
    ("lnt", ["reset_actor=release", "reset.actor.preact_penalty=0.01"]),
    ("ours", ["reset.actor.head=tanh_normal", "reset.actor.entropy=auto"]),
    ("lnt", ["reset.actor.head=tanh_normal", "reset.actor.entropy=auto"]),
], ids=["ours-inverting", "lnt-preact", "ours-tanh_normal_auto", "lnt-tanh_normal_auto"])
def test_each_remedy_trains_and_every_run_logs_saturation(tmp_path, algo, remedy):
    summary = train.train(_config(tmp_path, f"algo={algo}", *remedy))
    assert summary["finished"]
    with open(tmp_path / "progress.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    before = {"forward": 0, "reset": 0}
    for row in rows:  # a value in [0, 1] for a window in which the phase took steps, NaN for one without
        for phase in before:
            took, value = int(row[f"{phase}_steps"]) - before[phase], float(row[f"{phase}_saturation"])
            assert (0.0 <= value <= 1.0 and float(row[f"{phase}_preact_abs"]) >= 0.0) if took else math.isnan(value)
            before[phase] = int(row[f"{phase}_steps"])
    assert before["reset"] > 0
    saved = json.loads((tmp_path / "summary.json").read_text())["saturation"]
    assert set(saved) == {"last_window", "last_quarter"} and "reset_saturation" in saved["last_quarter"]
    if "reset.actor.entropy=auto" in remedy:  # the temperature is learned, saved with the loss
        state = torch.load(next((tmp_path / "checkpoints").glob("step_*/state.pt")), weights_only=False)
        assert "temperature.log_alpha" in state["reset_loss"]
        assert state["reset_loss"]["temperature.log_alpha"] != pytest.approx(math.log(0.01))


@pytest.mark.parametrize("overrides, message", [
    (["reset.actor.head=sigmoid"], "reset.actor.head must be one of"),
    (["reset.actor.preact_penalty=-1"], "preact_penalty must be a number >= 0"),
    (["reset.actor.entropy=0"], "entropy must be a number > 0 or auto"),
    (["reset.actor.head=tanh_normal", "update_order=joint"], "needs update_order=release"),
    (["forward.actor.head=sigmoid"], "forward.actor.head must be one of"),
    (["forward.actor.action_l2=-0.5"], "forward.actor.action_l2 must be a number >= 0"),
    (["forward.actor.head=tanh_normal", "reset_actor=release", "update_order=joint"],
     "forward.actor.head=tanh_normal needs update_order=release .*the critic's TD targets"),
])
def test_bad_actor_settings_are_refused(tmp_path, overrides, message):
    with pytest.raises(ConfigError, match=message):
        validate(_config(tmp_path, *overrides))


@pytest.mark.parametrize("overrides, head, entropy", [
    ([], "tanh_normal", "auto"),  # the project's reset actor (reset_actor=rce, the default)
    (["preset=paper"], "tanh", 0.0001),  # the paper as the release runs it: the deterministic tanh, OU noise
    (["reset_actor=release"], "tanh", 0.0001),
    (["preset=paper", "reset_actor=rce"], "tanh_normal", "auto"),  # the command line's choice wins
])
def test_the_default_reset_actor_is_the_projects_and_the_paper_preset_restores_the_releases(overrides, head, entropy):
    from torchrl_reset_recipes.training.hydra_config import compose

    cfg = compose(overrides)
    assert (cfg.reset.actor.head, cfg.reset.actor.entropy) == (head, entropy)
    assert cfg.reset.actor.preact_penalty == 0.0 and cfg.reset.actor.action_l2 == 0.0
    assert list(cfg.hidden_sizes) == [400, 300]  # the paper's networks either way


def test_the_forward_actor_is_the_papers_ddpg_by_default_and_takes_the_projects_head_when_asked(tmp_path):
    """forward.actor.*: by default the deterministic tanh explored by OU noise (DDPGLoss, no temperature); with
    tanh_normal the forward agent samples its own actions (no noise module), its loss has the entropy term, and its
    learned temperature moves and is saved with the loss."""
    from torchrl_reset_recipes.training.agents import make_forward_agent, with_exploration
    from torchrl_reset_recipes.training.run_spec import run_spec
    from torchrl_reset_recipes.training.task_envs import task_dimensions

    cfg = _config(tmp_path / "default")
    obs_dim, action_spec = task_dimensions(cfg)
    spec = run_spec(cfg)
    paper = make_forward_agent(spec, obs_dim, action_spec)
    assert isinstance(paper.head, TanhHead) and not getattr(paper.loss, "stochastic", False)
    assert len(with_exploration(paper.actor, action_spec, spec, paper.head)) == 2  # the actor, then OU noise
    cfg = _config(tmp_path / "tanh_normal", "forward.actor.head=tanh_normal")
    spec = run_spec(cfg)
    project = make_forward_agent(spec, obs_dim, action_spec)
    assert isinstance(project.head, TanhNormalHead) and project.loss.stochastic
    assert with_exploration(project.actor, action_spec, spec, project.head) is project.actor  # its own samples
    assert project.loss.temperature.learned and float(project.loss.temperature.log_alpha.detach()) == pytest.approx(math.log(0.01))
    # the temperature is one of the optimizer's parameters, stepped at the critic's rate
    lrs = {id(p): group["lr"] for group in project.optimizer.param_groups for p in group["params"]}
    assert lrs[id(project.loss.temperature.log_alpha)] == cfg.forward.critic_lr

    summary = train.train(cfg)
    assert summary["finished"]
    with open(tmp_path / "tanh_normal" / "progress.csv", newline="") as f:
        last = list(csv.DictReader(f))[-1]
    assert last["loss_forward_actor"] not in ("", "nan") and 0.0 <= float(last["forward_saturation"]) <= 1.0
    assert int(last["forward_steps"]) > 41  # past the forward agent's heat-up of 40 steps: it updated
    checkpoints = tmp_path / "tanh_normal" / "checkpoints"
    state = torch.load(checkpoints / (checkpoints / "latest").read_text() / "state.pt", weights_only=False)
    assert state["forward_loss"]["temperature.log_alpha"] != pytest.approx(math.log(0.01))
