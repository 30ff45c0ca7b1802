"""The training recipe: smoke runs of every task x algorithm, resume equivalence, kill -9, config errors, NaN stop."""
from __future__ import annotations

import csv
import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from tensordict import TensorDict
from torchrl.objectives import DDPGLoss

RECIPES = Path(__file__).resolve().parents[1] / "recipes"

from torchrl_reset_recipes.training import single_run

from torchrl_reset_recipes.training.run_spec import run_spec
from torchrl_reset_recipes import train
from torchrl_reset_recipes.training.hydra_config import compose
from torchrl_reset_envs import make_env  # noqa: E402
from torchrl_reset_recipes.training.agents import make_actor, make_reset_agent
from torchrl_reset_recipes.training.reset_agents import lnt_batch
from torchrl_reset_recipes.training.buffers import make_buffers
from torchrl_reset_recipes.training.checkpoints import Checkpoints
from torchrl_reset_recipes.training.run_folder import processor_name
from torchrl_reset_recipes.training.task_envs import UpdateBudget, realtime_env, task_dimensions
from torchrl_reset_recipes.training.config_checks import ALGOS, ConfigError

from torchrl_reset import EnsembleValueOperator, accel  # noqa: E402
from torchrl_reset_envs import TASKS  # noqa: E402

TINY = [
    "hidden_sizes=[16,16]", "heat_up=40", "task.forward_horizon=20", "forward.batch_size=16", "reset.batch_size=16",
    "forward.buffer_size=2000", "reset.buffer_size=2000", "eval_every=100", "log_every=50", "checkpoint_every=100",
    "progress_bar=false", "speed.compile=[]", "threads=1",
]


def config(tmp_path, *overrides):
    return compose([*TINY, f"run_dir={tmp_path}", *overrides])


def rows(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


#: the paper's three algorithms on every task; the release's LNT ensembles (the other kinds of ALGOS, the same
#: task code) train in tests/test_ensemble_ddpg.py
PAPER_ALGOS = ("ours", "lnt", "lnt_sparse")


def test_the_task_matrix_covers_every_kind_of_reset_agent():
    assert set(PAPER_ALGOS) <= set(ALGOS) and set(ALGOS) - set(PAPER_ALGOS) == {"lnt_release", "lnt_sparse_release"}


@pytest.mark.parametrize("algo", PAPER_ALGOS)
@pytest.mark.parametrize("task", list(TASKS))
def test_every_task_and_algorithm_trains_for_120_steps(tmp_path, task, algo):
    summary = train.train(config(tmp_path, f"task={task}", f"algo={algo}", "total_steps=120", "heat_up=20",
                                 "eval_every=60", "log_every=30", "checkpoint_every=60"))
    assert summary["steps"] == 120 and summary["finished"]
    saved = json.loads((tmp_path / "summary.json").read_text())
    assert saved["reset_episodes"] == saved["successful_resets"] + saved["manual_resets"]
    assert 0.0 <= saved["forward_share"] <= 1.0 and saved["evaluations"] == 2
    assert [int(r["frames"]) for r in rows(tmp_path / "progress.csv")] == [30, 60, 90, 120]
    progress = rows(tmp_path / "progress.csv")[-1]
    assert int(progress["forward_steps"]) + int(progress["reset_steps"]) == 120
    # updates ran for an agent that passed its 20-step heat-up (ours: both agents on every task but ur3_peg, whose
    # trigger fires before every forward step this early; LNT: the reset agent, its trigger firing likewise)
    for agent in ("forward", "reset"):
        if int(progress[f"{agent}_steps"]) > 21:
            assert progress[f"loss_{agent}_critic"] not in ("", "nan")
    assert (tmp_path / "checkpoints" / "latest").read_text() == "step_0000000120"
    assert (tmp_path / "config.yaml").exists() and any((tmp_path / "logs").rglob("*.csv"))
    if min(int(progress["forward_steps"]), int(progress["reset_steps"])) > 30:  # timed once both made 10 updates
        timed = {agent: s for agent, s in saved["step_seconds"].items() if s is not None}
        # a phase that took no step after both passed that point has no time (its entry is None)
        assert timed and all(0 < s < 10 for s in timed.values())


def test_compiled_losses_train_like_the_eager_ones(tmp_path):
    common = ["task=peg_insertion_insert", "algo=ours", "total_steps=150", "eval_every=150", "checkpoint_every=150"]
    eager = train.train(config(tmp_path / "eager", *common))
    compiled = train.train(config(tmp_path / "compiled", *common, "speed.compile=[forward,reset]"))
    assert compiled["finished"] and compiled["steps"] == 150
    # the same data and the same arithmetic up to rounding: the same episodes early in training
    same = ("manual_resets", "triggered_resets", "reset_episodes")
    assert {k: compiled[k] for k in same} == {k: eager[k] for k in same}
    a, b = rows(tmp_path / "eager" / "progress.csv")[-1], rows(tmp_path / "compiled" / "progress.csv")[-1]
    for key in ("loss_forward_critic", "loss_reset_critic", "loss_reset_actor"):
        assert float(a[key]) == pytest.approx(float(b[key]), rel=1e-3, abs=1e-5)


@pytest.mark.parametrize("algo", ["ours", "lnt"])
def test_the_plain_reference_path_trains_like_the_accelerator(tmp_path, algo):
    """speed.accelerate=false: the reference classes, stock Adam and plain float32 products. The same
    numbers up to float32 rounding, so early in training the same episodes and nearly the same losses."""
    common = ["task=peg_insertion_insert", f"algo={algo}", "total_steps=200", "eval_every=200", "checkpoint_every=200"]
    fast = train.train(config(tmp_path / "fast", *common))
    plain = train.train(config(tmp_path / "plain", *common, "speed.accelerate=false"))
    assert plain["matmul_precision"] == "ieee"
    same = ("manual_resets", "triggered_resets", "requested_resets", "reset_episodes", "successful_resets")
    assert {k: plain[k] for k in same} == {k: fast[k] for k in same}
    a, b = rows(tmp_path / "fast" / "progress.csv")[-1], rows(tmp_path / "plain" / "progress.csv")[-1]
    losses = [key for key in a if key.startswith("loss_") and a[key] not in ("", "nan")]
    assert len(losses) >= 2
    for key in losses:
        assert float(a[key]) == pytest.approx(float(b[key]), rel=1e-3, abs=1e-5), key


def test_a_resumed_run_reproduces_the_uninterrupted_run(tmp_path):
    """LNT's reset agent (20 critics, their targets, the bounded estimator) resumed: the same rows. Ours resumed
    is the Ctrl-C test's (through the printed command) and run_folder's (from the checkpoint before a damaged one)."""
    common = ["task=peg_insertion_remove", "algo=lnt"]
    whole = train.train(config(tmp_path / "whole", *common, "total_steps=400"))
    train.train(config(tmp_path / "split", *common, "total_steps=200"))
    resumed = train.train(config(tmp_path / "split", *common, "total_steps=400", "resume=true"))
    drop = {"steps_per_second"}
    a = [{k: v for k, v in r.items() if k not in drop} for r in rows(tmp_path / "whole" / "progress.csv")]
    b = [{k: v for k, v in r.items() if k not in drop} for r in rows(tmp_path / "split" / "progress.csv")]
    assert a == b and len(a) == 8  # counters, evaluation returns and the last losses, row by row
    same = ("manual_resets", "forward_share", "reset_success_rate", "average_return", "triggered_resets")
    assert {k: whole[k] for k in same} == {k: resumed[k] for k in same}
    assert rows(tmp_path / "whole" / "eval.csv") == rows(tmp_path / "split" / "eval.csv")


def test_a_finished_run_relaunched_with_resume_auto_is_left_as_it_is(tmp_path):
    # a grid launched again with resume=auto: its finished runs are not rebuilt, their files keep every byte
    common = ["task=peg_insertion_remove", "algo=ours", "total_steps=200"]
    first = train.train(config(tmp_path, *common))
    files = {name: (tmp_path / name).read_bytes() for name in ("summary.json", "code.jsonl", "progress.csv")}
    again = train.train(config(tmp_path, *common, "resume=auto"))
    assert again == first and first["finished"]
    assert {name: (tmp_path / name).read_bytes() for name in files} == files
    longer = train.train(config(tmp_path, "task=peg_insertion_remove", "algo=ours", "total_steps=300", "resume=auto"))
    assert longer["steps"] == 300  # a larger budget still continues the run
    assert len((tmp_path / "code.jsonl").read_text().splitlines()) == 2


def test_kill_9_loses_at_most_the_steps_since_the_last_checkpoint(tmp_path):
    run_dir = tmp_path / "run"
    args = [sys.executable, str(RECIPES / "train.py"), *TINY, "task=cliff_cheetah", "algo=ours", "total_steps=100000",
            f"run_dir={run_dir}", "checkpoint_every=100"]
    proc = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env={**os.environ, "RL_WARNINGS": "0"})
    latest = run_dir / "checkpoints" / "latest"
    deadline = time.time() + 240
    while time.time() < deadline and proc.poll() is None:
        if latest.exists() and latest.read_text() >= "step_0000000200":
            break
        time.sleep(0.2)
    assert proc.poll() is None, proc.stderr.read().decode()[-2000:]
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    saved = int(json.loads((run_dir / "checkpoints" / latest.read_text() / "meta.json").read_text())["frames"])
    assert saved >= 200
    logged = [int(r["frames"]) for r in rows(run_dir / "progress.csv")]
    # the last step any table logged after the checkpoint: the stretch the killed process loses
    lost = max((int(r["frames"]) for name in ("progress.csv", "eval.csv", "triggers.csv", "resets.csv",
                                               "diagnostics.csv") if (run_dir / name).exists()
                for r in rows(run_dir / name) if int(r["frames"]) > saved), default=None)
    summary = train.train(config(run_dir, "task=cliff_cheetah", "algo=ours", f"total_steps={saved + 100}", "resume=true"))
    assert summary["steps"] == saved + 100
    resumed = [int(r["frames"]) for r in rows(run_dir / "progress.csv")]
    # rows logged after the checkpoint by the killed process are dropped, then the run continues
    assert resumed == [f for f in logged if f <= saved] + [saved + 50, saved + 100]
    # code.jsonl keeps the lost stretch on record: this stretch starts at the checkpoint and replaces the
    # steps the killed process had logged beyond it
    stretches = [json.loads(line) for line in (run_dir / "code.jsonl").read_text().splitlines()]
    assert [s["from_step"] for s in stretches] == [0, saved]
    assert stretches[1].get("replaces_to_step") == lost and "replaces_to_step" not in stretches[0]


