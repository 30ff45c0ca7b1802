"""Several runs in one process (``seeds=``): each run of the batch is the same seed's run alone, and a
batch resumes exactly.

Each run keeps its own env, collector, buffers and random streams; only the updates are batched. The
batched products sum in another order than a run's own, so losses agree to float32 rounding (1e-3
relative after hundreds of updates, where training amplifies rounding) while every counter, which
depends on the losses only through decisions far from their thresholds in these short runs, is
identical. The runs alone use plain Adam (``speed.fused_adam=false``): the batch's Adam is the plain
update rule, and fused kernels round differently.
"""
from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir

RECIPES = Path(__file__).resolve().parents[1] / "recipes"
sys.path.insert(0, str(RECIPES))

import batch  # noqa: E402
import train  # noqa: E402
from config_checks import ConfigError  # noqa: E402

TINY = [
    "hidden_sizes=[16,16]", "heat_up=40", "task.forward_horizon=20", "forward.batch_size=16", "reset.batch_size=16",
    "forward.buffer_size=2000", "reset.buffer_size=2000", "eval_every=100", "log_every=50", "checkpoint_every=100",
    "progress_bar=false", "speed.compile=[]", "speed.fused_adam=false", "task=peg_insertion_remove",
]
# a batch runs the paper preset as it is: the release's update order and noise that goes on across episodes
COUNTERS = ["frames", "forward_steps", "reset_steps", "forward_episodes", "reset_episodes", "manual_resets",
            "triggered_resets", "requested_resets", "successful_resets", "forward_share", "reset_success_rate"]
LOSSES = ["loss_forward_actor", "loss_forward_critic", "loss_reset_actor", "loss_reset_critic", "eval_return"]


def config(*overrides):
    with initialize_config_dir(config_dir=str(RECIPES / "conf"), version_base="1.3"):
        return compose(config_name="config", overrides=[*TINY, *overrides])


def rows(path):
    if not Path(path).exists():  # a table gets its file with its first row (no trigger fired: no triggers.csv)
        return []
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def assert_same_run(a: Path, b: Path) -> None:
    """Two run folders: identical counters and trigger events; losses and returns to 1e-5 over the first
    60 updates, then to 1e-2: training amplifies the products' rounding (measured on LNT's reset critic,
    1e-7 after 10 updates, 6e-5 after 160, 2e-3 after 260: about 3x per 50 updates)."""
    pa, pb = rows(a / "progress.csv"), rows(b / "progress.csv")
    assert len(pa) == len(pb) > 0
    for ra, rb in zip(pa, pb):
        assert {k: ra[k] for k in COUNTERS} == {k: rb[k] for k in COUNTERS}, ra["frames"]
        rel = 1e-5 if int(ra["frames"]) <= 100 else 1e-2
        for k in LOSSES:
            if ra[k] not in ("", "nan"):
                assert float(ra[k]) == pytest.approx(float(rb[k]), rel=rel, abs=1e-5), (ra["frames"], k)
    assert [r["frames"] for r in rows(a / "triggers.csv")] == [r["frames"] for r in rows(b / "triggers.csv")]
    ea, eb = rows(a / "eval.csv"), rows(b / "eval.csv")
    assert [(r["frames"], r["triggered"], r["reset_success"]) for r in ea] == \
        [(r["frames"], r["triggered"], r["reset_success"]) for r in eb]


