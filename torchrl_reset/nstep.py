"""The state n steps later, for the n-step RCE label (docs/method.md section 3)."""
from __future__ import annotations

import json
import warnings
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.utils import NestedKey
from torchrl.data.replay_buffers.samplers import Sampler
from torchrl.envs.transforms import Transform

from ._validation import check_int

__all__ = ["NStepStateTransform", "EpisodeWindowSampler"]


class NStepStateTransform(Transform):
    """A replay-buffer transform that stores ``s_{t+n}`` beside ``s_{t+1}`` for every transition.

    torchrl's :class:`~torchrl.envs.transforms.MultiStepTransform` replaces ``("next", ...)`` by the
    state n steps ahead; the RCE label needs both the one-step and the n-step state, so this
    transform keeps ``"next"`` as it is and writes the state n steps later (the ``"next"`` entries
    of the transition n-1 rows further in the same trajectory) into a sub-tensordict ``out_key``.
    When the trajectory ends earlier, its last state is used.

    Like ``MultiStepTransform`` it runs on :meth:`~torchrl.data.ReplayBuffer.extend` and holds back
    the transitions whose n-step state has not arrived yet (at most n-1 of them); they are written
    as soon as it arrives or their trajectory ends. A trajectory ends at ``("next", "done")`` or
    when the trajectory id (``("collector", "traj_ids")``, written by torchrl's collectors and by
    :class:`~torchrl_reset.DualCollector`) changes. Data must be 1-dimensional, in time order.

    So a buffer fed one step at a time stays empty for the first n - 1 steps of its first episode
    (unless that episode ends sooner): sample it only once ``len(buffer) > 0``, which a heat-up of at
    least n steps guarantees. Sampled too early, torchrl's samplers raise "Cannot sample from an
    empty storage"; :class:`EpisodeWindowSampler` says what the buffer is waiting for.

    Args:
        n_steps (int): n >= 1. With n = 1 the n-step state equals ``("next", ...)``.
        state_keys (sequence of NestedKey): the state entries to copy. Defaults to ``("observation",)``.

    Keyword Args:
        traj_key (NestedKey): the trajectory id. Defaults to ``("collector", "traj_ids")``; when
            the data have no such entry only ``done_key`` separates trajectories.
        done_key (NestedKey): Defaults to ``("next", "done")``.
        out_key (NestedKey): the sub-tensordict written. Defaults to ``"nstep"``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl.data import LazyTensorStorage, ReplayBuffer
        >>> from torchrl_reset import NStepStateTransform
        >>> T = 5
        >>> data = TensorDict(
        ...     observation=torch.arange(T).float().unsqueeze(-1),
        ...     next=TensorDict(
        ...         observation=torch.arange(1, T + 1).float().unsqueeze(-1),
        ...         done=torch.tensor([False, False, False, False, True]).unsqueeze(-1),
        ...         batch_size=[T]),
        ...     batch_size=[T])
        >>> rb = ReplayBuffer(storage=LazyTensorStorage(10), transform=NStepStateTransform(3))
        >>> _ = rb.extend(data)
        >>> rb[:]["nstep", "observation"].squeeze(-1)
        tensor([3., 4., 5., 5., 5.])
    """

    def __init__(
        self,
        n_steps: int,
        state_keys: Sequence[NestedKey] = ("observation",),
        *,
        traj_key: NestedKey = ("collector", "traj_ids"),
        done_key: NestedKey = ("next", "done"),
        out_key: NestedKey = "nstep",
    ) -> None:
        check_int("n_steps", n_steps)
        super().__init__()
        self.n_steps = n_steps
        self.state_keys = list(state_keys)
        if not self.state_keys:
            raise ValueError("state_keys must name at least one state entry.")
        self.traj_key = traj_key
        self.done_key = done_key
        self.out_key = out_key
        # held-back transitions, one single-row tensordict each, in time order
        self._pending: list[TensorDictBase] = []

    @property
    def num_pending(self) -> int:
        """Transitions held back until their n-step state is known."""
        return len(self._pending)

    def _inv_call(self, tensordict: TensorDictBase) -> TensorDictBase | None:
        if tensordict.batch_dims != 1:
            raise ValueError(
                "NStepStateTransform expects 1-dimensional data in time order, got batch size "
                f"{tuple(tensordict.batch_size)}."
            )
        next_td = tensordict.get("next", None)
        next_keys = next_td.keys(True, True) if isinstance(next_td, TensorDictBase) else ()
        for key in self.state_keys:
            if key not in next_keys:
                raise KeyError(f"NStepStateTransform needs ('next', {key!r}) in the data.")
        if tensordict.shape[0] == 1:
            return self._add_one(tensordict)
        return self._complete(torch.cat([*self._pending, tensordict], 0), force_close=False)

    def _add_one(self, row: TensorDictBase) -> TensorDictBase | None:
        """One transition (the collector's step by step case), without re-scanning what is held back:
        it completes the oldest held-back transition, or, when it ends its trajectory, all of them."""
        traj = row.get(self.traj_key, None)
        previous = self._pending[-1].get(self.traj_key, None) if self._pending else None
        if previous is not None and traj is not None and not torch.equal(traj.reshape(-1), previous.reshape(-1)):
            # a new trajectory began without a done: the held-back ones end with the previous one
            closed = self._complete(torch.cat(self._pending, 0), force_close=True)
            rest = self._add_one(row)
            return closed if rest is None else torch.cat([closed, rest], 0)
        done = row.get(self.done_key, None)
        self._pending.append(row.clone())
        if done is not None and bool(done.any()):
            return self._complete(torch.cat(self._pending, 0), force_close=True)
        if len(self._pending) < self.n_steps:
            return None
        newest = self._pending[-1]  # row t + n - 1: its next state is s_{t+n} of the oldest row t
        first = self._pending.pop(0)
        first.set(self.out_key, newest.get("next").select(*self.state_keys))
        return first

    def _complete(self, total: TensorDictBase, force_close: bool) -> TensorDictBase | None:
        length = total.shape[0]
        index = torch.arange(length)
        done = total.get(self.done_key, None)
        done = torch.zeros(length, dtype=torch.bool) if done is None else done.reshape(length, -1).any(-1)
        new_segment = torch.zeros(length, dtype=torch.bool)
        new_segment[1:] = done[:-1]
        traj = total.get(self.traj_key, None)
        if traj is not None:
            traj = traj.reshape(length)
            new_segment[1:] |= traj[1:] != traj[:-1]
        segment = new_segment.long().cumsum(0)
        segment_end = torch.zeros(int(segment[-1]) + 1, dtype=torch.long).scatter_reduce_(
            0, segment, index, reduce="amax", include_self=False
        )[segment]
        closed = (segment_end < length - 1) | done[segment_end]
        if force_close:
            closed[:] = True
        ready = closed | (index + self.n_steps - 1 <= segment_end)
        # Only the last, still open trajectory can be unready, so the ready rows are a prefix.
        num_ready = int(ready.sum())
        self._pending = list(total[num_ready:].clone().split(1, 0)) if num_ready < length else []
        if num_ready == 0:
            return None
        source = torch.minimum(index[:num_ready] + self.n_steps - 1, segment_end[:num_ready])
        out = total[:num_ready]
        out.set(self.out_key, total.get("next").select(*self.state_keys)[source])
        return out

    def flush(self) -> TensorDictBase | None:
        """Returns the held-back transitions, completed with their trajectory's last state."""
        if not self._pending:
            return None
        pending = torch.cat(self._pending, 0)
        self._pending = []
        return self._complete(pending, force_close=True)

    def get_extra_state(self) -> dict:
        return {"pending": torch.cat(self._pending, 0).to_dict() if self._pending else None}

    def set_extra_state(self, state: dict) -> None:
        pending = state.get("pending")
        self._pending = [] if pending is None else list(
            TensorDict.from_dict(pending, auto_batch_size=True, batch_dims=1).split(1, 0)
        )

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        # Sampling reads what was written on extend; nothing to do.
        return tensordict


