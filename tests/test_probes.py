"""The analysis probes (``results/*/probes/*.py``): every one answers ``--help``, and every one runs on tiny run
folders, made once per session by the recipe, and prints what it should. Also the run-folder readers of
``recipes/analysis/saved_runs.py`` the probes use (the config, the CSV tables, the replay buffers)."""
from __future__ import annotations

import ast
import math
import re
import runpy
import shutil
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import pytest
from hydra import compose, initialize_config_dir

ROOT = Path(__file__).resolve().parents[1]
RECIPES = ROOT / "recipes"

from torchrl_reset_recipes import train
from torchrl_reset_recipes.analysis.saved_runs import latest_checkpoint, load_replay, run_config, run_table

#: every probe in the repository, found anew at each collection: a probe added later is tested as well
PROBES = sorted((ROOT / "results").glob("*/probes/*.py"))

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
    with initialize_config_dir(config_dir=str(RECIPES / "conf"), version_base="1.3"):
        cfg = compose(config_name="config", overrides=[*TINY, f"task={task}", f"algo={algo}", f"run_dir={run_dir}",
                                                       *overrides])
    summary = train.train(cfg)
    assert summary["finished"] and summary["steps"] == STEPS
    return run_dir


@pytest.fixture(scope="session")
def runs(tmp_path_factory) -> Runs:
    root = tmp_path_factory.mktemp("runs")
    made = Runs(root, cliff=_train(root, "cliff_cheetah", "ours", "algo.threshold=0.5"),
                peg=_train(root, "peg_insertion_insert", "lnt_sparse", "algo.num_members=3"))
    for run in (made.cliff, made.peg):  # several probes start from the trigger states
        if not run_table(run, "triggers.csv"):
            pytest.fail(f"{run} logged no trigger in {STEPS} steps: the probes of trigger states have nothing to read")
    return made


@dataclass(frozen=True)
class ProbeRun:
    """How the test runs one probe: its arguments (given the session's runs and the test's own folder), lines
    its output must hold (regular expressions, searched line by line), and a check of the files it wrote."""

    args: Callable[[Runs, Path], list]
    prints: tuple[str, ...]
    wrote: Callable[[Runs, Path], None] | None = None


def _series_csv_matches_the_committed_ones(runs: Runs, out: Path) -> None:
    """lnt_critics.py's --csv rows, as plot_series.py reads them (the committed series' header)."""
    written = (out / "series.csv").read_text().splitlines()
    committed = (ROOT / "results" / "100000" / "probes" / "series_lnt_seed2.csv").read_text().splitlines()
    assert len(written) == 2 and written[0] == committed[0] and written[1].startswith(f"{STEPS},")


def _copy_of_a_committed_series(runs: Runs, out: Path) -> list:
    """plot_series.py writes its PNG beside the CSV: a copy in the test's folder, not the committed file."""
    shutil.copy(ROOT / "results" / "100000" / "probes" / "series_lnt_seed2.csv", out)
    return [out / "series_lnt_seed2.csv"]


def _exists(*names: str) -> Callable[[Runs, Path], None]:
    def check(runs: Runs, out: Path) -> None:
        missing = [name for name in names if not (out / name).is_file()]
        assert not missing, f"not written: {missing}"
    return check


