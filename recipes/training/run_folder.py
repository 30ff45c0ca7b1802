"""A run folder's other files and guards: append-only CSV tables, the code version and processor a run ran on,
the lock that keeps two runs out of one folder, and the signals that stop a run after its step."""
from __future__ import annotations

import csv
import os
import platform
import signal
import subprocess
import sys
from contextlib import contextmanager
from pathlib import Path

__all__ = ['RunFolderBusy', 'run_folder_lock', 'code_version', 'processor_name', 'RunInterrupted', 'stop_on_signals', 'reset_outcomes_by_quarter', 'CsvTable']


def code_version(script: str | None = None) -> dict:
    """The commit the code runs at and whether the work tree differs from it (None outside a git checkout).

    The checkout is the one the package is imported from (an editable install, or a run from the checkout);
    where the package is installed as a copy (``pip install .``), the checkout of the script being run
    (``script``, default ``sys.argv[0]``: ``recipes/train.py``), which such an install was made from."""
    script = sys.argv[0] if script is None else script
    roots = [Path(__file__).resolve().parents[2]]
    if script:
        roots.append(Path(script).resolve().parent.parent)
    for root in roots:
        try:
            commit = subprocess.run(["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True, text=True,
                                    timeout=10, check=True).stdout.strip()
            status = subprocess.run(["git", "-C", str(root), "status", "--porcelain", "--untracked-files=no"],
                                    capture_output=True, text=True, timeout=10, check=True).stdout.strip()
        except (OSError, subprocess.SubprocessError):
            continue
        return {"commit": commit, "modified": bool(status)}
    return {"commit": None, "modified": None}



def processor_name(cpuinfo: Path = Path("/proc/cpuinfo")) -> str:
    """The processor's model name and its widest vector extension (``/proc/cpuinfo`` on Linux), such as
    ``"AMD EPYC, AVX2"``: a run is reproducible bit for bit on one kind of processor only, since the
    float rounding of the products differs between kinds."""
    name, flags = platform.processor() or platform.machine(), set()
    try:
        for line in Path(cpuinfo).read_text().splitlines():
            if line.startswith("model name"):
                name = line.split(":", 1)[1].strip()
            elif line.startswith("flags"):
                flags = set(line.split(":", 1)[1].split())
            if flags and name:
                break
    except OSError:
        pass
    widest = next((label for flag, label in (("avx512_bf16", "AVX-512 BF16"), ("avx512f", "AVX-512"), ("avx2", "AVX2"))
                   if flag in flags), None)
    return f"{name}, {widest}" if widest else name



class RunInterrupted(Exception):
    """A signal stopped the run before ``total_steps``. ``summaries``: the run's summary (a list of one), the
    run checkpointed at the step it stopped; empty when a second Ctrl-C cut the step under way short (the last
    checkpoint stands). ``exit_code``: the shell's convention, 128 + the signal's number (130 for SIGINT, 143
    for SIGTERM)."""

    def __init__(self, signum: int, summaries: list[dict], message: str) -> None:
        super().__init__(message)
        self.signum, self.summaries = int(signum), summaries
        self.exit_code = 128 + self.signum



STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)



@contextmanager
def stop_on_signals():
    """Yields a list that gets the signal's number when SIGINT (Ctrl-C) or SIGTERM (a cluster's pre-emption,
    ``kill``) arrives, so that the loop can stop after its current step with a checkpoint, which then resumes
    exactly. A second Ctrl-C stops at once (KeyboardInterrupt): the step under way is lost, the last
    checkpoint stands. Off the main thread, signals are left alone."""
    requested: list[int] = []

    def on_signal(signum, frame):
        name = signal.Signals(signum).name
        if signum == signal.SIGINT and signal.SIGINT in requested:
            _say(f"{name} again: stopping at once; the step under way is not checkpointed (resume continues from "
                 "the last checkpoint)")
            raise KeyboardInterrupt
        if not requested:
            again = " (Ctrl-C again stops at once, without it)" if signum == signal.SIGINT else ""
            _say(f"{name}: stopping after the current step with a checkpoint{again}")
        requested.append(signum)

    previous = {}
    try:
        for signum in STOP_SIGNALS:
            previous[signum] = signal.signal(signum, on_signal)
    except ValueError:  # not the main thread
        pass
    try:
        yield requested
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)



def _say(message: str) -> None:
    """A line on stderr from a signal handler: written to the file descriptor directly, since the handler may
    run while the code it interrupted is writing to ``sys.stderr``'s buffer (a progress bar, a log line)."""
    try:
        os.write(2, f"\n{message}\n".encode())
    except OSError:
        pass



def reset_outcomes_by_quarter(resets: Path, steps: int, reset_episodes: int) -> dict:
    """The reset episodes that ended in the first and in the last quarter of a run's ``steps`` (steps 0 to
    steps // 4, and the last steps // 4), and how many of them got back to the start state, counted from
    ``resets.csv`` (one row per reset episode, at the step it ended). A quarter's counts are None when the
    table does not hold the run's ``reset_episodes`` (a run begun before it was written)."""
    rows = []
    if Path(resets).exists():
        with open(resets, newline="") as f:
            rows = [(int(float(r["frames"])), r["outcome"]) for r in csv.DictReader(f)]
    complete = len(rows) == int(reset_episodes)
    quarter = int(steps) // 4
    out = {}
    for name, (start, end) in (("first", (0, quarter)), ("last", (int(steps) - quarter, int(steps)))):
        ended = [outcome for frame, outcome in rows if start < frame <= end]
        out[name] = {"from_step": start, "to_step": end, "reset_episodes": len(ended) if complete else None,
                     "successful_resets": ended.count("success") if complete else None}
    return out



class CsvTable:
    """An append-only CSV file with a fixed header; on resume, rows after the checkpoint are dropped."""

    def __init__(self, path: Path, fields: list[str]):
        self.path = Path(path)
        self.fields = fields

    def truncate_after(self, frames: int) -> int | None:
        """Drops the rows logged after step ``frames``; returns the step of the last one dropped (None if none)."""
        if not self.path.exists():
            return None
        with open(self.path, newline="") as f:
            rows = list(csv.DictReader(f))
        kept = [row for row in rows if int(float(row["frames"])) <= frames]
        dropped = [int(float(row["frames"])) for row in rows if int(float(row["frames"])) > frames]
        self._rewrite(kept)
        return max(dropped, default=None)

    def _rewrite(self, rows) -> None:
        tmp = self.path.with_suffix(".tmp")
        with open(tmp, "w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=self.fields)
            writer.writeheader()
            writer.writerows(rows)
        os.replace(tmp, self.path)

    def append(self, row: dict) -> None:
        new = not self.path.exists()
        with open(self.path, "a", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=self.fields, extrasaction="ignore")
            if new:
                writer.writeheader()
            writer.writerow(row)



class RunFolderBusy(RuntimeError):
    """Another process is training in this run folder."""



@contextmanager
def run_folder_lock(run_dir: Path):
    """Holds ``run_dir/.lock`` for the whole run, so that two runs never write into one folder (two jobs
    of a grid whose run_dir does not tell them apart, say). Where file locks are unavailable, does nothing."""
    try:
        import fcntl
    except ImportError:  # not a POSIX system
        yield
        return
    handle = open(Path(run_dir) / ".lock", "w")
    try:
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            raise RunFolderBusy(
                f"another process is training in {run_dir}. Give every run its own run_dir; in a grid over "
                "other keys, put them in it (run_dir='runs/${task.name}/${algo.name}/p${task.p_thresh}/seed${seed}')."
            ) from None
        yield
    finally:
        handle.close()