def _why_empty(storage) -> str:
    """What an empty replay buffer waits for: the transitions an NStepStateTransform on it holds back."""
    for buffer in getattr(storage, "_attached_entities", ()):
        transforms = getattr(buffer, "_transform", None)
        transforms = getattr(transforms, "transforms", [transforms])  # a Compose, or one transform
        for transform in transforms:
            if isinstance(transform, NStepStateTransform):
                n = transform.n_steps
                return (
                    f"The buffer's NStepStateTransform(n_steps={n}) holds back {transform.num_pending} "
                    f"transition(s): it writes a transition once the state {n} steps after it has arrived or its "
                    f"episode has ended, so the first rows appear after {n} steps of the first episode, or at its "
                    f"end. Sample once len(buffer) > 0 (a heat-up of at least {n} of this agent's steps is enough)."
                )
    return "Extend the buffer before sampling it."


class EpisodeWindowSampler(Sampler):
    """Samples replay rows whose whole n-step window lies inside one episode, episodes first.

    The authors' release draws an RCE replay row by picking an episode uniformly among those with
    at least ``n_steps`` transitions, then a start ``t`` uniformly among the positions with
    ``t + n - 1`` at most the episode's last transition (docs/method.md section 9). So ``s_{t+n}`` (the
    ``"nstep"`` entry that :class:`NStepStateTransform` writes) is always a real state n steps later
    in the same episode; the last n - 1 transitions of an episode and episodes shorter than n are
    never drawn. While no episode has n transitions, rows are drawn uniformly (counted in
    ``fallbacks``; the release then uses n = 1).

    Episodes are the runs of consecutive writes with the same ``traj_key`` (``("collector",
    "traj_ids")``, written by :class:`~torchrl_reset.DualCollector`), so the storage must keep that
    entry; rows overwritten by a full circular storage leave their episode. Random numbers come from
    torch's global generator.

    Args:
        n_steps (int): the window length n >= 1.

    Keyword Args:
        traj_key (NestedKey): the episode id entry. Defaults to ``("collector", "traj_ids")``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl.data import LazyTensorStorage, ReplayBuffer
        >>> from torchrl_reset import EpisodeWindowSampler
        >>> traj = torch.tensor([0, 0, 0, 0, 1, 1, 2, 2, 2])  # episodes of 4, 2 and 3 rows
        >>> data = TensorDict({"t": torch.arange(9), ("collector", "traj_ids"): traj}, batch_size=[9])
        >>> rb = ReplayBuffer(storage=LazyTensorStorage(20), sampler=EpisodeWindowSampler(3), batch_size=1000)
        >>> _ = rb.extend(data)
        >>> sorted(rb.sample()["t"].unique().tolist())  # windows of 3 inside episodes 0 and 2
        [0, 1, 6]
    """

    def __init__(self, n_steps: int, *, traj_key: NestedKey = ("collector", "traj_ids")) -> None:
        super().__init__()
        self.n_steps = check_int("n_steps", n_steps)
        self.traj_key = traj_key
        self.fallbacks = 0
        self._empty()

    def _empty(self) -> None:
        self._unread: list[torch.Tensor] = []  # written slots whose episode ids are not read yet
        self._traj = np.zeros(0, dtype=np.int64)  # per episode segment: id, first slot, length
        self._start = np.zeros(0, dtype=np.int64)
        self._length = np.zeros(0, dtype=np.int64)
        self._first = 0  # segments before it were overwritten entirely
        self._count = 0
        self._rows = 0  # rows held
        self._rebuild = False

    def add(self, index) -> None:
        self._unread.append(torch.as_tensor(index).reshape(-1))

    def extend(self, index) -> None:
        self._unread.append(torch.as_tensor(index).reshape(-1))

    def _grow(self) -> None:
        size = max(16, 2 * len(self._traj))
        for name in ("_traj", "_start", "_length"):
            old = getattr(self, name)
            new = np.zeros(size, dtype=np.int64)
            new[: len(old)] = old
            setattr(self, name, new)

    def _read(self, storage) -> None:
        if not self._unread:
            return
        slots = torch.cat(self._unread)
        self._unread = []
        traj = storage[slots].get(self.traj_key, None)
        if traj is None:
            raise KeyError(f"EpisodeWindowSampler needs the episode id {self.traj_key!r} in the stored rows.")
        capacity = storage.max_size
        for slot, episode in zip(slots.tolist(), traj.reshape(len(slots), -1)[:, 0].tolist()):
            if self._rows == capacity:  # the oldest row is overwritten by this one
                first = self._first
                self._start[first] = (self._start[first] + 1) % capacity
                self._length[first] -= 1
                if self._length[first] == 0:
                    self._first += 1
                self._rows -= 1
            last = self._count - 1
            if (last >= self._first and self._traj[last] == episode
                    and (self._start[last] + self._length[last]) % capacity == slot):
                self._length[last] += 1
            else:
                if self._count == len(self._traj):
                    self._grow()
                self._traj[self._count], self._start[self._count], self._length[self._count] = episode, slot, 1
                self._count += 1
            self._rows += 1

    def sample(self, storage, batch_size: int) -> tuple[torch.Tensor, dict]:
        if len(storage) == 0:
            raise RuntimeError(f"EpisodeWindowSampler: cannot sample from an empty storage. {_why_empty(storage)}")
        if self._rebuild:
            self._rebuild = False
            self._unread = [torch.arange(len(storage))]
        self._read(storage)
        lengths = self._length[self._first : self._count]
        eligible = np.flatnonzero(lengths >= self.n_steps) + self._first
        if len(eligible) == 0:
            self.fallbacks += 1
            return torch.randint(len(storage), (batch_size,)), {"fallback": True}
        eligible = torch.from_numpy(eligible)
        episode = eligible[torch.randint(len(eligible), (batch_size,))].numpy()
        positions = torch.from_numpy(self._length[episode] - self.n_steps + 1)
        offset = (torch.rand(batch_size, dtype=torch.float64) * positions).long().clamp_max(positions - 1)
        index = (torch.from_numpy(self._start[episode]) + offset) % storage.max_size
        return index, {"fallback": False}

    def state_dict(self) -> dict:
        live = slice(self._first, self._count)
        unread = torch.cat(self._unread).tolist() if self._unread else []
        return {"traj": self._traj[live].tolist(), "start": self._start[live].tolist(),
                "length": self._length[live].tolist(), "rows": self._rows, "unread": unread,
                "fallbacks": self.fallbacks}

    def load_state_dict(self, state_dict: dict) -> None:
        self._empty()
        for name, key in (("_traj", "traj"), ("_start", "start"), ("_length", "length")):
            setattr(self, name, np.asarray(state_dict[key], dtype=np.int64).reshape(-1))
        self._count = len(self._traj)
        self._rows = int(state_dict["rows"])
        self._unread = [torch.as_tensor(state_dict["unread"], dtype=torch.long)] if state_dict["unread"] else []
        self.fallbacks = int(state_dict.get("fallbacks", 0))

    def dumps(self, path) -> None:
        path = Path(path)
        path.mkdir(parents=True, exist_ok=True)
        (path / "episode_window_sampler.json").write_text(json.dumps(self.state_dict()))

    def loads(self, path) -> None:
        file = Path(path) / "episode_window_sampler.json"
        if file.exists():
            self.load_state_dict(json.loads(file.read_text()))
            return
        # a buffer saved with another sampler: rebuild the episodes from the stored rows at the next
        # sample (in slot order, which is write order unless the storage had wrapped around)
        warnings.warn("no EpisodeWindowSampler state in the saved buffer: rebuilding its episodes from the "
                      "stored rows.", stacklevel=2)
        self._empty()
        self._rebuild = True

    def __repr__(self) -> str:
        return f"{type(self).__name__}(n_steps={self.n_steps}, episodes={self._count - self._first}, rows={self._rows})"
