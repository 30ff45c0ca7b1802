"""The recipe's configuration checks: every configuration that cannot run fails before anything is built."""
from __future__ import annotations

import difflib
import functools
import json
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from torchrl_reset.accel import MATMUL_PRECISIONS
from torchrl_reset_recipes import CONF
from torchrl_reset_recipes.training.absent_keys import setting
from torchrl_reset.actor_heads import ACTOR_HEADS
from torchrl_reset_recipes.training.reset_agents import KINDS
from torchrl_reset_recipes.training.streams import STREAMS
from torchrl_reset_recipes.training.checkpoints import Checkpoints, identity_differences, no_intact_checkpoint
from torchrl_reset_envs import TASKS
from torchrl_reset_recipes.training.hydra_config import task_node

__all__ = ["ALGOS", "ConfigError", "validate", "reset_horizon", "should_resume", "recipe_settings", "unknown_settings", "RETIRED_KEYS",
           "retired_key_problem"]


ALGOS = tuple(KINDS)  # the kinds of reset agent (reset_agents.py)

#: the keys of run batching (several runs in one process, or one agent pair over copies of a task), retired;
#: older runs' ``config.yaml`` files still hold them (null, false), which the report reads as no setting
RETIRED_KEYS = ("seeds", "arms", "vary", "vary_values", "speed.batched_acting")
#: the last commit that had run batching (docs/many-runs.md)
LAST_BATCHING_COMMIT = "eb8b414"


#: the settings that take one of two words, and those words (a configuration without the key: absent_keys)
CHOICES = {"exploration.restart": ("never", "episode"), "update_order": ("release", "joint"),
           "learner.streams": STREAMS, "learner.mode": ("sync", "async"),
           "forward.sampling": ("episode", "transition"), "target_init": ("release", "copy")}


class ConfigError(ValueError):
    """A configuration that cannot run; raised before anything is built."""


def reset_horizon(cfg: DictConfig) -> int:
    """H_r: ``reset.max_steps``, or 2 H_f where it is null."""
    return 2 * int(cfg.task.forward_horizon) if cfg.reset.max_steps is None else int(cfg.reset.max_steps)


def should_resume(cfg: DictConfig) -> bool:
    """``resume``: true, false, or auto (continue from the run folder's checkpoint when it has one:
    launching the same grid again continues every run where it stopped). A checkpoint is what
    :meth:`Checkpoints.folders` lists, intact or not: resuming takes the newest intact one
    (:meth:`Checkpoints.latest`), and a folder whose checkpoints are all damaged stops with an error instead
    of starting over."""
    if cfg.resume == "auto":
        return bool(Checkpoints(Path(cfg.run_dir) / "checkpoints").folders())
    return bool(cfg.resume)


def learner_problems(cfg: DictConfig) -> list[str]:
    """Problems with ``learner.*``: async's streams, the lag bound and the timeout."""
    problems = []
    lag, timeout = setting(cfg, "learner.max_lag"), setting(cfg, "learner.timeout")
    if isinstance(lag, bool) or not isinstance(lag, int) or lag < 0:
        problems.append(f"learner.max_lag must be a whole number of steps >= 0, got {lag!r}")
    if isinstance(timeout, bool) or not isinstance(timeout, (int, float)) or timeout <= 0:
        problems.append(f"learner.timeout must be a number of seconds > 0, got {timeout!r}")
    if setting(cfg, "learner.mode") == "async":
        if setting(cfg, "learner.streams") != "separate":
            problems.append("learner.mode=async draws the actor's and the learner's randomness in two processes: "
                            "set learner.streams=separate")
        if str(cfg.device) != "cpu":
            problems.append(f"learner.mode=async runs on the CPU (device={cfg.device})")
    return problems