@pytest.mark.parametrize("algo,steps,acting", [("ours", 300, "false"), ("lnt", 200, "false"), ("ours", 300, "true")])
def test_each_run_of_a_batch_is_the_same_seed_run_alone(tmp_path, algo, steps, acting):
    summaries = batch.train_batch(
        config(f"algo={algo}", f"total_steps={steps}", f"sweep_dir={tmp_path / 'batch'}", f"speed.batched_acting={acting}"),
        [0, 1])
    assert all(s["batch"]["acting"] == ("batched" if acting == "true" else "per run") for s in summaries)
    assert [s["seed"] for s in summaries] == [0, 1] and all(s["steps"] == steps and s["finished"] for s in summaries)
    for seed in (0, 1):
        alone = train.train(config(f"algo={algo}", f"total_steps={steps}", f"seed={seed}",
                                   f"sweep_dir={tmp_path / 'alone'}"))
        folder = f"peg_insertion_remove/{algo}/seed{seed}"
        assert_same_run(tmp_path / "batch" / folder, tmp_path / "alone" / folder)
        assert summaries[seed]["manual_resets"] == alone["manual_resets"]
    # the two seeds are different runs (the batch did not run one seed twice)
    first, second = (rows(tmp_path / "batch" / f"peg_insertion_remove/{algo}/seed{s}" / "progress.csv") for s in (0, 1))
    assert [r["loss_reset_critic"] for r in first] != [r["loss_reset_critic"] for r in second]


@pytest.fixture(scope="module")
def whole_batch(tmp_path_factory):
    root = tmp_path_factory.mktemp("whole")
    batch.train_batch(config("algo=ours", "total_steps=400", f"sweep_dir={root}"), [3, 4])
    return root


def test_a_resumed_batch_reproduces_the_uninterrupted_batch(tmp_path, whole_batch):
    batch.train_batch(config("algo=ours", "total_steps=200", f"sweep_dir={tmp_path}"), [3, 4])
    batch.train_batch(config("algo=ours", "total_steps=400", f"sweep_dir={tmp_path}", "resume=true"), [3, 4])
    drop = {"steps_per_second"}
    for seed in (3, 4):
        folder = f"peg_insertion_remove/ours/seed{seed}"
        a = [{k: v for k, v in r.items() if k not in drop} for r in rows(whole_batch / folder / "progress.csv")]
        b = [{k: v for k, v in r.items() if k not in drop} for r in rows(tmp_path / folder / "progress.csv")]
        assert a == b and len(a) == 8  # bit for bit: counters, returns, losses
        assert rows(whole_batch / folder / "eval.csv") == rows(tmp_path / folder / "eval.csv")


def test_kill_9_and_resume_reproduce_the_uninterrupted_batch(tmp_path, whole_batch):
    args = [sys.executable, str(RECIPES / "train.py"), *TINY, "algo=ours", "seeds=[3,4]", "total_steps=400",
            f"sweep_dir={tmp_path}", "checkpoint_every=100", "eval_every=100"]
    proc = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env={**os.environ, "RL_WARNINGS": "0"})
    latest = [tmp_path / f"peg_insertion_remove/ours/seed{s}/checkpoints/latest" for s in (3, 4)]
    deadline = time.time() + 300
    while time.time() < deadline and proc.poll() is None:
        if all(p.exists() and p.read_text() >= "step_0000000200" for p in latest):
            break
        time.sleep(0.1)
    assert proc.poll() is None, proc.stderr.read().decode()[-2000:]
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    saved = [int(json.loads((p.parent / p.read_text() / "meta.json").read_text())["frames"]) for p in latest]
    assert min(saved) >= 200
    batch.train_batch(config("algo=ours", "total_steps=400", f"sweep_dir={tmp_path}", "resume=true"), [3, 4])
    for seed in (3, 4):
        folder = f"peg_insertion_remove/ours/seed{seed}"
        a = [{k: v for k, v in r.items() if k != "steps_per_second"} for r in rows(whole_batch / folder / "progress.csv")]
        b = [{k: v for k, v in r.items() if k != "steps_per_second"} for r in rows(tmp_path / folder / "progress.csv")]
        assert a == b


