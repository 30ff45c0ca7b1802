"""A run's checkpoints: crash-safe folders of its whole training state, each listed by a manifest written last, the
newest intact one found on resume, damaged ones named."""
from __future__ import annotations

import hashlib
import json
import logging
import os
import random
import re
import shutil
import time
from pathlib import Path
from typing import Callable

import numpy as np
import torch

__all__ = ['run_identity', 'identity_differences', 'Checkpoints', 'CheckpointDamaged', 'checkpoint_step', 'checkpoint_problems', 'no_intact_checkpoint', 'TrainingState', 'dump_buffer', 'MANIFEST']

log = logging.getLogger("torchrl_reset.train")


MANIFEST = "manifest.json"  # a checkpoint's list of its files, written last



_STEP_FOLDER = re.compile(r"step_(\d+)")



def run_identity(cfg) -> dict:
    """What names a run in its checkpoints' ``meta.json``: task, algorithm and seed."""
    return {"task": cfg.task.name, "algo": cfg.algo.name, "seed": int(cfg.seed)}



def identity_differences(meta: dict, cfg) -> dict[str, tuple]:
    """``{key: (saved, here)}`` for each part of :func:`run_identity` where a checkpoint's ``meta.json`` names
    another run than ``cfg``. Older code also wrote ``arms`` there: null (or absent) for a run on one
    environment, as every run is now; a number, one agent pair over that many copies of the task (run
    batching, retired), is another run: ``{"arms": (N, None)}``."""
    differ = {key: (meta.get(key), value) for key, value in run_identity(cfg).items() if meta.get(key) != value}
    if meta.get("arms") is not None:
        differ["arms"] = (meta["arms"], None)
    return differ



class CheckpointDamaged(RuntimeError):
    """No intact checkpoint to resume from; the message names each damaged one and what is wrong with it."""



def dump_buffer(rb, path: Path) -> None:
    """``rb.dumps(path)`` for a replay buffer. A buffer loaded from a checkpoint and not written to since has
    no last write cursor, and torchrl warns that it "may not be saved properly": that cursor only sets the
    shift of a checkpointer's save hooks (the trajectory layouts), so where its storage has no such hooks,
    as here, the buffer is saved whole and exactly, and that warning alone is silenced (a hook present: it
    stands)."""
    import warnings

    hookless = not getattr(rb.storage.checkpointer, "_save_hooks", None)
    with warnings.catch_warnings():
        if hookless:
            warnings.filterwarnings("ignore", message="last_cursor is None", category=UserWarning)
        rb.dumps(path)



