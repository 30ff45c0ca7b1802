"""The recipe's replay buffers: what each keeps, and the reset buffer's n-step transform and sampler."""
from __future__ import annotations

from omegaconf import DictConfig, OmegaConf
from torchrl.data import LazyTensorStorage, ReplayBuffer

from agents import Agent
from torchrl_reset import EpisodeWindowSampler, NStepStateTransform

__all__ = ["make_buffers", "buffer_keys"]


def make_buffers(cfg: DictConfig) -> tuple[ReplayBuffer, ReplayBuffer]:
    forward_rb = ReplayBuffer(storage=LazyTensorStorage(cfg.forward.buffer_size), batch_size=cfg.forward.batch_size)
    ours = cfg.algo.name == "ours"
    transform = NStepStateTransform(cfg.algo.n_steps) if ours else None
    episodes = ours and OmegaConf.select(cfg, "algo.nstep_sampling", default="episode") == "episode"
    sampler = EpisodeWindowSampler(cfg.algo.n_steps) if episodes else None
    reset_rb = ReplayBuffer(storage=LazyTensorStorage(cfg.reset.buffer_size), batch_size=cfg.reset.batch_size,
                            transform=transform, sampler=sampler)
    return forward_rb, reset_rb


def buffer_keys(cfg: DictConfig, forward: Agent, reset: Agent) -> tuple[list, list]:
    """The entries each replay buffer keeps: what its loss (and, for ours, the n-step transform) reads.

    A collected step carries about 24 entries (flags, scores, the trigger's outputs, phase tags);
    the forward buffer needs 6 and the reset buffer 6 to 8. Writing, sampling and checkpointing
    fewer columns is faster and smaller.
    """
    def nested(key) -> tuple:
        return (key,) if isinstance(key, str) else tuple(key)

    states = [nested(key) for key in (*reset.model.in_keys[:-1], *reset.actor.in_keys)]
    reset_keys = [*states, *[("next", *key) for key in states], ("action",), ("next", "done"), ("next", "terminated")]
    if cfg.algo.name == "ours":
        reset_keys.append(("collector", "traj_ids"))  # NStepStateTransform's trajectory boundaries
    else:
        reset_keys += [("next", "reset_reward"), ("next", "reset_success")]  # lnt_batch's rewards
    forward_keys = [nested(key) for key in forward.loss.in_keys]
    return list(dict.fromkeys(forward_keys)), list(dict.fromkeys(reset_keys))