def test_batched_acting_gives_the_per_run_batch_with_a_threshold_per_run(tmp_path):
    """One env of S copies, one policy and one trigger call for all (speed.batched_acting) against one env and
    collector per run: the actions are the runs' own bit for bit (RunPolicies.act), so the runs are the same
    up to the update calls' grouping. A run whose trigger stops its action executes nothing at that
    iteration, so it updates in a later call than with its own collector (which goes on to the next step
    at once), and a batched product over another set of runs rounds differently: counters and trigger
    events identical, losses to float32 rounding. The thresholds differ between the runs (a p_thresh sweep):
    each row of the shared trigger uses its own, and both fire."""
    folders = {}
    for acting in ("true", "false"):
        cfg = config("algo=ours", "total_steps=300", "seeds=[5]", "vary=task.p_thresh", "vary_values=[0.5,0.9]",
                     f"run_dir={tmp_path}/{acting}/p${{task.p_thresh}}", f"speed.batched_acting={acting}")
        summaries = batch.train_batch(cfg, batch.batch_runs(cfg))
        folders[acting] = summaries
    for threshold in ("0.5", "0.9"):
        assert_same_run(tmp_path / "true" / f"p{threshold}", tmp_path / "false" / f"p{threshold}")
    triggered = [s["triggered_resets"] for s in folders["true"]]
    assert triggered == [s["triggered_resets"] for s in folders["false"]]
    assert triggered[1] > triggered[0] > 0  # the higher threshold stops more actions: each row has its own


def test_a_resumed_batch_with_batched_acting_reproduces_the_uninterrupted_one(tmp_path):
    """Each run's checkpoint holds its copy in a single collector's format; resuming rebuilds the shared
    collector from them and continues bit for bit."""
    acting = ("algo=ours", "speed.batched_acting=true", "task.p_thresh=0.7")
    batch.train_batch(config(*acting, "total_steps=300", f"sweep_dir={tmp_path / 'whole'}"), [3, 4])
    batch.train_batch(config(*acting, "total_steps=150", f"sweep_dir={tmp_path / 'cut'}"), [3, 4])
    batch.train_batch(config(*acting, "total_steps=300", f"sweep_dir={tmp_path / 'cut'}", "resume=true"), [3, 4])
    for seed in (3, 4):
        folder = f"peg_insertion_remove/ours/seed{seed}"
        for name in ("progress.csv", "eval.csv", "triggers.csv", "resets.csv"):
            a = [{k: v for k, v in r.items() if k != "steps_per_second"} for r in rows(tmp_path / "whole" / folder / name)]
            b = [{k: v for k, v in r.items() if k != "steps_per_second"} for r in rows(tmp_path / "cut" / folder / name)]
            assert a == b, (seed, name)
        assert rows(tmp_path / "whole" / folder / "triggers.csv")  # the trigger fired (its state was resumed too)


@pytest.mark.parametrize("overrides,message", [
    (["seeds=0"], "must be >= 1"),
    (["seeds=[1,1]"], "twice"),
    (["seeds=[0,1]", "run_dir=/tmp/one_folder"], "one run_dir each"),
    (["seeds=2", "speed.compile=[reset]"], "speed.compile"),
    (["seeds=2", "speed.batched_acting=yes"], "true or false"),
])
def test_bad_batches_fail_before_training(tmp_path, overrides, message):
    cfg = config(f"sweep_dir={tmp_path}", *overrides)
    with pytest.raises(ConfigError, match=message):
        seeds = batch.batch_seeds(cfg)
        batch.run_configs(cfg, seeds)
    assert not any(tmp_path.rglob("*.csv"))


@pytest.mark.parametrize("overrides,message", [
    (["vary_values=[0.1,0.2]"], "needs vary"),
    (["vary=task.p_thresh", "vary_values=[0.1,0.2]"], "one run_dir each"),
    (["vary=reset.critic_lr", "vary_values=[0.001,0.0001]"], "share it"),
    (["vary=task.no_such_key", "vary_values=[1,2]"], "no such setting"),
    (["vary=task.p_thresh", "vary_values=[0.1,0.1]"], "distinct"),
    (["vary=task.forward_horizon", "vary_values=[10,20]", "speed.batched_acting=true",
      "run_dir=/tmp/x/h${task.forward_horizon}/s${seed}"], "share one collector"),
])
def test_bad_varied_batches_fail_before_training(tmp_path, overrides, message):
    cfg = config(f"sweep_dir={tmp_path}", *overrides)
    with pytest.raises(ConfigError, match=message):
        batch.run_configs(cfg, batch.batch_runs(cfg))