def test_sigterm_ends_the_run_after_its_step_with_a_checkpoint_and_a_summary(tmp_path):
    # what a cluster sends before it pre-empts a job: the run stops cleanly and resume=true continues it
    run_dir = tmp_path / "run"
    args = [sys.executable, str(RECIPES / "train.py"), *TINY, "task=cliff_cheetah", "algo=ours", "total_steps=100000",
            f"run_dir={run_dir}", "checkpoint_every=100000"]
    proc = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env={**os.environ, "RL_WARNINGS": "0"})
    progress = run_dir / "progress.csv"
    deadline = time.time() + 240
    while time.time() < deadline and proc.poll() is None:
        if progress.exists() and len(rows(progress)) >= 3:
            break
        time.sleep(0.2)
    assert proc.poll() is None, proc.stderr.read().decode()[-2000:]
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(timeout=120) == 143  # the shell's 128 + SIGTERM: the run did not finish
    summary = json.loads((run_dir / "summary.json").read_text())
    assert not summary["finished"] and 150 <= summary["steps"] < 100000
    meta = json.loads((run_dir / "checkpoints" / (run_dir / "checkpoints" / "latest").read_text() / "meta.json").read_text())
    assert meta["frames"] == summary["steps"]  # checkpointed where it stopped, not at the last periodic checkpoint
    resumed = train.train(config(run_dir, "task=cliff_cheetah", "algo=ours", f"total_steps={summary['steps'] + 50}",
                                 "resume=true"))
    assert resumed["steps"] == summary["steps"] + 50 and resumed["finished"]


def test_a_crash_while_checkpointing_keeps_the_previous_checkpoint(tmp_path):
    checkpoints = Checkpoints(tmp_path)
    checkpoints.save(100, lambda folder: (folder / "state.pt").write_text("first"), {"frames": 100})

    def crash(folder):
        (folder / "state.pt").write_text("half")
        raise OSError("disk full")

    with pytest.raises(OSError):
        checkpoints.save(200, crash, {"frames": 200})
    latest = checkpoints.latest()
    assert latest.name == "step_0000000100" and (latest / "state.pt").read_text() == "first"


@pytest.mark.parametrize(
    "overrides, message",
    [
        (["task.p_thresh=1.5"], r"p_thresh must lie in \(0, 1\)"),
        (["task.p_thresh=0"], r"p_thresh must lie in \(0, 1\)"),
        (["reset.max_steps=10"], r"H_r = 10\) must be >= H_f = 20"),
        (["task.name=cliff_chetah"], "unknown task 'cliff_chetah'"),
        (["algo.name=sac"], "unknown algorithm 'sac'"),
        (["resume=true"], "no complete checkpoint"),
        (["total_steps=0"], "total_steps must be a positive integer"),
        (["keep_states_every=150"], r"keep_states_every must be null or a positive multiple of checkpoint_every \(100\)"),
        (["keep_states_every=0"], "keep_states_every must be null or a positive multiple"),
        (["speed.compile=[backward]"], "speed.compile must be a list of agents among forward, reset"),
        (["speed.matmul_precision=fp16"], "speed.matmul_precision must be one of auto, ieee, bf16"),
        (["speed.accelerate=fast"], "speed.accelerate must be true or false"),
        (["reset.learn_from_forward=sometimes"], "reset.learn_from_forward must be true or false"),
        (["algo=ours", "+algo.reward_bounds=[0,1]"], "algo.reward_bounds clips LNT's TD targets"),
        (["algo=lnt", "algo.reward_bounds=[1,0]"], r"algo.reward_bounds must be \[low, high\] with low < high"),
        (["algo=lnt_sparse", "algo.reward_bounds=[0]"], r"algo.reward_bounds must be \[low, high\]"),
    ],
)
def test_bad_configs_fail_before_training(tmp_path, overrides, message):
    with pytest.raises(ConfigError, match=message):
        train.train(config(tmp_path, "task=peg_insertion_insert", *overrides))
    assert not (tmp_path / "progress.csv").exists()


def test_resume_from_another_runs_checkpoint_and_rerun_without_resume_fail(tmp_path):
    train.train(config(tmp_path, "task=peg_insertion_insert", "total_steps=100"))
    with pytest.raises(ConfigError, match="from task 'peg_insertion_insert'"):
        train.train(config(tmp_path, "task=ball_in_cup_catch", "total_steps=200", "resume=true"))
    # another seed in the same folder would carry on the first seed's random streams under the second's name
    with pytest.raises(ConfigError, match="is from seed 0, this run is seed 3"):
        train.train(config(tmp_path, "task=peg_insertion_insert", "seed=3", "total_steps=200", "resume=auto"))
    with pytest.raises(ConfigError, match="pass resume=true"):
        train.train(config(tmp_path, "task=peg_insertion_insert", "total_steps=200"))


def test_unknown_config_group_option_is_rejected_by_hydra(tmp_path):
    from hydra.errors import ConfigCompositionException

    with pytest.raises(ConfigCompositionException, match="nope"):
        config(tmp_path, "task=nope")


def test_a_nan_loss_stops_the_run_with_a_checkpoint_of_the_last_good_state(tmp_path, monkeypatch):
    original = make_buffers

    def poisoned(cfg):
        forward_rb, reset_rb = original(cfg)
        sample = forward_rb.sample

        def nan_rewards(*args, **kwargs):
            batch = sample(*args, **kwargs)
            batch.set(("next", "reward"), torch.full_like(batch.get(("next", "reward")), float("nan")))
            return batch

        forward_rb.sample = nan_rewards
        return forward_rb, reset_rb

    monkeypatch.setattr(single_run, "make_buffers", poisoned)
    with pytest.raises(train.TrainingDiverged, match="non-finite loss at step"):
        train.train(config(tmp_path, "task=peg_insertion_insert", "total_steps=300"))
    latest = Checkpoints(tmp_path / "checkpoints").latest()
    state = torch.load(latest / "state.pt", weights_only=False)
    params = [v for v in state["forward_loss"].values() if torch.is_tensor(v) and v.is_floating_point()]
    assert params and all(torch.isfinite(p).all() for p in params)  # no update was applied with the NaN loss
    assert state["collector"]["counters"]["forward_steps"] == 41  # the first update after the 40-step heat-up


