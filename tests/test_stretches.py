"""recipes/analysis/stretches.py: a run stretch by stretch, on run folders written by hand."""
from __future__ import annotations

import csv
from pathlib import Path

import pytest


from torchrl_reset_recipes.analysis import stretches

PROGRESS = ["frames", "forward_steps", "reset_steps", "forward_episodes", "irrecoverable_forward", "irrecoverable_reset"]


def write(path: Path, fields: list[str], rows: list[list]) -> None:
    with open(path, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(fields)
        writer.writerows(rows)


def cliff_run(root: Path, task: str = "cliff_cheetah") -> Path:
    root.mkdir()
    (root / "config.yaml").write_text(f"task:\n  name: {task}\n")
    # logged every 500 steps; the counters are cumulative
    write(root / "progress.csv", PROGRESS, [
        [500, 400, 100, 2, 1, 0], [1000, 700, 300, 3, 2, 0],
        [1500, 1100, 400, 5, 2, 1], [2000, 1600, 400, 7, 4, 1],
    ])
    # the x position before each trigger, and whether it was already over the edge (lost)
    write(root / "triggers.csv", ["frames", "steps", "value", "irrecoverable", "observation"], [
        [120, 40, 1.0, 0, ""], [600, 80, 3.0, 0, ""], [900, 90, 5.0, 1, ""], [1900, 200, 4.0, 0, ""],
    ])
    write(root / "resets.csv", ["frames", "outcome", "steps", "distance_to_start", "distance_to_examples"], [
        [300, "success", 50, 0.1, 0.1], [1000, "manual", 200, 3.0, 3.0], [1200, "success", 20, 0.1, 0.1],
        [1800, "manual", 200, 3.0, 3.0],
    ])
    return root


def test_stretches_count_what_happened_between_their_bounds(tmp_path):
    table = stretches.stretches(cliff_run(tmp_path / "run"), window=1000)
    # 0-1k: triggers at 120, 600, 900 (900 too late); x positions 1, 3, 5 -> median 3; progress 0 -> the 1000
    # row: 3 forward episodes, 700 forward steps of 1000; resets ending at 300 (success) and 1000 (manual);
    # 2 entries into the ditch in forward steps, none in reset steps
    assert table[0] == {"steps": "0-1k", "triggers": 3, "too late": 1, "trigger position (median)": "3",
                        "forward episodes": 3, "forward share": "0.700", "reset episodes": 2, "successful": 1,
                        "manual": 1, "success rate": "50%", "lost in forward": 2, "lost in reset": 0}
    # 1k-2k: one trigger (x = 4); rows 1000 -> 2000: 4 episodes, 900 forward steps; resets at 1200 and 1800
    assert table[1] == {"steps": "1k-2k", "triggers": 1, "too late": 0, "trigger position (median)": "4",
                        "forward episodes": 4, "forward share": "0.900", "reset episodes": 2, "successful": 1,
                        "manual": 1, "success rate": "50%", "lost in forward": 2, "lost in reset": 1}
    assert len(table) == 2
    # --upto cuts; a stretch past the last logged row is not reported
    assert [r["steps"] for r in stretches.stretches(tmp_path / "run", window=500, upto=1000)] == ["0-500", "500-1k"]
    assert len(stretches.stretches(tmp_path / "run", window=3000)) == 0


def test_a_task_without_irrecoverable_states_has_no_cliff_columns_and_bad_input_is_refused(tmp_path, capsys):
    run = cliff_run(tmp_path / "peg", task="peg_insertion_insert")
    table = stretches.stretches(run, window=1000)
    assert list(table[0]) == ["steps", "triggers", "forward episodes", "forward share", "reset episodes",
                              "successful", "manual", "success rate"]
    with pytest.raises(ValueError, match="window"):
        stretches.stretches(run, window=0)
    with pytest.raises(SystemExit):
        stretches.main([str(tmp_path / "nothing-here")])
    assert "no progress.csv" in capsys.readouterr().err
    stretches.main([str(run), "--window", "1000"])
    assert "| 0-1k | 3 | 3 | 0.700 | 2 | 1 | 1 | 50% |" in capsys.readouterr().out


def test_each_trigger_finds_the_reset_episode_that_began_where_it_fired(tmp_path):
    run = cliff_run(tmp_path / "run")
    after = stretches.resets_by_start(run)
    # a reset episode ending at frame 1000 after 200 steps began at 800; the one ending at 300 after 50, at 250
    assert sorted(after) == [250, 800, 1180, 1600]
    assert (after[800]["outcome"], after[1180]["outcome"]) == ("manual", "success")
    # none of this hand-made run's triggers (at 120, 600, 900, 1900) began one: no pairing by nearness
    assert [after.get(t) for t in (120, 600, 900, 1900)] == [None] * 4
    assert stretches.keyed_by_start(stretches.csv_rows(run / "resets.csv")) == after  # the rows already read
    # two episodes beginning at one step come from an arms run (frames counts every arm's steps): refused
    with pytest.raises(ValueError, match="two reset episodes began at step 140"):
        stretches.keyed_by_start([{"frames": "180", "steps": "40"}, {"frames": "180", "steps": "40"}])
    arms = cliff_run(tmp_path / "arms")
    (arms / "config.yaml").write_text("task:\n  name: cliff_cheetah\narms: 3\n")
    with pytest.raises(ValueError, match="3 arms"):
        stretches.resets_by_start(arms)
    assert stretches.resets_by_start(tmp_path / "empty") == {} and stretches.csv_rows(tmp_path / "none.csv") == []


def test_a_trigger_on_the_runs_first_action_falls_in_the_first_stretch(tmp_path):
    # an event is logged at the step count after it: a trigger on the first forward action is logged at 0
    assert stretches.within(0, 0, 1000) and stretches.within(1000, 0, 1000)
    assert not stretches.within(1000, 1000, 2000) and not stretches.within(0, 1000, 2000)
    run = cliff_run(tmp_path / "run")
    write(run / "triggers.csv", ["frames", "steps", "value", "irrecoverable", "observation"], [
        [0, 0, 2.0, 0, ""], [120, 40, 1.0, 0, ""], [600, 80, 3.0, 0, ""], [900, 90, 5.0, 1, ""], [1900, 200, 4.0, 0, ""],
    ])
    first, second = stretches.stretches(run, window=1000)
    # x positions 2, 1, 3, 5 -> median 2.5; the second stretch as before
    assert (first["triggers"], first["trigger position (median)"], second["triggers"]) == (4, "2.5", 1)


def test_a_run_that_logged_the_check_says_how_many_triggers_fired_at_the_start(tmp_path):
    """triggers.csv's at_initial_state (written since the column existed): 0-1k holds the triggers at 120 (at the
    start), 600 (not) and 900 (at the start): 2; 1k-2k the one at 1900 (not): 0. A run logged before the column
    existed (the other tests' folders) has no such column in its table."""
    run = cliff_run(tmp_path / "run", task="peg_insertion_insert")
    write(run / "triggers.csv", ["frames", "steps", "value", "irrecoverable", "at_initial_state", "observation"], [
        [120, 40, 1.0, "", 1, ""], [600, 80, 3.0, "", 0, ""], [900, 90, 5.0, "", 1, ""], [1900, 200, 4.0, "", 0, ""],
    ])
    table = stretches.stretches(run, window=1000)
    assert [(row["triggers"], row["at the start"]) for row in table] == [(3, 2), (1, 0)]
    assert list(table[0])[:3] == ["steps", "triggers", "at the start"]
