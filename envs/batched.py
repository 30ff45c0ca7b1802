"""N copies of a simulated task in one torchrl env of batch size ``[N]``, stepped and reset row by row."""
from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from .tasks import make_gym_env, task_spec

__all__ = ["BatchedTaskEnv"]


class BatchedTaskEnv(EnvBase):
    """``num_envs`` copies of a task, each its own simulator, as one env with batch size ``[num_envs]``.

    The entries are those of :func:`~torchrl_reset_envs.make_env` with a leading env dimension:
    ``observation`` ``[N, d]``, ``reward``, ``done``, ``terminated``, ``truncated``,
    ``reset_success``, ``reset_reward`` and ``irrecoverable`` ``[N, 1]``. The copies are
    independent: each row is stepped by its own simulator, and

    - a **partial step** (a boolean ``"_step"`` entry ``[N]`` in the input, torchrl's convention,
      which :class:`~torchrl_reset.ResetTriggerTransform` writes for the rows it stops) steps only
      the rows where it is True; the other rows keep their state, reward 0;
    - a **partial reset** (``"_reset"`` ``[N, 1]``) resets only the rows where it is True and returns
      the others' current state.

    Row ``i`` seeded ``seeds[i]`` draws exactly what ``make_env(task, seed=seeds[i])`` draws, so a
    copy follows the single env's trajectory under the same actions. The copies' simulator state is
    saved and restored with :meth:`get_simulator_state` / :meth:`set_simulator_state` (one entry per
    row), so :class:`~torchrl_reset.BatchedDualCollector` resumes exactly.

    Args:
        task (str): a simulated task of :data:`~torchrl_reset_envs.TASKS` (the UR3 tasks are one arm each).
        num_envs (int, optional): the number of copies; defaults to ``len(seeds)``.

    Keyword Args:
        seeds (sequence of int, optional): one seed per copy.
        device: the tensordicts' device (the simulators run on the CPU).
        **kwargs: passed to every copy's gymnasium class.

    Examples:
        >>> from torchrl.envs.utils import check_env_specs
        >>> from torchrl_reset_envs import BatchedTaskEnv
        >>> env = BatchedTaskEnv("peg_insertion_insert", seeds=[0, 1, 2])
        >>> check_env_specs(env)
        >>> env.reset()["observation"].shape
        torch.Size([3, 14])
    """

    def __init__(self, task: str, num_envs: int | None = None, *, seeds: Sequence[int] | None = None,
                 device: torch.device | str | None = None, **kwargs) -> None:
        spec = task_spec(task)
        if spec.gym_id is None:
            raise ValueError(f"{spec.name} is a robot (one arm is one env): BatchedTaskEnv batches the simulated tasks.")
        if seeds is not None:
            seeds = [int(s) for s in seeds]
            if num_envs is not None and num_envs != len(seeds):
                raise ValueError(f"num_envs ({num_envs}) differs from the number of seeds ({len(seeds)}).")
            num_envs = len(seeds)
        if num_envs is None or isinstance(num_envs, bool) or not isinstance(num_envs, int) or num_envs < 1:
            raise ValueError(f"num_envs must be a positive integer (or pass seeds), got {num_envs!r}.")
        super().__init__(device=device, batch_size=torch.Size([num_envs]))
        self.task_spec = spec
        self.forward_horizon, self.p_thresh = spec.forward_horizon, spec.p_thresh
        self.envs = [make_gym_env(spec, **kwargs) for _ in range(num_envs)]
        first = self.envs[0]
        obs_dim = first.observation_space.shape[0]
        low = torch.as_tensor(first.action_space.low, dtype=torch.float32)
        high = torch.as_tensor(first.action_space.high, dtype=torch.float32)
        n, flag = num_envs, Categorical(2, shape=(num_envs, 1), dtype=torch.bool, device=self.device)
        self.observation_spec = Composite(
            observation=Unbounded(shape=(n, obs_dim), dtype=torch.float32, device=self.device),
            reset_success=flag.clone(),
            reset_reward=Unbounded(shape=(n, 1), dtype=torch.float32, device=self.device),
            irrecoverable=flag.clone(),
            shape=(n,),
        )
        self.action_spec = Bounded(low.expand(n, -1).clone(), high.expand(n, -1).clone(), shape=(n, low.shape[0]),
                                   dtype=torch.float32, device=self.device)
        self.reward_spec = Unbounded(shape=(n, 1), dtype=torch.float32, device=self.device)
        self.full_done_spec = Composite(done=flag.clone(), terminated=flag.clone(), truncated=flag.clone(), shape=(n,))
        self._obs = np.zeros((n, obs_dim), dtype=np.float32)
        self._success = np.zeros((n, 1), dtype=bool)
        self._reset_reward = np.zeros((n, 1), dtype=np.float32)
        self._irrecoverable = np.zeros((n, 1), dtype=bool)
        if seeds is not None:
            for env, seed in zip(self.envs, seeds):
                env.reset(seed=seed)  # as make_env(task, seed=...) seeds its env

    def _rows(self, mask: torch.Tensor | None) -> list[int]:
        if mask is None:
            return list(range(self.batch_size[0]))
        return mask.reshape(-1).nonzero().flatten().tolist()

    def _store(self, i: int, observation: np.ndarray, info: dict[str, Any]) -> None:
        self._obs[i] = observation
        self._success[i, 0] = bool(info["reset_success"])
        self._reset_reward[i, 0] = float(info["reset_reward"])
        self._irrecoverable[i, 0] = bool(info["irrecoverable"])

    def _output(self, **extra: torch.Tensor) -> TensorDict:
        n = self.batch_size[0]
        false = torch.zeros((n, 1), dtype=torch.bool)
        return TensorDict(
            {
                "observation": torch.from_numpy(self._obs.copy()),
                "reset_success": torch.from_numpy(self._success.copy()),
                "reset_reward": torch.from_numpy(self._reset_reward.copy()),
                "irrecoverable": torch.from_numpy(self._irrecoverable.copy()),
                "done": false, "terminated": false.clone(), "truncated": false.clone(),
                **extra,
            },
            batch_size=self.batch_size,
        ).to(self.device)

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        mask = None if tensordict is None else tensordict.get("_reset", None)
        for i in self._rows(mask):
            observation, info = self.envs[i].reset()
            self._store(i, observation, info)
        return self._output()

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        actions = tensordict.get("action").detach().cpu().numpy()
        reward = np.zeros((self.batch_size[0], 1), dtype=np.float32)
        terminated = np.zeros((self.batch_size[0], 1), dtype=bool)
        for i in self._rows(tensordict.get("_step", None)):
            observation, r, term, _, info = self.envs[i].step(actions[i])
            self._store(i, observation, info)
            reward[i, 0], terminated[i, 0] = r, term
        out = self._output(reward=torch.from_numpy(reward))
        if terminated.any():
            out.set("terminated", torch.from_numpy(terminated).to(self.device))
            out.set("done", torch.from_numpy(terminated).to(self.device))
        return out

    def _set_seed(self, seed: int | None) -> None:
        """Seeds copy ``i`` with ``seed + i`` (a copy's start-state noise)."""
        for i, env in enumerate(self.envs):
            env.reset(seed=None if seed is None else seed + i)

    def get_simulator_state(self) -> list[dict[str, Any]]:
        """Every copy's simulator state (physics, latched flags, random generator) and its last outputs."""
        return [{**env.get_simulator_state(), "observation": self._obs[i].copy(), "reset_success": bool(self._success[i, 0]),
                 "reset_reward": float(self._reset_reward[i, 0]), "irrecoverable_flag": bool(self._irrecoverable[i, 0])}
                for i, env in enumerate(self.envs)]

    def set_simulator_state(self, state: Sequence[dict[str, Any]]) -> None:
        if len(state) != len(self.envs):
            raise ValueError(f"a state of {len(state)} copies cannot be restored into {len(self.envs)}.")
        for i, (env, row) in enumerate(zip(self.envs, state)):
            env.set_simulator_state(row)
            self._obs[i] = row["observation"]
            self._success[i, 0], self._reset_reward[i, 0] = row["reset_success"], row["reset_reward"]
            self._irrecoverable[i, 0] = row["irrecoverable_flag"]

    def get_copy_state(self, i: int) -> dict[str, Any]:
        """Copy ``i``'s simulator state as the single env (``make_env``) gives it."""
        return self.envs[i].get_simulator_state()

    def set_copy_state(self, i: int, state: dict[str, Any], outputs: dict[str, Any]) -> None:
        """Restores copy ``i`` from a single env's simulator state and its last outputs (a root tensordict
        of that env as a dict: ``observation``, ``reset_success``, ``reset_reward``, ``irrecoverable``)."""
        self.envs[i].set_simulator_state(state)
        info = {key: np.asarray(outputs[key]).reshape(-1)[0] for key in ("reset_success", "reset_reward", "irrecoverable")}
        self._store(i, np.asarray(outputs["observation"]).reshape(self._obs[i].shape), info)

    def close(self, *, raise_if_closed: bool = True) -> None:
        for env in self.envs:
            env.close()
        super().close(raise_if_closed=raise_if_closed)
