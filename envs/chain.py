"""A chain with a ditch: the smallest task on which the whole method can be run and checked."""
from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

__all__ = ["ChainEnv"]


class ChainEnv(EnvBase):
    """A walk on ``num_states`` cells with a ditch at the right end, for tests and demonstrations.

    The agent stands on cell ``x`` in ``0 .. num_states - 1`` and starts on cell 0 (the initial
    state). Cells ``x >= ditch`` form the ditch: once in it the agent can no longer move and only a
    manual reset (``env.reset()``) brings it back, like the cliff tasks' ditch.

    ======================  ===========================================================
    observation             one-hot of ``x`` (``num_states`` floats)
    action                  one number in [-1, 1]: below -1/3 steps left, above 1/3 right,
                            otherwise stays; walls at both ends
    reward (forward task)   ``x / (ditch - 1)`` outside the ditch, 0 in it (go right, but
                            not over the edge)
    ``reset_success``       ``x == 0``
    ``reset_reward``        ``1 - x / (num_states - 1)`` outside the ditch, 0 in it
    ``irrecoverable``       ``x >= ditch``
    start state             ``x = 0`` (``start`` overrides it)
    ======================  ===========================================================

    A reset policy that always steps left reaches the initial state from cell ``k`` in exactly
    ``k`` steps and stays there, so its success probability is ``gamma ** k`` (docs/method.md section 1).
    The env never terminates by itself. It is deterministic; ``get_simulator_state`` / ``set_simulator_state``
    save and restore it.

    Args:
        num_states (int): number of cells, >= 2. Defaults to 10.
        ditch (int, optional): first ditch cell, in ``1 .. num_states``; ``num_states`` (default)
            means no ditch.
        start (int): the start cell. Defaults to 0.

    Examples:
        >>> import torch
        >>> from torchrl.envs.utils import check_env_specs
        >>> from torchrl_reset_envs import ChainEnv
        >>> env = ChainEnv(num_states=6, ditch=4)
        >>> check_env_specs(env)
        >>> td = env.reset()
        >>> td["action"] = torch.ones(1)
        >>> td = env.step(td)
        >>> td["next", "observation"].argmax().item(), td["next", "reward"].item()
        (1, 0.3333333432674408)
    """

    def __init__(self, num_states: int = 10, ditch: int | None = None, start: int = 0, device=None) -> None:
        if isinstance(num_states, bool) or not isinstance(num_states, int) or num_states < 2:
            raise ValueError(f"num_states must be an integer >= 2, got {num_states!r}.")
        ditch = num_states if ditch is None else ditch
        if not (1 <= ditch <= num_states):
            raise ValueError(f"ditch must lie in 1..{num_states}, got {ditch!r}.")
        if not (0 <= start < ditch):
            raise ValueError(f"start must lie in 0..{ditch - 1} (outside the ditch), got {start!r}.")
        super().__init__(device=device, batch_size=torch.Size([]))
        self.num_states = num_states
        self.ditch = ditch
        self.start = start
        self._position = start
        flag = Categorical(2, shape=(1,), dtype=torch.bool)
        self.observation_spec = Composite(
            observation=Bounded(0.0, 1.0, shape=(num_states,)),
            reset_success=flag.clone(),
            irrecoverable=flag.clone(),
            reset_reward=Unbounded(shape=(1,)),
        )
        self.action_spec = Bounded(-1.0, 1.0, shape=(1,))
        self.reward_spec = Unbounded(shape=(1,))

    def _observe(self) -> TensorDict:
        x = self._position
        in_ditch = x >= self.ditch
        observation = torch.zeros(self.num_states)
        observation[x] = 1.0
        return TensorDict(
            observation=observation,
            reset_success=torch.tensor([x == 0]),
            irrecoverable=torch.tensor([in_ditch]),
            reset_reward=torch.tensor([0.0 if in_ditch else 1.0 - x / (self.num_states - 1)]),
            done=torch.zeros(1, dtype=torch.bool),
            terminated=torch.zeros(1, dtype=torch.bool),
        )

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        self._position = self.start
        return self._observe()

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = tensordict.get("action")
        if action.shape != (1,):
            raise ValueError(f"ChainEnv expects an action of shape (1,), got {tuple(action.shape)}.")
        a = float(action)
        if a != a:
            raise ValueError("ChainEnv got a NaN action.")
        if self._position < self.ditch:
            move = 1 if a > 1 / 3 else (-1 if a < -1 / 3 else 0)
            self._position = min(max(self._position + move, 0), self.num_states - 1)
        out = self._observe()
        x = self._position
        reward = 0.0 if x >= self.ditch else x / max(self.ditch - 1, 1)
        out.set("reward", torch.tensor([reward]))
        return out

    def _set_seed(self, seed: int | None) -> None:
        # Deterministic dynamics: nothing to seed.
        return None

    @property
    def position(self) -> int:
        return self._position

    def get_simulator_state(self) -> dict:
        return {"position": self._position}

    def set_simulator_state(self, state: dict) -> None:
        self._position = int(state["position"])