#: each probe's arguments on the session's runs, kept small (few states, episodes and updates), and lines it prints
PROBE_RUNS: dict[str, ProbeRun] = {
    "100000/probes/lnt_critics.py": ProbeRun(
        lambda r, out: [r.peg, str(STEPS), "--csv", out / "series.csv"],
        (rf"at step {STEPS}: \d+ reset replay rows, 3 members, reward sparse, Q_thresh 0.1$",
         r"^uniform: reward mean", r"^  Q\(s, pi_r\(s\)\): mean .*members outside \[0, 100\]: \d+ of 3$",
         r"^  TD\(0\) error \(rms\), members: \S+ \S+ \S+$"),
        wrote=_series_csv_matches_the_committed_ones),
    "100000/probes/plot_series.py": ProbeRun(
        _copy_of_a_committed_series, (r"series_lnt_seed2\.png$",), wrote=_exists("series_lnt_seed2.png")),
    "100000-release/probes/arm_reach.py": ProbeRun(
        lambda r, out: ["--episodes", "2", "--steps", "10", "--out", out / "arm_reach.csv"],
        (r"^2 episodes of 10 steps from the insert task's start$", r"^\| tier 1 \| noise \|",
         r"^\| release \| policy \+ noise \|"),
        wrote=_exists("arm_reach.csv")),
    "100000-release/probes/compare.py": ProbeRun(
        lambda r, out: ["--new", r.cliff.parent, "--old", r.cliff.parent, "--seeds", "0", "--upto", str(STEPS),
                        "--window", "100"],
        (r"^seed 0, release's settings \(", r"^seed 0, before \(", r"^\| 100-200 \| \d+ \|")),
    "100000-release/probes/offline_classifier.py": ProbeRun(
        lambda r, out: ["--seeds", "0", "--updates", "2", "--every", "1", "--rows", "40", "--init-seeds", "1",
                        "--out", out / "offline.csv", "--settings", "hidden_sizes=[16,16]", "task.forward_horizon=20",
                        "reset.buffer_size=2000", "reset.batch_size=16", "algo.num_members=2"],
        (r"^data: \d+ transitions of \d+ failed reset episodes", r"^untrained, xavier, 1 seeds x 2000 rows",
         r"^seed 0 fan_in: replay score [\d.]+ at 0 -> [\d.]+ at 2", r"^seed 0 xavier: replay score"),
        wrote=_exists("offline.csv", "offline_init.csv")),
    "100000-release/probes/offline_lnt_ensemble.py": ProbeRun(
        lambda r, out: [r.peg / "checkpoints" / f"step_{STEPS:010d}", "--upto", "100", "--seeds", "0", "--scales", "0",
                        "3", "--updates", "2", "--every", "1", "--out", out / "ensemble.csv"],
        (r"^data at 100 steps: \d+ forward rows, \d+ reset rows \(\d+ one step from success\)$",
         r"^seed 0 prior_scale 0 at +0 updates: forward rows' minimum", r"^seed 0 prior_scale 3 at +2 updates"),
        wrote=_exists("ensemble.csv")),
    "lnt-sparse/probes/offline_options.py": ProbeRun(
        lambda r, out: [r.peg / "checkpoints" / f"step_{STEPS:010d}", "--seeds", "0", "--options", "project",
                        "all_four", "--updates", "2", "--every", "1", "--out", out / "options.csv"],
        (r": \d+ forward rows, \d+ reset rows \(\d+ one step from success\)$",
         r"^seed 0 +project at +0 updates: forward rows' minimum", r"^seed 0 +all_four at +2 updates"),
        wrote=_exists("options.csv")),
    "100000-tier2/probes/actor_saturation.py": ProbeRun(
        lambda r, out: [r.cliff, "--states", "5", "--out", out / "saturation"],
        (r": 2 checkpoints, \d+ fixed trigger states$", r"^100 \| ", rf"^{STEPS} \| .* \| \d+ / \d+$", r"^wrote "),
        wrote=_exists("saturation.csv", "saturation.png")),
    "100000-tier2/probes/reset_failures.py": ProbeRun(
        lambda r, out: [r.cliff, "--states", "2"],
        (rf": checkpoint step_{STEPS:010d}; \d trigger states from frames", r"^reset actor on these states: ",
         r"^held from the start state for 200 steps, no torque: \d+ steps pass the check",
         r"^greedy: success \d+, flipped \d+, away \d+, near \d+", r"^noisy : success \d+",
         r"^logged outcome of the reset that followed these triggers in training: ")),
    "100000-tier2/probes/trigger_states.py": ProbeRun(
        lambda r, out: [r.cliff],
        (r"^  reset episodes, success: \d+, [\d,]+ steps$", r"^  triggers: \d+; within the first 2 forward steps: ",
         r"^  before a reset that ended in manual \(\d+\): \|pitch\| quartiles")),
    "lnt-sparse/probes/peg_check.py": ProbeRun(
        lambda r, out: ["--episodes", "2", "--samples", "20", "--window", "100", "--runs", r.peg],
        (r"^1\. the check against the task$", r"^   d_start between the start and the goal: 0\.927",
         r"^   one corner of the action box held: end inside the check", r"^3\. trigger states of the runs",
         r"seed0: \d+ triggers, \d+% already inside the check",
         r"^     (0-100|100-200): \d+ triggers, \d+% inside the check, d_start median [\d.]+$")),
    "lnt-sparse/probes/trained_ensembles.py": ProbeRun(
        lambda r, out: [f"at100={r.peg}:step_{100:010d}", f"at{STEPS}={r.peg}:step_{STEPS:010d}", "--triggers", "3",
                        "--rollouts", "2", "--burn-in", "5", "--out", out / "ensembles.csv"],
        (rf"^at{STEPS}: .* at {STEPS} steps, \d+ forward rows, \d+ reset rows \(\d+ one step from success\), Q_thresh 0.1$",
         r"^  its last \d trigger states: logged at \d+-\d+ steps$",
         rf"^\| at100 \| at{STEPS}'s forward rows \| \d+ \| -?[\d.]+ \| [\d.]+% \| \d+% \| -?[\d.]+ \| [\d.]+ \| [\d.]+ \|$",
         rf"^\| at{STEPS} \| at100's trigger states, its actor's action \| [1-3] \| ",
         r"^Forward episodes with the trigger armed \(2 per pair, H_f 20, seed 0\)",
         rf"^\| at{STEPS}'s (\| \d+% \[\d+%, \d+%\] \((\d+|-)\) ){{2}}\|$"),
        wrote=_exists("ensembles.csv")),
    "100000-tanh-normal-auto/probes/trigger_actions.py": ProbeRun(
        lambda r, out: [r.cliff, "--last", "5"],  # the run's trigger set at 0.5 (algo.threshold)
        (rf"at step_{STEPS:010d}: the last \d+ trigger states, p_thresh 0.5$",
         r"^\| forward actor's \| [\d.]+ \| \d+% \|$", r"^\| reset actor's \| [\d.]+ \| \d+% \|$",
         r"^forward actor at these states: \d+% beyond \+-0.9",
         r"^forward replay(, \d+ rows|: none here \(.*the forward agent had stored no step)",
         r"^reset replay, \d+ rows: \d+% beyond")),
    "screening-reset-actor/probes/reset_exploration.py": ProbeRun(
        lambda r, out: [f"tiny={r.cliff.parent}", "--seeds", "0", "--checkpoint", f"step_{STEPS:010d}", "--last", "50",
                        "--out", out],
        (r"^configuration tiny, seed 0, spread [\d.e-]+, p_stored .* triggers \d+, forward_before_trigger",
         r"^\| tiny \| 1 \| "),
        wrote=_exists("reset_exploration.csv", "reset_exploration.md")),
    "100000-tanh-normal-auto/probes/trigger_noise.py": ProbeRun(
        lambda r, out: [r.cliff, "--episodes", "2", "--trajectory", "3", "--burn-in", "10"],
        (r"2 forward episodes per case, H_f 20, p_thresh 0.5, seed 0$",
         r"^\| 0 \| (yes|no) \| [\d.]+ \| [\d.]+ \| [\d.]+ \|$",
         *(rf"^\| {case} \| \d+% \| \d+% \| ([\d.]+|-) \| (\d+%|-) \| [\d.]+ \|$"
           for case in ("carried", "carried, clipped", "restarted", "none")))),
    "peg-early-triggers/probes/coverage.py": ProbeRun(
        lambda r, out: [r.peg, "--start", "50", "--end", "150"],
        (r"^Rows written in 50-150 steps",
         *(rf"seed0 \| {agent} \| (\d+ \| \d+% \| [\d.]+, [\d.]+, [\d.]+|0 \| \| ) \|$"
           for agent in ("reset", "forward")))),
    "peg-early-triggers/probes/resets_from_the_start.py": ProbeRun(
        lambda r, out: [r.peg, "--start", "0", "--end", str(STEPS), "--last", "3"],
        (rf"of the last \d+ trigger states in 0-{STEPS}, \d+ inside the check; reset horizon 40, the run's minimum 5 steps$",)),
    "peg-early-triggers/probes/measure.py": ProbeRun(
        lambda r, out: [f"tiny={r.peg.parent}", "absent=" + str(out / "none"), "--seeds", "0", "--start", "0",
                        "--end", str(STEPS), "--figure", out / "stretches.png", "--window", "100"],
        # the kinematic check and the env's own flag logged with each trigger must agree on every trigger state
        (r"^\| tiny \| 0 \| \d+ \| \d+% \(env's flag agrees on 100%\) \| \d+ \| \d+% \| \d+ \| [\d.]+ \|$",
         r"^\| absent \| 0 \| not started \|", r"^\| tiny \| 1 \| \d+% \| ", r"stretches\.png$",
         r"^\| tiny \| 0 \| \d+ \| (\d+%|-) \| \d+ \| (\d+%|-) \|$"),
        wrote=_exists("stretches.png")),
    "quick-ball-in-cup/probes/example_action.py": ProbeRun(
        lambda r, out: ["--seeds", "0", "--steps", "150", "--updates", "2", "--every", "1"],
        (r"^seed 0, from its checkpoint at 150 steps, 2 more reset updates$", r"^\| variant \| updates \| mean action",
         r"^\| pi\(s\*\) \| 0 \|", r"^\| uniform and shuffled \| 2 \|")),
    "quick-ball-in-cup/probes/min_member.py": ProbeRun(
        lambda r, out: [r.cliff, "--rows", "50"],
        (rf"\(step_{STEPS:010d}, 50 states\): the minimum member (\d+%, ){{4}}\d+% of rows \(members 0-4\)",
         r"^  d\(min logit\)/da, trained part df/da: mean", r"^  where \|a\| > 0.9, pointing further out of the box")),
    "quick-ball-in-cup/probes/reset_actions.py": ProbeRun(
        lambda r, out: [r.cliff, "--last", "50"],
        (rf"\(step_{STEPS:010d}, last 50 reset actions\): mean \|a\| [\d.]+; outside \[-1, 1\] \d+%",)),
}


