"""A run folder's trained agents, read back from one of its checkpoints, and what else the folder holds (its
config, its CSV tables, its replay buffers): what the video, the probes and anyone studying a finished run
start from (the recipe itself resumes through ``training.checkpoints``)."""
from __future__ import annotations

import csv
import json
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

import torch
from tensordict import TensorDict
from omegaconf import DictConfig, OmegaConf
from torchrl.data import ReplayBuffer
from torchrl.envs.utils import ExplorationType, set_exploration_type

from torchrl_reset import InitialStateBuffer, success_probability
from torchrl_reset_recipes.training.updates import update
from torchrl_reset_recipes.training.agents import Agent, make_forward_agent, make_reset_agent
from torchrl_reset_recipes.training.buffers import make_buffers
from torchrl_reset_recipes.training.run_spec import RunSpec, run_spec
from torchrl_reset_recipes.training.checkpoints import MANIFEST, CheckpointDamaged, Checkpoints, checkpoint_problems, checkpoint_step, identity_differences
from torchrl_reset_recipes.training.task_envs import task_dimensions

__all__ = ["SavedRun", "load_agents", "load_replay", "load_examples", "latest_checkpoint", "run_config", "run_table", "logged_observations",
           "greedy_actions", "model_values", "trigger_probability", "ensemble_scores", "ensemble_minimum", "new_reset_agent",
           "offline_updates", "CarriedNoise"]

_ABSENT = object()


@dataclass
class SavedRun:
    cfg: DictConfig  # the run's config.yaml, with the overrides applied
    checkpoint: Path  # the checkpoint folder the agents were read from
    step: int  # its step (from the folder's name)
    forward: Agent | None  # None where not asked for (``agents``)
    reset: Agent | None
    spec: RunSpec | None = None  # what the recipe worked out of ``cfg`` (the reset agent's kind, the horizons...)


def load_agents(run_dir: Path | str, *, checkpoint: Path | str | None = None,
                overrides: Mapping[str, Any] | None = None,
                agents: tuple[str, ...] = ("forward", "reset")) -> SavedRun:
    """The agents of ``run_dir`` as saved in ``checkpoint`` (default: its latest complete one; also a
    kept state, ``checkpoints/kept/step_<steps>``, see ``keep_states_every``), built from the run's own
    config on the CPU. ``overrides`` set dotted config keys before the agents are built
    (``{"speed.accelerate": False}`` gives the reference ensemble, whose parts can be read apart).
    ``agents`` names the ones to build (``("reset",)`` for a probe of the reset agent alone); the others
    are None in the result. A ``checkpoint`` given (absolute, relative to the working directory, or to
    ``run_dir``) is checked as a resume checks one: a damaged one raises ``CheckpointDamaged``, another
    run's (task, algo or seed differ) ``ValueError``."""
    run_dir = Path(run_dir)
    unknown = set(agents) - {"forward", "reset"}
    if isinstance(agents, str) or unknown or not agents:
        raise ValueError(f"agents must name 'forward' and/or 'reset' (a tuple), got {agents!r}")
    cfg = run_config(run_dir)
    checkpoint = _checkpoint(run_dir, checkpoint, cfg)
    cfg.device = "cpu"
    for key, value in (overrides or {}).items():
        if OmegaConf.select(cfg, key, default=_ABSENT) is _ABSENT:
            raise KeyError(f"{key!r} is not a key of {run_dir / 'config.yaml'}: an override can only change a "
                           "setting the run has")
        OmegaConf.update(cfg, key, value)
    spec = run_spec(cfg, check=False)  # the run's own config, checked when it ran
    obs_dim, action_spec = task_dimensions(cfg)
    state = torch.load(checkpoint / "state.pt", weights_only=False, map_location="cpu")
    forward = reset = None
    if "forward" in agents:
        forward = make_forward_agent(spec, obs_dim, action_spec)
        forward.loss.load_state_dict(state["forward_loss"])
    if "reset" in agents:
        reset = make_reset_agent(spec, obs_dim, action_spec)
        reset.loss.load_state_dict(state["reset_loss"])
    return SavedRun(cfg, checkpoint, checkpoint_step(checkpoint), forward, reset, spec)


