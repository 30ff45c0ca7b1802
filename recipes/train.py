"""Train a forward agent with a learned reset agent (ours, LNT or LNT-sparse) on one task, without free resets.

    python recipes/train.py task=peg_insertion_insert algo=ours seed=0            # the paper's settings
    python recipes/train.py task=cliff_cheetah algo=lnt preset=quick              # a short CPU run
    python recipes/train.py task=cliff_cheetah algo=lnt preset=quick resume=true  # continue a killed run
    python recipes/train.py -m task=peg_insertion_insert algo=ours,lnt,lnt_sparse seed=0,1,2  # a grid, in parallel
    python recipes/train.py -m task=cliff_cheetah algo=ours seed=0,1,2 task.p_thresh=0.1,0.3 \
        run_dir='runs/${task.name}/${algo.name}/p${task.p_thresh}/seed${seed}'  # Fig. 4: 6 runs

Tasks: every name of the task registry, ``torchrl_reset_envs.TASKS`` (the paper's six and the UR3 arm's two;
``task=`` with no name lists them). Everything lands in ``run_dir`` (default ``runs/<task>/<algo>/seed<seed>``):
``progress.csv`` (the training metrics every ``log_every`` steps), ``eval.csv`` (one row per
evaluation), ``triggers.csv`` (the state before each triggered reset), ``diagnostics.csv`` (the
trigger's scores and the reset classifier on examples, replay and forward states, every
``log_every`` steps), ``resets.csv`` (each reset episode's outcome and its distance from the start), ``summary.json`` (the paper's
Table 1 metrics), ``checkpoints/`` and torchrl's CSV (and optionally wandb) logs. ``report.py`` turns
run folders into the paper's table and figures.
"""
from __future__ import annotations

import json
import logging
import os
import re
import shlex
import signal
import sys
from pathlib import Path

import hydra
from omegaconf import DictConfig

from torchrl_reset import DualCollector
from torchrl_reset_envs.ur3_backends import RobotFault
from torchrl_reset_recipes.training.async_learner import AsyncLearner, LearnerFailed
from torchrl_reset_recipes.training.checkpoints import CheckpointDamaged, Checkpoints
from torchrl_reset_recipes.training.config_checks import ConfigError, command_line_problems, validate
from torchrl_reset_recipes.training.learner import NonFiniteLoss
from torchrl_reset_recipes.training.run_folder import RunFolderBusy, RunInterrupted, run_folder_lock, stop_on_signals
from torchrl_reset_recipes.training.hydra_config import register_task_configs
from torchrl_reset_recipes.training.run_spec import RunSpec, run_spec
from torchrl_reset_recipes.training.single_run import RobotStopped, TrainingDiverged, build_run, set_up_frozen, set_up_process
from torchrl_reset_recipes.training.updates import learn_step

log = logging.getLogger("torchrl_reset.train")