def test_wandb_logging_is_offline_by_default_and_needs_no_account(tmp_path, monkeypatch):
    monkeypatch.setenv("WANDB_SILENT", "true")
    monkeypatch.delenv("WANDB_API_KEY", raising=False)
    train.train(config(tmp_path, "task=peg_insertion_insert", "total_steps=100", "logger.wandb=true"))
    runs = list((tmp_path / "wandb").rglob("offline-run-*"))
    assert len(runs) == 1 and list(runs[0].glob("*.wandb"))


def test_lnt_reset_loss_gives_each_member_its_own_td_target(tmp_path):
    from tensordict import TensorDict

    cfg = config(tmp_path, "task=peg_insertion_insert", "algo=lnt")
    spec = make_env("peg_insertion_insert").action_spec
    agent = make_reset_agent(run_spec(cfg, check=False), 14, spec)
    k, b = cfg.algo.num_members, 6
    td = TensorDict({
        "observation": torch.randn(b, 14), "action": torch.rand(b, 7) * 4 - 2,
        "next": {"observation": torch.randn(b, 14), "reset_reward": torch.rand(b, 1),
                 "reset_success": torch.tensor([True, False, True, False, False, True]).reshape(b, 1),
                 "done": torch.zeros(b, 1, dtype=torch.bool), "terminated": torch.zeros(b, 1, dtype=torch.bool)},
    }, [b])
    for reward_kind, reward in (("shaped", td["next", "reset_reward"]), ("sparse", td["next", "reset_success"].float())):
        cfg.algo.reset_reward = reward_kind
        loss = agent.loss(lnt_batch(td.clone(), cfg.algo, k))["loss_value"]
        with torch.no_grad():  # targets start equal to the online networks
            q_next = agent.model(agent.actor(td["next"].clone()))["state_action_value"]
            q = agent.model(td.clone())["state_action_value"]
        assert q.shape == (b, k)
        expected = ((q - (reward + cfg.gamma * q_next)) ** 2).mean()  # member i against r + gamma Q_i(s', pi(s'))
        assert float(loss.detach()) == pytest.approx(float(expected), rel=1e-5)
    # algo.success_terminal (not the paper's): no bootstrapping past a step into the success check, Q = r there
    cfg.algo.success_terminal = True
    loss = agent.loss(lnt_batch(td.clone(), cfg.algo, k))["loss_value"]
    ended = td["next", "reset_success"]  # [b, 1]: the target is r alone on these rows
    expected = ((q - (reward + cfg.gamma * (~ended).float() * q_next)) ** 2).mean()
    assert float(loss.detach()) == pytest.approx(float(expected), rel=1e-5)


def test_update_budget_skips_updates_that_would_not_fit_in_the_control_period():
    budget = UpdateBudget(margin=0.002, warmup=2, window=5, skip_decay=0.5)
    assert budget.fits("reset", 0.04)  # nothing measured yet
    budget.record("reset", 0.200)  # the first two updates (one-time costs) are no estimate
    budget.record("reset", 0.100)
    assert budget.fits("reset", 0.010)
    for seconds in (0.030, 0.031, 0.029):
        budget.record("reset", seconds)
    assert budget.estimate["reset"] == pytest.approx(0.030)  # the median of 30, 31, 29 ms
    assert not budget.fits("reset", 0.031)  # 31 ms left - 2 ms margin < 30 ms: skipped, the estimate halves
    assert budget.estimate["reset"] == pytest.approx(0.015)
    assert budget.fits("reset", 0.018) and budget.fits("forward", 0.003)  # tried again
    budget.record("reset", 0.200)  # one slow update (a collection of freed memory) among 29, 30, 31, 200 ms
    assert budget.estimate["reset"] == pytest.approx(0.031)  # the median: not the outlier
    for seconds in (0.005,) * 5:  # updates that became quick: the window forgets the old ones
        budget.record("reset", seconds)
    assert budget.estimate["reset"] == pytest.approx(0.005)
    assert budget.skipped == 1


def test_realtime_env_is_found_only_on_a_real_time_backend():
    from test_ur3 import ClockedBackend, FakeClock
    from torchrl.envs import TransformedEnv

    from torchrl_reset_envs import UR3Env

    assert realtime_env(make_env("ur3_peg")) is None
    robot = UR3Env("peg", backend=ClockedBackend(FakeClock()), manual_reset=lambda env: None)
    assert realtime_env(TransformedEnv(robot)) is robot


def test_fused_soft_update_moves_every_target_by_tau_and_tensor_module_writes_its_output():
    from torchrl.data import Bounded

    actor = make_actor(3, Bounded(-1.0, 1.0, shape=(2,)), (8,))
    obs = torch.randn(5, 3)
    net = actor[0].module
    torch.testing.assert_close(actor(TensorDict(observation=obs, batch_size=[5]))["action_preactivation"], net(obs))

    critic = EnsembleValueOperator(3, 2, num_members=1, hidden_sizes=(8, 8), prior_scale=0.0,
                                   out_keys=["state_action_value"])
    loss = DDPGLoss(actor, critic, delay_actor=True, delay_value=True)
    updater = accel.FusedSoftUpdate(loss, tau=0.25)
    sources = [*loss.actor_network_params.values(True, True), *loss.value_network_params.values(True, True)]
    targets = [*loss.target_actor_network_params.values(True, True), *loss.target_value_network_params.values(True, True)]
    trained = [p.requires_grad for p in sources]  # the tanh bounds are buffers: no target update
    assert sum(trained) == 4 + 7  # actor: 2 weights, 2 biases; critic: 3 weights, 3 biases, action weight
    with torch.no_grad():
        for p in sources:
            p.add_(1.0)  # sources move by 1 from the targets
    before = [t.clone() for t in targets]
    updater.step()
    for was, now, moves in zip(before, targets, trained):
        torch.testing.assert_close(now, was + (0.25 if moves else 0.0))  # (1 - tau) t + tau (t + 1) = t + tau


def test_matmul_precision_auto_keeps_float32_accuracy_and_products_restore_the_setting():
    backend = torch.backends.mkldnn.matmul
    before = backend.fp32_precision
    gen = torch.Generator().manual_seed(3)
    a, b = torch.randn(128, 400, generator=gen), torch.randn(400, 300, generator=gen)
    exact = a.double() @ b.double()
    chosen = accel.choose_matmul_precision("auto")
    assert chosen in ("ieee", "bf16") and backend.fp32_precision == before
    with accel.matmul_products(chosen):
        assert backend.fp32_precision == chosen
        # float32 keeps 24 bits: a product of 400 terms is good to well under 1e-5 of its largest
        # value; bf16 arithmetic (8 bits) would be off by about 1e-3
        assert float(((a @ b).double() - exact).abs().max() / exact.abs().max()) < 1e-5
    assert backend.fp32_precision == before
    assert accel.choose_matmul_precision("ieee") == "ieee"
    with pytest.raises(ValueError, match="matmul precision"):
        accel.choose_matmul_precision("fp16")


def test_video_plays_the_evaluation_of_the_latest_checkpoint_into_a_gif(tmp_path):
    import imageio.v2 as imageio
    import numpy as np
    from torchrl_reset_recipes.analysis import video

    train.train(config(tmp_path, "task=ball_in_cup_catch", "total_steps=200"))
    try:
        info = video.main([str(tmp_path), "--size", "48", "--fps", "10"])
    except Exception as err:  # no OpenGL backend on this machine: the env says so
        assert "MUJOCO_GL" in str(err)
        pytest.skip("no off-screen rendering here")
    frames = imageio.mimread(tmp_path / "eval.gif")
    # the first state, one frame per forward step (or the trigger's), one per reset step
    assert len(frames) == info["frames"] == 1 + info["forward_steps"] + info["triggered"] + info["reset_steps"]
    assert info["forward_steps"] + info["triggered"] <= 20 and 1 <= info["reset_steps"] <= 40  # H_f = 20, H_r = 2 H_f
    assert frames[0].shape[:2] == (48, 48)
    assert tuple(frames[0][0, 24, :3]) == video.COLOURS["forward"]  # the border marks the phase
    assert tuple(frames[-1][0, 24, :3]) == video.COLOURS["reset"]
    assert np.abs(frames[1][8:-8, 8:-8, :3].astype(int) - frames[-1][8:-8, 8:-8, :3].astype(int)).sum() > 0
    with pytest.raises(FileNotFoundError, match="config.yaml"):
        video.record(tmp_path / "nothing")


