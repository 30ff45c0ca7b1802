"""The recipe's replay buffers: what each keeps, and the reset buffer's n-step transform and sampler."""
from __future__ import annotations

from pathlib import Path

import torch
from omegaconf import DictConfig
from torchrl.data import LazyTensorStorage, ReplayBuffer

from absent_keys import setting
from agents import Agent
from run_files import arm_count
from reset_agents import reset_kind
from torchrl_reset import EpisodeWindowSampler

__all__ = ["make_buffers", "buffer_keys", "ArmReplay", "fallback_counts", "restore_fallbacks"]


def make_buffers(cfg: DictConfig) -> tuple[ReplayBuffer, ReplayBuffer | ArmReplay]:
    """The forward agent's buffer (with ``forward.sampling: episode``, the release's episode-first sampler
    with windows of one step) and the reset agent's (:meth:`~reset_agents.ResetAgentKind.replay`; ours': the
    n-step transform and the release's episode-first sampler). With ``arms``, ours' reset buffer is one per
    arm, sampled as one (:class:`ArmReplay`): the n-step windows need each arm's steps in time order; so is
    the forward buffer with episode-first sampling, whose episodes are each arm's runs of consecutive steps
    (the arms' capacity that of one run's buffer, split evenly)."""
    episodes_first = setting(cfg, "forward.sampling") == "episode"
    kind, arms = reset_kind(cfg), arm_count(cfg)

    def forward_buffer(size: int, batch_size: int | None) -> ReplayBuffer:
        return ReplayBuffer(storage=LazyTensorStorage(size), batch_size=batch_size,
                            sampler=EpisodeWindowSampler(1) if episodes_first else None)

    if arms is not None and episodes_first:  # each arm's episodes whole, in a buffer of its own
        size = -(-int(cfg.forward.buffer_size) // arms)
        forward_rb = ArmReplay([forward_buffer(size, None) for _ in range(arms)], batch_size=cfg.forward.batch_size)
    else:
        forward_rb = forward_buffer(int(cfg.forward.buffer_size), cfg.forward.batch_size)
    if arms is None or not kind.time_ordered_replay:  # LNT's rows are single transitions: one buffer serves every arm
        return forward_rb, kind.replay(cfg, int(cfg.reset.buffer_size), cfg.reset.batch_size)
    size = -(-int(cfg.reset.buffer_size) // arms)  # the arms share the capacity of one run's buffer
    return forward_rb, ArmReplay([kind.replay(cfg, size, None) for _ in range(arms)], batch_size=cfg.reset.batch_size)


def fallback_counts(rb) -> list[int | None]:
    """Each buffer's sampler fallback count (one per arm of an :class:`ArmReplay`); None without that sampler."""
    return [getattr(b.sampler, "fallbacks", None) for b in getattr(rb, "buffers", [rb])]


def restore_fallbacks(rb, counts: list[int | None]) -> None:
    """Sets each buffer's sampler fallback count back (``counts`` from :func:`fallback_counts`)."""
    for buffer, count in zip(getattr(rb, "buffers", [rb]), counts):
        if count is not None:
            buffer.sampler.fallbacks = count


class ArmReplay:
    """One agent's replay buffer over N arms: each arm's rows in a buffer of its own, sampled as one.

    A row goes to the buffer of its arm (``("collector", "env_ids")``, which :class:`~torchrl_reset.BatchedDualCollector`
    writes), so each arm's transform sees its steps in time order (the n-step state of
    :class:`~torchrl_reset.NStepStateTransform`) and each arm's sampler its episodes whole. A sample of B
    rows splits B over the arms in proportion to the rows they hold (one multinomial draw; none with
    one arm, which then samples exactly as a single buffer), and each arm draws its share by its own
    sampler: uniform rows over all arms with uniform samplers; episodes first, then a window, within
    an arm with :class:`~torchrl_reset.EpisodeWindowSampler`. ``dumps`` / ``loads`` save every arm's
    buffer in ``arm<i>/``.
    """

    def __init__(self, buffers: list[ReplayBuffer], *, batch_size: int) -> None:
        if not buffers:
            raise ValueError("ArmReplay needs one buffer per arm, got none.")
        self.buffers, self.batch_size = list(buffers), int(batch_size)

    def __len__(self) -> int:
        return sum(len(b) for b in self.buffers)

    def extend(self, data) -> None:
        arms = data.get(("collector", "env_ids"), None)
        if arms is None:
            raise KeyError("ArmReplay routes rows by their arm: the data need ('collector', 'env_ids').")
        arms = arms.reshape(-1)
        for arm in arms.unique().tolist():
            if not 0 <= arm < len(self.buffers):
                raise IndexError(f"a row of arm {arm} for an ArmReplay of {len(self.buffers)} arms.")
            self.buffers[arm].extend(data[arms == arm])

    def sample(self, batch_size: int | None = None, return_info: bool = False):
        """B rows over the arms; with ``return_info``, also ``{"fallback": bool}``: whether an arm's
        :class:`~torchrl_reset.EpisodeWindowSampler` fell back to uniform rows for its share."""
        size = self.batch_size if batch_size is None else int(batch_size)
        if len(self.buffers) == 1:
            return self.buffers[0].sample(size, return_info=return_info)
        held = torch.tensor([len(b) for b in self.buffers], dtype=torch.float64)
        if not held.sum():
            raise RuntimeError("ArmReplay: cannot sample from empty buffers.")
        shares = torch.bincount(torch.multinomial(held, size, replacement=True), minlength=len(self.buffers))
        parts = [b.sample(int(k), return_info=True) for b, k in zip(self.buffers, shares.tolist()) if k]
        data = torch.cat([part for part, _ in parts], 0)
        return (data, {"fallback": any(info.get("fallback", False) for _, info in parts)}) if return_info else data

    def dumps(self, path) -> None:
        Path(path).mkdir(parents=True, exist_ok=True)
        for i, buffer in enumerate(self.buffers):
            if len(buffer):  # torchrl cannot dump a buffer that never received data
                buffer.dumps(Path(path) / f"arm{i}")

    def loads(self, path) -> None:
        for i, buffer in enumerate(self.buffers):
            if (Path(path) / f"arm{i}").exists():
                buffer.loads(Path(path) / f"arm{i}")


def buffer_keys(cfg: DictConfig, forward: Agent, reset: Agent) -> tuple[list, list]:
    """The entries each replay buffer keeps: what its loss reads (``loss.in_keys``), its end flags and what
    its sampler or transform reads (:meth:`~reset_agents.ResetAgentKind.buffer_keys`).

    A collected step carries about 24 entries (flags, scores, the trigger's outputs, phase tags);
    the forward buffer needs 6 and the reset buffer 6 to 8. Writing, sampling and checkpointing
    fewer columns is faster and smaller.
    """
    forward_keys = [(key,) if isinstance(key, str) else tuple(key) for key in forward.loss.in_keys]
    if setting(cfg, "forward.sampling") == "episode":
        forward_keys.append(("collector", "traj_ids"))  # the episode-first sampler's episodes
        if arm_count(cfg) is not None:
            forward_keys.append(("collector", "env_ids"))  # ArmReplay's routing
    reset_keys = reset_kind(cfg).buffer_keys(cfg, reset, arms=arm_count(cfg) is not None)
    return list(dict.fromkeys(forward_keys)), list(dict.fromkeys(reset_keys))