def actor_problems(cfg: DictConfig) -> list[str]:
    """Problems with ``reset.actor.*`` and ``forward.actor.*``: each actor's head and the terms added to its loss."""
    problems = []
    for agent in ("forward", "reset"):
        head = setting(cfg, f"{agent}.actor.head")
        if head not in ACTOR_HEADS:
            problems.append(f"{agent}.actor.head must be one of {', '.join(ACTOR_HEADS)}, got {head!r}")
        for key in (f"{agent}.actor.preact_penalty", f"{agent}.actor.action_l2"):
            value = setting(cfg, key)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or value < 0:
                problems.append(f"{key} must be a number >= 0, got {value!r}")
        entropy = setting(cfg, f"{agent}.actor.entropy")
        if entropy != "auto" and (isinstance(entropy, bool) or not isinstance(entropy, (int, float)) or entropy <= 0):
            problems.append(f"{agent}.actor.entropy must be a number > 0 or auto, got {entropy!r}")
        if head in ACTOR_HEADS and ACTOR_HEADS[head].stochastic and setting(cfg, "update_order") != "release":
            uses = "the classifiers' labels" if agent == "reset" else "the critic's TD targets"
            problems.append(f"{agent}.actor.head={head} needs update_order=release (its actor step samples actions; "
                            f"{uses} take its deterministic action)")
    return problems




def validate(cfg: DictConfig) -> None:
    """Raise :class:`ConfigError` for every configuration that cannot run, before training starts."""
    problems = unknown_settings(cfg)
    run_dir = Path(cfg.run_dir)
    existing = next((p for p in (run_dir, *run_dir.parents) if p.exists()), None)
    if existing is not None and not existing.is_dir():
        what = f"{run_dir} is a file" if existing == run_dir else f"{existing}, in {run_dir}'s path, is a file"
        problems.append(f"run_dir must name a folder, but {what}; choose another run_dir")
    if cfg.task.name not in TASKS:
        problems.append(f"unknown task {cfg.task.name!r}; known: {', '.join(TASKS)}")
    if cfg.algo.name not in ALGOS:
        problems.append(f"unknown algorithm {cfg.algo.name!r}; known: {', '.join(ALGOS)}")
    else:
        problems += KINDS[cfg.algo.name].check(cfg)  # the keys only that kind of reset agent reads
    if not 0.0 < float(cfg.task.p_thresh) < 1.0:
        problems.append(f"task.p_thresh must lie in (0, 1), got {cfg.task.p_thresh}")
    h_f = int(cfg.task.forward_horizon)
    if h_f < 1:
        problems.append(f"task.forward_horizon (H_f) must be >= 1, got {h_f}")
    elif reset_horizon(cfg) < h_f:
        problems.append(f"reset.max_steps (H_r = {reset_horizon(cfg)}) must be >= H_f = {h_f}")
    for key in ("total_steps", "eval_every", "log_every", "checkpoint_every", "forward.batch_size", "reset.batch_size"):
        value = OmegaConf.select(cfg, key)
        if not isinstance(value, int) or value < 1:
            problems.append(f"{key} must be a positive integer, got {value!r}")
    kept = OmegaConf.select(cfg, "keep_states_every", default=None)
    if kept is not None and (not isinstance(kept, int) or isinstance(kept, bool) or kept < 1
                             or (isinstance(cfg.checkpoint_every, int) and kept % cfg.checkpoint_every)):
        problems.append(f"keep_states_every must be null or a positive multiple of checkpoint_every "
                        f"({cfg.checkpoint_every}), got {kept!r}")
    env = cfg.get("env") or {}
    if env.get("backend", "sim") == "rtde" and not env.get("host"):
        problems.append("env.backend=rtde needs env.host=<the controller's address>")
    if env and not cfg.task.name.startswith("ur3_"):
        problems.append(f"env.* options ({', '.join(env)}) only apply to the UR3 tasks")
    precision = OmegaConf.select(cfg, "speed.matmul_precision", default="ieee")
    if precision not in MATMUL_PRECISIONS:
        problems.append(f"speed.matmul_precision must be one of {', '.join(MATMUL_PRECISIONS)}; got {precision!r}")
    for flag in ("speed.accelerate", "speed.fused_adam", "speed.retain_memory"):
        value = OmegaConf.select(cfg, flag, default=True)
        if not isinstance(value, bool):
            problems.append(f"{flag} must be true or false, got {value!r}")
    compile_agents = OmegaConf.select(cfg, "speed.compile", default=[])
    if not OmegaConf.is_list(compile_agents) or not set(compile_agents) <= {"forward", "reset"}:
        problems.append(f"speed.compile must be a list of agents among forward, reset; got {compile_agents!r}")
    for key, choices in CHOICES.items():
        value = setting(cfg, key)
        if value not in choices:
            problems.append(f"{key} must be {' or '.join(choices)}, got {value!r}")
    for key in ("exploration.clip", "reset.learn_from_forward"):
        if not isinstance(setting(cfg, key), bool):
            problems.append(f"{key} must be true or false, got {OmegaConf.select(cfg, key)!r}")
    problems += actor_problems(cfg)
    problems += learner_problems(cfg)
    if int(cfg.heat_up) < 0:
        problems.append(f"heat_up must be >= 0, got {cfg.heat_up}")
    if problems:
        raise ConfigError("invalid configuration:\n  - " + "\n  - ".join(problems))
    checkpoints = Checkpoints(run_dir / "checkpoints", keep=int(cfg.keep_checkpoints))
    if cfg.resume not in (True, False, "auto"):
        raise ConfigError(f"resume must be true, false or auto, got {cfg.resume!r}")
    if should_resume(cfg):
        latest, damaged = checkpoints.survey()
        if latest is None and damaged:
            raise ConfigError(no_intact_checkpoint(checkpoints.root, damaged))
        if latest is None:
            raise ConfigError(f"resume=true but {checkpoints.root} holds no complete checkpoint to resume from.")
        differ = identity_differences(json.loads((latest / "meta.json").read_text()), cfg)
        if differ:
            key, (saved, value) = next(iter(differ.items()))
            raise ConfigError(
                f"the checkpoint in {latest} is from {key} {saved!r}, this run is {key} {value!r}; "
                "use another run_dir or the matching task, algo and seed."
            )
    elif held := checkpoints.folders():
        raise ConfigError(
            f"{cfg.run_dir} already holds a checkpoint ({held[0].name}); pass resume=true to "
            "continue it, or choose another run_dir."
        )
    threads = cfg.threads
    if threads != "auto" and not (isinstance(threads, int) and threads >= 1):
        raise ConfigError(f"threads must be a positive integer or auto, got {threads!r}")