def test_load_agents_reads_a_run_folders_agents_back_from_its_checkpoints(tmp_path):
    from torchrl_reset_recipes.training.checkpoints import CheckpointDamaged
    from torchrl_reset_recipes.analysis.saved_runs import load_agents

    # checkpoints at 100 and 200, the agents' state of both also kept
    train.train(config(tmp_path, "task=ball_in_cup_catch", "total_steps=200", "keep_states_every=100"))
    saved = load_agents(tmp_path)
    assert (saved.step, saved.checkpoint.name, saved.cfg.task.name) == (200, "step_0000000200", "ball_in_cup_catch")
    state = torch.load(saved.checkpoint / "state.pt", weights_only=False)
    for agent, key in ((saved.forward, "forward_loss"), (saved.reset, "reset_loss")):
        loaded = agent.loss.state_dict()
        assert loaded.keys() == state[key].keys()
        assert all(torch.equal(loaded[name], value) for name, value in state[key].items())
    # a freshly built agent acts otherwise: the numbers above came from the checkpoint
    obs_dim, action_spec = task_dimensions(saved.cfg)
    observation = TensorDict(observation=torch.linspace(-1, 1, obs_dim).unsqueeze(0), batch_size=[1])
    torch.manual_seed(123)
    fresh = make_reset_agent(run_spec(saved.cfg, check=False), obs_dim, action_spec)
    with torch.no_grad():
        assert not torch.equal(fresh.actor(observation.clone())["action"], saved.reset.actor(observation.clone())["action"])
    # an older checkpoint by its folder; the reference ensemble built from the same state gives the
    # same classifier values as the fast one (the override reaches the build)
    older = load_agents(tmp_path, checkpoint=tmp_path / "checkpoints" / "step_0000000100")
    reference = load_agents(tmp_path, checkpoint=older.checkpoint, overrides={"speed.accelerate": False})
    assert older.step == 100 and reference.cfg.speed.accelerate is False
    acted = older.reset.actor(observation.clone())
    with torch.no_grad():
        fast = older.reset.model(acted.clone())[older.reset.model.out_keys[0]]
        slow = reference.reset.model(acted.clone())[reference.reset.model.out_keys[0]]
    assert torch.allclose(fast, slow, atol=1e-5)
    kept = load_agents(tmp_path, checkpoint=tmp_path / "checkpoints" / "kept" / "step_0000000100")
    assert kept.step == 100 and all(torch.equal(kept.reset.loss.state_dict()[name], value)
                                    for name, value in older.reset.loss.state_dict().items())
    alone = load_agents(tmp_path, checkpoint=older.checkpoint, agents=("reset",))
    assert alone.forward is None and all(torch.equal(alone.reset.loss.state_dict()[name], value)
                                         for name, value in older.reset.loss.state_dict().items())
    for bad in ("reset", (), ("forward", "rest")):
        with pytest.raises(ValueError, match="agents must name"):
            load_agents(tmp_path, agents=bad)
    with pytest.raises(KeyError, match="speed.acelerate"):
        load_agents(tmp_path, overrides={"speed.acelerate": False})
    # a checkpoint by hand is checked as a resume checks it: relative to the run folder, damaged, another run's
    assert load_agents(tmp_path, checkpoint="checkpoints/kept/step_0000000100", agents=("reset",)).step == 100
    other = tmp_path / "other"
    other.mkdir()
    from omegaconf import OmegaConf

    other_cfg = OmegaConf.load(tmp_path / "config.yaml")
    other_cfg.seed = 5
    OmegaConf.save(other_cfg, other / "config.yaml")
    with pytest.raises(ValueError, match="seed 0 there, 5 here"):
        load_agents(other, checkpoint=older.checkpoint)
    with open(kept.checkpoint / "state.pt", "r+b") as f:  # the kept link and step 100's checkpoint: one file
        f.seek(100)
        byte = f.read(1)
        f.seek(100)
        f.write(bytes([byte[0] ^ 0xFF]))
    with pytest.raises(CheckpointDamaged, match="state.pt differs from the manifest"):
        load_agents(tmp_path, checkpoint=kept.checkpoint)
    with pytest.raises(FileNotFoundError, match="config.yaml"):
        load_agents(tmp_path / "nothing")
    with pytest.raises(FileNotFoundError, match="not a complete checkpoint"):
        load_agents(tmp_path, checkpoint=tmp_path / "checkpoints")


def test_diagnostics_score_every_forward_step_and_resets_csv_has_every_reset_episode(tmp_path):
    train.train(config(tmp_path, "task=peg_insertion_insert", "algo=ours", "total_steps=400"))
    progress = rows(tmp_path / "progress.csv")[-1]
    diagnostics = rows(tmp_path / "diagnostics.csv")
    assert [int(r["frames"]) for r in diagnostics] == list(range(50, 401, 50))
    # the trigger scores every forward action: the executed ones, and one more per forward episode that it
    # stopped or that reached H_f (that action is scored, not executed); peg-insertion never terminates
    scored = sum(int(r["trigger_scored_steps"]) for r in diagnostics)
    assert scored == int(progress["forward_steps"]) + int(progress["triggered_resets"]) + int(progress["requested_resets"])
    below = sum(float(r["trigger_below_share"]) * int(r["trigger_scored_steps"]) for r in diagnostics
                if r["trigger_below_share"] not in ("", "nan"))
    assert round(below) == int(progress["triggered_resets"])  # exactly the stopped actions are below p_thresh
    for r in diagnostics:
        for column in ("trigger_score_mean", "example_p", "reset_replay_p", "forward_p"):
            if r[column] not in ("", "nan"):
                assert 0.0 <= float(r[column]) <= 1.0  # success probabilities
        if r["trigger_score_min"] not in ("", "nan"):
            assert float(r["trigger_score_min"]) <= float(r["trigger_score_mean"])
    resets = rows(tmp_path / "resets.csv")
    outcomes = [r["outcome"] for r in resets]
    assert len(resets) == int(progress["reset_episodes"])
    assert outcomes.count("success") == int(progress["successful_resets"])
    assert outcomes.count("manual") == int(progress["manual_resets"])

    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["episodic_resets"] == int(progress["forward_episodes"])
    assert summary["resets_saved"] == summary["episodic_resets"] - summary["manual_resets"]
    # the release's baseline, TINY's H_f = 20: one hard reset per 20 forward step calls, triggered ones included
    assert summary["baseline_hard_resets"] == (int(progress["forward_steps"]) + int(progress["triggered_resets"])) // 20


def test_options_beside_the_paper_a_pessimistic_start_and_the_reset_agents_own_tau(tmp_path):
    # the paper's setting: trained output biases start at zero and the reset agent's tau is the global one
    spec = make_env("peg_insertion_insert").action_spec
    torch.manual_seed(0)
    paper = make_reset_agent(run_spec(config(tmp_path, "algo=ours"), check=False), 14, spec)
    torch.manual_seed(0)
    pessimistic = make_reset_agent(run_spec(config(tmp_path, "algo=ours", "algo.initial_logit_bias=-4",
                                                     "reset.tau=0.01"), check=False), 14, spec)
    td = TensorDict(observation=torch.randn(32, 14), action=torch.rand(32, 7) * 2 - 1, batch_size=[32])
    with torch.no_grad():
        shift = pessimistic.model(td.clone())["state_action_logit"] - paper.model(td.clone())["state_action_logit"]
    torch.testing.assert_close(shift, torch.full_like(shift, -4.0))  # every member's logit, exactly -4 lower
    target = pessimistic.loss.target_classifier_network_params
    assert torch.all(target.get(f"bias_{pessimistic.model.num_layers - 1}") == -4.0)  # the targets start alike
    assert paper.targets.eps == pytest.approx(1 - 0.001) and pessimistic.targets.eps == pytest.approx(1 - 0.01)