def load_replay(run_dir: Path | str, agent: str = "reset", *, checkpoint: Path | str | None = None) -> ReplayBuffer:
    """The replay buffer of ``agent`` (``"forward"`` or ``"reset"``) of ``run_dir`` as ``checkpoint`` holds it
    (default: the run's latest complete checkpoint; named as for :func:`load_agents`, and checked as it checks
    one), in the buffer the recipe builds for the run (``buffers.make_buffers``, from the run's config, so its
    sampler and transform are the run's). Its ``storage`` holds the rows as they were written, oldest first
    until the buffer is full (``write_count`` rows written in all; ours' reset buffer writes a row with its
    n-step state, once that state is known). A kept state (``checkpoints/kept/``) holds the agents alone, no
    buffer: FileNotFoundError."""
    if agent not in ("forward", "reset"):
        raise ValueError(f"agent must be 'forward' or 'reset', got {agent!r}")
    run_dir = Path(run_dir)
    cfg = run_config(run_dir)
    checkpoint = _checkpoint(run_dir, checkpoint, cfg)
    folder = checkpoint / f"{agent}_buffer"
    if not folder.is_dir():
        kept = checkpoint.parent.name == "kept"
        raise FileNotFoundError(f"{checkpoint} holds no {agent} replay buffer"
                                + (": a kept state holds the agents alone" if kept else
                                   f" (the {agent} agent had stored no step when it was written)"))
    forward_rb, reset_rb = make_buffers(run_spec(cfg, check=False))
    rb = forward_rb if agent == "forward" else reset_rb
    rb.loads(folder)
    return rb


def load_examples(run_dir: Path | str, *, checkpoint: Path | str | None = None) -> InitialStateBuffer:
    """The example buffer (``S*``) of ``run_dir`` as ``checkpoint`` holds it (named and checked as for
    :func:`load_agents`; default: the latest complete one): the state at the start of every forward episode up
    to that step (``states()``, in slot order: oldest first until the buffer is full). A kept state (``checkpoints/kept/``) holds the agents alone:
    FileNotFoundError."""
    run_dir = Path(run_dir)
    checkpoint = _checkpoint(run_dir, checkpoint, run_config(run_dir))
    if checkpoint.parent.name == "kept":
        raise FileNotFoundError(f"{checkpoint} holds no example buffer: a kept state holds the agents alone")
    saved = torch.load(checkpoint / "state.pt", weights_only=False, map_location="cpu")["collector"]["example_buffer"]
    examples = InitialStateBuffer(max_size=saved["max_size"], state_keys=saved["state_keys"])
    examples.load_state_dict(saved)
    return examples


def latest_checkpoint(run_dir: Path | str) -> Path:
    """The newest complete (intact) checkpoint of ``run_dir``, ``checkpoints/step_<steps>``; a damaged newer one
    is passed over, as a resume passes it over. A run folder without one: FileNotFoundError."""
    run_dir = Path(run_dir)
    run_config(run_dir)  # a clear error for a folder that is no run folder
    checkpoint = Checkpoints(run_dir / "checkpoints").latest()
    if checkpoint is None:
        raise FileNotFoundError(f"{run_dir / 'checkpoints'} holds no complete checkpoint yet.")
    return checkpoint


def run_config(run_dir: Path | str) -> DictConfig:
    """A run folder's ``config.yaml``: the configuration ``recipes/train.py`` ran it with, overrides applied (as
    written: ``device`` and every other key as the run had them). A folder without one is no run folder:
    FileNotFoundError."""
    config = Path(run_dir) / "config.yaml"
    if not config.exists():
        raise FileNotFoundError(f"{run_dir} holds no config.yaml: is it a run folder of recipes/train.py?")
    return OmegaConf.load(config)