class Checkpoints:
    """Complete checkpoints in ``root/step_<frames>/``, the newest named by ``root/latest``.

    A checkpoint is written into a temporary folder: the training state, ``meta.json``, then
    ``manifest.json`` (every file's relative path, size and sha256), written last. The folder is then
    renamed into place and ``latest`` replaced atomically, so a crash while checkpointing leaves the
    previous checkpoint and ``latest`` untouched. A checkpoint is intact when its files match its
    manifest; a damaged one (a file missing, truncated or changed) is passed over for the newest intact
    one before it. Checkpoints written before manifests existed (``meta.json``, no manifest) count as
    intact, unverified. A checkpoint folder is never written again once in place: saving the state a
    folder already holds (no step since it was saved or loaded) keeps that folder.
    """

    def __init__(self, root: Path, keep: int = 2, keep_states_every: int | None = None):
        self.root = Path(root)
        self.keep = max(1, int(keep))
        # the agents' state (``state.pt``, without the buffers) of each checkpoint at a multiple of these steps
        # stays in ``root/kept/step_<frames>/`` after the checkpoint itself is pruned: a run's course, for study
        self.keep_states_every = int(keep_states_every) if keep_states_every else None
        self.current: str | None = None  # the folder that holds this process's state now (saved or loaded)
        self.trusted: set[str] = set()  # checkpoint folders this process wrote or verified and loaded
        self.started_from: int | None = None  # 0 for a fresh start, the checkpoint's step for a resume
        self._kept_here: set[str] = set()  # the kept states this process wrote

    def loaded(self, folder: Path) -> None:
        """Records that this process resumed from ``folder`` (verified, then read): its state is what the
        process holds now, and the kept states past its step that another process wrote are a lost
        continuation's."""
        self.current = Path(folder).name
        self.trusted.add(self.current)
        self.started_from = checkpoint_step(folder)

    def started_fresh(self) -> None:
        """Records that this process starts its run at step 0: any state kept in the folder is another attempt's."""
        self.started_from = 0

    def folders(self) -> list[Path]:
        """Every checkpoint a resume could start from, intact or not, newest first: the ``step_*`` folders up
        to the one ``latest`` names (all of them when ``latest`` is missing or unreadable)."""
        steps = {s: path for path in self.root.glob("step_*") if (s := checkpoint_step(path)) is not None and path.is_dir()}
        newest = self._pointer()
        return [steps[s] for s in sorted(steps, reverse=True) if newest is None or s <= newest]

    def survey(self) -> tuple[Path | None, list[tuple[Path, list[str]]]]:
        """The newest intact checkpoint (None when there is none), and the damaged ones newer than it, each
        with what is wrong with it."""
        damaged = []
        for folder in self.folders():
            problems = checkpoint_problems(folder)
            if not problems:
                return folder, damaged
            damaged.append((folder, problems))
        return None, damaged

    def latest(self) -> Path | None:
        """The newest intact checkpoint, or None."""
        return self.survey()[0]

    def save(self, frames: int, write: Callable[[Path], None], meta: dict) -> Path:
        self.root.mkdir(parents=True, exist_ok=True)
        final = self.root / f"step_{frames:010d}"
        if final.name == self.current and final.is_dir():
            # no step since this state was saved or loaded: the folder holds it already (and may be read now)
            self._point_to(final)
            self.trusted.add(final.name)
            self._drop_lost_kept(frames)
            self._keep_due(frames)
            self._prune(frames)
            return final
        for stale in self.root.glob(".tmp-*"):  # left by a crash while checkpointing (one process per run folder)
            shutil.rmtree(stale, ignore_errors=True)
        tmp = self.root / f".tmp-step_{frames:010d}-{os.getpid()}"
        tmp.mkdir()
        write(tmp)
        (tmp / "meta.json").write_text(json.dumps({**meta, "manifest": MANIFEST}, indent=2))
        _write_manifest(tmp)  # last: it lists everything above
        _fsync_tree(tmp)
        replaced = None
        if final.exists():  # this step's checkpoint from an earlier attempt: moved aside, then removed
            replaced = self.root / f".tmp-replaced-{final.name}-{os.getpid()}"
            os.rename(final, replaced)
        os.rename(tmp, final)
        self._point_to(final)
        if replaced is not None:
            shutil.rmtree(replaced, ignore_errors=True)
        self.trusted.add(final.name)
        self._drop_lost_kept(frames)
        self._keep_due(frames)
        self._prune(frames)
        self.current = final.name
        return final

    def _pointer(self) -> int | None:
        try:
            return checkpoint_step(Path(self.root / "latest").read_text().strip())
        except OSError:
            return None

    def _point_to(self, folder: Path) -> None:
        if self._pointer() == checkpoint_step(folder):
            return
        pointer_tmp = self.root / f".latest-{os.getpid()}"
        with open(pointer_tmp, "w") as f:
            f.write(folder.name)
            f.flush()
            os.fsync(f.fileno())
        os.replace(pointer_tmp, self.root / "latest")
        _fsync_dir(self.root)

    def kept(self) -> list[Path]:
        """The kept states' folders (``kept/step_<frames>/state.pt``), oldest first."""
        found = [(s, p) for p in (self.root / "kept").glob("step_*") if (s := checkpoint_step(p)) is not None]
        return [p for _, p in sorted(found) if (p / "state.pt").exists()]

    def due_for_keeping(self, frames: int, kept_steps: list[int] | None = None) -> bool:
        """Whether a checkpoint at step ``frames`` keeps its state: the first checkpoint at or past each
        multiple of ``keep_states_every`` does (mostly the multiple itself, a multiple of ``checkpoint_every``;
        one past it where a run stopped there). ``kept_steps``: the steps of the kept states, where the caller
        has them (default: read from ``kept/``)."""
        every = self.keep_states_every
        if not every or frames < every:
            return False
        mark = frames // every * every
        if kept_steps is None:
            kept_steps = [checkpoint_step(p) for p in self.kept()]
        return not any(mark <= s < frames for s in kept_steps)

    def _keep_due(self, frames: int) -> None:
        """Keeps the state of every checkpoint up to ``frames`` that is due and not kept yet, oldest first: the
        one just written, and one whose keeping a crash interrupted (then loaded again by the resume). Only
        folders this process wrote or verified and loaded are read: an older one may be damaged."""
        if not self.keep_states_every:
            return
        steps = sorted((s, path) for path in self.root.glob("step_*")
                       if (s := checkpoint_step(path)) is not None and s <= frames and path.name in self.trusted)
        kept_steps = [checkpoint_step(p) for p in self.kept()]  # listed once, then followed as states are kept
        for s, path in steps:
            # a kept state is complete once its manifest is in place (written last); one at this step that
            # this process did not keep is another process's (the same state after a resume: kept again)
            done = (self.root / "kept" / path.name / MANIFEST).exists() and (s < frames or path.name in self._kept_here)
            if not done and self.due_for_keeping(s, kept_steps):
                self._keep_state(path)
                kept_steps.append(s)

    def _keep_state(self, folder: Path) -> None:
        """``folder``'s ``state.pt`` linked (copied where links are not possible) into ``kept/``, with its
        ``meta.json`` and a manifest of ``state.pt`` alone (so ``checkpoint_problems`` checks a kept state as
        it checks a checkpoint), replacing a state kept there for the same step by a continuation the run no
        longer has. Each file is written under a temporary name, synced, then renamed into place."""
        kept = self.root / "kept" / folder.name
        kept.mkdir(parents=True, exist_ok=True)
        tmp = kept / f".state.pt-{os.getpid()}"
        tmp.unlink(missing_ok=True)
        try:
            os.link(folder / "state.pt", tmp)  # the checkpoint's file, synced when it was written
        except OSError:
            shutil.copy2(folder / "state.pt", tmp)
            with open(tmp, "rb") as f:
                os.fsync(f.fileno())
        entry = json.loads((folder / MANIFEST).read_text())["files"]["state.pt"] if (folder / MANIFEST).exists() else None
        texts = {"meta.json": (folder / "meta.json").read_text() if (folder / "meta.json").exists() else None,
                 MANIFEST: json.dumps({"files": {"state.pt": entry}}, indent=1) if entry else None}
        for name, text in texts.items():
            if text is None:
                continue
            part = kept / f".{name}-{os.getpid()}"
            with open(part, "w") as f:
                f.write(text)
                f.flush()
                os.fsync(f.fileno())
        # the manifest last: until it is in place, an interrupted keeping reads as damaged, not as intact
        os.replace(tmp, kept / "state.pt")
        for name in ("meta.json", MANIFEST):
            if texts[name] is not None:
                os.replace(kept / f".{name}-{os.getpid()}", kept / name)
        _fsync_dir(kept)
        _fsync_dir(kept.parent)
        self._kept_here.add(kept.name)

    def _drop_lost_kept(self, frames: int) -> None:
        """Removes the kept states of a continuation the run no longer has (it resumed before them, from a
        checkpoint older than a damaged one, or started afresh): those past ``frames``, and those past the
        step this process started from that it did not keep itself."""
        for path in self.kept():
            step = checkpoint_step(path)
            if step > frames or (self.started_from is not None and step > self.started_from
                                 and path.name not in self._kept_here):
                shutil.rmtree(path, ignore_errors=True)

    def _prune(self, frames: int) -> None:
        """Keeps the newest ``keep`` checkpoints up to step ``frames``; later ones belong to a continuation the
        run no longer has (a damaged checkpoint it resumed before)."""
        steps = sorted((s, path) for path in self.root.glob("step_*") if (s := checkpoint_step(path)) is not None)
        for s, path in steps:
            if s > frames:
                shutil.rmtree(path, ignore_errors=True)
        for _, path in [(s, path) for s, path in steps if s <= frames][: -self.keep]:
            shutil.rmtree(path, ignore_errors=True)