def _name(probe: Path) -> str:
    return probe.relative_to(ROOT / "results").as_posix()


def _history_has(commit: str) -> bool:
    return subprocess.run(["git", "-C", str(ROOT), "cat-file", "-e", commit], capture_output=True).returncode == 0


def test_the_probes_are_found():
    assert len(PROBES) >= 13 and all(p.parent.name == "probes" for p in PROBES)


def test_every_entry_of_the_table_names_a_probe():
    stale = sorted(set(PROBE_RUNS) - {_name(p) for p in PROBES})
    assert not stale, f"PROBE_RUNS names probes that are not in results/*/probes/: {stale}"


@pytest.mark.parametrize("probe", PROBES, ids=_name)
def test_every_probe_answers_help(probe, monkeypatch, capsys):
    """``python <probe> --help`` (run in this process: it exits before the probe does any work): usage, and the
    module docstring as its description."""
    doc = ast.get_docstring(ast.parse(probe.read_text()))
    assert doc, f"{_name(probe)} has no module docstring to describe it"
    monkeypatch.setattr(sys, "argv", [str(probe), "--help"])
    try:
        runpy.run_path(str(probe), run_name="__main__")
    except SystemExit as exited:
        code = exited.code
    else:
        pytest.fail(f"{_name(probe)} --help did not stop at its usage: it ran (on an argument named --help)")
    out = capsys.readouterr().out
    assert code in (0, None), f"{_name(probe)} --help exited with {code!r}"
    assert out.startswith("usage: ") and "--help" in out, f"{_name(probe)} --help printed no usage:\n{out}"
    first_line = " ".join(doc.splitlines()[0].split())
    assert first_line in " ".join(out.split()), f"{_name(probe)} --help does not describe it by its docstring"