def recipe_settings(conf: Path = CONF) -> tuple[frozenset[str], frozenset[str]]:
    """The settings the recipe defines, as dotted keys: those of ``config.yaml``, of every option of its
    groups (``algo/``, ``preset/``, ``reset_actor/``), each where Hydra puts it (under the group's name, or where
    the file's ``# @package`` header says), and of every task of the registry (:func:`.hydra_config.task_node`).
    Also returns the open mappings: an empty mapping in a file (``env: {}``) holds another function's keyword
    arguments, which that function checks."""
    file_keys, file_open = _file_settings(conf)
    keys, open_mappings = set(file_keys), set(file_open)
    for spec in TASKS.values():  # read at each call: a task added to the registry is known at once
        _add_keys(task_node(spec), "", keys, open_mappings)
    return frozenset(keys), frozenset(open_mappings)


@functools.lru_cache(maxsize=None)
def _file_settings(conf: Path) -> tuple[frozenset[str], frozenset[str]]:
    """The settings of ``conf``'s files: ``config.yaml`` and its groups' options (:func:`recipe_settings`)."""
    keys, open_mappings = set(), set()

    def add(node: dict, prefix: str) -> None:
        _add_keys(node, prefix, keys, open_mappings)

    root = OmegaConf.to_container(OmegaConf.load(conf / "config.yaml"), resolve=False)
    for hydra_key in ("defaults", "hydra"):
        root.pop(hydra_key, None)
    add(root, "")
    for group in sorted(p for p in conf.iterdir() if p.is_dir()):
        for option in sorted(group.glob("*.yaml")):
            package = _package_header(option) or group.name
            if package != "_global_":
                keys.update(".".join(package.split(".")[: i + 1]) for i in range(package.count(".") + 1))
            node = OmegaConf.to_container(OmegaConf.load(option), resolve=False) or {}
            node.pop("defaults", None)  # the option's own choices of other groups (preset=paper's reset actor)
            add(node, "" if package == "_global_" else f"{package}.")
    return frozenset(keys), frozenset(open_mappings)


