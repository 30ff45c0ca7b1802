"""The run-folder readers of ``recipes/analysis/saved_runs.py`` (the config, the CSV tables, the replay buffers,
the carried noise, the ensemble's scores), on tiny run folders made once per session by the recipe.

The probes under ``results/*/probes/`` that used them answered decided questions and are frozen at commit
271779f (results/README.md says how to run one there); they are not in the suite."""
from __future__ import annotations

import fcntl
import math
import os
import shutil
from dataclasses import dataclass
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]

from torchrl_reset_recipes import train
from torchrl_reset_recipes.training.hydra_config import compose
from torchrl_reset_recipes.analysis.saved_runs import latest_checkpoint, load_examples, load_replay, run_config, run_table

#: a few hundred steps of small networks, both agents updating (heat-up 40), checkpoints and kept states at
#: 100 and 200 steps; one thread: on a busy machine the runs take a few seconds each
TINY = [
    "hidden_sizes=[16,16]", "heat_up=40", "task.forward_horizon=20", "forward.batch_size=16", "reset.batch_size=16",
    "forward.buffer_size=2000", "reset.buffer_size=2000", "total_steps=200", "log_every=50", "eval_every=200",
    "checkpoint_every=100", "keep_states_every=100", "threads=1", "progress_bar=false", "speed.compile=[]",
]
STEPS = 200


@dataclass(frozen=True)
class Runs:
    """The session's run folders (``root/<task>/<algo>/seed0``, as the recipe names them)."""

    root: Path
    cliff: Path  # cliff-cheetah, ours: the reset agent's classifiers; its trigger set high, so that it fires
    peg: Path  # peg-insertion (insert), LNT-sparse with 3 Q-functions


def _train(root: Path, task: str, algo: str, *overrides: str) -> Path:
    run_dir = root / task / algo / "seed0"
    cfg = compose([*TINY, f"task={task}", f"algo={algo}", f"run_dir={run_dir}", *overrides])
    summary = train.train(cfg)
    assert summary["finished"] and summary["steps"] == STEPS
    return run_dir