@pytest.mark.parametrize("probe", PROBES, ids=_name)
def test_every_probe_runs_on_a_run_folder(probe, request, tmp_path, monkeypatch, capsys):
    """Each probe run as ``python <probe> <args>`` would run it, in this process (its imports are made once for the
    session, not once per probe): its arguments, the working directory the results' READMEs run it from, temporary
    folders (example_action's runs) in the test's own folder; it must end without an error and print its lines."""
    name = _name(probe)
    if name not in PROBE_RUNS:
        pytest.fail(f"{name} has no entry in PROBE_RUNS (tests/test_probes.py): add the arguments that run it, small, "
                    "on the session's run folders and lines its output must hold")
    if name == "100000-release/probes/arm_reach.py" and not _history_has("d7b4986~1"):
        pytest.skip("arm_reach.py builds tier 1's arm from the repository's history (commit d7b4986), absent here")
    entry = PROBE_RUNS[name]
    runs = request.getfixturevalue("runs")  # made once, on the first probe that has an entry
    args = [str(a) for a in entry.args(runs, tmp_path)]
    monkeypatch.chdir(ROOT)
    monkeypatch.setattr(sys, "argv", [str(probe), *args])
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    capsys.readouterr()
    try:
        runpy.run_path(str(probe), run_name="__main__")
    except SystemExit as exited:
        assert exited.code in (0, None), f"{name} {' '.join(args)} exited with {exited.code!r}:\n{capsys.readouterr()}"
    out = capsys.readouterr().out
    lines = out.splitlines()
    missing = [pattern for pattern in entry.prints if not any(re.search(pattern, line) for line in lines)]
    assert not missing, f"{name} printed no line matching {missing}:\n{out[-3000:]}"
    if entry.wrote is not None:
        entry.wrote(runs, tmp_path)