@pytest.mark.parametrize("accelerate", [True, False])
def test_lnt_option_beside_the_paper_targets_clipped_to_the_rewards_bounds(tmp_path, accelerate):
    from torchrl.objectives.value import TD0Estimator

    from torchrl_reset.td_bounds import BoundedTD0Estimator

    spec = make_env("peg_insertion_insert").action_spec
    paper = make_reset_agent(run_spec(config(tmp_path, "algo=lnt", f"speed.accelerate={accelerate}"), check=False), 14, spec)
    assert type(paper.loss.value_estimator) is TD0Estimator  # the paper's LNT: unclipped
    clipped = make_reset_agent(run_spec(config(tmp_path, "algo=lnt", "algo.reward_bounds=[0,1]",
                                                  f"speed.accelerate={accelerate}"), check=False), 14, spec)
    estimator = clipped.loss.value_estimator
    # rewards in [0, 1] at gamma = 0.99: every value lies in [0, 1 / 0.01] = [0, 100]
    assert isinstance(estimator, BoundedTD0Estimator) and estimator.bounds == pytest.approx((0.0, 100.0))
    assert estimator.tensor_keys.reward == "lnt_reward" and float(estimator.gamma) == pytest.approx(0.99)


def test_two_runs_never_train_in_one_folder(tmp_path):
    # a grid whose run_dir does not tell its jobs apart would send them into one folder: the second stops at once
    import fcntl

    from torchrl_reset_recipes.training.run_folder import RunFolderBusy

    tmp_path.mkdir(exist_ok=True)
    with open(tmp_path / ".lock", "w") as held:
        fcntl.flock(held, fcntl.LOCK_EX | fcntl.LOCK_NB)  # another process's run, as far as this one can tell
        with pytest.raises(RunFolderBusy, match="own run_dir"):
            train.train(config(tmp_path, "task=cliff_cheetah", "algo=ours", "total_steps=100"))
    assert not (tmp_path / "config.yaml").exists()  # nothing was written
    assert train.train(config(tmp_path, "task=cliff_cheetah", "algo=ours", "total_steps=100"))["steps"] == 100


def test_a_robot_fault_stops_the_run_after_a_checkpoint(tmp_path, monkeypatch):
    # e.g. more protective stops in the window than allowed: the run must not go on, and nothing is lost
    from torchrl_reset_envs.ur3_backends import RobotFault

    original = train.DualCollector._step

    def faulty(self):  # the backend raises inside env.step, as RTDEBackend.read_state does
        if self.frames >= 120:
            raise RobotFault("11 protective stops within 600 s")
        return original(self)

    monkeypatch.setattr(train.DualCollector, "_step", faulty)
    with pytest.raises(train.RobotStopped, match="protective stops.*resume=true"):
        train.train(config(tmp_path, "task=ur3_peg", "algo=ours", "total_steps=400"))
    latest = Checkpoints(tmp_path / "checkpoints").latest()
    assert int(json.loads((latest / "meta.json").read_text())["frames"]) == 120  # every step taken is kept
    assert int(rows(tmp_path / "progress.csv")[-1]["frames"]) == 100


def test_the_summary_names_the_processor_kind_a_run_reproduces_on(tmp_path):
    info = tmp_path / "cpuinfo"
    info.write_text("processor\t: 0\nmodel name\t: AMD EPYC\nflags\t\t: fpu sse2 avx2 avx512f avx512_bf16\n\n"
                    "processor\t: 1\nmodel name\t: AMD EPYC\nflags\t\t: fpu sse2 avx2 avx512f avx512_bf16\n")
    assert processor_name(info) == "AMD EPYC, AVX-512 BF16"
    info.write_text("model name\t: Intel(R) Xeon(R) Processor\nflags\t\t: fpu sse2 avx2\n")
    assert processor_name(info) == "Intel(R) Xeon(R) Processor, AVX2"
    info.write_text("model name\t: Some CPU\nflags\t\t: fpu sse2\n")
    assert processor_name(info) == "Some CPU"


@pytest.mark.parametrize("release_order", [True, False])
def test_release_order_steps_the_critic_then_the_actor_with_it_on_rows_drawn_again(tmp_path, release_order):
    """update_order=release (train.py's update): a critic step, then an actor step whose loss uses the updated classifiers, on
    B rows drawn with replacement from the batch. Worked out here with plain SGD steps, by hand."""
    from torchrl_reset_recipes.training.updates import update

    cfg = config(tmp_path, "algo=ours", "reset_actor=release")  # the deterministic actor, worked out by hand below
    spec = make_env("peg_insertion_insert").action_spec
    torch.manual_seed(0)
    agent = make_reset_agent(run_spec(cfg, check=False), 14, spec)
    actor_params, critic_params = list(agent.actor.parameters()), list(agent.model.parameters())
    agent.optimizer = torch.optim.SGD([{"params": actor_params, "lr": 0.3}, {"params": critic_params, "lr": 0.5}])
    b = 16
    state = lambda: TensorDict(observation=torch.randn(b, 14), batch_size=[b])  # noqa: E731
    sample = TensorDict(observation=torch.randn(b, 14), action=torch.rand(b, 7) * 2 - 1, next=state(),
                        nstep=state(), example=state(), batch_size=[b])
    torch.manual_seed(0)
    reference = make_reset_agent(run_spec(cfg, check=False), 14, spec)  # the same networks, to be stepped by hand
    ref_actor, ref_critic = list(reference.actor.parameters()), list(reference.model.parameters())

    # by hand: theta_c <- theta_c - 0.5 dL_c; then rows drawn with replacement, theta_a <- theta_a - 0.3 dL_a
    grads = torch.autograd.grad(reference.loss.loss_classifier(sample.clone())[0], ref_critic)
    with torch.no_grad():
        for p, g in zip(ref_critic, grads):
            p -= 0.5 * g
    torch.manual_seed(7)
    rows = torch.randint(b, (b,)) if release_order else torch.arange(b)
    if not release_order:  # the joint step: the actor's loss from the classifiers before their step
        torch.manual_seed(0)
        reference = make_reset_agent(run_spec(cfg, check=False), 14, spec)
        ref_actor = list(reference.actor.parameters())
    grads = torch.autograd.grad(reference.loss.loss_actor(sample[rows].clone())[0], ref_actor)
    expected_actor = [(p - 0.3 * g).detach() for p, g in zip(ref_actor, grads)]

    target_before = agent.loss.target_classifier_network_params.get("weight_0").clone()
    torch.manual_seed(7)
    update(agent, sample.clone(), agent.loss, release_order=release_order)
    for p, e in zip(actor_params, expected_actor):
        torch.testing.assert_close(p.detach(), e, rtol=1e-5, atol=1e-6)
    # the soft target update follows both steps: target <- (1 - tau) target + tau network
    tau = 1.0 - agent.targets.eps
    torch.testing.assert_close(agent.loss.target_classifier_network_params.get("weight_0"),
                               (1 - tau) * target_before + tau * agent.model.weight_0.detach())


def test_cliff_walker_explores_with_the_releases_smaller_noise(tmp_path):
    """The release's configs: sigma 0.01 and dt 0.01 for cliff-walker's two agents, 0.2 and 0.05 elsewhere."""
    from torchrl_reset_recipes.training.agents import exploration_settings, with_exploration

    spec = make_env("peg_insertion_insert").action_spec
    for task, sigma, dt in (("cliff_walker", 0.01, 0.01), ("cliff_cheetah", 0.2, 0.05), ("peg_insertion_insert", 0.2, 0.05)):
        cfg = config(tmp_path, f"task={task}")
        settings = exploration_settings(run_spec(cfg, check=False))
        assert settings | {"sigma": sigma, "dt": dt, "theta": 0.15} == settings
        noise = with_exploration(make_actor(14, spec, [16, 16]), spec, run_spec(cfg, check=False))[-1].ou
        assert (noise.sigma, noise.dt, noise.theta) == (sigma, dt, 0.15)


# ------------------------------------------------- interrupts, exit codes, keys the recipe does not define
def _signal_when(args, ready, sig, *, poll: float) -> tuple[int, str]:
    """Starts the command ``args``, sends it ``sig`` once ``ready()`` holds (it must still be running then), and
    returns its exit status and standard error."""
    proc = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env={**os.environ, "RL_WARNINGS": "0"})
    deadline = time.time() + 300
    while time.time() < deadline and proc.poll() is None:
        if ready():
            break
        time.sleep(poll)
    assert proc.poll() is None, proc.stderr.read().decode()[-2000:]
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=300)
    return proc.returncode, err.decode()


