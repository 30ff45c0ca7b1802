"""The run's random streams: one shared generator (the default), or one for the actor and one for the learner.

``learner.streams: shared`` keeps today's single stream: torch's global generator serves acting (the
exploration noise, a stochastic actor's samples) and learning (replay and example sampling, the actor's
reparameterised samples, the rows of the release's actor step) alike, so every committed result reproduces.
``separate`` gives acting and learning a stream each, seeded from the run's seed (the actor's as the shared
stream would be, the learner's from ``seed + LEARNER_SEED_OFFSET``): what an actor process and a learner
process each hold when they run apart, so that a lockstep run of two processes can equal a run of one.
Only torch's CPU generator is split: the envs and the evaluation draw from their own generators.
"""
from __future__ import annotations

import contextlib

import torch

__all__ = ["STREAMS", "LEARNER_SEED_OFFSET", "RandomStreams"]

STREAMS = ("shared", "separate")
#: the learner's stream is seeded ``seed + LEARNER_SEED_OFFSET`` (``separate``)
LEARNER_SEED_OFFSET = 7_919


class RandomStreams:
    """Which generator state torch's global generator holds: ``use("actor")`` / ``use("learner")`` switch it
    (``separate``) or do nothing (``shared``). A switch stores the outgoing stream's state and loads the incoming
    one's, so each stream goes on exactly where it stopped, however the two interleave.

    Examples:
        >>> streams = RandomStreams("separate", seed=0)
        >>> with streams.use("actor"):
        ...     a = torch.rand(2)
        >>> with streams.use("learner"):
        ...     _ = torch.rand(5)  # the learner's draws do not move the actor's stream
        >>> with streams.use("actor"):
        ...     b = torch.rand(2)
        >>> _ = torch.manual_seed(0); bool(torch.equal(torch.cat([a, b]), torch.rand(4)))
        True
    """

    def __init__(self, mode: str = "shared", seed: int = 0) -> None:
        if mode not in STREAMS:
            raise ValueError(f"learner.streams must be one of {', '.join(STREAMS)}, got {mode!r}.")
        self.mode = mode
        self.active: str | None = None
        self.states: dict[str, torch.Tensor] = {}
        if mode == "separate":
            with torch.random.fork_rng(devices=[]):
                torch.manual_seed(seed)
                self.states["actor"] = torch.get_rng_state()
                torch.manual_seed(seed + LEARNER_SEED_OFFSET)
                self.states["learner"] = torch.get_rng_state()

    @contextlib.contextmanager
    def use(self, name: str):
        """Torch's global generator holds stream ``name`` inside (and after: switching back is lazy)."""
        if self.mode == "separate" and name != self.active:
            if name not in self.states:
                raise KeyError(f"no random stream {name!r}; the streams are {sorted(self.states)}.")
            if self.active is not None:
                self.states[self.active] = torch.get_rng_state()
            torch.set_rng_state(self.states[name])
            self.active = name
        yield

    def state_dict(self) -> dict:
        """Every stream's state as it stands now (the active one read from the global generator)."""
        if self.mode == "shared":
            return {"mode": "shared"}
        states = dict(self.states)
        if self.active is not None:
            states[self.active] = torch.get_rng_state()
        return {"mode": "separate", "states": states, "active": self.active}

    def load_state_dict(self, state: dict | None) -> None:
        """Restores :meth:`state_dict`'s streams (the active one into the global generator)."""
        mode = "shared" if state is None else state["mode"]
        if mode != self.mode:
            raise ValueError(f"the checkpoint's random streams are {mode!r}, the run's learner.streams is "
                             f"{self.mode!r}: resume with learner.streams={mode}.")
        if mode == "separate":
            self.states = {k: v.clone() for k, v in state["states"].items()}
            self.active = state["active"]
            if self.active is not None:
                torch.set_rng_state(self.states[self.active])
