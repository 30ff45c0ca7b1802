"""A run, stretch by stretch: how its trigger, forward share and resets changed over training.

    python recipes/analysis/stretches.py runs/peg_insertion_insert/ours/seed0 --window 25000
    python recipes/analysis/stretches.py results/table1-peg-insert/peg_insertion_insert/*/seed0 --window 10000 --upto 30000

For each run folder and each ``--window``-step stretch (forward and reset steps together) a markdown
table row, read from the run's ``progress.csv``, ``resets.csv`` and ``triggers.csv``:

- triggers: triggered resets in the stretch; where the run logged it (``triggers.csv``'s ``at_initial_state``),
  how many stopped the forward agent at a state that already passed the env's at-initial-state check; on a
  task with irrecoverable states (the cliff tasks, run
  with the code that logs them) also how many came too late (the state before the trigger was already lost), and
  the median of the curriculum entry just before the triggers (Fig. 5's state: the x position on the
  cliff tasks);
- forward episodes and forward share (forward steps over the stretch's steps), from ``progress.csv``;
- reset episodes that ended in the stretch, successful and manual ones, the success rate;
- on such a task, the entries into an irrecoverable state in forward and in reset steps.

A stretch is reported once ``progress.csv`` has a row at or past its end (a row at its start or before
it and one at its end or before it bound it: with ``log_every`` dividing ``--window`` they are exact).
"""
from __future__ import annotations

import argparse
import csv
import statistics
from pathlib import Path

__all__ = ["stretches", "markdown", "run_task", "has_irrecoverable_states", "resets_by_start", "keyed_by_start", "csv_rows", "within"]


def csv_rows(path: Path) -> list[dict]:
    """A CSV file's rows as dicts of strings; none for a file not written (yet)."""
    if not path.exists():
        return []
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def within(frames: int, start: int, end: int) -> bool:
    """Whether an event logged at step ``frames`` falls in the stretch ``(start, end]``: an event is logged at
    the step count after it, so the first stretch also holds step 0 (a trigger on the run's first action)."""
    return start < frames <= end or frames == start == 0


def keyed_by_start(resets: list[dict]) -> dict[int, dict]:
    """Rows of ``resets.csv`` keyed by the step each reset episode began (``frames - steps``): a trigger's
    row in ``triggers.csv`` (its ``frames``, the step it fired) finds the reset episode that followed it.
    Two rows with one start cannot come from a run on one env: refused (ValueError)."""
    keyed = {}
    for r in resets:
        start = int(r["frames"]) - int(r["steps"])
        if start in keyed:
            raise ValueError(f"two reset episodes began at step {start} (ending at frames {keyed[start]['frames']} and "
                             f"{r['frames']}): not the resets.csv of a run on one env")
        keyed[start] = r
    return keyed


def resets_by_start(run: Path) -> dict[int, dict]:
    """``keyed_by_start`` of a run folder's ``resets.csv``. The folder of an ``arms`` run (one agent pair over
    N copies of a task, which older code ran: run batching, retired) is refused (ValueError): its ``frames``
    count the steps of all its envs, and ``steps`` one env's, so ``frames - steps`` is no start."""
    from omegaconf import OmegaConf

    cfg, _ = run_task(run)
    arms = None if cfg is None else OmegaConf.select(cfg, "arms", default=None)
    if arms is not None and int(arms) > 1:
        raise ValueError(f"{run} ran {arms} arms: its reset episodes cannot be paired with its triggers by their start")
    return keyed_by_start(csv_rows(Path(run) / "resets.csv"))


def _at(progress: list[dict], frames: int) -> dict | None:
    """The last ``progress.csv`` row at or before ``frames`` (None before the first)."""
    before = [r for r in progress if int(r["frames"]) <= frames]
    return before[-1] if before else None


def run_task(run: Path):
    """A run folder's ``config.yaml`` and its task's spec (``TASKS[task.name]``): ``(cfg, spec)``, with
    ``(None, None)`` for a folder without a config and ``spec`` None for a task this code does not know."""
    config = Path(run) / "config.yaml"
    if not config.exists():
        return None, None
    from omegaconf import OmegaConf
    from torchrl_reset_envs import TASKS

    cfg = OmegaConf.load(config)
    return cfg, TASKS.get(str(OmegaConf.select(cfg, "task.name")))


