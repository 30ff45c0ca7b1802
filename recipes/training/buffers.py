"""The recipe's replay buffers: what each keeps, and the reset buffer's n-step transform and sampler."""
from __future__ import annotations

from torchrl.data import LazyTensorStorage, ReplayBuffer

from torchrl_reset_recipes.training.agents import Agent
from torchrl_reset_recipes.training.run_spec import RunSpec
from torchrl_reset import EpisodeWindowSampler

__all__ = ["make_buffers", "buffer_keys", "fallback_count", "restore_fallback_count"]


def make_buffers(spec: RunSpec) -> tuple[ReplayBuffer, ReplayBuffer]:
    """The forward agent's buffer (with ``forward.sampling: episode``, the release's episode-first sampler
    with windows of one step) and the reset agent's (:meth:`~reset_agents.ResetAgentKind.replay`; ours': the
    n-step transform and the release's episode-first sampler)."""
    cfg, episodes_first = spec.cfg, spec["forward.sampling"] == "episode"
    forward_rb = ReplayBuffer(storage=LazyTensorStorage(int(cfg.forward.buffer_size)),
                              batch_size=cfg.forward.batch_size,
                              sampler=EpisodeWindowSampler(1) if episodes_first else None)
    return forward_rb, spec.kind.replay(spec, int(cfg.reset.buffer_size), cfg.reset.batch_size)


def fallback_count(rb) -> int | None:
    """The buffer's sampler fallback count (:class:`~torchrl_reset.EpisodeWindowSampler`); None without that
    sampler."""
    return getattr(rb.sampler, "fallbacks", None)


def restore_fallback_count(rb, count: int | None) -> None:
    """Sets the buffer's sampler fallback count back (``count`` from :func:`fallback_count`)."""
    if count is not None:
        rb.sampler.fallbacks = count


def buffer_keys(spec: RunSpec, forward: Agent, reset: Agent) -> tuple[list, list]:
    """The entries each replay buffer keeps: what its loss reads (``loss.in_keys``), its end flags and what
    its sampler or transform reads (:meth:`~reset_agents.ResetAgentKind.buffer_keys`).

    A collected step carries about 24 entries (flags, scores, the trigger's outputs, phase tags);
    the forward buffer needs 6 and the reset buffer 6 to 8. Writing, sampling and checkpointing
    fewer columns is faster and smaller.
    """
    forward_keys = [(key,) if isinstance(key, str) else tuple(key) for key in forward.loss.in_keys]
    if spec["forward.sampling"] == "episode":
        forward_keys.append(("collector", "traj_ids"))  # the episode-first sampler's episodes
    reset_keys = spec.kind.buffer_keys(spec, reset)
    return list(dict.fromkeys(forward_keys)), list(dict.fromkeys(reset_keys))