def train(cfg: DictConfig) -> dict:
    """Run (or resume) one training run; returns the summary also written to ``summary.json``. A signal that
    stops it (Ctrl-C, SIGTERM) raises :class:`RunInterrupted` once it is checkpointed, with the summary."""
    run_dir = Path(cfg.run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    with run_folder_lock(run_dir):
        return _train(cfg)


def _train(cfg: DictConfig) -> dict:
    spec = run_spec(cfg)  # checked (again: under the run folder's lock) and worked out, once
    if (done := finished_summary(spec)) is not None:  # relaunched (a grid again with resume=auto): nothing to run
        log.info("%s finished at step %d; its files are left as they are", cfg.run_dir, done["steps"])
        return done
    run = build_run(spec, set_up_process(spec))
    remote = start_async_learner(run) if spec["learner.mode"] == "async" else None  # the learner's own process
    try:
        with set_up_frozen(run.robot):  # on a real-time arm: no full garbage collection over the set-up's objects
            return _loop(cfg, run, remote)
    except LearnerFailed as err:  # the learner process crashed or hung: the arm stops, the last checkpoint stands
        if run.robot is not None:
            run.robot.backend.stop()
        raise LearnerStopped(f"{err}\nThe arm is stopped; the last checkpoint stands, and resume=auto continues from "
                             "it.") from err
    finally:
        if remote is not None:
            remote.close()


def _loop(cfg: DictConfig, run, remote) -> dict:
    """Algorithm 1's loop over the run's collector (the learner's part here, or in its process with ``remote``)."""
    collector, learner = run.collector, run.learner

    # Algorithm 1, lines 5-28: each batch is one action of a forward or a reset episode
    stopped_by = None  # the signal (SIGINT, SIGTERM) that ends the run after its current step
    try:
        with stop_on_signals() as stop_requested:
            steps, streams = iter(collector), run.streams
            while True:
                with streams.use("actor"):  # learner.streams: separate gives acting and learning a stream each
                    batch = next(steps, None)
                if batch is None:
                    break
                batch = batch.to(cfg.device)
                phase = DualCollector.phase_of(batch)
                if remote is not None:  # learner.mode=async: the learner stores it and updates in its process
                    remote.send(batch, phase)
                    remote.after_step(episode_ended=bool(batch.get(("next", "done")).any()),
                                      halted=bool(batch.get(("next", "terminated")).any()))
                else:
                    with streams.use("learner"):
                        learn_step(learner, batch, phase)  # store the step, then that agent's updates
                with streams.use("actor"):
                    run.after_step(batch, phase)  # its record; the evaluation, log row and checkpoint when due
                if stop_requested:
                    stopped_by = stop_requested[0]
                    log.warning("%s at step %d: checkpointing", signal.Signals(stopped_by).name, collector.frames)
                    break
            if remote is not None:  # the acting is over: the learner works off the updates it still owes
                remote.achieved_at_end = remote.updates_achieved()
                remote.drain()
    except KeyboardInterrupt:  # a second Ctrl-C: the step under way was cut short, its state is not saved
        raise RunInterrupted(signal.SIGINT, [], f"stopped at once at step {collector.frames}, without a checkpoint "
                                                "there; the last checkpoint stands") from None
    except NonFiniteLoss as err:
        path = run.state.save()  # the update stopped before it changed anything: the last good state
        raise TrainingDiverged(
            f"non-finite loss at step {collector.frames} ({err}); the last good state is checkpointed in {path}. "
            "Lower the learning rates or check the inputs."
        ) from err
    except RobotFault as err:  # the robot must not go on (emergency stop, too many protective stops...)
        path = run.checkpoint()
        raise RobotStopped(f"{err} The run is checkpointed in {path}; resume=true continues it.") from err
    finally:
        run.record.close()
    summary = run.finish(stopped_by is not None)
    if stopped_by is not None:
        raise RunInterrupted(stopped_by, [summary], f"{signal.Signals(stopped_by).name} stopped the run at step "
                                                    f"{collector.frames}, checkpointed there")
    return summary


class LearnerStopped(RuntimeError):
    """``learner.mode=async``: the learner process failed; the arm was stopped."""


def start_async_learner(run) -> AsyncLearner:
    """``learner.mode=async``: starts the learner process (from the checkpoint the run resumed from), writes its
    part into every checkpoint, and stands in for the run's learner in the records."""
    resumed = run.state.loaded_from if run.spec.resume else None
    remote = AsyncLearner(run.spec, run.forward, run.reset, run.collector, None if resumed is None else str(resumed),
                          updates=run.record.history["updates"], last_losses=run.record.history["last_losses"],
                          robot=run.robot)
    run.state.extra_writers.append(remote.checkpoint)
    run.learner = remote
    return remote


def finished_summary(spec: RunSpec) -> dict | None:
    """The saved summary of a run that already reached ``total_steps`` and is asked to resume, or None. Such a
    run is not rebuilt: its tables, ``code.jsonl`` and summary stay as its last stretch wrote them."""
    cfg, summary_file = spec.cfg, Path(spec.cfg.run_dir) / "summary.json"
    if not spec.resume or not summary_file.exists():
        return None
    summary = json.loads(summary_file.read_text())
    latest = Checkpoints(Path(cfg.run_dir) / "checkpoints").latest()
    saved = None if latest is None else int(json.loads((latest / "meta.json").read_text())["frames"])
    if summary.get("finished") and saved == summary.get("steps") and saved >= int(cfg.total_steps):
        return summary
    return None


# Hydra makes its run folder and writes its own files there (.hydra/, its log) before the recipe sees the
# configuration. A single run's Hydra folder is therefore the working directory, with those files off (unless
# the command line sets them): a refused configuration (an unknown key, run_dir naming a file) leaves nothing
# behind, and the recipe writes train.log into the run folder itself. A -m grid keeps Hydra's job folders.
SINGLE_RUN_HYDRA = (("hydra.run.dir", "hydra.run.dir=."), ("hydra.output_subdir", "hydra.output_subdir=null"),
                    ("hydra.job_logging", "~hydra.job_logging.handlers.file"),
                    ("hydra.job_logging", "hydra.job_logging.root.handlers=[console]"))
LOG_FORMAT = "[%(asctime)s][%(name)s][%(levelname)s] - %(message)s"  # Hydra's


def main() -> None:
    """The command line: ``python recipes/train.py [overrides]`` (see the module's docstring). An override no
    configuration could take stops it before Hydra (exit 2, :func:`command_line_problems`): a key of run batching
    (``seeds=3``, ``arms=2``: retired), with what runs seeds instead, or a misspelled key (``total_step=1000``),
    with the closest known key."""
    args = sys.argv[1:]
    problems = command_line_problems(args)
    if problems:
        print("error: invalid configuration:\n  - " + "\n  - ".join(problems), file=sys.stderr)
        sys.exit(2)
    if not any(a in ("-m", "--multirun") or a.startswith("hydra.mode=") for a in args):
        given = {a.lstrip("+~").split("=")[0].replace("/", ".") for a in args}
        extra = [override for key, override in SINGLE_RUN_HYDRA if not any(g.startswith(key) for g in given)]
        # beside the command line's overrides: Hydra reads them as one run of arguments among its options
        at = max((i + 1 for i, a in enumerate(args) if "=" in a and not a.startswith("-")), default=len(args))
        sys.argv = [sys.argv[0], *args[:at], *extra, *args[at:]]
    register_task_configs()  # the group task=<name>, from the task registry as it stands now (envs/tasks.py TASKS)
    run_command()


@hydra.main(version_base="1.3", config_path="conf", config_name="config")
def run_command(cfg: DictConfig) -> None:
    """Runs the configuration's run and prints its summary. Exit status: 0 for a finished run; 2 for a
    configuration refused before anything was written; 3 for a diverged run, 4 for a robot fault (both
    checkpointed); 5 for a failed learner process (``learner.mode=async``; the last checkpoint stands); 128 + the
    signal's number for a run a signal stopped (130 for Ctrl-C, 143 for SIGTERM),
    which then prints the command that continues it."""
    try:
        validate(cfg)  # refused before the run folder exists (train checks again under the folder's lock)
        _log_to_run_folder(cfg)
        summary = train(cfg)
    except RunInterrupted as stop:
        _print_results(cfg, stop.summaries)
        print(f"{stop}. To continue:\n  {continue_command(cfg)}", file=sys.stderr)
        sys.exit(stop.exit_code)
    except KeyboardInterrupt:  # outside the training loop: while the run was being built or checkpointed
        print(f"interrupted before the run could stop cleanly; its last checkpoint stands. To continue:\n  "
              f"{continue_command(cfg)}", file=sys.stderr)
        sys.exit(128 + signal.SIGINT)
    except (ConfigError, CheckpointDamaged, RunFolderBusy, TrainingDiverged, RobotStopped, LearnerStopped) as err:
        print(f"error: {err}", file=sys.stderr)
        sys.exit({ConfigError: 2, CheckpointDamaged: 2, RunFolderBusy: 2, TrainingDiverged: 3,
                  LearnerStopped: 5}.get(type(err), 4))
    _print_results(cfg, [summary])


def _print_results(cfg: DictConfig, summaries: list[dict]) -> None:
    for summary in summaries:
        width = max(map(len, summary))
        for key, value in summary.items():
            print(f"{key:<{width}}  {value:.4g}" if isinstance(value, float) else f"{key:<{width}}  {value}")
        print(_in_words(summary))
        print(f"results in {cfg.run_dir}")


def _log_to_run_folder(cfg: DictConfig) -> None:
    """The log's lines also go to ``train.log`` in the run folder, which the file gets with its first line."""
    handler = logging.FileHandler(Path(cfg.run_dir) / "train.log", delay=True)
    handler.setFormatter(logging.Formatter(LOG_FORMAT))
    logging.getLogger().addHandler(handler)


def continue_command(cfg: DictConfig) -> str:
    """The command that continues the run: the command line as given, with ``resume=true`` when the run
    folder holds a checkpoint (``resume=auto`` otherwise, which also starts the run if it has none); a command
    with ``resume=auto`` is given back as it is. In a -m grid: this job's overrides."""
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    argv = list(sys.orig_argv)
    if HydraConfig.initialized() and HydraConfig.get().mode == RunMode.MULTIRUN:
        argv = [Path(sys.executable).name, os.path.relpath(__file__), *HydraConfig.get().overrides.task]
    if any(re.fullmatch(r"\+{0,2}resume=auto", a) for a in argv):
        return shlex.join(argv)
    held = bool(Checkpoints(Path(cfg.run_dir) / "checkpoints").folders())
    return shlex.join([*(a for a in argv if not re.fullmatch(r"\+{0,2}resume=.*", a)),
                       "resume=true" if held else "resume=auto"])


def _in_words(summary: dict) -> str:
    """The run's effect in one sentence: resets saved against an episodic agent, and how many reset episodes
    got back to the start in the first and in the last quarter of the run."""
    quarters = summary["reset_episodes_by_quarter"]
    return (f"{summary['manual_resets']} manual resets where an episodic agent would have needed "
            f"{summary['episodic_resets']} ({summary['resets_saved']} saved); "
            f"{_quarter_in_words(quarters['first'], 'the first quarter of the run')}; "
            f"{_quarter_in_words(quarters['last'], 'the last quarter')}.")


def _quarter_in_words(quarter: dict, where: str) -> str:
    span = f"steps {quarter['from_step']}-{quarter['to_step']}"
    ended, succeeded = quarter["reset_episodes"], quarter["successful_resets"]
    if ended is None:
        return f"the reset episodes of {where} ({span}) are not all in resets.csv"
    if not ended:
        return f"no reset episode ended in {where} ({span})"
    return f"{succeeded} of {ended} reset episodes succeeded in {where} ({span}, {100 * succeeded / ended:.0f}%)"


if __name__ == "__main__":
    main()
