"""A run folder's files: crash-safe checkpoints, append-only CSV tables, the code version, summaries."""
from __future__ import annotations

import csv
import json
import os
import platform
import random
import shutil
import signal
import subprocess
from contextlib import contextmanager
from pathlib import Path
from typing import Callable

import numpy as np
import torch
from omegaconf import OmegaConf

__all__ = ["RunFolderBusy", "run_folder_lock", "code_version", "processor_name", "Checkpoints", "TrainingState", "stop_on_sigterm",
           "success_rate_by_quarter", "CsvTable"]


def code_version() -> dict:
    """The commit the code runs at and whether the work tree differs from it (None outside a git checkout)."""
    root = Path(__file__).resolve().parents[1]
    try:
        commit = subprocess.run(["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True, text=True,
                                timeout=10, check=True).stdout.strip()
        status = subprocess.run(["git", "-C", str(root), "status", "--porcelain", "--untracked-files=no"],
                                capture_output=True, text=True, timeout=10, check=True).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return {"commit": None, "modified": None}
    return {"commit": commit, "modified": bool(status)}


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


class Checkpoints:
    """Complete checkpoints in ``root/step_<frames>/``, the newest named by ``root/latest``.

    A checkpoint is written into a temporary folder, which is renamed into place once complete; then
    ``latest`` is replaced atomically. A crash while checkpointing leaves the previous checkpoint and
    ``latest`` untouched.
    """

    def __init__(self, root: Path, keep: int = 2):
        self.root = Path(root)
        self.keep = max(1, int(keep))

    def latest(self) -> Path | None:
        pointer = self.root / "latest"
        if not pointer.exists():
            return None
        path = self.root / pointer.read_text().strip()
        return path if (path / "meta.json").exists() else None

    def save(self, frames: int, write: Callable[[Path], None], meta: dict) -> Path:
        self.root.mkdir(parents=True, exist_ok=True)
        tmp = self.root / f".tmp-step_{frames:010d}-{os.getpid()}"
        if tmp.exists():
            shutil.rmtree(tmp)
        tmp.mkdir()
        write(tmp)
        (tmp / "meta.json").write_text(json.dumps(meta, indent=2))  # written last: marks the folder complete
        _fsync_tree(tmp)
        final = self.root / f"step_{frames:010d}"
        if final.exists():
            shutil.rmtree(final)
        os.rename(tmp, final)
        pointer_tmp = self.root / f".latest-{os.getpid()}"
        with open(pointer_tmp, "w") as f:
            f.write(final.name)
            f.flush()
            os.fsync(f.fileno())
        os.replace(pointer_tmp, self.root / "latest")
        _fsync_dir(self.root)
        for old in sorted(self.root.glob("step_*"))[: -self.keep]:
            shutil.rmtree(old, ignore_errors=True)
        return final


class TrainingState:
    """Everything a run needs to go on exactly where it stopped: both agents (losses with their target
    copies, optimizers), the collector (its episode, counters and success examples), both replay
    buffers, the run's history and every random stream."""

    def __init__(self, checkpoints: Checkpoints, cfg, forward, reset, collector, forward_rb, reset_rb) -> None:
        self.checkpoints, self.cfg = checkpoints, cfg
        self.forward, self.reset, self.collector = forward, reset, collector
        self.buffers = {"forward_buffer": forward_rb, "reset_buffer": reset_rb}
        self.history: dict = {}
        self.before_save = None  # called first by save(): a batch writes the run's optimizer state back here

    def save(self) -> Path:
        """A complete checkpoint at the collector's step (crash-safe: see :class:`Checkpoints`)."""
        cfg = self.cfg
        meta = {"task": cfg.task.name, "algo": cfg.algo.name, "seed": int(cfg.seed), "frames": self.collector.frames,
                "arms": OmegaConf.select(cfg, "arms", default=None)}
        if self.before_save is not None:
            self.before_save()
        return self.checkpoints.save(self.collector.frames, self._write, meta)

    def _write(self, folder: Path) -> None:
        torch.save(
            {
                "forward_loss": _own(self.forward.loss.state_dict()),
                "reset_loss": _own(self.reset.loss.state_dict()),
                "forward_optimizer": self.forward.optimizer.state_dict(),
                "reset_optimizer": self.reset.optimizer.state_dict(),
                "collector": self.collector.state_dict(),
                "history": self.history,
                "rng": {"torch": torch.get_rng_state(), "numpy": np.random.get_state(), "python": random.getstate()},
            },
            folder / "state.pt",
        )
        for name, rb in self.buffers.items():
            if len(rb):  # torchrl cannot dump a buffer that never received data
                rb.dumps(folder / name)

    def load(self) -> Path:
        """Loads the latest checkpoint into the agents, collector and buffers; sets ``history``."""
        folder = self.checkpoints.latest()
        state = torch.load(folder / "state.pt", weights_only=False)
        self.forward.loss.load_state_dict(state["forward_loss"])
        self.reset.loss.load_state_dict(state["reset_loss"])
        self.forward.optimizer.load_state_dict(state["forward_optimizer"])
        self.reset.optimizer.load_state_dict(state["reset_optimizer"])
        for name, rb in self.buffers.items():
            if (folder / name).exists():
                rb.loads(folder / name)
        self.collector.load_state_dict(state["collector"])
        self.history = state["history"]
        torch.set_rng_state(state["rng"]["torch"])
        np.random.set_state(state["rng"]["numpy"])
        random.setstate(state["rng"]["python"])
        return folder


def _own(state: dict) -> dict:
    """The state dict's tensors in storage of their own: torch.save writes a view's whole storage, and a
    run of a batch keeps its parameters as views into the batch's stacked tensors."""
    return {k: v.clone() if isinstance(v, torch.Tensor) else v for k, v in state.items()}


@contextmanager
def stop_on_sigterm():
    """Yields a list that gets an entry when SIGTERM arrives (a cluster's pre-emption, ``kill``), so that
    the loop can stop after its current step with a checkpoint; off the main thread, signals are left alone."""
    requested: list[int] = []
    try:
        previous = signal.signal(signal.SIGTERM, lambda signum, frame: requested.append(signum))
    except ValueError:  # not the main thread
        previous = None
    try:
        yield requested
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)


