"""Factories and helpers of the training recipe: config checks, agents, evaluation, checkpoints, logs."""
from __future__ import annotations

import csv
import ctypes
import json
import os
import shutil
import sys
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import torch
from omegaconf import DictConfig, OmegaConf
from tensordict.nn import TensorDictModuleBase, TensorDictSequential
from torch import nn
from torchrl.data import LazyTensorStorage, ReplayBuffer
from torchrl.envs import TransformedEnv
from torchrl.envs.utils import ExplorationType, set_exploration_type, step_mdp
from torchrl.modules import OrnsteinUhlenbeckProcessModule, TanhModule
from torchrl.objectives import SoftUpdate

from torchrl_reset import (
    DirectDDPGLoss,
    EnsembleValueOperator,
    EpisodeWindowSampler,
    NStepStateTransform,
    RCELoss,
    ResetTriggerTransform,
)
from torchrl_reset_envs import TASKS, make_env

ALGOS = ("ours", "lnt", "lnt_sparse")


class ConfigError(ValueError):
    """A configuration that cannot run; raised before anything is built."""


# ------------------------------------------------------------------------------------------ checks
def reset_horizon(cfg: DictConfig) -> int:
    return 2 * int(cfg.task.forward_horizon) if cfg.reset.max_steps is None else int(cfg.reset.max_steps)


def validate(cfg: DictConfig) -> None:
    """Raise :class:`ConfigError` for every configuration that cannot run, before training starts."""
    problems = []
    if cfg.task.name not in TASKS:
        problems.append(f"unknown task {cfg.task.name!r}; known: {', '.join(TASKS)}")
    if cfg.algo.name not in ALGOS:
        problems.append(f"unknown algorithm {cfg.algo.name!r}; known: {', '.join(ALGOS)}")
    if not 0.0 < float(cfg.task.p_thresh) < 1.0:
        problems.append(f"task.p_thresh must lie in (0, 1), got {cfg.task.p_thresh}")
    if cfg.algo.name == "ours" and cfg.algo.threshold is not None and not 0.0 < float(cfg.algo.threshold) < 1.0:
        problems.append(f"algo.threshold (a success probability) must lie in (0, 1), got {cfg.algo.threshold}")
    h_f = int(cfg.task.forward_horizon)
    if h_f < 1:
        problems.append(f"task.forward_horizon (H_f) must be >= 1, got {h_f}")
    elif reset_horizon(cfg) < h_f:
        problems.append(f"reset.max_steps (H_r = {reset_horizon(cfg)}) must be >= H_f = {h_f}")
    for key in ("total_steps", "eval_every", "log_every", "checkpoint_every", "forward.batch_size", "reset.batch_size"):
        value = OmegaConf.select(cfg, key)
        if not isinstance(value, int) or value < 1:
            problems.append(f"{key} must be a positive integer, got {value!r}")
    env = cfg.get("env") or {}
    if env.get("backend", "sim") == "rtde" and not env.get("host"):
        problems.append("env.backend=rtde needs env.host=<the controller's address>")
    if env and not cfg.task.name.startswith("ur3_"):
        problems.append(f"env.* options ({', '.join(env)}) only apply to the UR3 tasks")
    precision = OmegaConf.select(cfg, "speed.matmul_precision", default="ieee")
    if precision not in MATMUL_PRECISIONS:
        problems.append(f"speed.matmul_precision must be one of {', '.join(MATMUL_PRECISIONS)}; got {precision!r}")
    sampling = OmegaConf.select(cfg, "algo.nstep_sampling", default="episode")
    if cfg.algo.name == "ours" and sampling not in ("episode", "transition"):
        problems.append(f"algo.nstep_sampling must be episode or transition, got {sampling!r}")
    compile_agents = OmegaConf.select(cfg, "speed.compile", default=[])
    if not OmegaConf.is_list(compile_agents) or not set(compile_agents) <= {"forward", "reset"}:
        problems.append(f"speed.compile must be a list of agents among forward, reset; got {compile_agents!r}")
    if int(cfg.heat_up) < 0:
        problems.append(f"heat_up must be >= 0, got {cfg.heat_up}")
    if problems:
        raise ConfigError("invalid configuration:\n  - " + "\n  - ".join(problems))
    checkpoints = Checkpoints(Path(cfg.run_dir) / "checkpoints", keep=int(cfg.keep_checkpoints))
    latest = checkpoints.latest()
    if cfg.resume not in (True, False, "auto"):
        raise ConfigError(f"resume must be true, false or auto, got {cfg.resume!r}")
    if should_resume(cfg):
        if latest is None:
            raise ConfigError(f"resume=true but {checkpoints.root} holds no complete checkpoint to resume from.")
        meta = json.loads((latest / "meta.json").read_text())
        for key, value in (("task", cfg.task.name), ("algo", cfg.algo.name)):
            if meta[key] != value:
                raise ConfigError(
                    f"the checkpoint in {latest} is from {key} {meta[key]!r}, this run is {key} {value!r}; "
                    "use another run_dir or the matching task and algo."
                )
    elif latest is not None:
        raise ConfigError(
            f"{cfg.run_dir} already holds a checkpoint ({latest.name}); pass resume=true to continue it, or "
            "choose another run_dir."
        )
    threads = cfg.threads
    if threads != "auto" and not (isinstance(threads, int) and threads >= 1):
        raise ConfigError(f"threads must be a positive integer or auto, got {threads!r}")