def assert_same_tables(whole, split):
    """The run folders' tables, row by row but for the wall-clock column; a table is written with its first row
    (triggers.csv: with a trigger), so either both folders have it or neither."""
    for table in ("progress.csv", "eval.csv", "resets.csv", "triggers.csv", "diagnostics.csv"):
        a, b = whole / table, split / table
        assert a.exists() == b.exists(), table
        assert [{k: v for k, v in r.items() if k != "steps_per_second"} for r in (rows(a) if a.exists() else [])] \
            == [{k: v for k, v in r.items() if k != "steps_per_second"} for r in (rows(b) if b.exists() else [])], table


def test_ctrl_c_ends_the_run_after_its_step_and_the_printed_command_resumes_it_exactly(tmp_path):
    import shlex

    common = ["task=cliff_cheetah", "algo=ours", "total_steps=200"]
    train.train(config(tmp_path / "whole", *common))
    run_dir = tmp_path / "run"
    args = [sys.executable, str(RECIPES / "train.py"), *TINY, *common, f"run_dir={run_dir}"]
    progress = run_dir / "progress.csv"
    returncode, err = _signal_when(args, lambda: progress.exists() and len(rows(progress)) >= 2,  # past step 100
                                   signal.SIGINT, poll=0.05)
    assert returncode == 130, err[-2000:]  # the shell's 128 + SIGINT
    summary = json.loads((run_dir / "summary.json").read_text())
    stopped = summary["steps"]
    assert 100 <= stopped < 200 and not summary["finished"]
    latest = run_dir / "checkpoints" / (run_dir / "checkpoints" / "latest").read_text()
    assert json.loads((latest / "meta.json").read_text())["frames"] == stopped  # checkpointed after the step
    assert f"SIGINT stopped the run at step {stopped}" in err
    command = err.strip().splitlines()[-1].strip()
    assert command == shlex.join([*args, "resume=true"])

    resumed = subprocess.run(shlex.split(command), capture_output=True, text=True, timeout=600,
                             env={**os.environ, "RL_WARNINGS": "0"})
    assert resumed.returncode == 0, resumed.stderr[-2000:]
    assert_same_tables(tmp_path / "whole", run_dir)  # losses, reset episodes' lengths and end distances, row by row
    assert len(rows(run_dir / "progress.csv")) == 4


@pytest.mark.parametrize("override, message", [
    ("+total_step=1000", "unknown key total_step: .*the closest known key is total_steps"),
    ("run_dir=FILE", "run_dir must name a folder, but .*file is a file"),
    ("seeds=3", r"unknown key seeds: run batching .* was retired.*-m seed=0,1,2"),
], ids=["misspelled-key", "run-dir-a-file", "retired-seeds"])
def test_a_refused_command_exits_2_with_the_reason_and_leaves_nothing_behind(tmp_path, override, message):
    """The three ways a command is refused: by the config's check (after Hydra composed it), by the run folder, and
    before Hydra (a retired key without ``+``). Every message of the check is tested in this process elsewhere."""
    (tmp_path / "file").write_text("kept")
    run_dir = str(tmp_path / "file") if override == "run_dir=FILE" else str(tmp_path / "run")
    args = [sys.executable, str(RECIPES / "train.py"), "task=cliff_cheetah", f"run_dir={run_dir}"]
    args += [] if override == "run_dir=FILE" else [override]
    done = subprocess.run(args, capture_output=True, text=True, timeout=300, cwd=tmp_path,
                          env={**os.environ, "RL_WARNINGS": "0"})
    assert done.returncode == 2, done.stderr[-2000:]
    assert re.search(message, done.stderr) and "Traceback" not in done.stderr
    # no run folder, and none of Hydra's files (.hydra/, train.log) in the working directory either
    assert [p.name for p in tmp_path.iterdir()] == ["file"] and (tmp_path / "file").read_text() == "kept"


def test_keys_the_recipe_does_not_define_are_refused_and_those_its_groups_add_are_not(tmp_path):
    from torchrl_reset_recipes.training.config_checks import validate

    with pytest.raises(ConfigError, match="unknown key total_step: .*closest known key is total_steps"):
        validate(config(tmp_path, "+total_step=1000"))
    with pytest.raises(ConfigError, match="unknown key forward.batchsize: .*closest known key is forward.batch_size"):
        validate(config(tmp_path, "+forward.batchsize=8"))
    with pytest.raises(ConfigError, match="unknown key zzz: .*would read it$"):  # nothing close: no suggestion
        validate(config(tmp_path, "+zzz=1"))
    # the keys of run batching, retired, say so and what runs seeds instead
    with pytest.raises(ConfigError) as refused:
        validate(config(tmp_path, "+seeds=3", "+arms=2", "+speed.batched_acting=false"))
    for key in ("seeds", "arms", "speed.batched_acting"):
        assert re.search(rf"unknown key {key}: run batching .* was retired.*-m seed=0,1,2", str(refused.value))
    validate(config(tmp_path, "task=peg_insertion_insert", "+task.exploration.sigma=0.1"))  # cliff_walker's key
    validate(config(tmp_path, "task=ur3_peg", "+env.acceleration=1.0"))  # env holds the env's own arguments
    validate(config(tmp_path, "preset=quick", "algo=lnt", "algo.reward_bounds=[0,1]"))


def test_a_plain_override_of_a_key_defined_nowhere_is_refused_before_hydra_with_the_closest_key():
    """What main() refuses before Hydra composes anything (exit 2): a plain override of a key that no file and no
    task defines, with the closest known key, and the keys of run batching, retired, with or without +."""
    from torchrl_reset_recipes.training.config_checks import command_line_problems

    (line,) = command_line_problems(["task=cliff_cheetah", "total_step=1000"])
    assert re.fullmatch(r"unknown key total_step: .* does not define it, so nothing would read it; "
                        r"the closest known key is total_steps", line)
    (line,) = command_line_problems(["qqqqqq.zzzz=1"])  # nothing close: no suggestion
    assert line.startswith("unknown key qqqqqq.zzzz:") and "closest" not in line
    retired = command_line_problems(["seeds=3", "+seeds=4", "arms=2"])  # each key once
    assert len(retired) == 2 and all(re.match(r"unknown key (seeds|arms): run batching .* was retired", p) for p in retired)
    # left to Hydra and to the check after composition: group choices, a -m grid's values, keys of every file and
    # of one task only (cliff-walker's noise), a key under an open mapping, Hydra's own, added and deleted keys
    assert command_line_problems([
        "-m", "task=cliff_walker", "algo=ours,lnt", "preset=quick", "reset_actor=release", "seed=0,1,2",
        "task.exploration.sigma=0.1", "forward.actor.head=tanh_normal", "env.acceleration=1.0",
        "hydra/launcher=joblib", "hydra.run.dir=.", "+zzz=1", "~eval_every", "run_dir=a=b"]) == []


@pytest.mark.parametrize("written_before", [False, True], ids=["today", "before-the-release-keys"])
def test_a_config_without_the_release_keys_runs_as_the_recipe_ran_before_them(tmp_path, written_before):
    """The six keys that made the recipe follow the authors' release (docs/release-audit.md) arrived with the
    earlier behaviour as their fallback: a config.yaml written before them (an older run resumed) builds the
    run it described, not today's preset."""
    from omegaconf import open_dict
    from torchrl_reset import EpisodeWindowSampler

    cfg = config(tmp_path, "algo=ours", "task=peg_insertion_insert", "total_steps=60")
    if written_before:
        with open_dict(cfg):
            for section, key in (("algo", "prior_bias_draw"), ("exploration", "restart"), ("exploration", "clip"),
                                 (None, "update_order"), ("forward", "sampling"), (None, "target_init")):
                del (cfg if section is None else cfg[section])[key]
    run = single_run.build_run(run_spec(cfg, check=False), "ieee")
    try:
        release = not written_before
        assert run.reset.model.prior_bias_draw == ("xavier" if release else "fan_in")
        assert run.collector.restart_exploration is (not release)  # the noise restarted at every episode
        assert run.collector.forward_policy[-1].safe is (not release)  # the noisy action projected onto the box
        assert run.learner.release_order is release  # critic then actor, else one joint step
        assert isinstance(run.forward_rb.sampler, EpisodeWindowSampler) is release
        # the forward actor's target: an independent draw (the release's constructors), else a copy
        pairs = zip(run.forward.loss.actor_network_params.flatten_keys().values(),
                    run.forward.loss.target_actor_network_params.flatten_keys().values())
        assert all(torch.equal(a, b) for a, b in pairs) is (not release)
    finally:
        run.collector.shutdown()
        run.eval_env.close()


