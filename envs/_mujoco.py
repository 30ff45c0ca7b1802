"""Shared machinery of the MuJoCo tasks: model building, checked stepping, task flags, state and rendering."""
from __future__ import annotations

import math
import os
from typing import Any, ClassVar

import gymnasium
import mujoco
import numpy as np
import torch
from gymnasium import spaces

__all__ = ["MujocoResetEnv", "RenderingUnavailableError", "tolerance", "asset_path", "get_physics", "set_physics"]

_STATE_SPEC = mujoco.mjtState.mjSTATE_INTEGRATION


def get_physics(model: mujoco.MjModel, data: mujoco.MjData) -> torch.Tensor:
    """The full integration state (``mj_getState``: time, qpos, qvel, act, warm start, controls...) as float64."""
    physics = np.empty(mujoco.mj_stateSize(model, _STATE_SPEC))
    mujoco.mj_getState(model, data, physics, _STATE_SPEC)
    return torch.from_numpy(physics)


def set_physics(model: mujoco.MjModel, data: mujoco.MjData, physics, owner: str = "env") -> None:
    """Restore a state from :func:`get_physics`; a clear error when it belongs to another model."""
    physics = torch.as_tensor(physics, dtype=torch.float64).numpy()
    expected = mujoco.mj_stateSize(model, _STATE_SPEC)
    if physics.shape != (expected,):
        raise ValueError(
            f"{owner}: simulator state has {physics.size} numbers, this model needs {expected} "
            "(a state saved from another task?)."
        )
    mujoco.mj_setState(model, data, physics, _STATE_SPEC)
    mujoco.mj_forward(model, data)

_TANH_SQUARED_W = math.atanh(math.sqrt(0.95))


def tolerance(x, lo: float, hi: float, margin: float):
    """The paper's ``Cond(x; lo, hi, m)``: 1 inside ``[lo, hi]``, ``1 - tanh(w d)**2`` at distance ``d`` outside.

    ``w = atanh(sqrt(0.95)) / m``, so the value is 0.05 at ``d = m`` (the control suite's tolerance with
    a ``tanh_squared`` sigmoid). Works on floats and numpy arrays.

    Examples:
        >>> round(float(tolerance(10.0, 9.0, 11.0, 7.0)), 6), round(float(tolerance(4.0, 9.0, 11.0, 5.0)), 6)
        (1.0, 0.05)
    """
    if margin <= 0:
        raise ValueError(f"margin must be > 0, got {margin!r}.")
    d = np.maximum(np.maximum(lo - np.asarray(x, dtype=np.float64), np.asarray(x, dtype=np.float64) - hi), 0.0)
    out = 1.0 - np.tanh(_TANH_SQUARED_W / margin * d) ** 2
    return float(out) if out.ndim == 0 else out


def asset_path(package: str, relative: str) -> str:
    """Path of a model file shipped by ``package`` (``"gymnasium"`` or ``"dm_control"``)."""
    if package == "gymnasium":
        root = os.path.join(os.path.dirname(gymnasium.__file__), "envs", "mujoco", "assets")
    elif package == "dm_control":
        import dm_control

        root = os.path.join(os.path.dirname(dm_control.__file__), "suite")
    else:
        raise ValueError(f"unknown asset package {package!r}")
    path = os.path.join(root, relative)
    if not os.path.exists(path):
        raise FileNotFoundError(f"{package} does not ship {relative!r} (looked in {root}); check the installed version.")
    return path


class RenderingUnavailableError(RuntimeError):
    """Off-screen rendering needs an OpenGL context that this process could not create."""


_RENDERING_HELP = (
    "Off-screen rendering needs an OpenGL backend. Set MUJOCO_GL=egl (needs libEGL: an NVIDIA driver, or Mesa's "
    "libegl1 and libgl1-mesa-dri) or MUJOCO_GL=osmesa (needs libOSMesa: apt install libosmesa6) before Python "
    "imports mujoco (importing torchrl imports it). Everything except render() works without it."
)