def checkpoint_step(path) -> int | None:
    """The step of a checkpoint folder's name (``step_0000000300``: 300), or None for another name."""
    match = _STEP_FOLDER.fullmatch(Path(path).name)
    return int(match[1]) if match else None



def _sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            digest.update(chunk)
    return digest.hexdigest()



# sha256 of the checkpoint files this process has read, by path and by what stat said of the file when it was
# read (device, inode, size, modification time in ns). A resume verifies the same folder more than once at
# start-up (the configuration check, again under the run folder's lock, then the load); a file written since has
# a later modification time and is read again. File systems stamp times with a coarse clock, so a file modified
# within _SETTLED_NS of being read could be written again under the same stamp: such a file is not remembered.
_hashed: dict[str, tuple[tuple[int, int, int, int], str]] = {}
_SETTLED_NS = 2_000_000_000



def _checkpoint_sha256(path: Path, stat: os.stat_result) -> str:
    key = str(path.resolve())
    identity = (stat.st_dev, stat.st_ino, stat.st_size, stat.st_mtime_ns)
    known = _hashed.get(key)
    if known is not None and known[0] == identity:
        return known[1]
    digest = _sha256(path)
    if stat.st_mtime_ns < time.time_ns() - _SETTLED_NS:
        _hashed[key] = (identity, digest)
    return digest