@pytest.fixture(scope="session")
def runs(tmp_path_factory) -> Runs:
    """Made once per session: under ``pytest -n 2`` the first worker to ask trains them, the other waits on the lock
    and reads the same folders (the session's temporary folder is shared by its workers)."""
    shared = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        shared = shared.parent
    root = shared / "saved-runs"
    with open(shared / "saved-runs.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if (root / "made").exists():
            made = Runs(root, cliff=root / "cliff_cheetah" / "ours" / "seed0",
                        peg=root / "peg_insertion_insert" / "lnt_sparse" / "seed0")
        else:
            made = Runs(root, cliff=_train(root, "cliff_cheetah", "ours", "algo.threshold=0.5"),
                        peg=_train(root, "peg_insertion_insert", "lnt_sparse", "algo.num_members=3"))
            (root / "made").touch()
    for run in (made.cliff, made.peg):  # the trigger-state readers below need triggers
        if not run_table(run, "triggers.csv"):
            pytest.fail(f"{run} logged no trigger in {STEPS} steps: run_table's triggers.csv has nothing to read")
    return made


def test_run_config_reads_a_run_folders_config(runs, tmp_path):
    cfg = run_config(runs.cliff)
    assert (cfg.task.name, cfg.algo.name, cfg.total_steps, list(cfg.hidden_sizes)) == ("cliff_cheetah", "ours", STEPS,
                                                                                       [16, 16])
    with pytest.raises(FileNotFoundError, match="holds no config.yaml"):
        run_config(tmp_path)


def test_run_table_reads_a_run_folders_csv_tables(runs, tmp_path):
    progress = run_table(runs.peg, "progress.csv")
    assert [row["frames"] for row in progress] == ["50", "100", "150", "200"]
    assert int(progress[-1]["forward_steps"]) + int(progress[-1]["reset_steps"]) == STEPS
    triggers = run_table(runs.cliff, "triggers.csv")
    assert triggers and all(len(row["observation"].split()) == 18 for row in triggers)  # cliff-cheetah: qpos, qvel
    assert {row["outcome"] for row in run_table(runs.cliff, "resets.csv")} <= {"success", "manual"}
    # a table the run has not written yet (triggers.csv before the first trigger) has no rows
    shutil.copy(runs.cliff / "config.yaml", tmp_path / "config.yaml")
    assert run_table(tmp_path, "triggers.csv") == []
    for bad in ("resets", "../resets.csv", "checkpoints/latest"):
        with pytest.raises(ValueError, match="by its file name"):
            run_table(runs.cliff, bad)
    with pytest.raises(FileNotFoundError, match="holds no config.yaml"):
        run_table(tmp_path / "nothing", "resets.csv")


def test_load_replay_reads_a_checkpoints_replay_buffers(runs, tmp_path):
    progress = {int(row["frames"]): row for row in run_table(runs.peg, "progress.csv")}
    # every step a phase took is in its buffer: the latest checkpoint's, then one named relative to the run folder
    for step, checkpoint in ((STEPS, None), (100, "checkpoints/step_0000000100")):
        for agent in ("forward", "reset"):
            rb = load_replay(runs.peg, agent, checkpoint=checkpoint)
            assert len(rb) == rb.write_count == int(progress[step][f"{agent}_steps"])
    assert latest_checkpoint(runs.peg).name == f"step_{STEPS:010d}"
    # ours' reset buffer: its rows with the n-step state its transform writes beside them
    rows = load_replay(runs.cliff, "reset")[:]
    reset_steps = int(run_table(runs.cliff, "progress.csv")[-1]["reset_steps"])
    assert ("nstep", "observation") in rows.keys(True) and 0 < len(rows) <= reset_steps
    with pytest.raises(FileNotFoundError, match="a kept state holds the agents alone"):
        load_replay(runs.cliff, "reset", checkpoint="checkpoints/kept/step_0000000100")
    with pytest.raises(ValueError, match="agent must be 'forward' or 'reset'"):
        load_replay(runs.cliff, "both")
    shutil.copy(runs.cliff / "config.yaml", tmp_path / "config.yaml")
    for read in (latest_checkpoint, load_replay):
        with pytest.raises(FileNotFoundError, match="holds no complete checkpoint"):
            read(tmp_path)


def test_load_examples_reads_one_example_per_forward_episode_begun(runs):
    """Algorithm 1 adds the state at the start of every forward episode to S*: at each checkpoint the example
    buffer holds as many states as the run had begun forward episodes (progress.csv's count at that step)."""
    progress = {int(row["frames"]): row for row in run_table(runs.cliff, "progress.csv")}
    for step, checkpoint in ((STEPS, None), (100, "checkpoints/step_0000000100")):
        examples = load_examples(runs.cliff, checkpoint=checkpoint)
        assert len(examples) == int(progress[step]["forward_episodes"]) > 0
        assert examples.states()["observation"].shape[-1] == 18  # cliff-cheetah's observation
    with pytest.raises(FileNotFoundError, match="a kept state holds the agents alone"):
        load_examples(runs.cliff, checkpoint="checkpoints/kept/step_0000000100")


def test_guidance_groups_every_reset_replay_row_and_reads_only_ours(runs):
    from torchrl_reset_recipes.analysis.guidance import guidance

    text = guidance(runs.cliff, bins=4)
    table = [line for line in text.splitlines() if line.startswith("| ") and not line.startswith("| distance")]
    replay_rows = len(load_replay(runs.cliff, "reset"))
    assert table[0].startswith(f"| the examples ({len(torch.unique(load_examples(runs.cliff).states()['observation'], dim=0))} distinct)")
    assert len(table) == 5 and sum(int(line.split("|")[2]) for line in table[1:]) == replay_rows
    assert "Spearman rank correlation" in text
    with pytest.raises(SystemExit, match="this reads ours' classifiers"):
        guidance(runs.peg)


def test_the_scoring_helpers_read_logged_states_act_greedily_and_score_as_ours_trigger():
    """logged_observations parses triggers.csv's column; greedy_actions takes a tanh-Gaussian's tanh(loc), not a
    sample; trigger_probability is the members' mean of p = exp(min(logit, 0)) (C clipped at 0.5), worked out by
    hand: logits (0, ln 0.25) -> (1 + 0.25) / 2 = 0.625, logits (2, ln 0.5) -> (1 + 0.5) / 2 = 0.75."""
    import math

    import torch
    from tensordict.nn import TensorDictModule
    from torchrl.modules import ProbabilisticActor, TanhNormal

    from torchrl_reset_recipes.analysis.saved_runs import greedy_actions, logged_observations, trigger_probability

    states = logged_observations([{"observation": "1 -2.5"}, {"observation": "0.25 4"}])
    assert states.dtype == torch.float32 and states.tolist() == [[1.0, -2.5], [0.25, 4.0]]
    net = TensorDictModule(lambda obs: (obs / 4, torch.ones_like(obs)), ["observation"], ["loc", "scale"])
    actor = ProbabilisticActor(net, in_keys=["loc", "scale"], distribution_class=TanhNormal, return_log_prob=False)
    assert torch.allclose(greedy_actions(actor, states), torch.tanh(states / 4))

    class Logits:
        def logits(self, observation, action):
            return torch.tensor([[0.0, math.log(0.25)], [2.0, math.log(0.5)]])

    assert torch.allclose(trigger_probability(Logits(), states, states), torch.tensor([0.625, 0.75]))


def test_carried_noise_carries_the_runs_ornstein_uhlenbeck_noise():
    """saved_runs.CarriedNoise (: the recipe's module carried from call to call), worked out by hand: without sigma
    it decays by (1 - theta dt) a step (0.9925 ** 10 = 0.92748 at theta 0.15, dt 0.05) and is added to the action;
    without theta each step adds sigma sqrt(dt) eps, so that after n steps from zero its variance is n sigma**2 dt
    (100 steps at sigma 0.2, dt 0.05: 0.2); after a restart the next step starts again from zero."""
    import torch
    from torchrl.data import Bounded
    from torchrl.modules import OrnsteinUhlenbeckProcessModule

    def module(dim, theta, sigma, dt):
        return OrnsteinUhlenbeckProcessModule(spec=Bounded(-1.0, 1.0, shape=(dim,)), eps_init=1.0, eps_end=1.0,
                                              annealing_num_steps=1, theta=theta, sigma=sigma, dt=dt, safe=False)

    from torchrl_reset_recipes.analysis.saved_runs import CarriedNoise

    noise = CarriedNoise(module(3, theta=0.15, sigma=0.0, dt=0.05))
    noise(torch.zeros(3))  # the first call starts the state at zero
    noise.state["_ou_prev_noise"] = torch.ones(3)
    for _ in range(9):
        noise(torch.zeros(3))
    assert torch.allclose(noise(torch.full((3,), 0.5)), torch.full((3,), 0.5 + 0.92748), atol=1e-5)
    noise.restart()
    assert torch.equal(noise(torch.zeros(3)), torch.zeros(3))
    torch.manual_seed(0)
    walk = CarriedNoise(module(20000, theta=0.0, sigma=0.2, dt=0.05))
    for _ in range(99):
        walk(torch.zeros(20000))
    assert abs(float(walk(torch.zeros(20000)).var()) - 0.2) < 0.01  # 20,000 components: the sample variance within 5%


def test_ensemble_scores_scores_rows_as_the_trigger_would():
    """saved_runs.ensemble_scores (and ensemble_minimum's parts) on four rows of two forward episodes, three members' Q-values chosen by hand, Q_thresh 0.1: the minima are
    1, 0.05, 4 and 2 (mean 1.7625), one row below Q_thresh (25%), in the first episode (1 of 2 episodes); the
    members' means 2, 0.2, 4, 3 (mean 2.3); their standard deviations 1, 0.15, 0, 1 (mean 0.5375); mean - minimum
    1, 0.15, 0, 1 (mean 0.5375). ensemble_minimum on rows 0-1 (forward) and 2-3: minima 1, 0.05 (mean 0.525, half
    below), std 1, 0.15 (mean 0.575); minima 4, 2 (mean 3, none below)."""
    import torch
    from tensordict import TensorDict

    from torchrl_reset_recipes.analysis.saved_runs import ensemble_minimum, ensemble_scores

    q = torch.tensor([[1.0, 2.0, 3.0], [0.05, 0.2, 0.35], [4.0, 4.0, 4.0], [2.0, 3.0, 4.0]])

    def model(td):  # a row's observation is its index into q
        return td.set("state_action_value", q[td["observation"][:, 0].long()])

    rows = TensorDict({"observation": torch.arange(4.0).reshape(4, 1), "action": torch.zeros(4, 1),
                       "collector": {"traj_ids": torch.tensor([0, 0, 1, 1])}}, [4])
    got = ensemble_scores(model, rows, 0.1, rows["collector", "traj_ids"])
    expected = {"rows": 4, "min_mean": 1.7625, "below_q_thresh": 0.25, "episodes_flagged": 0.5, "member_mean": 2.3,
                "member_std": 0.5375, "mean_minus_min": 0.5375}
    assert got == pytest.approx(expected)
    unflagged = ensemble_scores(model, rows.exclude("collector"), 0.1)  # rows without episodes
    assert math.isnan(unflagged["episodes_flagged"]) and unflagged["below_q_thresh"] == 0.25
    # ensemble_minimum: the first two rows as the forward rows, the last two as those one step from success
    assert ensemble_minimum(model, rows[:2], rows[2:], 0.1) == pytest.approx(
        {"forward_min_mean": 0.525, "forward_below_q_thresh": 0.5, "forward_member_std": 0.575,
         "near_success_min_mean": 3.0, "near_success_below_q_thresh": 0.0})
