"""The state n steps later, for the n-step RCE label (method.md section 3)."""
from __future__ import annotations

from collections.abc import Sequence

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.utils import NestedKey
from torchrl.envs.transforms import Transform

from ._validation import check_int

__all__ = ["NStepStateTransform"]


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
        self._pending: TensorDictBase | None = None

    @property
    def num_pending(self) -> int:
        """Transitions held back until their n-step state is known."""
        return 0 if self._pending is None else self._pending.shape[0]

    def _inv_call(self, tensordict: TensorDictBase) -> TensorDictBase | None:
        if tensordict.batch_dims != 1:
            raise ValueError(
                "NStepStateTransform expects 1-dimensional data in time order, got batch size "
                f"{tuple(tensordict.batch_size)}."
            )
        next_keys = tensordict.get("next").keys(True, True) if "next" in tensordict.keys() else ()
        for key in self.state_keys:
            if key not in next_keys:
                raise KeyError(f"NStepStateTransform needs ('next', {key!r}) in the data.")
        total = tensordict if self._pending is None else torch.cat([self._pending, tensordict], 0)
        return self._complete(total, force_close=False)

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
        self._pending = total[num_ready:].clone() if num_ready < length else None
        if num_ready == 0:
            return None
        source = torch.minimum(index[:num_ready] + self.n_steps - 1, segment_end[:num_ready])
        out = total[:num_ready]
        out.set(self.out_key, total.get("next").select(*self.state_keys)[source])
        return out

    def flush(self) -> TensorDictBase | None:
        """Returns the held-back transitions, completed with their trajectory's last state."""
        if self._pending is None:
            return None
        pending, self._pending = self._pending, None
        return self._complete(pending, force_close=True)

    def get_extra_state(self) -> dict:
        return {"pending": None if self._pending is None else self._pending.to_dict()}

    def set_extra_state(self, state: dict) -> None:
        pending = state.get("pending")
        self._pending = None if pending is None else TensorDict.from_dict(pending, auto_batch_size=True, batch_dims=1)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        # Sampling reads what was written on extend; nothing to do.
        return tensordict