def _add_keys(node: dict, prefix: str, keys: set, open_mappings: set) -> None:
    """Adds the dotted keys of ``node`` under ``prefix`` to ``keys``, and its empty mappings to ``open_mappings``."""
    for key, value in node.items():
        path = f"{prefix}{key}"
        keys.add(path)
        if isinstance(value, dict):
            if not value:
                open_mappings.add(path)
            _add_keys(value, f"{path}.", keys, open_mappings)


def _package_header(path: Path) -> str | None:
    """The ``# @package <name>`` header of a config file's leading comments, or None."""
    for line in path.read_text().splitlines():
        if not line.startswith("#"):
            break
        if line.lstrip("# ").startswith("@package"):
            return line.lstrip("# ").split(None, 1)[1].strip()
    return None


def retired_key_problem(key: str) -> str:
    """The line for a key of run batching (:data:`RETIRED_KEYS`): unknown now, and what runs seeds instead."""
    return (f"unknown key {key}: run batching (seeds=, arms=, vary=, speed.batched_acting) was retired, its last "
            f"commit is {LAST_BATCHING_COMMIT}; run seeds and settings as a Hydra -m grid instead, one process per run "
            "(python recipes/train.py -m seed=0,1,2; docs/many-runs.md)")


def command_line_problems(args, conf: Path = CONF) -> list[str]:
    """The lines for the overrides of a command line (``sys.argv[1:]``) that no configuration could take, found
    before Hydra composes one: a key of run batching (retired, with or without ``+``: what runs seeds instead),
    and a plain override (``key=value``, no leading ``+`` or ``~``) of a key that the recipe defines nowhere
    (:func:`recipe_settings`), with the closest known key. Hydra would refuse the latter as well, but says only
    that the key is not in its struct and suggests appending it with ``+``. A group's choice (``task=...``), a
    key under an open mapping (``env.acceleration=...``) and Hydra's own (``hydra.*``, ``hydra/launcher=...``)
    are left to Hydra; an added key (``+key=...``) is checked once composed (:func:`unknown_settings`)."""
    keys, open_mappings = recipe_settings(conf)
    groups = {p.name for p in conf.iterdir() if p.is_dir()} | {"task"}
    lines, seen = [], set()
    for arg in args:
        if "=" not in arg or arg.startswith("-"):
            continue
        raw = arg.split("=", 1)[0]
        key = raw.lstrip("+~").replace("/", ".")
        if key in seen:
            continue
        seen.add(key)
        if key in RETIRED_KEYS or not (raw[:1] in "+~" or "@" in key or key.split(".")[0] == "hydra" or key in keys
                                       or key in groups or any(key.startswith(f"{m}.") for m in open_mappings)):
            lines.append(_unknown_key_problem(key, keys, added=False))
    return lines


def unknown_settings(cfg: DictConfig, conf: Path = CONF) -> list[str]:
    """A line for each key of ``cfg`` that the recipe does not define (:func:`recipe_settings`), such as the
    misspelled ``+total_step=1000``: the recipe would never read it (a key of run batching, retired, says so
    and what runs seeds instead). Hydra's own ``hydra.*`` is left alone."""
    keys, open_mappings = recipe_settings(conf)
    unknown = []

    def walk(node: dict, prefix: str) -> None:
        for key, value in node.items():
            path = f"{prefix}{key}"
            if not prefix and key == "hydra":
                continue
            if path not in keys:
                unknown.append(path)
            elif isinstance(value, dict) and path not in open_mappings:
                walk(value, f"{path}.")

    walk(OmegaConf.to_container(cfg, resolve=False), "")
    return [_unknown_key_problem(path, keys, added=True) for path in unknown]


def _unknown_key_problem(key: str, keys, *, added: bool) -> str:
    """The line for a key the recipe does not define: a key of run batching says it was retired; another names the
    closest known key, if one is close (``added``: the key came with a leading +, which the fix drops)."""
    if key in RETIRED_KEYS:
        return retired_key_problem(key)
    close = difflib.get_close_matches(key, sorted(keys), n=1, cutoff=0.6)
    hint = ""
    if close:
        hint = f"; the closest known key is {close[0]}" + (f" (set it without a leading +: {close[0]}=...)" if added else "")
    return (f"unknown key {key}: the recipe's configuration (recipes/conf and the task registry) does not define it, so "
            f"nothing would read it{hint}")