def code_version() -> dict:
    """The commit the code runs at and whether the work tree differs from it (None outside a git checkout)."""
    import subprocess

    root = Path(__file__).resolve().parents[1]
    try:
        commit = subprocess.run(["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True, text=True,
                                timeout=10, check=True).stdout.strip()
        status = subprocess.run(["git", "-C", str(root), "status", "--porcelain", "--untracked-files=no"],
                                capture_output=True, text=True, timeout=10, check=True).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return {"commit": None, "modified": None}
    return {"commit": commit, "modified": bool(status)}


def should_resume(cfg: DictConfig) -> bool:
    """``resume``: true, false, or auto (continue from the run folder's checkpoint when it has one:
    launching the same grid again continues every run where it stopped)."""
    if cfg.resume == "auto":
        return Checkpoints(Path(cfg.run_dir) / "checkpoints").latest() is not None
    return bool(cfg.resume)


def torch_threads(cfg: DictConfig) -> int:
    """``threads``: a number, or auto: one per run in a Hydra multirun (runs go in parallel, one per
    core), else up to two."""
    if cfg.threads != "auto":
        return int(cfg.threads)
    try:
        from hydra.core.hydra_config import HydraConfig
        from hydra.types import RunMode

        if HydraConfig.initialized() and HydraConfig.get().mode == RunMode.MULTIRUN:
            return 1
    except (ImportError, ValueError):
        pass
    return max(1, min(2, os.cpu_count() or 1))


# ------------------------------------------------------------------------------------------ agents
class TensorModule(TensorDictModuleBase):
    """``tensordict[out_key] = module(tensordict[in_key])``: what ``TensorDictModule`` does for one
    tensor in and one out, written with a single ``set``.

    tensordict 0.14's ``TensorDictModule`` passes each output through ``TensorDict.from_any``,
    which for a plain tensor searches the import path for pandas on every call: about 0.2 ms
    measured on the 2-core machines, more than a batch-1 policy's arithmetic, paid by every policy
    call of the loop and twice per forward update.
    """

    def __init__(self, module: nn.Module, in_key: str, out_key: str) -> None:
        super().__init__()
        self.module = module
        self.in_keys = [in_key]
        self.out_keys = [out_key]

    def forward(self, tensordict):
        tensordict.set(self.out_keys[0], self.module(tensordict.get(self.in_keys[0])))
        return tensordict


class FusedSoftUpdate(SoftUpdate):
    """torchrl's :class:`~torchrl.objectives.SoftUpdate` (``target <- (1 - tau) target + tau source``)
    with all target tensors moved by one ``torch._foreach_lerp_`` instead of one ``lerp_`` each
    (0.23 ms -> 0.03 ms per step for the forward agent on the 2-core machines)."""

    def step(self) -> None:
        if not self.initialized:
            return super().step()  # raises torchrl's message
        pairs = self.__dict__.get("_fused_pairs")
        if pairs is None:
            sources, targets = [], []
            for key, source in self._sources.items(True, True):
                key = (key,) if isinstance(key, str) else key
                sources.append(source)
                targets.append(self._targets.get(("target_" + key[0], *key[1:])))
            pairs = self.__dict__["_fused_pairs"] = (sources, targets)
        with torch.no_grad():
            torch._foreach_lerp_(pairs[1], pairs[0], 1.0 - self.eps)


def make_actor(obs_dim: int, action_spec, hidden_sizes) -> TensorDictSequential:
    """The paper's policy: a 400-300 ReLU MLP, Xavier-uniform weights and zero biases, tanh onto the action box."""
    layers, width = [], obs_dim
    for size in hidden_sizes:
        layers += [nn.Linear(width, size), nn.ReLU()]
        width = size
    layers.append(nn.Linear(width, action_spec.shape[-1]))
    net = nn.Sequential(*layers)
    for layer in net:
        if isinstance(layer, nn.Linear):
            nn.init.xavier_uniform_(layer.weight)
            nn.init.zeros_(layer.bias)
    return TensorDictSequential(
        TensorModule(net, "observation", "action_preactivation"),
        TanhModule(["action_preactivation"], ["action"], spec=action_spec),
    )


def with_exploration(actor, action_spec, cfg: DictConfig) -> TensorDictSequential:
    noise = OrnsteinUhlenbeckProcessModule(
        spec=action_spec, eps_init=1.0, eps_end=1.0, annealing_num_steps=1,
        theta=cfg.exploration.theta, sigma=cfg.exploration.sigma, dt=cfg.exploration.dt,
    )
    return TensorDictSequential(actor, noise)


def retain_freed_memory() -> bool:
    """Keep memory freed by the process instead of handing it back to the system (glibc only).

    An update allocates tens of MB of temporaries; by default glibc returns big blocks to the
    system on free and every new allocation then page-faults on first touch (about 1000 faults,
    1.5 ms per reset update measured on 2 cores). Returns whether the setting was applied.
    """
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL("libc.so.6")
        m_trim_threshold, m_mmap_threshold = -1, -3
        return bool(libc.mallopt(m_mmap_threshold, 1 << 30)) and bool(libc.mallopt(m_trim_threshold, 1 << 30))
    except (OSError, AttributeError):  # not glibc
        return False


MATMUL_PRECISIONS = ("auto", "ieee", "bf16")


def _product_error(a: torch.Tensor, b: torch.Tensor, exact: torch.Tensor) -> float:
    return float(((a @ b).double() - exact).abs().max() / exact.abs().max())


def choose_matmul_precision(setting: str) -> str:
    """How the updates' float32 matrix products run on CPU: ``ieee`` or ``bf16`` (see :func:`matmul_products`).

    ``ieee``: plain float32 products. ``bf16``: torch's ``torch.backends.mkldnn.matmul.fp32_precision
    = "bf16"``, which hands float32 products to oneDNN and lets it use bf16 arithmetic inside. On
    the 2-core AVX512-BF16 machines this project is measured on, that path is about 2x faster on the
    reset update's products and as accurate as plain float32 (a reset update's losses and gradients
    agree with float64 to about 1e-7 either way), but other processors may use plain bf16 there
    (about 3 significant digits). ``auto`` therefore measures it: one 256 x 400 x 300 product
    against float64, and ``bf16`` only when its error stays within 4x that of plain float32.
    Leaves the process's setting as it found it.
    """
    if setting not in MATMUL_PRECISIONS:
        raise ValueError(f"matmul precision must be one of {MATMUL_PRECISIONS}, got {setting!r}.")
    if setting == "ieee" or not torch.backends.mkldnn.is_available():
        return "ieee"
    if setting == "bf16":
        return "bf16"
    gen = torch.Generator().manual_seed(0)
    a = torch.rand(256, 400, generator=gen) * 2 - 1
    b = torch.rand(400, 300, generator=gen) * 2 - 1
    exact = a.double() @ b.double()
    with matmul_products("bf16"):
        fast = _product_error(a, b, exact)
    with matmul_products("ieee"):
        plain = _product_error(a, b, exact)
    return "bf16" if fast <= 4 * max(plain, 1e-7) else "ieee"


@contextmanager
def matmul_products(precision: str):
    """Runs the block with CPU float32 products in ``precision`` (``ieee`` or ``bf16``), then restores.

    The recipe uses it around each update only: for the one-row products of acting (policy and
    trigger, every step) oneDNN's path costs more per call (about 29 instead of 10 microseconds for
    a 400 x 300 layer on one row), while for the updates' batches it is about 2x faster.
    """
    backend = torch.backends.mkldnn.matmul
    previous = backend.fp32_precision
    backend.fp32_precision = precision
    try:
        yield
    finally:
        backend.fp32_precision = previous


def make_adam(cfg: DictConfig, groups: list[dict]) -> torch.optim.Optimizer:
    """Adam over parameter groups; with ``speed.fused_adam`` the fused kernels (one pass over all
    parameters, the same update rule) where this torch supports them for these parameters."""
    fused = bool(OmegaConf.select(cfg, "speed.fused_adam", default=False))
    if fused:
        try:
            return torch.optim.Adam(groups, fused=True)
        except (RuntimeError, ValueError):  # a device or dtype without fused kernels
            pass
    return torch.optim.Adam(groups)


@dataclass
class Agent:
    """One agent: its policy, loss module, optimizer and target updater."""

    actor: TensorDictSequential
    loss: Any
    optimizer: torch.optim.Optimizer
    targets: SoftUpdate
    model: Any  # the critic or classifier ensemble


def make_forward_agent(cfg: DictConfig, obs_dim: int, action_spec, loss_class: type = DirectDDPGLoss) -> Agent:
    """DDPG with the paper's critic layout (action joined after the first hidden layer).

    ``loss_class``: the recipe's :class:`~torchrl_reset.DirectDDPGLoss`, or torchrl's ``DDPGLoss``
    (the same losses; the benchmarks compare the two)."""
    act_dim = action_spec.shape[-1]
    actor = make_actor(obs_dim, action_spec, cfg.hidden_sizes)
    critic = EnsembleValueOperator(
        obs_dim, act_dim, num_members=1, hidden_sizes=tuple(cfg.hidden_sizes), prior_scale=0.0, out_keys=["state_action_value"]
    )
    loss = loss_class(actor, critic, delay_actor=True, delay_value=True)
    loss.make_value_estimator(gamma=cfg.gamma)
    optimizer = make_adam(cfg, [
        {"params": list(loss.actor_network_params.values(True, True)), "lr": cfg.forward.actor_lr},
        {"params": list(loss.value_network_params.values(True, True)), "lr": cfg.forward.critic_lr},
    ])
    return Agent(actor, loss, optimizer, FusedSoftUpdate(loss, tau=cfg.tau), critic)


def make_reset_agent(cfg: DictConfig, obs_dim: int, action_spec) -> Agent:
    """``ours``: RCE on a classifier ensemble with priors; ``lnt``/``lnt_sparse``: DDPG on a Q ensemble."""
    act_dim = action_spec.shape[-1]
    actor = make_actor(obs_dim, action_spec, cfg.hidden_sizes)
    if cfg.algo.name == "ours":
        model = EnsembleValueOperator(
            obs_dim, act_dim, num_members=cfg.algo.num_members, hidden_sizes=tuple(cfg.hidden_sizes),
            prior_scale=cfg.algo.prior_scale,
        )
        loss = RCELoss(actor, model, gamma=cfg.gamma, n_steps=cfg.algo.n_steps,
                       clip_target_values=bool(OmegaConf.select(cfg, "algo.clip_target_values", default=False)))
        optimizer = make_adam(cfg, [
            {"params": list(actor.parameters()), "lr": cfg.reset.actor_lr},
            {"params": list(model.parameters()), "lr": cfg.reset.critic_lr},
        ])
    else:
        model = EnsembleValueOperator(
            obs_dim, act_dim, num_members=cfg.algo.num_members, hidden_sizes=tuple(cfg.hidden_sizes),
            prior_scale=cfg.algo.prior_scale, out_keys=["state_action_value"],
        )
        loss = DirectDDPGLoss(actor, model, delay_actor=True, delay_value=True)
        loss.set_keys(reward="lnt_reward")
        loss.make_value_estimator(gamma=cfg.gamma)
        optimizer = make_adam(cfg, [
            {"params": list(loss.actor_network_params.values(True, True)), "lr": cfg.reset.actor_lr},
            {"params": list(loss.value_network_params.values(True, True)), "lr": cfg.reset.critic_lr},
        ])
    return Agent(actor, loss, optimizer, FusedSoftUpdate(loss, tau=cfg.tau), model)


def make_trigger(cfg: DictConfig, reset_agent: Agent) -> ResetTriggerTransform:
    if cfg.algo.name == "ours":
        threshold = cfg.task.p_thresh if cfg.algo.threshold is None else cfg.algo.threshold
        return ResetTriggerTransform(reset_agent.model, float(threshold))
    return ResetTriggerTransform(
        reset_agent.model, float(cfg.algo.threshold), score="value", reduction="min",
        model_out_key="state_action_value", score_key="reset_value",
    )


def env_kwargs(cfg: DictConfig, *, for_eval: bool = False) -> dict:
    """``make_env`` arguments. A real arm cannot be copied: evaluation and probing then use its simulated twin."""
    env = cfg.get("env")
    kwargs = {} if env is None else dict(OmegaConf.to_container(env, resolve=True))
    if for_eval and kwargs.get("backend", "sim") != "sim":
        kwargs.update(backend="sim", host=None)
    return kwargs


#: the evaluation env is seeded ``cfg.seed + EVAL_SEED_OFFSET``, apart from the training env
EVAL_SEED_OFFSET = 10_000


def task_dimensions(cfg: DictConfig):
    """Observation size and action spec of the task (from a throw-away env)."""
    env = make_env(cfg.task.name, **env_kwargs(cfg, for_eval=True))
    out = env.observation_spec["observation"].shape[-1], env.action_spec.clone()
    env.close()
    return out


def make_task_env(cfg: DictConfig, reset_agent: Agent, *, for_eval: bool = False,
                  **options) -> tuple[TransformedEnv, ResetTriggerTransform]:
    """The task's env with the reset trigger of ``reset_agent``; ``options`` go to ``make_env``
    (``render_mode``, ``width``...)."""
    env = make_env(cfg.task.name, device=cfg.device, **env_kwargs(cfg, for_eval=for_eval), **options)
    trigger = make_trigger(cfg, reset_agent)
    env.append_transform(trigger)
    return env, trigger


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


def lnt_batch(sample, algo: DictConfig, num_members: int):
    """The LNT reset agent's batch: its reward (shaped or sparse) and done flags, one column per ensemble member."""
    nxt = sample.get("next")
    reward = nxt.get("reset_reward") if algo.reset_reward == "shaped" else nxt.get("reset_success").float()
    shape = (*reward.shape[:-1], num_members)
    nxt.set("lnt_reward", reward.expand(shape))
    for key in ("done", "terminated"):
        nxt.set(key, nxt.get(key).expand(shape))
    return sample


class UpdateBudget:
    """On a real-time robot, run an update only if it fits in the time left in the control period.

    Keeps a running estimate of each agent's update duration (the slowest recent one, decaying);
    ``fits(agent, time_left)`` says whether that estimate fits; skipped updates are counted.
    """

    def __init__(self, margin: float = 0.002):
        self.margin = margin
        self.estimate: dict[str, float] = {}
        self.skipped = 0

    def fits(self, agent: str, time_left: float) -> bool:
        if time_left - self.margin >= self.estimate.get(agent, 0.0):
            return True
        self.skipped += 1
        return False

    def record(self, agent: str, seconds: float) -> None:
        self.estimate[agent] = max(seconds, 0.9 * self.estimate.get(agent, seconds))


def realtime_env(env: TransformedEnv):
    """The innermost env if it runs in real time (the UR3 arm on the rtde backend), else None."""
    base = env
    while isinstance(base, TransformedEnv):
        base = base.base_env
    backend = getattr(base, "backend", None)
    return base if backend is not None and getattr(backend, "realtime", False) and hasattr(base, "time_left") else None


def safety_counters(env: TransformedEnv) -> dict[str, int]:
    """The robot's safety counters (protective stops, host watchdog stops...) when the env has them (UR3Env)."""
    base = env
    while isinstance(base, TransformedEnv):
        base = base.base_env
    counters = getattr(base, "safety_counters", None)
    return dict(counters()) if callable(counters) else {}


# ------------------------------------------------------------------------------------------ evaluation
def evaluate(env: TransformedEnv, trigger: ResetTriggerTransform, forward_actor, reset_actor, *, horizon: int,
             reset_horizon: int, min_reset_steps: int, gamma: float,
             observe: Callable[[str], None] | None = None) -> dict[str, Any]:
    """One forward and one reset episode with exploration off, from ``env.reset()`` (method.md section 7).

    ``observe(phase)``, when given, is called after the reset and after every step, with ``phase``
    ``"forward"``, ``"trigger"`` (the step the trigger stopped) or ``"reset"`` (recipes/video.py
    renders there).
    """
    seen = observe or (lambda phase: None)
    td = env.reset()
    seen("forward")
    ret, forward_steps, triggered = 0.0, 0, False
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        trigger.set_enabled(True)
        for t in range(horizon):
            td = env.step(forward_actor(td))
            if bool(td.get(("next", "reset_trigger")).any()):
                triggered = True
                seen("trigger")
                break
            ret += gamma**t * float(td.get(("next", "reward")))
            forward_steps += 1
            td = step_mdp(td)
            seen("forward")
        trigger.set_enabled(False)
        success, reset_steps = False, 0
        for t in range(reset_horizon):
            td = step_mdp(env.step(reset_actor(td)))
            reset_steps += 1
            seen("reset")
            if bool(td.get("reset_success").any()) and reset_steps >= min_reset_steps:
                success = True
                break
        trigger.set_enabled(True)
    return {"forward_return": ret, "forward_steps": forward_steps, "triggered": triggered,
            "reset_success": success, "reset_steps": reset_steps}


# ------------------------------------------------------------------------------------------ checkpoints
class Checkpoints:
    """Complete checkpoints in ``root/step_<frames>/``, the newest named by ``root/latest``.

    A checkpoint is written into a temporary folder, which is renamed into place once complete; then
    ``latest`` is replaced atomically. A crash while checkpointing leaves the previous checkpoint and
    ``latest`` untouched.
    """

    def __init__(self, root: Path, keep: int = 2):
        self.root = Path(root)
        self.keep = max(1, int(keep))

    def latest(self) -> Path | None:
        pointer = self.root / "latest"
        if not pointer.exists():
            return None
        path = self.root / pointer.read_text().strip()
        return path if (path / "meta.json").exists() else None

    def save(self, frames: int, write: Callable[[Path], None], meta: dict) -> Path:
        self.root.mkdir(parents=True, exist_ok=True)
        tmp = self.root / f".tmp-step_{frames:010d}-{os.getpid()}"
        if tmp.exists():
            shutil.rmtree(tmp)
        tmp.mkdir()
        write(tmp)
        (tmp / "meta.json").write_text(json.dumps(meta, indent=2))  # written last: marks the folder complete
        _fsync_tree(tmp)
        final = self.root / f"step_{frames:010d}"
        if final.exists():
            shutil.rmtree(final)
        os.rename(tmp, final)
        pointer_tmp = self.root / f".latest-{os.getpid()}"
        with open(pointer_tmp, "w") as f:
            f.write(final.name)
            f.flush()
            os.fsync(f.fileno())
        os.replace(pointer_tmp, self.root / "latest")
        _fsync_dir(self.root)
        for old in sorted(self.root.glob("step_*"))[: -self.keep]:
            shutil.rmtree(old, ignore_errors=True)
        return final


def _fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _fsync_tree(root: Path) -> None:
    for dirpath, _, filenames in os.walk(root):
        for name in filenames:
            with open(os.path.join(dirpath, name), "rb") as f:
                os.fsync(f.fileno())
        _fsync_dir(Path(dirpath))


# ------------------------------------------------------------------------------------------ logs
def success_rate_by_quarter(progress: Path) -> dict:
    """The reset success rate within the first and the last quarter of a run's steps, from ``progress.csv``
    (the cumulative counters at the log rows): whether the reset agent got better."""
    out = {"reset_success_rate_first_quarter": None, "reset_success_rate_last_quarter": None}
    if not Path(progress).exists():
        return out
    with open(progress, newline="") as f:
        rows = [(int(float(r["frames"])), int(r["successful_resets"]), int(r["manual_resets"])) for r in csv.DictReader(f)]
    if len(rows) < 4:
        return out
    total = rows[-1][0]

    def at(frames: int) -> tuple[int, int]:
        before = [r for r in rows if r[0] <= frames]
        return (before[-1][1], before[-1][2]) if before else (0, 0)

    def rate(start: tuple[int, int], end: tuple[int, int]):
        ended = (end[0] - start[0]) + (end[1] - start[1])
        return (end[0] - start[0]) / ended if ended else None

    out["reset_success_rate_first_quarter"] = rate((0, 0), at(total // 4))
    out["reset_success_rate_last_quarter"] = rate(at(total - total // 4), at(total))
    return out



class CsvTable:
    """An append-only CSV file with a fixed header; on resume, rows after the checkpoint are dropped."""

    def __init__(self, path: Path, fields: list[str]):
        self.path = Path(path)
        self.fields = fields

    def truncate_after(self, frames: int) -> None:
        if not self.path.exists():
            return
        with open(self.path, newline="") as f:
            rows = [row for row in csv.DictReader(f) if int(float(row["frames"])) <= frames]
        self._rewrite(rows)

    def _rewrite(self, rows) -> None:
        tmp = self.path.with_suffix(".tmp")
        with open(tmp, "w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=self.fields)
            writer.writeheader()
            writer.writerows(rows)
        os.replace(tmp, self.path)

    def append(self, row: dict) -> None:
        new = not self.path.exists()
        with open(self.path, "a", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=self.fields, extrasaction="ignore")
            if new:
                writer.writeheader()
            writer.writerow(row)

