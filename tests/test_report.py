"""report.py on small fabricated run folders: Table 1 numbers worked out by hand, and the figures."""
from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import matplotlib.colors
import matplotlib.image as mpimg
import pytest


from torchrl_reset_recipes.analysis import figures, report
from torchrl_reset_recipes.analysis import runs as run_groups


def fabricate(root: Path, task, algo, seed, p_thresh, avg_return, manual, share, success, steps=1000):
    folder = root / task / algo / f"p{p_thresh}" / f"seed{seed}"
    folder.mkdir(parents=True)
    summary = {"task": task, "algo": algo, "seed": seed, "p_thresh": p_thresh, "steps": steps,
               "average_return": avg_return, "manual_resets": manual, "forward_share": share, "reset_success_rate": success}
    (folder / "summary.json").write_text(json.dumps(summary))
    tables = {
        "progress.csv": (["frames", "manual_resets"], [(f, manual * f // steps) for f in range(250, steps + 1, 250)]),
        "eval.csv": (["frames", "forward_return"], [(f, avg_return * f / steps) for f in range(500, steps + 1, 500)]),
        "triggers.csv": (["frames", "steps", "value", "observation"], [(f, 10, 0.01 * f, "0 0") for f in range(100, steps, 100)]),
    }
    for name, (header, rows) in tables.items():
        with open(folder / name, "w", newline="") as f:
            writer = csv.writer(f)
            writer.writerow(header)
            writer.writerows(rows)
    return folder


def test_table1_and_figures_from_fabricated_runs(tmp_path):
    runs = tmp_path / "runs"
    folder = fabricate(runs, "cliff_cheetah", "ours", 0, 0.05, 2.0, 10, 0.3, 0.9)
    with open(folder / "diagnostics.csv", "w", newline="") as f:
        csv.writer(f).writerows([["frames", "trigger_score_mean", "trigger_score_min", "example_p", "forward_p"],
                                 [500, 0.8, 0.5, 0.99, 0.6], [1000, 0.4, 0.05, 0.98, 0.3]])
    with open(folder / "resets.csv", "w", newline="") as f:
        csv.writer(f).writerows([["frames", "outcome", "steps", "distance_to_start", "distance_to_examples"],
                                 [300, "manual", 200, 2.0, 1.5], [900, "success", 20, 0.1, 0.0]])
    fabricate(runs, "cliff_cheetah", "ours", 1, 0.05, 4.0, 30, 0.5, 1.0)
    fabricate(runs, "cliff_cheetah", "ours", 0, 0.2, 1.0, 5, 0.1, 0.5)
    fabricate(runs, "cliff_cheetah", "lnt", 0, 0.05, 5.0, 100, 0.2, 0.8)
    written = report.report([runs], tmp_path / "out")
    table = (tmp_path / "out" / "table1.md").read_text()
    # seeds 0 and 1: returns 2 and 4 -> 3.00 ± 1.00; manual 10, 30 -> 20 ± 10; shares 0.3, 0.5 -> 40.0% ± 10.0;
    # success 0.9, 1.0 -> 95.0% ± 5.0 (population standard deviation); the paper's cliff-cheetah row beside
    assert ("| cliff-cheetah | ours | 0.05 | 2 | 1000 | 3.00 ± 1.00 (paper 1.96) | 20 ± 10 (paper 371) | "
            "40.0% ± 10.0 (paper 31.4%) | 95.0% ± 5.0 (paper 94.8%) |") in table
    assert "| cliff-cheetah | LNT | 0.05 | 1 | 1000 | 5.00 ± 0.00 (paper 4.77) |" in table
    assert "| cliff-cheetah | ours | 0.2 | 1 |" in table
    names = {kind: [p.name for p in paths] for kind, paths in written.items()}
    assert names["fig3"] == ["fig3_cliff_cheetah.png"]
    assert names["diagnostics"] == ["diagnostics_cliff_cheetah_ours.png"]  # only that run logged diagnostics
    assert names["fig4"] == ["fig4_cliff_cheetah_ours.png"]  # only ours has two p_thresh values
    assert sorted(names["fig5"]) == ["fig5_cliff_cheetah_lnt.png", "fig5_cliff_cheetah_ours.png"]
    for paths in written.values():
        for path in paths:
            if path.suffix == ".png":
                assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
                assert mpimg.imread(path).std() > 0.01  # something was drawn


def test_report_without_runs_and_with_a_foreign_summary(tmp_path):
    with pytest.raises(SystemExit, match="no summary.json"):
        report.report([tmp_path])
    (tmp_path / "x").mkdir()
    (tmp_path / "x" / "summary.json").write_text(json.dumps({"task": "t"}))
    with pytest.raises(ValueError, match="not written by train.py"):
        report.report([tmp_path])


def test_a_budget_compares_runs_as_they_stood_at_that_step(tmp_path):
    folder = tmp_path / "runs" / "peg_insertion_insert" / "ours" / "seed0"
    folder.mkdir(parents=True)
    summary = {"task": "peg_insertion_insert", "algo": "ours", "seed": 0, "p_thresh": 0.1, "steps": 4000,
               "average_return": 9.0, "manual_resets": 99, "forward_share": 0.9, "reset_success_rate": 0.9}
    (folder / "summary.json").write_text(json.dumps(summary))
    header = ["frames", "forward_steps", "reset_steps", "forward_episodes", "successful_resets", "manual_resets",
              "triggered_resets"]
    rows = [(1000, 300, 700, 3, 0, 3, 1), (2000, 800, 1200, 8, 2, 5, 2), (3000, 1500, 1500, 15, 6, 7, 9),
            (4000, 2400, 1600, 24, 14, 8, 9)]
    with open(folder / "progress.csv", "w", newline="") as f:
        csv.writer(f).writerows([header, *rows])
    with open(folder / "eval.csv", "w", newline="") as f:
        csv.writer(f).writerows([["frames", "forward_return"], [1000, 1.0], [2000, 2.0], [3000, 6.0], [4000, 30.0]])
    (folder / "config.yaml").write_text("task: {forward_horizon: 60}\n")
    report.report([tmp_path / "runs"], tmp_path / "out", budget=3000)
    table = (tmp_path / "out" / "table1.md").read_text()
    # at 3000 steps: return mean(1, 2, 6) = 3.00; manual 7; share 1500 / 3000 = 50.0%; success 6 / 13 = 46.2%
    assert "| peg-insertion (insert) | ours | 0.1 | 1 | 3000 | 3.00 ± 0.00 (paper 29.20) | 7 ± 0 (paper 343) | " \
           "50.0% ± 0.0 (paper 66.3%) | 46.2% ± 0.0 (paper 96.6%) |" in table
    # 15 forward episodes, 15 - 7 = 8 saved; last quarter of 3000 steps from the row at 2000 (the last at or
    # before 2250): (7 - 5) manual resets in 1000 steps = 2.00 per 1k
    # the release's baseline: (1500 forward steps + 9 triggered calls) // H_f = 60 gives 25, 25 - 7 = 18 saved
    assert "| peg-insertion (insert) | ours | 0.1 | 1 | 7 ± 0 | 15 ± 0 | 8 ± 0 | 25 ± 0 | 18 ± 0 | 2.00 ± 0.00 |" in table
    assert "at a budget of 3000 steps" in table


def test_a_run_still_going_is_read_from_its_config_and_logs(tmp_path):
    folder = tmp_path / "runs" / "cliff_cheetah" / "lnt" / "seed2"
    folder.mkdir(parents=True)
    (folder / "config.yaml").write_text("seed: 2\ntask: {name: cliff_cheetah, p_thresh: 0.05}\nalgo: {name: lnt}\n")
    with open(folder / "progress.csv", "w", newline="") as f:
        csv.writer(f).writerows([["frames", "forward_steps", "reset_steps", "forward_episodes", "successful_resets",
                                  "manual_resets"], [500, 100, 400, 2, 1, 3], [1000, 250, 750, 5, 3, 4]])
    run, = run_groups.find_runs([tmp_path / "runs"])
    # as it stands at 1000 steps: share 250 / 1000, success 3 / 7, no evaluation yet
    assert run.summary["steps"] == 1000 and run.summary["manual_resets"] == 4 and not run.summary["finished"]
    assert run.summary["forward_share"] == pytest.approx(0.25) and run.summary["reset_success_rate"] == pytest.approx(3 / 7)
    assert run.summary["episodic_resets"] == 5


def test_runs_short_of_the_budget_are_left_out_of_their_groups_means(tmp_path):
    runs = tmp_path / "runs"
    # two seeds of ours: seed 0 reached 1000 steps with 40 manual resets, seed 1 only 500 (10 so far)
    fabricate(runs, "peg_insertion_insert", "ours", 0, 0.1, 2.0, 40, 0.5, 0.5, steps=1000)
    fabricate(runs, "peg_insertion_insert", "ours", 1, 0.1, 1.0, 20, 0.5, 0.5, steps=1000)
    with open(runs / "peg_insertion_insert" / "ours" / "p0.1" / "seed1" / "progress.csv", "w", newline="") as f:
        csv.writer(f).writerows([["frames", "manual_resets"], [250, 5], [500, 10]])
    # LNT has no run at the budget: its row is kept, marked in progress
    fabricate(runs, "peg_insertion_insert", "lnt", 0, 0.1, 1.0, 8, 0.5, 0.5, steps=1000)
    with open(runs / "peg_insertion_insert" / "lnt" / "p0.1" / "seed0" / "progress.csv", "w", newline="") as f:
        csv.writer(f).writerows([["frames", "manual_resets"], [250, 3], [750, 6]])
    report.report([runs], tmp_path / "out", budget=1000)
    table = (tmp_path / "out" / "table1.md").read_text()
    assert "| peg-insertion (insert) | ours | 0.1 | 1 | 1000 |" in table  # seed 1 out of the mean: 40, not 25
    assert "| ours | 0.1 | 1 | 40 ± 0 |" in table
    assert "| peg-insertion (insert) | LNT | 0.1 | 1 | 750 (in progress) |" in table
    assert "Left out of the means, still short of the budget: ours seed 1 at 500 steps." in table
    # Fig. 3 draws the same runs: ours from seed 0 alone, LNT's only run marked in progress
    groups = figures.figure3_groups(run_groups.find_runs([runs], budget=1000))
    assert [r.summary["seed"] for r in groups["ours"][0]] == [0] and groups["ours"][1] == "ours"
    assert [r.summary["seed"] for r in groups["lnt"][0]] == [0] and groups["lnt"][1] == "LNT, in progress"


def test_step_axes_read_in_thousands_and_millions():
    assert [figures._steps_label(v) for v in (0, 500, 2000, 12500, 150000, 1.5e6)] == ["0", "500", "2k", "12.5k", "150k", "1.5M"]


def _config_yaml(*overrides: str, drop: str | None = None, task: str = "peg_insertion_insert") -> str:
    """A run's config.yaml as train.py writes it (the recipe config of ``task`` at the paper preset, resolved), with ``drop``
    removed as from a config written before that setting existed."""
    from omegaconf import OmegaConf, open_dict

    from torchrl_reset_recipes.training.hydra_config import compose

    cfg = compose([f"task={task}", "algo=ours", "preset=paper", *overrides])
    if drop is not None:
        section, key = drop.split(".")
        with open_dict(cfg):
            del cfg[section][key]
    return OmegaConf.to_yaml(cfg, resolve=True)


def test_runs_with_different_settings_are_kept_apart_and_named_by_what_they_changed(tmp_path):
    runs = tmp_path / "runs"
    task = "peg_insertion_insert"
    # seeds 0 and 1 at the paper's setting; seed 1 ran with other bookkeeping (threads, length, folder,
    # speed paths, logging, the keys of run batching that older code wrote) and from a config written before
    # algo.initial_logit_bias existed: still one setting
    a = fabricate(runs, task, "ours", 0, 0.1, 2.0, 10, 0.3, 0.9)
    (a / "config.yaml").write_text(_config_yaml("seed=0", "threads=1"))
    b = fabricate(runs, task, "ours", 1, 0.1, 4.0, 30, 0.5, 1.0)
    (b / "config.yaml").write_text(_config_yaml(
        "seed=1", "threads=2", "total_steps=5000", "sweep_dir=elsewhere", "resume=auto", "+seeds=null", "+arms=null",
        "+vary=null", "+vary_values=null", "+speed.batched_acting=true",
        "checkpoint_every=777", "log_every=10", drop="algo.initial_logit_bias"))
    # two options, one seed each: a pessimistic start, and a smaller prior scale with it
    c = fabricate(runs, task, "ours", 2, 0.1, 1.0, 50, 0.1, 0.2)
    (c / "config.yaml").write_text(_config_yaml("seed=2", "algo.initial_logit_bias=-4"))
    d = fabricate(runs, task, "ours", 3, 0.1, 3.0, 70, 0.2, 0.4)
    (d / "config.yaml").write_text(_config_yaml("seed=3", "algo.initial_logit_bias=-4", "algo.prior_scale=1.0"))
    written = report.report([runs], tmp_path / "out")
    table = (tmp_path / "out" / "table1.md").read_text()
    # seeds 0 and 1 averaged (returns 2, 4 -> 3.00 ± 1.00; manual 10, 30 -> 20 ± 10), the paper's numbers beside
    assert ("| peg-insertion (insert) | ours (paper's setting) | 0.1 | 2 | 1000 | 3.00 ± 1.00 (paper 29.20) | "
            "20 ± 10 (paper 343) |") in table
    # each option alone, named by what it changed from the recipe's defaults, no paper numbers beside it
    assert ("| peg-insertion (insert) | ours (algo.initial_logit_bias=-4) | 0.1 | 1 | 1000 | 1.00 ± 0.00 | "
            "50 ± 0 | 10.0% ± 0.0 | 20.0% ± 0.0 |") in table
    assert ("| peg-insertion (insert) | ours (algo.initial_logit_bias=-4, algo.prior_scale=1.0) | 0.1 | 1 | 1000 | "
            "3.00 ± 0.00 | 70 ± 0 |") in table
    assert table.index("ours (paper's setting)") < table.index("ours (algo.initial_logit_bias=-4)")
    groups = figures.figure3_groups(run_groups.find_runs([runs]))
    assert {key: sorted(r.summary["seed"] for r in members) for key, (members, _) in groups.items()} == {
        "ours (paper's setting)": [0, 1], "ours (algo.initial_logit_bias=-4)": [2],
        "ours (algo.initial_logit_bias=-4, algo.prior_scale=1.0)": [3]}
    assert sorted(p.name for p in written["fig5"]) == [
        "fig5_peg_insertion_insert_ours.png", "fig5_peg_insertion_insert_ours_algo.initial_logit_bias-4.png",
        "fig5_peg_insertion_insert_ours_algo.initial_logit_bias-4_algo.prior_scale1.0.png"]
    # without the options the same two runs are one group and the table reads as before
    for folder in (c, d):
        for path in folder.iterdir():
            path.unlink()
        folder.rmdir()
    report.report([runs], tmp_path / "alone")
    assert "| peg-insertion (insert) | ours | 0.1 | 2 | 1000 | 3.00 ± 1.00 (paper 29.20) |" in (
        tmp_path / "alone" / "table1.md").read_text()


def test_a_key_an_older_config_lacks_means_what_its_absence_meant_and_a_named_folder_is_one_setting(tmp_path):
    task = "peg_insertion_insert"
    # today's config, and one written before algo.prior_bias_draw existed: that run drew its priors' biases
    # U(+-1/sqrt(fan_in)) (the key arrived with that fallback), so it is not today's preset (xavier)
    new = fabricate(tmp_path / "new", task, "ours", 0, 0.1, 2.0, 10, 0.3, 0.9)
    (new / "config.yaml").write_text(_config_yaml("seed=0"))
    old = fabricate(tmp_path / "old", task, "ours", 0, 0.1, 4.0, 30, 0.5, 1.0)
    (old / "config.yaml").write_text(_config_yaml("seed=0", drop="algo.prior_bias_draw"))
    option = fabricate(tmp_path / "old", task, "ours", 1, 0.1, 1.0, 50, 0.1, 0.2)
    (option / "config.yaml").write_text(_config_yaml("seed=1", "algo.initial_logit_bias=-4", drop="algo.prior_bias_draw"))
    settings = {r.folder: r.setting for r in run_groups.find_runs([tmp_path / "new", tmp_path / "old"])}
    assert settings == {new: run_groups.PAPER_SETTING, old: "algo.prior_bias_draw=fan_in",
                        option: "algo.initial_logit_bias=-4, algo.prior_bias_draw=fan_in"}
    # the older runs alone: what both changed alike still keeps them from being the paper's setting
    settings = {r.folder: r.setting for r in run_groups.find_runs([tmp_path / "old"])}
    assert settings == {old: "algo.prior_bias_draw=fan_in", option: "algo.initial_logit_bias=-4, algo.prior_bias_draw=fan_in"}
    # a key of another algorithm is not read into LNT's settings (LNT has no priors): only its own absent keys
    lnt_new = fabricate(tmp_path / "lnt", task, "lnt", 0, 0.1, 2.0, 10, 0.3, 0.9)
    (lnt_new / "config.yaml").write_text(_config_yaml("seed=0", "algo=lnt"))
    lnt_old = fabricate(tmp_path / "lnt", task, "lnt", 1, 0.1, 2.0, 10, 0.3, 0.9)
    (lnt_old / "config.yaml").write_text(_config_yaml("seed=1", "algo=lnt", drop="forward.sampling"))
    settings = {r.folder: r.setting for r in run_groups.find_runs([tmp_path / "lnt"])}
    assert settings == {lnt_new: run_groups.PAPER_SETTING, lnt_old: "forward.sampling=transition"}
    # NAME=PATH: the runs under PATH are the setting NAME, told apart inside it by what differs between them
    report.main([f"release={tmp_path / 'new'}", f"before={tmp_path / 'old'}", "--out", str(tmp_path / "out")])
    table = (tmp_path / "out" / "table1.md").read_text()
    assert "| peg-insertion (insert) | ours (release) | 0.1 | 1 | 1000 | 2.00 ± 0.00 | 10 ± 0 |" in table
    assert "| peg-insertion (insert) | ours (before) | 0.1 | 1 | 1000 | 4.00 ± 0.00 | 30 ± 0 |" in table
    assert ("| peg-insertion (insert) | ours (before, algo.initial_logit_bias=-4) | 0.1 | 1 | 1000 | 1.00 ± 0.00 | "
            "50 ± 0 |") in table
    assert "- release, peg-insertion (insert), ours: the paper preset's settings" in table
    assert ("- before, peg-insertion (insert), ours: algo.initial_logit_bias=-4, algo.prior_bias_draw=fan_in"
            in table)
    with pytest.raises(SystemExit):
        report.main([f"release={tmp_path / 'nowhere'}"])


def write_run(root: Path, algo: str, seed: int, task: str = "peg_insertion_insert", steps: int = 4000,
              config: str | None = None, **tables) -> Path:
    """A run folder with a summary and the given tables (``progress=(header, rows)``, ...), named by file."""
    folder = root / task / algo / f"seed{seed}"
    folder.mkdir(parents=True)
    summary = {"task": task, "algo": algo, "seed": seed, "p_thresh": 0.1, "steps": steps, "average_return": 1.0,
               "manual_resets": 1, "forward_share": 0.5, "reset_success_rate": 0.5}
    (folder / "summary.json").write_text(json.dumps(summary))
    if config is not None:
        (folder / "config.yaml").write_text(config)
    for name, (header, rows) in tables.items():
        with open(folder / f"{name}.csv", "w", newline="") as f:
            csv.writer(f).writerows([header, *rows])
    return folder


def _progress(manual, episodes):
    return ["frames", "manual_resets", "forward_episodes"], [(1000 * (i + 1), m, e) for i, (m, e) in
                                                             enumerate(zip(manual, episodes))]


def _lines(ax) -> dict:
    return {line.get_label(): line for line in ax.get_lines()}


def _texts(ax) -> list[str]:
    return [t.get_text() for t in ax.texts]


def _looks(ax) -> list[tuple]:
    return [(matplotlib.colors.to_hex(line.get_color()), str(line.get_linestyle()), str(line.get_marker()),
             line.get_linewidth()) for line in ax.get_lines()]


def test_fig3_draws_each_groups_episodic_resets_beside_its_manual_resets_in_its_colour(tmp_path):
    runs = tmp_path / "runs"
    write_run(runs, "ours", 0, progress=_progress([2, 4, 6, 8], [3, 6, 9, 12]))
    write_run(runs, "ours", 1, progress=_progress([4, 6, 8, 10], [5, 8, 11, 14]))
    write_run(runs, "lnt", 0, progress=_progress([1, 2, 3, 4], [2, 3, 5, 6]))
    fig = figures.draw_figure3("peg_insertion_insert", run_groups.find_runs([runs]))
    lines = _lines(fig.axes[1])
    # the mean of the two seeds' forward episodes: (3+5)/2, (6+8)/2, (9+11)/2, (12+14)/2
    assert list(lines["ours: episodic (n=2)"].get_ydata()) == [4, 7, 10, 13]
    assert list(lines["LNT: episodic (n=1)"].get_ydata()) == [2, 3, 5, 6]
    for algo, n in (("ours", 2), ("LNT", 1)):
        manual, episodic = lines[f"{algo} (n={n})"], lines[f"{algo}: episodic (n={n})"]
        assert manual.get_color() == episodic.get_color()
        assert manual.get_linestyle() == "-" and episodic.get_linestyle() == "--"
    looks = _looks(fig.axes[1])
    assert len(set(looks)) == len(looks) == 4
    legend = fig.axes[1].get_legend()
    assert {t.get_text() for t in legend.get_texts()} == set(lines)
    assert min(t.get_fontsize() for t in legend.get_texts()) >= 8
    figures.plt.close(fig)


def test_fig3_of_a_cliff_task_counts_the_falls_into_the_ditch_per_phase(tmp_path):
    """Runs that log the entries into the ditch get a third panel: per algorithm, the mean over seeds of the
    cumulative entries in forward steps (solid) and in reset steps (dotted, the same colour)."""
    runs = tmp_path / "runs"
    header = ["frames", "manual_resets", "forward_episodes", "irrecoverable_forward", "irrecoverable_reset"]
    write_run(runs, "ours", 0, task="cliff_cheetah", progress=(header, [(1000, 1, 2, 0, 0), (2000, 3, 4, 2, 1)]))
    write_run(runs, "ours", 1, task="cliff_cheetah", progress=(header, [(1000, 2, 3, 1, 0), (2000, 4, 6, 4, 3)]))
    write_run(runs, "lnt_sparse", 0, task="cliff_cheetah", progress=(header, [(1000, 1, 1, 1, 1), (2000, 5, 5, 5, 1)]))
    fig = figures.draw_figure3("cliff_cheetah", run_groups.find_runs([runs]))
    assert len(fig.axes) == 3
    lines = _lines(fig.axes[2])
    # ours: forward (0+1)/2, (2+4)/2; reset (0+0)/2, (1+3)/2
    assert list(lines["ours: forward (n=2)"].get_ydata()) == [0.5, 3.0]
    assert list(lines["ours: reset (n=2)"].get_ydata()) == [0.0, 2.0]
    assert list(lines["LNT-sparse: forward (n=1)"].get_ydata()) == [1, 5]
    assert lines["ours: forward (n=2)"].get_color() == lines["ours: reset (n=2)"].get_color()
    assert lines["ours: reset (n=2)"].get_linestyle() == ":" and lines["ours: forward (n=2)"].get_linestyle() == "-"
    assert "ditch" in fig.axes[2].get_title() and fig.axes[2].get_ylim()[0] == 0 and not _texts(fig.axes[2])
    figures.plt.close(fig)
    # no fall yet in any run: said on the panel
    write_run(tmp_path / "calm", "ours", 0, task="cliff_cheetah", progress=(header, [(1000, 1, 2, 0, 0), (2000, 3, 4, 0, 0)]))
    fig = figures.draw_figure3("cliff_cheetah", run_groups.find_runs([tmp_path / "calm"]))
    assert _texts(fig.axes[2]) == ["no entry into the ditch so far"]
    figures.plt.close(fig)
    # two settings: the reset line is thin in its group's style with hollow markers, unlike any forward line
    write_run(runs, "ours", 2, task="cliff_cheetah", config=_config_yaml("algo.prior_scale=2", task="cliff_cheetah"),
              progress=(header, [(1000, 1, 2, 0, 0), (2000, 3, 4, 1, 1)]))
    write_run(runs, "ours", 3, task="cliff_cheetah", config=_config_yaml("algo.prior_scale=1", task="cliff_cheetah"),
              progress=(header, [(1000, 1, 2, 0, 0), (2000, 3, 4, 1, 1)]))
    fig = figures.draw_figure3("cliff_cheetah", run_groups.find_runs([runs / "cliff_cheetah"]))
    looks = _looks(fig.axes[2])
    assert len(set(looks)) == len(looks)
    resets = [line for label, line in _lines(fig.axes[2]).items() if ": reset" in label]
    assert resets and all(line.get_marker() == "o" and line.get_markerfacecolor() == "none" for line in resets)
    figures.plt.close(fig)
    # a task without irrecoverable states logs the columns too (zeros): the two panels only; older logs alike
    write_run(runs, "ours", 0, progress=(header, [(1000, 1, 2, 0, 0), (2000, 3, 4, 0, 0)]))
    write_run(runs, "ours", 1, progress=_progress([1, 2], [1, 2]))
    fig = figures.draw_figure3("peg_insertion_insert", run_groups.find_runs([runs / "peg_insertion_insert"]))
    assert len(fig.axes) == 2
    figures.plt.close(fig)


def test_fig3_companion_lines_stay_apart_from_other_settings_and_say_when_they_leave_the_panel(tmp_path):
    runs = tmp_path / "runs"
    write_run(runs, "ours", 0, progress=_progress([2, 4, 6, 8], [3, 6, 9, 12]))
    write_run(runs, "ours", 1, progress=_progress([4, 6, 8, 10], [5, 8, 11, 14]))
    write_run(runs, "lnt", 0, progress=_progress([1, 2, 3, 4], [50, 100, 150, 200]))
    found = run_groups.find_runs([runs])
    # two settings of ours, named as assign_settings names them
    ours = {r.summary["seed"]: r for r in found if r.algo == "ours"}
    ours[0].setting, ours[1].setting = run_groups.PAPER_SETTING, "algo.initial_logit_bias=-4"
    fig = figures.draw_figure3("peg_insertion_insert", found)
    ax = fig.axes[1]
    looks = _looks(ax)
    assert len(set(looks)) == len(looks) == 6  # ours twice and LNT, each manual and episodic
    # LNT's 200 episodic resets pass twice the most manual resets (10): the panel stops at 1.08 times the
    # highest line left in it (ours' option: 14 episodic resets) and the legend names the count
    assert ax.get_ylim()[1] == pytest.approx(1.08 * 14)
    assert "LNT: episodic (n=1)\noff the scale: 200 at 4k steps" in _lines(ax)
    figures.plt.close(fig)


def test_fig3_says_why_a_forward_return_panel_is_empty_or_flat(tmp_path):
    runs = tmp_path / "runs"
    config = "seed: 0\neval_every: 10000\ntask: {name: peg_insertion_insert, p_thresh: 0.1}\nalgo: {name: ours}\n"
    write_run(runs, "ours", 0, config=config, progress=_progress([1, 2, 3, 4], [1, 2, 3, 4]))
    fig = figures.draw_figure3("peg_insertion_insert", run_groups.find_runs([runs]))
    assert _texts(fig.axes[0]) == ["no evaluation yet (every 10,000 steps)"]
    figures.plt.close(fig)
    write_run(runs, "lnt", 0, progress=_progress([1, 2, 3, 4], [1, 2, 3, 4]),
              eval=(["frames", "forward_return"], [(2000, 0.0), (4000, 0.0)]))
    write_run(runs, "lnt_sparse", 0, progress=_progress([1, 2, 3, 4], [1, 2, 3, 4]),
              eval=(["frames", "forward_return"], [(2000, 0.0), (4000, 0.5)]))
    fig = figures.draw_figure3("peg_insertion_insert", run_groups.find_runs([runs]))
    assert _texts(fig.axes[0]) == ["LNT: forward return 0 at every evaluation so far\n"
                                   "ours: no evaluation yet (every 10,000 steps)"]
    figures.plt.close(fig)


def test_success_rate_per_stretch_counts_the_resets_that_ended_in_the_centred_window():
    frames = [1000, 2000, 3000, 4000, 5000, 6000, 7000]
    successful = [0, 1, 1, 3, 3, 3, 3]
    manual = [1, 1, 2, 2, 4, 4, 4]
    rate = figures.success_rate_per_stretch(frames, successful, manual, 2000)
    # at 1000: (0, 2000] holds 1 success and 1 manual reset; at 2000: (1000, 3000] 1 and 1; at 3000:
    # (2000, 4000] 2 and 1; at 4000: (3000, 5000] 2 and 2; at 5000: (4000, 6000] 0 and 2; at 6000 and 7000
    # nothing ended
    assert rate[:5] == pytest.approx([1 / 2, 1 / 2, 2 / 3, 2 / 4, 0.0])
    assert math.isnan(rate[5]) and math.isnan(rate[6])


def _diagnostics(seed_shift: float, lnt: bool = False):
    header = ["frames", "trigger_score_mean", "trigger_score_min", "example_p", "reset_replay_p", "forward_p",
              "forward_p_min_member"]
    return header, [(1000 * k, 0.5 + seed_shift, 0.2, 0.9, 0.6, 0.4, 0.4 if lnt else 0.3) for k in range(1, 41)]


def _resets():
    return (["frames", "outcome", "steps", "distance_to_start", "distance_to_examples"],
            [(500, "manual", 200, 3.0, 2.0), (1500, "success", 40, 0.5, 0.1), (2500, "success", 30, 0.4, 0.1)])


def _long_progress():
    rows = [(1000 * k, k // 2, k - k // 2) for k in range(1, 41)]  # successes and manual resets alternate
    return ["frames", "successful_resets", "manual_resets"], rows


def test_diagnostics_series_are_told_apart_and_say_what_they_plot(tmp_path, monkeypatch):
    runs = tmp_path / "runs"
    for seed in range(3):
        write_run(runs, "ours", seed, steps=40000, diagnostics=_diagnostics(0.1 * seed), resets=_resets(),
                  progress=_long_progress())
    members = run_groups.find_runs([runs])
    fig = figures.draw_diagnostics("peg_insertion_insert", "ours", "", members)
    score, probes, success, distance = fig.axes
    for ax in fig.axes:
        looks = _looks(ax)
        assert len(set(looks)) == len(looks)  # no two series of a panel drawn alike
    assert len(probes.get_lines()) == 3 * 4 + 1  # three seeds' four probes and p_thresh
    assert "seed 2: forward replay, lowest member" in _lines(probes)
    legends = [ax.get_legend() for ax in (score, probes, distance)] + fig.legends
    assert min(t.get_fontsize() for legend in legends for t in legend.get_texts()) >= 8
    assert "p_thresh = 0.1" in [t.get_text() for t in probes.get_legend().get_texts()]
    assert score.get_ylabel().startswith("p:") and probes.get_ylabel().startswith("p:")
    # a twentieth of 40k steps: windows of 2,000 steps; at 10,000 steps, (9000, 11000] holds one success
    # (4 at 9k, 5 at 11k) and one manual reset (5 at 9k, 6 at 11k)
    assert success.get_title() == "reset success rate per 2,000 steps"
    assert _lines(success)["seed 0"].get_ydata()[9] == pytest.approx(1 / 2)
    # the distance panel marks each reset episode's outcome; peg-insertion's check is on the peg, not on
    # this distance, so no line is drawn and the panel says so
    markers = {label: line.get_marker() for label, line in _lines(distance).items()}
    assert markers["seed 0: success"] == "o" and markers["seed 0: manual"] == "x"
    assert list(_lines(distance)["seed 1: success"].get_ydata()) == [0.5, 0.4]
    assert any("not a bound on this distance" in " ".join(text.split()) for text in _texts(distance))
    assert not any(label.startswith("reset success") for label in _lines(distance))
    figures.plt.close(fig)
    # a task whose check is a bound on this distance gets its line instead
    monkeypatch.setitem(figures.RESET_SUCCESS, "peg_insertion_insert", ("within 0.5 of the start", 0.5))
    fig = figures.draw_diagnostics("peg_insertion_insert", "ours", "", members)
    line = _lines(fig.axes[3])["reset success below 0.5"]
    assert list(line.get_ydata()) == [0.5, 0.5] and not _texts(fig.axes[3])
    figures.plt.close(fig)


def test_an_async_learners_lag_and_weight_age_get_a_panel_of_their_own(tmp_path):
    runs = tmp_path / "runs"
    header = ["frames", "successful_resets", "manual_resets", "learner_lag_mean", "learner_lag_max", "weight_age_mean"]
    for seed, lag in ((0, 0.0), (1, 12.5)):  # one run in lockstep (never behind), one lagging
        write_run(runs, "ours", seed, steps=4000, diagnostics=_diagnostics(0.0), resets=_resets(),
                  progress=(header, [(1000 * k, k // 2, k - k // 2, lag * k, 3 * lag * k, lag * k + 1)
                                     for k in range(1, 5)]))
    fig = figures.draw_diagnostics("peg_insertion_insert", "ours", "", run_groups.find_runs([runs]))
    assert len(fig.axes) == 5  # the four panels, then the learner's (these runs logged no saturation)
    lag = fig.axes[4]
    assert "lag" in lag.get_title() and list(_lines(lag)["seed 1: learner_lag_mean"].get_ydata()) == [12.5, 25, 37.5, 50]
    assert list(_lines(lag)["seed 1: weight_age_mean"].get_ydata()) == [13.5, 26, 38.5, 51]
    figures.plt.close(fig)
    still = tmp_path / "still"
    for seed in (0, 1):  # runs that never lagged (sync, lockstep): no such panel
        write_run(still, "ours", seed, steps=4000, diagnostics=_diagnostics(0.0), resets=_resets(),
                  progress=(header, [(1000 * k, k // 2, k - k // 2, 0, 0, 0) for k in range(1, 5)]))
    fig = figures.draw_diagnostics("peg_insertion_insert", "ours", "", run_groups.find_runs([still]))
    assert len(fig.axes) == 4
    figures.plt.close(fig)


def test_lnt_diagnostics_say_q_and_q_thresh_where_they_plot_q(tmp_path):
    runs = tmp_path / "runs"
    for seed in range(2):
        write_run(runs, "lnt", seed, steps=40000, diagnostics=_diagnostics(10.0 * seed, lnt=True),
                  resets=_resets(), progress=_long_progress(),
                  config=f"seed: {seed}\ntask: {{name: peg_insertion_insert, p_thresh: 0.1}}\n"
                         "algo: {name: lnt, threshold: 20.0}\n")
    fig = figures.draw_diagnostics("peg_insertion_insert", "lnt", "", run_groups.find_runs([runs]))
    score, probes = fig.axes[:2]
    assert score.get_ylabel() == probes.get_ylabel() == "Q: reset Q-ensemble's minimum"
    assert "(Q)" in score.get_title() and "(Q)" in probes.get_title()
    # LNT's trigger takes the members' minimum: the lowest member is the forward-replay line, drawn once
    assert len(probes.get_lines()) == 2 * 3 + 1
    legend_texts = [t.get_text() for ax in (score, probes) for t in ax.get_legend().get_texts()]
    assert "Q_thresh = 20" in legend_texts
    labels = legend_texts + [line.get_label() for ax in (score, probes) for line in ax.get_lines()]
    assert not any("p_thresh" in text or text.endswith(" p") for text in labels)
    assert _lines(score)["Q_thresh = 20"].get_ydata()[0] == 20.0
    figures.plt.close(fig)


def test_fig5_is_drawn_for_runs_without_triggers_and_says_so(tmp_path):
    runs = tmp_path / "runs"
    write_run(runs, "ours", 0, progress=_progress([1, 2, 3, 4], [1, 2, 3, 4]))
    written = report.report([runs], tmp_path / "out")
    assert [p.name for p in written["fig5"]] == ["fig5_peg_insertion_insert_ours.png"]
    fig = figures.draw_figure5("peg_insertion_insert", "ours", "", run_groups.find_runs([runs]))
    assert _texts(fig.axes[0]) == ["no triggered reset in this run (4,000 steps)"]
    figures.plt.close(fig)
    write_run(runs, "ours", 1, progress=_progress([1, 2, 3, 4], [1, 2, 3, 4]),
              triggers=(["frames", "steps", "value", "observation"], [(1500, 10, 0.3, "0.3 0")]))
    fig = figures.draw_figure5("peg_insertion_insert", "ours", "", run_groups.find_runs([runs]))
    assert _texts(fig.axes[0]) == ["no triggered reset in seed 0"]
    assert [t.get_text() for t in fig.axes[0].get_legend().get_texts()] == ["seed 1"]
    figures.plt.close(fig)


def test_fig5_of_a_cliff_task_draws_the_edge_and_marks_the_triggers_that_came_too_late(tmp_path):
    """Cliff-cheetah's Fig. 5 plots the x position before each trigger: the edge (x = 14, the task's
    definition) is drawn, and a trigger in a state already irrecoverable is a cross, counted in the legend."""
    runs = tmp_path / "runs"
    config = "task:\n  name: cliff_cheetah\n  curriculum:\n    index: 0\n    label: x position (m)\n"
    write_run(runs, "ours", 0, task="cliff_cheetah", config=config, progress=_progress([1, 2, 3, 4], [1, 2, 3, 4]),
              triggers=(["frames", "steps", "value", "irrecoverable", "observation"],
                        [(1000, 40, 3.0, 0, "3 0"), (2000, 90, 13.5, 0, "13.5 0"), (3000, 120, 14.6, 1, "14.6 -1.5")]))
    fig = figures.draw_figure5("cliff_cheetah", "ours", "", run_groups.find_runs([runs]))
    ax = fig.axes[0]
    assert _lines(ax)["cliff edge (x = 14)"].get_ydata()[0] == 14.0
    dots, crosses = ax.collections
    assert dots.get_offsets().tolist() == [[1000.0, 3.0], [2000.0, 13.5]]
    assert crosses.get_offsets().tolist() == [[3000.0, 14.6]]
    assert [t.get_text() for t in ax.get_legend().get_texts()] == [
        "seed 0", "seed 0: already irrecoverable (1)", "cliff edge (x = 14)"]
    figures.plt.close(fig)
    # an older triggers.csv without the column, and a task without a cliff: no crosses, no edge
    write_run(runs, "ours", 1, progress=_progress([1, 2], [1, 2]),
              triggers=(["frames", "steps", "value", "observation"], [(1500, 10, 0.3, "0.3 0")]))
    fig = figures.draw_figure5("peg_insertion_insert", "ours", "", run_groups.find_runs([runs / "peg_insertion_insert"]))
    assert len(fig.axes[0].collections) == 1 and "cliff edge (x = 14)" not in _lines(fig.axes[0])
    figures.plt.close(fig)


def test_three_or_more_seeds_get_the_means_bootstrap_interval(tmp_path):
    runs = tmp_path / "runs"
    for seed, manual in enumerate((10, 20, 30, 40)):
        fabricate(runs, "cliff_cheetah", "lnt", seed, 0.05, 1.0, manual, 0.3, 0.9)
    table = report.table1(run_groups.find_runs([runs]))
    # manual 10, 20, 30, 40: mean 25, population std 11.18; a bootstrap mean of these lies within [10, 40]
    cell = next(line for line in table.splitlines() if line.startswith("| cliff-cheetah | LNT |")).split(" | ")[6]
    assert cell.startswith("25 ± 11 [") and cell.endswith("] (paper 835)")
    low, high = (float(v) for v in cell[cell.index("[") + 1:cell.index("]")].split(", "))
    assert 10 <= low < 25 < high <= 40


def test_the_diagnostics_figure_plots_each_runs_saturation_when_logged(tmp_path):
    runs = tmp_path / "runs"
    progress = (["frames", "successful_resets", "manual_resets", "reset_saturation", "forward_saturation"],
                [(1000, 0, 1, 0.25, 0.0), (2000, 1, 1, 0.5, 0.1)])
    write_run(runs, "ours", 0, steps=2000, diagnostics=_diagnostics(0.0), resets=_resets(), progress=progress)
    fig = figures.draw_diagnostics("peg_insertion_insert", "ours", "", run_groups.find_runs([runs]))
    assert len(fig.axes) == 5
    lines = _lines(fig.axes[4])
    assert list(lines["seed 0: reset"].get_ydata()) == [25.0, 50.0]  # in percent
    assert list(lines["seed 0: forward"].get_ydata()) == [0.0, 10.0]
    figures.plt.close(fig)


def test_the_wilson_interval_by_hand():
    """Worked from the formula: none of n gives [0, z^2 / (n + z^2)]; all of n the mirror image; half of 100 at
    z = 1.96: centre 0.5, half-width 1.96 * sqrt(0.25 / 100 + 1.96^2 / 40000) / (1 + 1.96^2 / 100)."""
    from torchrl_reset_recipes.analysis.runs import wilson_interval

    z2 = 1.96 ** 2
    assert wilson_interval(0, 24) == pytest.approx((0.0, z2 / (24 + z2)))  # 0.138: peg removal's 0 of 24
    assert wilson_interval(24, 24) == pytest.approx((24 / (24 + z2), 1.0))
    half = 1.96 * math.sqrt(0.25 / 100 + z2 / 40000) / (1 + z2 / 100)
    assert wilson_interval(50, 100) == pytest.approx((0.5 - half, 0.5 + half))
    assert all(math.isnan(v) for v in wilson_interval(0, 0))