def test_a_batch_over_a_setting_gives_each_value_its_own_runs_and_folder(tmp_path):
    cfg = config("algo=ours", "seeds=2", "vary=task.p_thresh", "vary_values=[0.1,0.3]", "total_steps=60",
                 f"run_dir={tmp_path}/p${{task.p_thresh}}/seed${{seed}}")
    runs = batch.batch_runs(cfg)
    assert runs == [(0, 0.1), (1, 0.1), (0, 0.3), (1, 0.3)]
    summaries = batch.train_batch(cfg, runs)
    assert [(s["seed"], s["p_thresh"]) for s in summaries] == runs  # each run's trigger uses its own threshold
    assert sorted(p.parent.name + "/" + p.name for p in tmp_path.glob("p*/seed*")) == \
        ["p0.1/seed0", "p0.1/seed1", "p0.3/seed0", "p0.3/seed1"]


def _noise_modules(count, sigma=0.2):
    from torchrl.data import Bounded
    from torchrl.modules import OrnsteinUhlenbeckProcessModule

    spec = Bounded(-1.0, 1.0, shape=(3,))
    return [OrnsteinUhlenbeckProcessModule(spec=spec.clone(), eps_init=1.0, eps_end=1.0, annealing_num_steps=1,
                                           theta=0.15, sigma=sigma, dt=0.05) for _ in range(count)]


def _streams(seeds):
    import torch

    streams = []
    for seed in seeds:
        torch.manual_seed(seed)
        streams.append(batch.RunRNG())
    return streams


def test_row_exploration_steps_every_acting_row_as_its_run_module_would():
    """The vector Ornstein-Uhlenbeck step against each run's own torchrl module called on its row: the same
    actions (clamped into [-1, 1] where the policy's output plus noise leaves it), process states and step
    counts, bit for bit, over 60 steps with rows that pause (not acting) and restart (is_init)."""
    import torch
    from tensordict import TensorDict

    count, seeds = 4, [3, 11, 5, 8]
    vector = batch.RowExploration(lambda td: td, _noise_modules(count), _streams(seeds))
    per_row = batch.RowExploration(lambda td: td, _noise_modules(count), _streams(seeds))
    assert vector.process is not None
    per_row.process = None  # each row through its run's module
    data = torch.Generator().manual_seed(0)
    a = b = None
    clamped = 0
    for step in range(60):
        acting = torch.rand(count, generator=data) < 0.7
        is_init = (torch.rand(count, 1, generator=data) < 0.1) | (step == 0)
        action = 1.5 * torch.randn(count, 3, generator=data)  # often outside the box
        fresh = TensorDict({"action": action, "is_init": is_init, "_acting": acting}, [count])
        if a is not None:  # the process state travels from step to step, as the collector carries it
            for key in ("_ou_prev_noise", "_ou_steps"):
                fresh.set(key, a.get(key))
        a = vector(fresh.clone())
        if b is not None:
            for key in ("_ou_prev_noise", "_ou_steps"):
                fresh.set(key, b.get(key))
        b = per_row(fresh.clone())
        for key in ("action", "_ou_prev_noise", "_ou_steps"):
            assert torch.equal(a.get(key), b.get(key)), (step, key)
        assert (a.get("action")[acting].abs() <= 1).all()
        clamped += int((a.get("action")[acting].abs() == 1).sum())  # on the box's edge: clamped
        assert torch.equal(a.get("action")[~acting], action[~acting])  # a paused row keeps the policy's action
    assert clamped > 0  # the clamp was exercised
    for s in range(count):  # each run's stream has drawn the same numbers
        assert torch.equal(vector.streams[s].torch, per_row.streams[s].torch)


def test_row_exploration_calls_each_module_when_the_runs_processes_differ():
    noises = _noise_modules(2)
    noises[1] = _noise_modules(1, sigma=0.3)[0]
    assert batch.RowExploration(lambda td: td, noises, _streams([0, 1])).process is None
    assert batch.RowExploration(lambda td: td, _noise_modules(2), _streams([0, 1])).process is not None
