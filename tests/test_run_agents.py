"""S runs' agents updated in one call: each run as its own loss module, optimizer and target update
compute it alone, and the runs that did not act untouched bit for bit.

The references are the recipe's own agents (torchrl's DDPG loss or our RCE loss, torch Adam, the
soft target update), one per run, each on its own sample. The batched update sums the same
products in another order (a batched product against one per run), so the two agree to float32
rounding: 1e-5 relative on losses and parameters after several updates, not bitwise.
"""
from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from tensordict import TensorDict

RECIPES = Path(__file__).resolve().parents[1] / "recipes"
sys.path.insert(0, str(RECIPES))

from agents import make_forward_agent, make_reset_agent  # noqa: E402
from reset_agents import lnt_batch  # noqa: E402

from torchrl_reset.many import RunDDPGUpdate, RunRCEUpdate, bind_runs  # noqa: E402

S, B, OBS, ACT = 3, 12, 5, 2


def cfg_for(algo: str, accelerate: bool):
    if algo == "lnt_bounded":  # LNT with the option beside the paper: targets clipped to [0, 100]
        cfg = cfg_for("lnt", accelerate)
        cfg.algo.reward_bounds = [0.0, 1.0]
        return cfg
    with initialize_config_dir(config_dir=str(RECIPES / "conf"), version_base="1.3"):
        return compose(config_name="config", overrides=[
            f"algo={algo}", "hidden_sizes=[16,16]", "algo.num_members=3", f"speed.accelerate={str(accelerate).lower()}",
            "speed.fused_adam=false", "algo.n_steps=3"] if algo == "ours" else [
            f"algo={algo}", "hidden_sizes=[16,16]", "algo.num_members=3", f"speed.accelerate={str(accelerate).lower()}",
            "speed.fused_adam=false"])


def spec():
    from torchrl.data import Bounded
    return Bounded(low=-torch.ones(ACT), high=torch.ones(ACT), shape=(ACT,))


def agents(algo: str, role: str, accelerate: bool = False):
    cfg = cfg_for(algo, accelerate)
    out = []
    for seed in range(S):
        torch.manual_seed(100 + seed)
        make = make_forward_agent if role == "forward" else make_reset_agent
        out.append(make(cfg, OBS, spec()))
    return cfg, out


def sample(gen, role: str, algo: str, one_step: bool = False) -> TensorDict:
    def r(*shape):
        return torch.randn(*shape, generator=gen)

    nxt = TensorDict(observation=r(B, OBS), reward=r(B, 1), done=torch.rand(B, 1, generator=gen) < 0.2,
                     batch_size=[B])
    nxt.set("terminated", nxt.get("done").clone())
    td = TensorDict(observation=r(B, OBS), action=torch.rand(B, ACT, generator=gen) * 2 - 1, next=nxt, batch_size=[B])
    if role == "reset" and algo == "ours":
        td.set("nstep", TensorDict(observation=r(B, OBS), batch_size=[B]))
        td.set("example", TensorDict(observation=r(B, OBS), batch_size=[B]))
        if one_step:
            td.set("one_step", torch.ones(B, dtype=torch.bool))
    if role == "reset" and algo != "ours":
        nxt.set("reset_reward", r(B, 1))
        nxt.set("reset_success", torch.rand(B, 1, generator=gen) < 0.3)
    return td


def reference_step(agent, td, names) -> dict:
    losses = agent.loss(td)
    agent.optimizer.zero_grad()
    sum(losses[n] for n in names).backward()
    agent.optimizer.step()
    agent.targets.step()
    return {n: float(losses[n].detach()) for n in names}


CASES = [("ours", "reset"), ("ours", "forward"), ("lnt", "reset"), ("lnt_sparse", "reset"), ("lnt_bounded", "reset")]


def release_reference(agent, td, names, seed: int) -> dict:
    """The recipe's own update of one run in the release's order (critic step, then actor step on rows
    drawn with replacement from torch's global generator, then targets), the generator seeded first."""
    import train

    torch.manual_seed(seed)
    return train.update(agent, td, agent.loss, release_order=True)