# the run-folder readers of recipes/analysis/saved_runs.py


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


def test_reset_exploration_measures_the_forward_steps_before_each_trigger(tmp_path):
    """A run of three forward episodes, worked out by hand: 100 forward steps ended by the horizon (no trigger),
    a reset of 200 steps; 5 forward steps, then a trigger (logged at step 305) and a reset of 15 steps; a trigger
    on the first forward action (step 320) and a reset of 200. Triggered episodes: 5 and 0 forward steps."""
    probe = runpy.run_path(str(ROOT / "results" / "screening-reset-actor" / "probes" / "reset_exploration.py"))
    (tmp_path / "config.yaml").write_text("task: {}\n")
    (tmp_path / "resets.csv").write_text("frames,outcome,steps\n300,manual,200\n320,success,15\n520,manual,200\n")
    (tmp_path / "triggers.csv").write_text("frames,steps,value\n305,0,0.05\n320,0,0.01\n")
    assert probe["forward_lengths_before_triggers"](tmp_path, 10_000) == [5, 0]
    assert probe["forward_lengths_before_triggers"](tmp_path, 400) == [5]  # the last reset ends after step 400


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


def test_measure_counts_the_triggers_at_the_start_stretch_by_stretch(tmp_path):
    """A run folder written by hand on peg insertion (insert): triggers at 50 and 150 with the arm at its reset
    pose (d_start near 0: inside the check) and at 160 with its first joint turned 1 rad (far outside); resets ending
    at 60, 170 and 180. Stretches of 100 steps: (0, 100] one trigger, inside, one reset; (100, 200] two, one
    inside, two resets."""
    probe = runpy.run_path(str(ROOT / "results" / "peg-early-triggers" / "probes" / "measure.py"))
    check = probe["AtStart"]("peg_insertion_insert")
    start = check.env.reset(seed=0)[0][:7]
    far = start.copy()
    far[0] += 1.0
    assert probe["d_start"](check.env, start) < 0.01 and probe["d_start"](check.env, far) > 0.2  # the reset pose
    (tmp_path / "config.yaml").write_text("task:\n  name: peg_insertion_insert\n")
    (tmp_path / "progress.csv").write_text("frames,manual_resets,forward_share\n100,1,0.5\n200,2,0.4\n")
    pose = lambda q: " ".join(f"{v:.6g}" for v in q)  # noqa: E731
    (tmp_path / "triggers.csv").write_text(f"frames,steps,value,irrecoverable,observation\n50,3,0,,{pose(start)}\n"
                                           f"150,4,0,,{pose(start)}\n160,2,0,,{pose(far)}\n")
    (tmp_path / "resets.csv").write_text("frames,outcome,steps\n60,success,7\n170,success,6\n180,manual,5\n")
    stops, shares, resets = probe["by_stretch"](check, tmp_path, 100)
    assert (stops, shares, resets) == ([100, 200], [1.0, 0.5], [1, 2])
    row = probe["measure"](check, tmp_path, 100, 200)
    assert (row["triggers"], row["inside"], row["reset_episodes"], row["reset_success"], row["manual_resets"]) == \
        (2, 0.5, 2, 0.5, 2)
    with pytest.raises(SystemExit, match="a run of peg_insertion_insert, the others of cliff_cheetah"):
        probe["measure"](probe["AtStart"]("cliff_cheetah"), tmp_path, 100, 200)


