"""The initial-state example buffer S* (docs/method.md section 2)."""
from __future__ import annotations

from collections.abc import Sequence

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torchrl.data import LazyTensorStorage, RandomSampler, ReplayBuffer

from ._validation import check_int

__all__ = ["InitialStateBuffer"]


class InitialStateBuffer:
    """Examples of initial states: the reset agent's only training signal besides its transitions.

    :class:`~torchrl_reset.DualCollector` adds the state at the start of every forward episode
    (after the first ``env.reset()``, after each successful reset episode, after each manual
    reset). :class:`~torchrl_reset.RCELoss` reads a uniform sample of it under the ``"example"``
    entry of its input. Backed by a torchrl :class:`~torchrl.data.ReplayBuffer`, so it saves and
    loads with ``state_dict`` / ``load_state_dict``.

    Args:
        max_size (int): capacity; the oldest examples are overwritten past it. Defaults to 100_000.
        state_keys (sequence of NestedKey): the entries of a state. Defaults to ``("observation",)``.

    Keyword Args:
        device: storage device. Defaults to ``"cpu"``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl_reset import InitialStateBuffer
        >>> examples = InitialStateBuffer(max_size=100)
        >>> examples.add(TensorDict(observation=torch.zeros(3), reward=torch.ones(1)))
        >>> len(examples)
        1
        >>> examples.sample(4)["observation"].shape
        torch.Size([4, 3])
    """

    def __init__(
        self,
        max_size: int = 100_000,
        state_keys: Sequence[NestedKey] = ("observation",),
        *,
        device: torch.device | str = "cpu",
    ) -> None:
        check_int("max_size", max_size)
        self.state_keys = list(state_keys)
        if not self.state_keys:
            raise ValueError("state_keys must name at least one state entry.")
        self.max_size = max_size
        self._buffer = ReplayBuffer(
            storage=LazyTensorStorage(max_size, device=device),
            sampler=RandomSampler(),
        )

    def __len__(self) -> int:
        return len(self._buffer)

    def add(self, state: TensorDictBase) -> None:
        """Adds one state (batch size ``[]``) or a batch of states (batch size ``[N]``)."""
        missing = [key for key in self.state_keys if state.get(key, None) is None]
        if missing:
            raise KeyError(
                f"InitialStateBuffer needs the state keys {missing}; got {sorted(map(str, state.keys(True, True)))}."
            )
        state = state.select(*self.state_keys)
        if state.batch_dims == 0:
            self._buffer.add(state.clone())
        elif state.batch_dims == 1:
            self._buffer.extend(state.clone())
        else:
            raise ValueError(f"add expects one state or a 1-dimensional batch, got batch size {tuple(state.batch_size)}.")

    def sample(self, batch_size: int) -> TensorDictBase:
        """A uniform sample with replacement of ``batch_size`` examples.

        Besides the state entries, ``"index"`` holds each example's slot in the buffer (int64):
        :class:`~torchrl_reset.RCELoss` uses it to compute the classifier priors' part of each
        example once instead of at every update.
        """
        if len(self) == 0:
            raise RuntimeError("InitialStateBuffer is empty: add at least one initial state before sampling.")
        data, info = self._buffer.sample(batch_size, return_info=True)
        data.set("index", torch.as_tensor(info["index"], dtype=torch.int64, device=data.device))
        return data

    def states(self) -> TensorDictBase:
        """Every stored example, in slot order (batch ``[len(self)]``)."""
        if len(self) == 0:
            raise RuntimeError("InitialStateBuffer is empty.")
        return self._buffer[: len(self)]

    def state_dict(self) -> dict:
        return {"max_size": self.max_size, "state_keys": self.state_keys, "buffer": self._buffer.state_dict()}

    def load_state_dict(self, state_dict: dict) -> None:
        if state_dict["max_size"] != self.max_size:
            raise ValueError(
                f"cannot load an InitialStateBuffer of max_size {state_dict['max_size']} into one of max_size {self.max_size}."
            )
        self._buffer.load_state_dict(state_dict["buffer"])

    def __repr__(self) -> str:
        return f"{type(self).__name__}(size={len(self)}, max_size={self.max_size}, state_keys={self.state_keys})"