def run_table(run_dir: Path | str, name: str) -> list[dict[str, str]]:
    """The rows of one of a run folder's CSV tables (``name``: ``progress.csv``, ``eval.csv``, ``resets.csv``,
    ``triggers.csv`` or ``diagnostics.csv``), oldest first, each a dict of strings keyed by the table's header.
    A table is written with its first row: none for one the run has not written yet (``triggers.csv`` before
    the first trigger). A folder without ``config.yaml`` is no run folder: FileNotFoundError."""
    run_dir = Path(run_dir)
    run_config(run_dir)
    if Path(name).name != name or not name.endswith(".csv"):
        raise ValueError(f"name a table of the run folder by its file name (such as 'resets.csv'), got {name!r}")
    path = run_dir / name
    if not path.exists():
        return []
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def _checkpoint(run_dir: Path, checkpoint: Path | str | None, cfg: DictConfig) -> Path:
    """The checkpoint folder ``checkpoint`` names (absolute, relative to the working directory, or to ``run_dir``),
    checked as a resume checks one (:func:`_check`); None: the run's latest complete checkpoint."""
    if checkpoint is None:
        return latest_checkpoint(run_dir)
    checkpoint = Path(checkpoint)
    if not checkpoint.is_absolute() and not checkpoint.exists() and (run_dir / checkpoint).exists():
        checkpoint = run_dir / checkpoint  # relative to the run folder
    if checkpoint_step(checkpoint) is None or not (checkpoint / "state.pt").exists():
        raise FileNotFoundError(f"{checkpoint} is not a complete checkpoint of a run (a step_<steps> folder "
                                "holding state.pt).")
    _check(checkpoint, run_dir, cfg)
    return checkpoint


def _check(checkpoint: Path, run_dir: Path, cfg: DictConfig) -> None:
    """A checkpoint named by hand is checked as a resume checks one: its files against its manifest
    (CheckpointDamaged), and its ``meta.json`` against the run's config (ValueError for another run's)."""
    if not (checkpoint / MANIFEST).exists() and not (checkpoint / "meta.json").exists():
        warnings.warn(f"{checkpoint} holds no manifest.json or meta.json (a state kept by older code): read unverified",
                      stacklevel=4)  # the caller of load_agents / load_replay
        return
    problems = checkpoint_problems(checkpoint)
    if problems:
        raise CheckpointDamaged(f"{checkpoint} is damaged: " + "; ".join(problems))
    differ = identity_differences(json.loads((checkpoint / "meta.json").read_text()), cfg)
    if differ:
        raise ValueError(f"{checkpoint} was saved by another run than {run_dir}: "
                         + ", ".join(f"{key} {saved!r} there, {value!r} here" for key, (saved, value) in differ.items()))


def logged_observations(rows: list[dict[str, str]]) -> torch.Tensor:
    """The ``observation`` column of logged rows (``triggers.csv``'s: the state each trigger stopped), one row
    of float32 per logged row."""
    return torch.tensor([[float(v) for v in r["observation"].split()] for r in rows], dtype=torch.float32)


def greedy_actions(actor, observation: torch.Tensor) -> torch.Tensor:
    """``actor``'s own actions on ``observation``, without exploration (a tanh-Gaussian's ``tanh(loc)``) and
    without gradients."""
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        return actor(TensorDict(observation=observation, batch_size=[len(observation)]))["action"]