def _write_manifest(folder: Path) -> None:
    files = {}
    for path in sorted(p for p in folder.rglob("*") if p.is_file()):
        files[path.relative_to(folder).as_posix()] = {"size": path.stat().st_size, "sha256": _sha256(path)}
    (folder / MANIFEST).write_text(json.dumps({"files": files}, indent=1))



def checkpoint_problems(folder: Path) -> list[str]:
    """What is wrong with a checkpoint folder, file by file: [] when every file its manifest lists is there
    with that size and sha256. A checkpoint written before manifests (none, and a ``meta.json`` that does not
    name one) is only checked for a readable ``meta.json``."""
    folder = Path(folder)
    if not (folder / MANIFEST).exists():
        try:
            meta = json.loads((folder / "meta.json").read_text())
        except FileNotFoundError:
            return ["meta.json is missing"]
        except (OSError, ValueError) as err:
            return [f"meta.json is unreadable ({err})"]
        return [f"{MANIFEST} is missing"] if isinstance(meta, dict) and meta.get("manifest") else []
    try:
        files = json.loads((folder / MANIFEST).read_text())["files"]
        listed = [(name, int(entry["size"]), str(entry["sha256"])) for name, entry in files.items()]
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as err:
        return [f"{MANIFEST} is unreadable ({err!r})"]
    problems = []
    for name, size, sha256 in listed:
        path = folder / name
        try:
            stat = path.stat()
        except OSError:
            problems.append(f"{name} is missing")
            continue
        if stat.st_size != size:
            problems.append(f"{name} has {stat.st_size} bytes, the manifest lists {size}")
        elif _checkpoint_sha256(path, stat) != sha256:
            problems.append(f"{name} differs from the manifest's sha256 (changed after it was written)")
    return problems



