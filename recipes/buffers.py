"""The recipe's replay buffers: what each keeps, and the reset buffer's n-step transform and sampler."""
from __future__ import annotations

from omegaconf import DictConfig
from torchrl.data import LazyTensorStorage, ReplayBuffer

from absent_keys import setting
from agents import Agent
from reset_agents import reset_kind
from torchrl_reset import EpisodeWindowSampler

__all__ = ["make_buffers", "buffer_keys", "fallback_count", "restore_fallback_count"]


def make_buffers(cfg: DictConfig) -> tuple[ReplayBuffer, ReplayBuffer]:
    """The forward agent's buffer (with ``forward.sampling: episode``, the release's episode-first sampler
    with windows of one step) and the reset agent's (:meth:`~reset_agents.ResetAgentKind.replay`; ours': the
    n-step transform and the release's episode-first sampler)."""
    episodes_first = setting(cfg, "forward.sampling") == "episode"
    forward_rb = ReplayBuffer(storage=LazyTensorStorage(int(cfg.forward.buffer_size)),
                              batch_size=cfg.forward.batch_size,
                              sampler=EpisodeWindowSampler(1) if episodes_first else None)
    return forward_rb, reset_kind(cfg).replay(cfg, int(cfg.reset.buffer_size), cfg.reset.batch_size)


def fallback_count(rb) -> int | None:
    """The buffer's sampler fallback count (:class:`~torchrl_reset.EpisodeWindowSampler`); None without that
    sampler."""
    return getattr(rb.sampler, "fallbacks", None)


def restore_fallback_count(rb, count: int | None) -> None:
    """Sets the buffer's sampler fallback count back (``count`` from :func:`fallback_count`)."""
    if count is not None:
        rb.sampler.fallbacks = count


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
    reset_keys = reset_kind(cfg).buffer_keys(cfg, reset)
    return list(dict.fromkeys(forward_keys)), list(dict.fromkeys(reset_keys))