class MujocoResetEnv(gymnasium.Env):
    """Base class of the MuJoCo tasks.

    A subclass builds its model (``_build_spec``), sets its start state (``_reset_state``) and defines
    ``_observation``, ``_forward_reward`` and ``_status``. This class steps the physics ``frame_skip``
    times per action, checks actions, latches the irrecoverable flag, saves and restores the simulator
    state, and renders off-screen.

    Actions are taken as sent, as in the authors' release: an action outside the action box (a policy's
    output plus unclipped exploration noise) reaches the motors clamped to their control range (as
    MuJoCo clamps a limited motor), and the rewards' control terms see it unclipped. The action box is
    the control range, or ``[-action_bound, action_bound]`` where a task's policy uses less of it.

    Every step's ``info`` holds ``reset_success`` (``np.bool_``, the at-initial-state check), ``reset_reward``
    (``np.float64`` in [0, 1], the shaped reset reward) and ``irrecoverable`` (``np.bool_``; once set it stays set until
    :meth:`reset`; always ``False`` for tasks without irrecoverable states), plus the forward reward's
    terms under ``reward_*`` names. :meth:`reset` returns the same keys. The env never terminates or
    truncates by itself: episode lengths belong to the collector.
    """

    metadata: ClassVar[dict] = {"render_modes": ["rgb_array"], "render_fps": 20}

    #: Task constants, set by subclasses.
    frame_skip: ClassVar[int] = 1
    forward_horizon: ClassVar[int] = 0
    p_thresh: ClassVar[float] = 0.0
    has_irrecoverable: ClassVar[bool] = False
    default_camera: ClassVar[str | int] = -1
    #: The action box ``[-action_bound, action_bound]`` where the task's actions are narrower than the
    #: motors' control range (``None``: the control range). Actions reach the motors unscaled.
    action_bound: ClassVar[float | None] = None

    def __init__(self, *, render_mode: str | None = None, width: int = 480, height: int = 480, camera: str | int | None = None):
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}.")
        for name, value in (("width", width), ("height", height)):
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"{name} must be a positive integer, got {value!r}.")
        mj_spec = self._build_spec()
        mj_spec.visual.global_.offwidth = max(width, mj_spec.visual.global_.offwidth)
        mj_spec.visual.global_.offheight = max(height, mj_spec.visual.global_.offheight)
        self.model = mj_spec.compile()
        self.data = mujoco.MjData(self.model)
        self._compiled()
        self.render_mode = render_mode
        self.width, self.height = width, height
        self.camera = self.default_camera if camera is None else camera
        self._renderer = None
        self._irrecoverable = False
        self.dt = float(self.model.opt.timestep) * self.frame_skip
        self.metadata = {**type(self).metadata, "render_fps": int(round(1.0 / self.dt))}
        ctrl_low, ctrl_high = self.model.actuator_ctrlrange.T.astype(np.float64)
        self._ctrl_low, self._ctrl_high = ctrl_low, ctrl_high
        low, high = ctrl_low, ctrl_high
        if self.action_bound is not None:
            low, high = np.maximum(low, -self.action_bound), np.minimum(high, self.action_bound)
        self.action_space = spaces.Box(low.astype(np.float32), high.astype(np.float32), dtype=np.float32)
        self._action_low, self._action_high = low, high
        mujoco.mj_forward(self.model, self.data)
        obs_dim = self._observation().shape[0]
        self.observation_space = spaces.Box(-np.inf, np.inf, shape=(obs_dim,), dtype=np.float32)

    # ------------------------------------------------------------------ subclass hooks
    def _build_spec(self) -> mujoco.MjSpec:
        raise NotImplementedError

    def _compiled(self) -> None:
        """Adjust ``self.model`` after compilation (default: nothing)."""

    def _reset_state(self) -> None:
        """Write the start state into ``self.data`` (qpos, qvel), drawing noise from ``self.np_random``."""
        raise NotImplementedError

    def _observation(self) -> np.ndarray:
        raise NotImplementedError

    def _forward_reward(self, action: np.ndarray, before: Any) -> tuple[float, dict[str, float]]:
        """The forward reward in [0, 1] and its named terms."""
        raise NotImplementedError

    def _status(self, action: np.ndarray) -> tuple[bool, float, bool]:
        """``(reset_success, reset_reward, irrecoverable_now)`` of the current state."""
        raise NotImplementedError

    def _before_step(self) -> Any:
        """Whatever ``_forward_reward`` needs from before the step (for example the x position)."""
        return None

    # ------------------------------------------------------------------ gymnasium API
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        mujoco.mj_resetData(self.model, self.data)
        self._reset_state()
        mujoco.mj_forward(self.model, self.data)
        self._irrecoverable = False
        return self._observation().astype(np.float32), self._info(np.zeros_like(self._action_low), {})

    def step(self, action):
        action = self._check_action(action)
        before = self._before_step()
        self.data.ctrl[:] = np.clip(action, self._ctrl_low, self._ctrl_high)  # as MuJoCo clamps a limited motor
        mujoco.mj_step(self.model, self.data, nstep=self.frame_skip)
        observation = self._observation()
        if not np.all(np.isfinite(observation)):
            raise FloatingPointError(
                f"{type(self).__name__}: the simulation diverged (non-finite state at time {self.data.time:.3f} s). "
                "Call reset()."
            )
        reward, terms = self._forward_reward(action, before)
        return observation.astype(np.float32), float(reward), False, False, self._info(action, terms)

    def current_info(self, action=None) -> dict[str, Any]:
        """The task flags of the current state, as :meth:`step` would report them after ``action`` (default zeros).

        Like a step, it latches the irrecoverable flag when the state is irrecoverable.
        """
        action = np.zeros_like(self._action_low) if action is None else self._check_action(action)
        return self._info(action, {})

    def _info(self, action: np.ndarray, terms: dict[str, float]) -> dict[str, Any]:
        reset_success, reset_reward, irrecoverable_now = self._status(action)
        self._irrecoverable = bool(self._irrecoverable or irrecoverable_now)
        # numpy scalars (np.float64 is a float): torchrl's info reader needs a dtype
        info = {
            "reset_success": np.bool_(reset_success),
            "reset_reward": np.float64(reset_reward),
            "irrecoverable": np.bool_(self._irrecoverable),
        }
        info.update({f"reward_{name}": np.float64(value) for name, value in terms.items()})
        return info

    def _check_action(self, action) -> np.ndarray:
        if isinstance(action, torch.Tensor):
            action = action.detach().cpu().numpy()
        action = np.asarray(action, dtype=np.float64)
        if action.shape != self.action_space.shape:
            raise ValueError(
                f"{type(self).__name__} expects an action of shape {self.action_space.shape}, got {action.shape}."
            )
        if not np.all(np.isfinite(action)):
            raise ValueError(f"{type(self).__name__} got a non-finite action (NaN or inf): {action.tolist()}.")
        return action

    # ------------------------------------------------------------------ state
    @property
    def irrecoverable(self) -> bool:
        """The latched irrecoverable flag (cleared only by :meth:`reset`, a manual reset)."""
        return self._irrecoverable

    def set_state(self, qpos, qvel) -> None:
        """Place the system at joint positions ``qpos`` and velocities ``qvel`` (the latched flag is kept)."""
        qpos, qvel = np.asarray(qpos, dtype=np.float64), np.asarray(qvel, dtype=np.float64)
        if qpos.shape != (self.model.nq,) or qvel.shape != (self.model.nv,):
            raise ValueError(f"set_state expects qpos of shape ({self.model.nq},) and qvel of shape ({self.model.nv},).")
        self.data.qpos[:] = qpos
        self.data.qvel[:] = qvel
        mujoco.mj_forward(self.model, self.data)

    def get_simulator_state(self) -> dict[str, Any]:
        """Everything needed to continue the exact same trajectory: physics, latched flag, RNG."""
        return {
            "physics": get_physics(self.model, self.data),
            "irrecoverable": self._irrecoverable,
            "np_random": self.np_random.bit_generator.state,
        }

    def set_simulator_state(self, state: dict[str, Any]) -> None:
        set_physics(self.model, self.data, state["physics"], type(self).__name__)
        self._irrecoverable = bool(state["irrecoverable"])
        self.np_random.bit_generator.state = state["np_random"]

    # ------------------------------------------------------------------ rendering
    def render(self):
        """An RGB frame ``(height, width, 3)`` uint8 from ``camera``; needs ``render_mode="rgb_array"``."""
        if self.render_mode is None:
            gymnasium.logger.warn(
                f"{type(self).__name__}.render() called without render_mode; pass render_mode='rgb_array' at construction."
            )
            return None
        if self._renderer is None:
            try:
                self._renderer = mujoco.Renderer(self.model, height=self.height, width=self.width)
            except Exception as err:  # the error types differ between GL backends
                raise RenderingUnavailableError(f"{_RENDERING_HELP} (underlying error: {err!r})") from err
        self._renderer.update_scene(self.data, camera=self.camera)
        return self._renderer.render()

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