class TrainingState:
    """Everything a run needs to go on exactly where it stopped: both agents (losses with their target
    copies, optimizers), the collector (its episode, counters and success examples), both replay
    buffers, the run's history and every random stream, the evaluation env's included (its next
    evaluation starts from the start state the run that never stopped would draw)."""

    def __init__(self, checkpoints: Checkpoints, cfg, forward, reset, collector, forward_rb, reset_rb,
                 eval_env=None, streams=None) -> None:
        self.checkpoints, self.cfg, self.streams = checkpoints, cfg, streams
        self.forward, self.reset, self.collector, self.eval_env = forward, reset, collector, eval_env
        self.buffers = {"forward_buffer": forward_rb, "reset_buffer": reset_rb}
        self.history: dict = {}
        #: writers of further parts of every checkpoint (``learner.mode=async``: the learner process's), each
        #: called with the folder being written
        self.extra_writers: list = []
        self.loaded_from: Path | None = None  # the checkpoint the run resumed from

    def save(self) -> Path:
        """A complete checkpoint at the collector's step (crash-safe: see :class:`Checkpoints`)."""
        cfg = self.cfg
        meta = {**run_identity(cfg), "frames": self.collector.frames}
        return self.checkpoints.save(self.collector.frames, self._write, meta)

    def _write(self, folder: Path) -> None:
        torch.save(
            {
                "forward_loss": owned_state(self.forward.loss.state_dict()),
                "reset_loss": owned_state(self.reset.loss.state_dict()),
                "forward_optimizer": self.forward.optimizer.state_dict(),
                "reset_optimizer": self.reset.optimizer.state_dict(),
                "collector": self.collector.state_dict(),
                "history": self.history,
                "rng": {"torch": torch.get_rng_state(), "numpy": np.random.get_state(), "python": random.getstate()},
                "streams": None if self.streams is None else self.streams.state_dict(),
                "eval_env": _simulator_state(self.eval_env),
            },
            folder / "state.pt",
        )
        for name, rb in self.buffers.items():
            if len(rb):  # torchrl cannot dump a buffer that never received data
                dump_buffer(rb, folder / name)
        for write in self.extra_writers:
            write(folder)

    def load(self) -> Path:
        """Loads the newest intact checkpoint into the agents, collector and buffers; sets ``history``. Each
        damaged checkpoint passed over is named with what is wrong with it; none intact raises
        :class:`CheckpointDamaged`. Nothing is written into the checkpoint folder."""
        folder, damaged = self.checkpoints.survey()
        for bad, problems in damaged:
            then = f"resuming from {folder.name}" if folder is not None else "no intact checkpoint before it"
            log.warning("checkpoint %s is damaged (%s); %s", bad, "; ".join(problems), then)
        if folder is None:
            raise CheckpointDamaged(no_intact_checkpoint(self.checkpoints.root, damaged))
        if not (folder / MANIFEST).exists():
            log.warning("checkpoint %s has no %s (written before checkpoints had one): it cannot be verified, "
                        "loading it as it is", folder, MANIFEST)
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
        if self.streams is not None:  # after the global generator: the active stream's state goes back into it
            self.streams.load_state_dict(state.get("streams"))
        if state.get("eval_env") is not None:  # absent from checkpoints written before it was kept
            _simulator(self.eval_env).set_simulator_state(state["eval_env"])
        self.checkpoints.loaded(folder)
        self.loaded_from = folder
        return folder



def _simulator(env):
    """The innermost env (or wrapper) of ``env`` with ``get_simulator_state`` / ``set_simulator_state``, or None."""
    while env is not None:
        if callable(getattr(env, "get_simulator_state", None)) and callable(getattr(env, "set_simulator_state", None)):
            return env
        env = getattr(env, "base_env", None)
    return None



def _simulator_state(env):
    simulator = _simulator(env)
    return None if simulator is None else simulator.get_simulator_state()



def no_intact_checkpoint(root: Path, damaged: list[tuple[Path, list[str]]]) -> str:
    """The message for a run folder whose checkpoints are all damaged: each one and what is wrong with it."""
    listed = "\n  - ".join(f"{folder.name}: {'; '.join(problems)}" for folder, problems in damaged)
    return (f"no intact checkpoint in {root} to resume from:\n  - {listed}\nRestore the damaged files, or move the "
            "checkpoints away and start the run again without resume.")



def owned_state(state: dict) -> dict:
    """The state dict's tensors in storage of their own: torch.save writes a view's whole storage (a tensor
    that views part of a larger one would carry all of it)."""
    return {k: v.clone() if isinstance(v, torch.Tensor) else v for k, v in state.items()}



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