def test_measure_checks_cliff_cheetah_at_its_start():
    """cliff-cheetah's check, |x| < 0.1 and |pitch| < 0.1 (the task's definition), on 18-value observations written
    by hand: the positions first (x, z, pitch, six joints), then nine velocities, which the check ignores."""
    probe = runpy.run_path(str(ROOT / "results" / "peg-early-triggers" / "probes" / "measure.py"))
    check = probe["AtStart"]("cliff_cheetah")

    def state(x, pitch, velocity=0.0):
        return " ".join(str(v) for v in [x, 0.02, pitch] + [0.3] * 6 + [velocity] * 9)

    assert check(state(0.05, -0.08)) and check(state(-0.09, 0.09, velocity=5.0))
    assert not check(state(0.15, 0.0)) and not check(state(0.0, -0.12)) and not check(state(-1.13, 0.08))
    with pytest.raises(SystemExit, match="a run of cliff_walker"):
        probe["AtStart"]("cliff_walker")


def test_carried_noise_carries_the_runs_ornstein_uhlenbeck_noise():
    """The probes' noise (saved_runs.CarriedNoise: the recipe's module carried from call to call), worked out by hand: without sigma
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
    """saved_runs.ensemble_scores (trained_ensembles.py's table, ensemble_minimum's parts) on four rows of two forward episodes, three members' Q-values chosen by hand, Q_thresh 0.1: the minima are
    1, 0.05, 4 and 2 (mean 1.7625), one row below Q_thresh (25%), in the first episode (1 of 2 episodes); the
    members' means 2, 0.2, 4, 3 (mean 2.3); their standard deviations 1, 0.15, 0, 1 (mean 0.5375); mean - minimum
    1, 0.15, 0, 1 (mean 0.5375). ensemble_minimum on rows 0-1 (forward) and 2-3: minima 1, 0.05 (mean 0.525, half
    below), std 1, 0.15 (mean 0.575); minima 4, 2 (mean 3, none below)."""
    import torch
    from tensordict import TensorDict

    from torchrl_reset_recipes.analysis.saved_runs import ensemble_minimum, ensemble_scores

    probe = runpy.run_path(str(ROOT / "results" / "lnt-sparse" / "probes" / "trained_ensembles.py"))
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
    with pytest.raises(SystemExit, match="NAME=RUN:CHECKPOINT"):
        probe["parse"]("no-checkpoint-named")
    # the Wilson interval of 0 in 30 at 95%: [0, z^2 / (n + z^2)] = [0, 3.8416 / 33.8416]; of 15 in 30, symmetric
    # about 1/2 with half-width z sqrt(1/120 + z^2/3600) / (1 + z^2/30) = 0.190034 / 1.128053 = 0.168462
    assert probe["wilson"](0, 30) == pytest.approx((0.0, 0.113517), abs=1e-6)
    assert probe["wilson"](15, 30) == pytest.approx((0.5 - 0.168462, 0.5 + 0.168462), abs=1e-5)