@pytest.mark.parametrize("algo, own", [
    ("ours", {("collector", "traj_ids")}),  # the n-step transform's trajectory boundaries
    ("lnt", {("next", "reset_reward"), ("next", "reset_success")}),  # what LNT's reward is made from
])
def test_each_replay_buffer_keeps_what_its_agent_reads_of_a_collected_step(tmp_path, algo, own):
    """The buffers keep the entries of a collected step that the losses list in ``in_keys`` (the state, the
    action, the next state, the end flags) and what the reset agent's kind adds; none of the trigger's,
    collector's or env's other entries. Listed here by hand from docs/method.md sections 3 and 6."""
    cfg = config(tmp_path, f"algo={algo}", "task=cliff_cheetah", "total_steps=60")
    run = single_run.build_run(run_spec(cfg, check=False), "ieee")
    try:
        step = next(iter(run.collector))
        collected = {k if isinstance(k, tuple) else (k,) for k in step.keys(True, True)}
        common = {("observation",), ("action",), ("next", "observation"), ("next", "done"), ("next", "terminated")}
        assert len(collected) > 15  # the step carries many more entries than the buffers keep
        kept = {k if isinstance(k, tuple) else (k,) for k in step.select(*run.learner.keys["reset"], strict=False).keys(True, True)}
        assert kept == common | own
        kept = {k if isinstance(k, tuple) else (k,) for k in step.select(*run.learner.keys["forward"], strict=False).keys(True, True)}
        assert kept == common | {("next", "reward"), ("collector", "traj_ids")}  # forward.sampling: episode
    finally:
        run.collector.shutdown()
        run.eval_env.close()


def _chain_record(tmp_path, *, ditch, trigger_cell, horizon, frames, reset_direction=-1.0):
    """A RunRecord over a DualCollector on ChainEnv: forward always right, reset always left (a reset cannot
    leave the ditch); the trigger is sure below ``trigger_cell`` and hopeless from it on."""
    from tensordict.nn import TensorDictModule
    from torchrl.envs import TransformedEnv
    from torchrl_reset_recipes.training.records import RunRecord
    from torchrl_reset import DualCollector, ResetTriggerTransform
    from torchrl_reset_envs import ChainEnv

    def policy(direction):
        return TensorDictModule(lambda obs: torch.full((*obs.shape[:-1], 1), direction), ["observation"], ["action"])

    def logits(obs):
        return torch.where(obs.argmax(-1, keepdim=True) >= trigger_cell, -10.0, 0.0)

    trigger = ResetTriggerTransform(TensorDictModule(logits, ["observation"], ["state_action_logit"]), 0.1)
    env = TransformedEnv(ChainEnv(num_states=8, ditch=ditch), trigger)
    collector = DualCollector(env, policy(1.0), policy(reset_direction), max_forward_steps=horizon, max_reset_steps=horizon,
                              min_reset_steps=1, total_frames=frames, event_keys=["irrecoverable", "reset_success"])
    cfg = config(tmp_path, "task.curriculum.index=0", "heat_up=1000")
    tmp_path.mkdir(parents=True)
    record = RunRecord(run_spec(cfg, check=False), tmp_path, collector, trigger)
    record.begin(None)
    for batch in collector:
        record.step(batch, DualCollector.phase_of(batch))
    record.close()
    return record


def test_the_records_count_entries_into_the_ditch_by_phase_and_say_which_triggers_and_resets_were_in_it(tmp_path):
    """Worked out by hand on an 8-cell chain (cells 0..7, start 0), forward steps right, reset steps left.

    Ditch at 4, no trigger reachable (it would fire from cell 6): each forward episode of H_f = 6 steps
    enters the ditch at its 4th step (cell 3 -> 4) and stays; the reset episode cannot move and ends in a
    manual reset after 6 steps. 24 steps: two forward episodes (2 entries), two failed resets in the ditch."""
    record = _chain_record(tmp_path / "a", ditch=4, trigger_cell=6, horizon=6, frames=24)
    assert record.irrecoverable == {"forward": 2, "reset": 0}
    resets = rows(tmp_path / "a" / "resets.csv")
    assert [(r["outcome"], r["started_by"], r["irrecoverable"]) for r in resets] == [("manual", "requested", "1")] * 2
    assert not (tmp_path / "a" / "triggers.csv").exists()

    # The trigger fires from cell 3, the ditch beyond it at 6: forward 0 -> 1 -> 2 -> 3, then the action from
    # cell 3 is stopped (a recoverable state); the reset walks 3 -> 0 in 3 steps and succeeds. Six steps a
    # cycle, no entry into the ditch.
    record = _chain_record(tmp_path / "b", ditch=6, trigger_cell=3, horizon=6, frames=12)
    assert record.irrecoverable == {"forward": 0, "reset": 0}
    triggers = rows(tmp_path / "b" / "triggers.csv")
    assert [(t["steps"], t["irrecoverable"]) for t in triggers] == [("3", "0")] * 2
    resets = rows(tmp_path / "b" / "resets.csv")
    assert [(r["outcome"], r["started_by"], r["irrecoverable"]) for r in resets] == [("success", "triggered", "0")] * 2

    # The trigger fires only in the ditch (from cell 3, the ditch's first cell): the forward step 2 -> 3 enters
    # it, the trigger stops the next action in a state already lost, and the reset fails (H_r steps in place).
    # H_f = 6: it fires mid-episode, recorded with the reset episode's first step; 3 + 6 steps a cycle.
    # H_f = 3: it fires on the action at H_f, recorded with the forward episode's last step; 3 + 3 a cycle.
    for name, horizon, cycles in (("c", 6, 2), ("d", 3, 3)):
        record = _chain_record(tmp_path / name, ditch=3, trigger_cell=3, horizon=horizon, frames=18)
        assert record.irrecoverable == {"forward": cycles, "reset": 0}
        triggers = rows(tmp_path / name / "triggers.csv")
        assert [(t["steps"], t["irrecoverable"]) for t in triggers] == [("3", "1")] * cycles
        resets = rows(tmp_path / name / "resets.csv")
        assert [(r["outcome"], r["started_by"], r["irrecoverable"]) for r in resets] == [("manual", "triggered", "1")] * cycles

    # A reset agent that walks the wrong way: the trigger stops the forward agent at cell 3 (recoverable, the
    # ditch at 4), and the reset's first step takes the system over the edge. The entry is the reset's; the
    # triggered state was recoverable.
    record = _chain_record(tmp_path / "e", ditch=4, trigger_cell=3, horizon=6, frames=18, reset_direction=1.0)
    assert record.irrecoverable == {"forward": 0, "reset": 2}
    assert [t["irrecoverable"] for t in rows(tmp_path / "e" / "triggers.csv")] == ["0", "0"]
    resets = rows(tmp_path / "e" / "resets.csv")
    assert [(r["outcome"], r["started_by"], r["irrecoverable"]) for r in resets] == [("manual", "triggered", "1")] * 2


def test_the_records_say_which_triggers_stopped_the_forward_agent_at_the_start(tmp_path):
    """The chain's at-initial-state check is x == 0. A trigger that fires everywhere stops the first forward action
    at cell 0 (a state that already counts as the start); the reset after it takes its one minimum step left
    (staying at 0) and succeeds: 1 step a cycle, so 4 steps give 4 such triggers. A trigger firing from cell 3
    stops the forward agent three cells out: not at the start (6 steps a cycle, 2 in 12 steps)."""
    record = _chain_record(tmp_path / "a", ditch=8, trigger_cell=0, horizon=6, frames=4)
    triggers = rows(tmp_path / "a" / "triggers.csv")
    assert [(t["steps"], t["at_initial_state"]) for t in triggers] == [("0", "1")] * 4
    assert record.history["triggers_at_initial_state"] == 4
    record = _chain_record(tmp_path / "b", ditch=8, trigger_cell=3, horizon=6, frames=12)
    assert [t["at_initial_state"] for t in rows(tmp_path / "b" / "triggers.csv")] == ["0", "0"]
    assert record.history["triggers_at_initial_state"] == 0


def test_the_summary_names_what_decides_the_float_rounding(tmp_path):
    """Two runs of one seed agree only on the same processor kind, product precision and torch thread count
    (a sum split over two threads rounds otherwise): the summary names all three."""
    before = torch.get_num_threads()
    try:
        saved = train.train(config(tmp_path, "task=ball_in_cup_catch", "total_steps=60", "threads=1"))
    finally:
        torch.set_num_threads(before)
    # the product precision is the one this processor's check chose (auto: bf16 only where it measures as accurate)
    assert saved["torch_threads"] == 1 and saved["processor"]
    assert saved["matmul_precision"] == accel.choose_matmul_precision("auto")