def trigger_probability(model, observation: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
    """What ours' trigger scores: the members' mean success ratio ``p`` of (observation, action), one value per
    row (the trigger fires below p_thresh)."""
    with torch.no_grad():
        return success_probability(model.logits(observation, action)).mean(-1)


def model_values(model, observation: torch.Tensor, action: torch.Tensor, key: str = "state_action_value",
                 chunk: int = 20000) -> torch.Tensor:
    """``model``'s output ``key`` (an ensemble's: one column per member) on the rows (observation, action),
    without gradients, ``chunk`` rows at a time."""
    values = []
    with torch.no_grad():
        for i in range(0, observation.shape[0], chunk):
            rows = min(chunk, observation.shape[0] - i)
            td = TensorDict({"observation": observation[i:i + rows], "action": action[i:i + rows]}, batch_size=[rows])
            values.append(model(td)[key])
    return torch.cat(values)


def ensemble_scores(model, rows: TensorDict, q_thresh: float, episodes: torch.Tensor | None = None) -> dict[str, float]:
    """LNT's trigger's view of ``rows`` (observation, action): from the members' Q-values per row, their minimum (the
    trigger's score: its mean and the share of rows below ``q_thresh``, where the trigger fires), the members' mean,
    their spread (standard deviation across members) and the mean minus the minimum, each averaged over the rows;
    given each row's episode (``episodes``, such as the collector's ``traj_ids``), also the share of the episodes with
    a row below ``q_thresh`` (else NaN)."""
    q = model_values(model, rows["observation"], rows["action"])
    minimum, mean = q.min(-1).values, q.mean(-1)
    below = minimum < q_thresh
    flagged = (float("nan") if episodes is None else  # episodes with a row the trigger would stop at
               episodes[below].unique().numel() / episodes.unique().numel())
    return {"rows": int(q.shape[0]), "min_mean": float(minimum.mean()), "below_q_thresh": float(below.float().mean()),
            "episodes_flagged": flagged, "member_mean": float(mean.mean()), "member_std": float(q.std(-1).mean()),
            "mean_minus_min": float((mean - minimum).mean())}


def ensemble_minimum(model, forward: TensorDict, near: TensorDict, q_thresh: float) -> dict[str, float]:
    """What LNT's trigger reads, the ensemble's minimum over its members, on two sets of rows (observation,
    action): ``forward`` (the states the trigger scores) and ``near`` (reset rows one step from success). Their
    means, the shares below ``q_thresh`` (where the trigger fires), and the members' spread on ``forward``
    (:func:`ensemble_scores` of each)."""
    on_forward, on_near = ensemble_scores(model, forward, q_thresh), ensemble_scores(model, near, q_thresh)
    return {"forward_min_mean": on_forward["min_mean"], "forward_below_q_thresh": on_forward["below_q_thresh"],
            "forward_member_std": on_forward["member_std"], "near_success_min_mean": on_near["min_mean"],
            "near_success_below_q_thresh": on_near["below_q_thresh"]}


def new_reset_agent(spec: RunSpec, seed: int) -> Agent:
    """A reset agent as the recipe builds one for ``spec``'s run, its networks drawn afresh after
    ``torch.manual_seed(seed)``: what the offline probes train on a run's saved rows."""
    torch.manual_seed(seed)
    obs_dim, action_spec = task_dimensions(spec.cfg)
    return make_reset_agent(spec, obs_dim, action_spec)


def offline_updates(agent: Agent, next_batch, updates: int, every: int, watch, *, release_order: bool = True) -> None:
    """``updates`` of the recipe's update of ``agent`` (``updates.update``), each on the batch ``next_batch()``
    returns, and ``watch(step)`` before the first and after every ``every``-th: how the probes train an agent
    offline on a run's saved rows and record its course."""
    watch(0)
    for step in range(1, updates + 1):
        update(agent, next_batch(), agent.loss, release_order=release_order)
        if step % every == 0:
            watch(step)


class CarriedNoise:
    """The runs' own noise module (the recipe's ``with_exploration``, torchrl's ``OrnsteinUhlenbeckProcessModule``)
    applied to one action at a time, its state carried from call to call in the private entries the collector
    carries (``_ou_prev_noise``, ``_ou_steps``); after ``restart`` the next call sets ``is_init``, which starts the
    noise again from zero, as the collector does at every episode's first step with ``exploration.restart: episode``."""

    def __init__(self, module) -> None:
        self.module, self.state, self.init = module, {}, True

    def restart(self) -> None:
        self.init = True

    def __call__(self, action: torch.Tensor) -> torch.Tensor:
        td = TensorDict({"action": action.clone(), "is_init": torch.tensor([self.init]), **self.state}, [])
        td = self.module(td)
        self.state = {key: td.get(key) for key in td.keys() if key.startswith("_")}
        self.init = False
        return td.get("action")