def has_irrecoverable_states(run: Path) -> bool:
    """Whether the run's task (its ``config.yaml``'s ``task.name``) has irrecoverable states (the cliff tasks)."""
    return bool(getattr(run_task(run)[1], "has_irrecoverable", False))


def _count(row: dict | None, column: str) -> int:
    return 0 if row is None or row.get(column) in (None, "") else int(float(row[column]))


def stretches(run: Path, window: int, upto: int | None = None) -> list[dict]:
    """The stretches of ``run`` (a run folder) of ``window`` steps each, up to ``upto`` (default: as far as
    ``progress.csv`` goes), one dict per stretch, in the columns described in the module's docstring."""
    run = Path(run)
    if not isinstance(window, int) or window < 1:
        raise ValueError(f"window must be a positive number of steps, got {window!r}")
    progress = csv_rows(run / "progress.csv")
    if not progress:
        raise FileNotFoundError(f"{run} has no progress.csv rows: not a run folder, or nothing logged yet")
    resets, triggers = csv_rows(run / "resets.csv"), csv_rows(run / "triggers.csv")
    cliff = has_irrecoverable_states(run) and "irrecoverable_forward" in progress[0]
    at_start = bool(triggers) and triggers[0].get("at_initial_state") not in (None, "")  # logged since it existed
    last = int(progress[-1]["frames"])
    end_of_run = last if upto is None else min(upto, last)
    out = []
    for start in range(0, end_of_run, window):
        end = start + window
        if end > end_of_run:
            break
        a, b = _at(progress, start), _at(progress, end)
        steps = int(b["frames"]) - (int(a["frames"]) if a else 0)
        fired = [t for t in triggers if within(int(t["frames"]), start, end)]
        ended = [r for r in resets if within(int(r["frames"]), start, end)]
        success = sum(r["outcome"] == "success" for r in ended)
        row = {"steps": f"{thousands(start)}-{thousands(end)}", "triggers": len(fired)}
        if at_start:
            row["at the start"] = sum(t.get("at_initial_state") == "1" for t in fired)
        if cliff:
            row["too late"] = sum(t.get("irrecoverable") == "1" for t in fired)
            values = [float(t["value"]) for t in fired if t.get("value") not in (None, "")]
            row["trigger position (median)"] = f"{statistics.median(values):.3g}" if values else ""
        row.update({
            "forward episodes": _count(b, "forward_episodes") - _count(a, "forward_episodes"),
            "forward share": f"{(_count(b, 'forward_steps') - _count(a, 'forward_steps')) / steps:.3f}" if steps else "",
            "reset episodes": len(ended),
            "successful": success,
            "manual": len(ended) - success,
            "success rate": f"{success / len(ended):.0%}" if ended else "",
        })
        if cliff:
            row["lost in forward"] = _count(b, "irrecoverable_forward") - _count(a, "irrecoverable_forward")
            row["lost in reset"] = _count(b, "irrecoverable_reset") - _count(a, "irrecoverable_reset")
        out.append(row)
    return out


def thousands(frames: int) -> str:
    return f"{frames // 1000}k" if frames % 1000 == 0 and frames else str(frames)


def markdown(table: list[dict]) -> str:
    if not table:
        return "(no complete stretch yet)"
    lines = ["| " + " | ".join(table[0]) + " |", "|" + "---|" * len(table[0])]
    lines += ["| " + " | ".join(str(v) for v in row.values()) + " |" for row in table]
    return "\n".join(lines)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", nargs="+", type=Path, help="run folders (each with its progress.csv)")
    parser.add_argument("--window", type=int, default=25000, help="steps per stretch (default 25000)")
    parser.add_argument("--upto", type=int, default=None, help="the last step reported (default: as far as logged)")
    args = parser.parse_args(argv)
    if args.window < 1:
        parser.error(f"--window must be a positive number of steps, got {args.window}")
    for run in args.runs:
        try:
            table = stretches(run, args.window, args.upto)
        except FileNotFoundError as err:
            parser.error(str(err))
        print(f"\n{run}\n\n{markdown(table)}")


if __name__ == "__main__":
    main()