@pytest.mark.parametrize("learn_from_forward", [False, True])
def test_learn_from_forward_puts_the_forward_steps_in_the_reset_buffer_too(tmp_path, learn_from_forward):
    """reset.learn_from_forward: every forward step the forward buffer keeps is also a row of the reset agent's
    buffer, its n-step state taken inside its own forward episode (the state n steps on, or the episode's last);
    off (the paper's B_r) the reset buffer holds reset steps alone. 150 collected steps, stored as train.py
    stores them, no update."""
    cfg = config(tmp_path, "algo=ours", "task=cliff_cheetah", "total_steps=150", "algo.n_steps=3",
                 f"reset.learn_from_forward={str(learn_from_forward).lower()}")
    run = single_run.build_run(run_spec(cfg, check=False), "ieee")
    try:
        for batch in run.collector:
            run.learner.store(batch, train.DualCollector.phase_of(batch))
        forward = run.forward_rb.storage[:len(run.forward_rb)]
        reset = run.reset_rb.storage[:len(run.reset_rb)]
        forward_ids = set(forward["collector", "traj_ids"].tolist())
        reset_ids = reset["collector", "traj_ids"].tolist()
        assert len(forward_ids) >= 3  # several forward episodes in 150 steps (H_f = 20)
        assert (forward_ids <= set(reset_ids)) is learn_from_forward
        assert forward_ids.isdisjoint(reset_ids) is (not learn_from_forward)
        if learn_from_forward:
            ids = forward["collector", "traj_ids"]
            rows = [i for i, t in enumerate(reset_ids) if t in forward_ids]
            # in the same order; the n-step transform holds back at most n - 1 = 2 rows of an episode still going
            assert len(forward) - 2 <= len(rows) <= len(forward)
            assert torch.equal(reset[rows]["observation"], forward[:len(rows)]["observation"])
            for i in range(len(rows)):  # s_{t+3}: the next state two rows on, in the same episode, or its last
                same = (ids == ids[i]).nonzero().squeeze(-1)
                j = min(i + 2, int(same.max()))
                assert torch.equal(reset[rows[i]]["nstep", "observation"], forward[j]["next", "observation"])
    finally:
        run.collector.shutdown()
        run.eval_env.close()


def test_the_code_version_is_the_scripts_checkout_where_the_package_is_an_installed_copy(tmp_path, monkeypatch):
    """With the package imported from outside any checkout (``pip install .``: a copy in site-packages), the commit
    is that of the checkout the running script lives in (``recipes/train.py``); with neither, None."""
    from torchrl_reset_recipes.training import run_folder

    root = RECIPES.parent
    head = subprocess.run(["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True, text=True)
    if head.returncode != 0:
        pytest.skip("the tests do not run from a git checkout here")
    copy = tmp_path / "site-packages" / "torchrl_reset_recipes" / "training" / "run_folder.py"
    monkeypatch.setattr(run_folder, "__file__", str(copy))
    assert run_folder.code_version(str(RECIPES / "train.py"))["commit"] == head.stdout.strip()
    assert run_folder.code_version(str(tmp_path / "elsewhere" / "train.py")) == {"commit": None, "modified": None}


def test_separate_random_streams_resume_exactly_and_part_from_the_shared_stream(tmp_path):
    """learner.streams=separate (the actor's and the learner's draws apart): a run stopped at 150 steps and resumed
    equals the run that never stopped, row by row; it parts from the shared stream's run once the learner draws
    (after heat-up), and not before: the actor's stream starts where the shared one does."""
    common = ["task=peg_insertion_remove", "algo=ours", "learner.streams=separate", "eval_every=300"]
    train.train(config(tmp_path / "whole", *common, "total_steps=300"))
    train.train(config(tmp_path / "split", *common, "total_steps=150"))
    train.train(config(tmp_path / "split", *common, "total_steps=300", "resume=true"))
    drop = {"steps_per_second"}
    a = [{k: v for k, v in r.items() if k not in drop} for r in rows(tmp_path / "whole" / "progress.csv")]
    b = [{k: v for k, v in r.items() if k not in drop} for r in rows(tmp_path / "split" / "progress.csv")]
    assert a == b and len(a) == 6
    train.train(config(tmp_path / "shared", "task=peg_insertion_remove", "algo=ours", "eval_every=300",
                       "total_steps=300"))
    shared = rows(tmp_path / "shared" / "progress.csv")
    # the first log row (50 steps) comes before either agent's heat-up (40 steps of each): the same episodes
    counters = ("forward_steps", "reset_steps", "forward_episodes", "manual_resets", "triggered_resets")
    assert {k: shared[0][k] for k in counters} == {k: a[0][k] for k in counters}
    assert any(shared[i][k] != a[i][k] for i in range(len(a)) for k in ("loss_reset_critic", "loss_forward_critic"))


def test_random_streams_are_independent_and_restore():
    import torch

    from torchrl_reset_recipes.training.streams import RandomStreams

    streams = RandomStreams("separate", seed=3)
    with streams.use("actor"):
        first = torch.rand(3)
    with streams.use("learner"):
        learner_draw = torch.rand(4)
    saved = streams.state_dict()
    with streams.use("actor"):
        second = torch.rand(3)
    torch.manual_seed(3)  # the actor's stream is the shared stream of seed 3, however the learner draws
    assert torch.equal(torch.cat([first, second]), torch.rand(6))
    torch.manual_seed(3 + 7_919)
    assert torch.equal(learner_draw, torch.rand(4))
    restored = RandomStreams("separate", seed=99)
    restored.load_state_dict(saved)
    with restored.use("actor"):
        assert torch.equal(torch.rand(3), second)  # goes on where the saved actor stream stood
    shared = RandomStreams("shared", seed=3)
    with pytest.raises(ValueError, match="resume with learner.streams=separate"):
        shared.load_state_dict(saved)
    with pytest.raises(ValueError, match="learner.streams must be one of shared, separate"):
        RandomStreams("both")


def test_ctrl_c_stops_an_async_run_and_both_processes_checkpoint_and_the_lockstep_run_resumes_exactly(tmp_path):
    """learner.mode=async, lockstep: Ctrl-C reaches both processes; the learner ignores it, the actor checkpoints
    after its step with the learner's part (learner.pt) and exits 130; the printed command resumes the run, which
    then equals the single process's uninterrupted run (learner.mode=sync, the same separate streams), table for
    table and in the summary's counters: lockstep gives exactly the single process's counters and losses."""
    import shlex

    common = ["task=cliff_cheetah", "algo=ours", "total_steps=200", "learner.streams=separate"]
    train.train(config(tmp_path / "whole", *common))
    common += ["learner.mode=async", "learner.max_lag=0"]
    run_dir = tmp_path / "run"
    args = [sys.executable, str(RECIPES / "train.py"), *TINY, *common, f"run_dir={run_dir}"]
    progress = run_dir / "progress.csv"
    returncode, err = _signal_when(args, lambda: progress.exists() and len(rows(progress)) >= 2,
                                   signal.SIGINT, poll=0.05)
    assert returncode == 130, err[-2000:]
    stopped = json.loads((run_dir / "summary.json").read_text())["steps"]
    latest = run_dir / "checkpoints" / (run_dir / "checkpoints" / "latest").read_text()
    assert json.loads((latest / "meta.json").read_text())["frames"] == stopped and (latest / "learner.pt").exists()
    resumed = subprocess.run(shlex.split(err.strip().splitlines()[-1].strip()), capture_output=True, text=True,
                             timeout=600, env={**os.environ, "RL_WARNINGS": "0"})
    assert resumed.returncode == 0, resumed.stderr[-2000:]
    assert_same_tables(tmp_path / "whole", run_dir)
    sync, lockstep = (json.loads((d / "summary.json").read_text()) for d in (tmp_path / "whole", run_dir))
    same = ("steps", "manual_resets", "episodic_resets", "successful_resets", "forward_share", "updates_achieved")
    assert {k: sync[k] for k in same} == {k: lockstep[k] for k in same}
    assert lockstep["learner"]["mode"] == "async" and lockstep["learner"]["lag_steps"]["max"] == 0