def _fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _fsync_tree(root: Path) -> None:
    for dirpath, _, filenames in os.walk(root):
        for name in filenames:
            with open(os.path.join(dirpath, name), "rb") as f:
                os.fsync(f.fileno())
        _fsync_dir(Path(dirpath))


def success_rate_by_quarter(progress: Path) -> dict:
    """The reset success rate within the first and the last quarter of a run's steps, from ``progress.csv``
    (the cumulative counters at the log rows): whether the reset agent got better."""
    out = {"reset_success_rate_first_quarter": None, "reset_success_rate_last_quarter": None}
    if not Path(progress).exists():
        return out
    with open(progress, newline="") as f:
        rows = [(int(float(r["frames"])), int(r["successful_resets"]), int(r["manual_resets"])) for r in csv.DictReader(f)]
    if len(rows) < 4:
        return out
    total = rows[-1][0]

    def at(frames: int) -> tuple[int, int]:
        before = [r for r in rows if r[0] <= frames]
        return (before[-1][1], before[-1][2]) if before else (0, 0)

    def rate(start: tuple[int, int], end: tuple[int, int]):
        ended = (end[0] - start[0]) + (end[1] - start[1])
        return (end[0] - start[0]) / ended if ended else None

    out["reset_success_rate_first_quarter"] = rate((0, 0), at(total // 4))
    out["reset_success_rate_last_quarter"] = rate(at(total - total // 4), at(total))
    return out


class CsvTable:
    """An append-only CSV file with a fixed header; on resume, rows after the checkpoint are dropped."""

    def __init__(self, path: Path, fields: list[str]):
        self.path = Path(path)
        self.fields = fields

    def truncate_after(self, frames: int) -> None:
        if not self.path.exists():
            return
        with open(self.path, newline="") as f:
            rows = [row for row in csv.DictReader(f) if int(float(row["frames"])) <= frames]
        self._rewrite(rows)

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