@pytest.mark.parametrize("order", ["joint", "release"])
@pytest.mark.parametrize("algo,role", CASES)
def test_a_batched_update_is_each_runs_own_update_and_leaves_idle_runs_untouched(algo, role, order):
    """``order``: one step on both losses, or the release's critic step, then actor step over rows drawn
    with replacement (each run's rows drawn as the recipe's update draws them alone), each run's Adam
    counting one step per update in both."""
    cfg, batched_agents = agents(algo, role)
    _, alone = agents(algo, role)  # the same seeds: equal starting networks
    if role == "forward" or algo != "ours":
        names = ("loss_actor", "loss_value")
        key = "reward" if role == "forward" else "lnt_reward"
        update = RunDDPGUpdate([a.loss for a in batched_agents], [a.optimizer for a in batched_agents],
                               gamma=cfg.gamma, tau=cfg.tau, reward_key=key)
    else:
        names = ("loss_actor", "loss_classifier")
        update = RunRCEUpdate([a.loss for a in batched_agents], [a.optimizer for a in batched_agents], tau=cfg.tau)
    gen = torch.Generator().manual_seed(7)
    schedule = [[0, 1, 2], [1], [0, 2], [], [0, 1, 2], [2]]
    for step, runs in enumerate(schedule):
        tds = [sample(gen, role, algo, one_step=(step == 1)) for _ in range(S)]
        if role == "reset" and algo != "ours":
            tds = [lnt_batch(td, cfg.algo, int(cfg.algo.num_members)) for td in tds]
        before = [{k: v.clone() for k, v in a.loss.state_dict().items()} for a in batched_agents]
        seeds = {s: 1000 + 10 * step + s for s in runs}
        rows = {}
        for s in runs:  # the rows the recipe's update draws for run s after its critic step
            torch.manual_seed(seeds[s])
            rows[s] = torch.randint(B, (B,))
        assert order == "joint" or not runs or any(len(set(r.tolist())) < B for r in rows.values())  # with replacement
        out = update.update([tds[s] for s in runs], runs,
                            actor_rows=[rows[s] for s in runs] if order == "release" else None)
        for j, s in enumerate(runs):
            expected = (reference_step(alone[s], tds[s], names) if order == "joint"
                        else release_reference(alone[s], tds[s], names, seeds[s]))
            for n in names:
                assert float(out[n][j]) == pytest.approx(expected[n], rel=1e-5, abs=1e-6), (step, s, n)
        for s in range(S):
            state = batched_agents[s].loss.state_dict()
            if s not in runs:  # exactly untouched: parameters, targets (and, below, Adam's step counts)
                assert all(torch.equal(state[k], before[s][k]) for k in state), (step, s)
            ref = alone[s].loss.state_dict()
            for k in state:
                torch.testing.assert_close(state[k], ref[k], rtol=1e-5, atol=1e-6, msg=f"{step} {s} {k}")
    counts = [sum(s in runs for runs in schedule) for s in range(S)]
    assert update.optimizer.steps.tolist() == counts
    # the batched optimizer's state, written back per run, is what each run's own Adam holds
    for s in range(S):
        update.export(s)
        mine, ref = batched_agents[s].optimizer.state_dict(), alone[s].optimizer.state_dict()
        assert mine["state"].keys() == ref["state"].keys()
        for i in ref["state"]:
            assert float(mine["state"][i]["step"]) == float(ref["state"][i]["step"]) == counts[s]
            for m in ("exp_avg", "exp_avg_sq"):
                torch.testing.assert_close(mine["state"][i][m], ref["state"][i][m], rtol=1e-4, atol=1e-7)


def test_the_fast_classes_batch_too_and_the_runs_modules_see_the_update():
    cfg, runs = agents("ours", "reset", accelerate=True)
    update = RunRCEUpdate([a.loss for a in runs], [a.optimizer for a in runs], tau=cfg.tau)
    gen = torch.Generator().manual_seed(3)
    obs = torch.randn(4, OBS, generator=gen)
    before = [a.model.logits(obs, torch.zeros(4, ACT)).clone() for a in runs]
    update.update([sample(gen, "reset", "ours") for _ in range(S)], [0, 1, 2])
    after = [a.model.logits(obs, torch.zeros(4, ACT)) for a in runs]
    assert all(not torch.equal(x, y) for x, y in zip(before, after))  # each run's own module moved with it


def test_exported_state_reloads_into_a_new_batch_exactly():
    cfg, first = agents("ours", "forward")
    update = RunDDPGUpdate([a.loss for a in first], [a.optimizer for a in first], gamma=cfg.gamma, tau=cfg.tau)
    gen = torch.Generator().manual_seed(5)
    for runs in ([0, 1, 2], [1], [0, 1]):
        update.update([sample(gen, "forward", "ours") for _ in runs], runs)
    # checkpoint each run alone, load it into fresh agents, rebatch: the next update is bitwise the same
    saved = []
    for s in range(S):
        update.export(s)
        saved.append(({k: v.clone() for k, v in first[s].loss.state_dict().items()}, first[s].optimizer.state_dict()))
    _, second = agents("ours", "forward")
    for s in range(S):
        second[s].loss.load_state_dict(saved[s][0])
        second[s].optimizer.load_state_dict(saved[s][1])
    again = RunDDPGUpdate([a.loss for a in second], [a.optimizer for a in second], gamma=cfg.gamma, tau=cfg.tau)
    assert again.optimizer.steps.tolist() == update.optimizer.steps.tolist() == [2, 3, 1]
    tds = [sample(gen, "forward", "ours") for _ in range(S)]
    a = update.update(tds, [0, 1, 2])
    b = again.update(tds, [0, 1, 2])
    assert all(torch.equal(a[n], b[n]) for n in a)
    for s in range(S):
        x, y = first[s].loss.state_dict(), second[s].loss.state_dict()
        assert all(torch.equal(x[k], y[k]) for k in x)


def test_policies_of_another_layout_are_refused():
    from tensordict.nn import TensorDictModule, TensorDictSequential
    from torchrl.modules import TanhModule

    net = torch.nn.Sequential(torch.nn.Linear(OBS, 8), torch.nn.Tanh(), torch.nn.Linear(8, ACT))
    actor = TensorDictSequential(TensorDictModule(net, ["observation"], ["action_preactivation"]),
                                 TanhModule(["action_preactivation"], ["action"], spec=spec()))
    from torchrl_reset.many import RunPolicies
    with pytest.raises(ValueError, match="ReLU MLP"):
        RunPolicies([actor, actor])


def test_bind_runs_makes_each_tensor_a_view_and_refuses_mixed_shapes():
    tensors = [torch.full((2,), float(s)) for s in range(3)]
    stacked = bind_runs(tensors)
    stacked[1].fill_(7.0)
    assert tensors[1].tolist() == [7.0, 7.0] and tensors[0].tolist() == [0.0, 0.0]
    tensors[2].fill_(-1.0)
    assert stacked[2].tolist() == [-1.0, -1.0]
    with pytest.raises(ValueError, match="one shape"):
        bind_runs([torch.zeros(2), torch.zeros(3)])
