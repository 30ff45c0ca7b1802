"""Train a forward agent with a learned reset agent (ours, LNT or LNT-sparse) on one task, without free resets.

    python recipes/train.py task=peg_insertion_insert algo=ours seed=0            # the paper's settings
    python recipes/train.py task=cliff_cheetah algo=lnt preset=quick              # a short CPU run
    python recipes/train.py task=cliff_cheetah algo=lnt preset=quick resume=true  # continue a killed run
    python recipes/train.py -m task=peg_insertion_insert algo=ours,lnt,lnt_sparse seed=0,1,2  # a grid, in parallel

Tasks: cliff_cheetah, cliff_walker, peg_insertion_insert, peg_insertion_remove, ball_in_cup_catch,
ball_in_cup_throw. Everything lands in ``run_dir`` (default ``runs/<task>/<algo>/seed<seed>``):
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
import math
import random
import signal
import sys
import time
from pathlib import Path

import hydra
import numpy as np
import torch
import torchrl
from omegaconf import DictConfig, OmegaConf
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parent))

from agents import lnt_batch, make_forward_agent, make_reset_agent, with_exploration  # noqa: E402
from buffers import buffer_keys, make_buffers  # noqa: E402
from config_checks import ConfigError, reset_horizon, should_resume, torch_threads, validate  # noqa: E402
from cpu_speed import choose_matmul_precision, matmul_products, retain_freed_memory  # noqa: E402
from run_files import (  # noqa: E402
    Checkpoints,
    CsvTable,
    RunFolderBusy,
    code_version,
    run_folder_lock,
    success_rate_by_quarter,
)
from task_envs import (  # noqa: E402
    EVAL_SEED_OFFSET,
    UpdateBudget,
    evaluate,
    make_task_env,
    realtime_env,
    safety_counters,
    task_dimensions,
)

from diagnostics import (  # noqa: E402
    DIAGNOSTIC_FIELDS,
    RESET_FIELDS,
    ResetDistances,
    TriggerScores,
    probe_classifier,
)

from torchrl_reset import DualCollector  # noqa: E402
from torchrl_reset_envs.ur3_backends import RobotFault  # noqa: E402

PROGRESS_FIELDS = [
    "frames", "forward_steps", "reset_steps", "forward_episodes", "reset_episodes", "manual_resets",
    "triggered_resets", "requested_resets", "successful_resets", "forward_share", "reset_success_rate",
    "eval_return", "average_return", "steps_per_second", "loss_forward_actor", "loss_forward_critic",
    "loss_reset_actor", "loss_reset_critic", "skipped_updates", "protective_stops",
]
EVAL_FIELDS = ["frames", "forward_return", "forward_steps", "triggered", "reset_success", "reset_steps"]
TRIGGER_FIELDS = ["frames", "steps", "value", "observation"]

log = logging.getLogger("torchrl_reset.train")


class TrainingDiverged(RuntimeError):
    """A loss became NaN or infinite; the last good state was checkpointed."""


class RobotStopped(RuntimeError):
    """The robot reported a fault the run must not go on through; the run was checkpointed."""


def train(cfg: DictConfig) -> dict:
    """Run (or resume) one training run; returns the summary also written to ``summary.json``."""
    run_dir = Path(cfg.run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    with run_folder_lock(run_dir):
        return _train(cfg)


def _train(cfg: DictConfig) -> dict:
    validate(cfg)
    run_dir = Path(cfg.run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    torch.set_num_threads(torch_threads(cfg))
    if cfg.speed.retain_memory:
        retain_freed_memory()
    # a setting of CPU products: with the networks on another device it changes nothing
    on_cpu = torch.device(cfg.device).type == "cpu"
    precision_setting = OmegaConf.select(cfg, "speed.matmul_precision", default="ieee") if on_cpu else "ieee"
    matmul_precision = choose_matmul_precision(precision_setting)
    torch.manual_seed(cfg.seed)
    np.random.seed(cfg.seed)
    random.seed(cfg.seed)
    logging.getLogger("torchrl").setLevel(logging.WARNING)

    # ------------------------------------------------------------------ build
    obs_dim, action_spec = task_dimensions(cfg)
    forward = make_forward_agent(cfg, obs_dim, action_spec)
    reset = make_reset_agent(cfg, obs_dim, action_spec)
    for agent in (forward, reset):
        agent.loss.to(cfg.device)
    env, trigger = make_task_env(cfg, reset)
    eval_env, eval_trigger = make_task_env(cfg, reset, for_eval=True)
    collector = DualCollector(
        env,
        with_exploration(forward.actor, env.action_spec, cfg),
        with_exploration(reset.actor, env.action_spec, cfg),
        max_forward_steps=int(cfg.task.forward_horizon),
        max_reset_steps=reset_horizon(cfg),
        min_reset_steps=int(cfg.reset.min_steps),
        total_frames=int(cfg.total_steps),
    )
    collector.set_seed(int(cfg.seed))
    eval_env.set_seed(int(cfg.seed) + EVAL_SEED_OFFSET)
    forward_rb, reset_rb = make_buffers(cfg)
    forward_keys, reset_keys = buffer_keys(cfg, forward, reset)
    checkpoints = Checkpoints(run_dir / "checkpoints", keep=int(cfg.keep_checkpoints))
    progress = CsvTable(run_dir / "progress.csv", PROGRESS_FIELDS)
    evals = CsvTable(run_dir / "eval.csv", EVAL_FIELDS)
    triggers = CsvTable(run_dir / "triggers.csv", TRIGGER_FIELDS)
    diagnostics = CsvTable(run_dir / "diagnostics.csv", DIAGNOSTIC_FIELDS)
    resets = CsvTable(run_dir / "resets.csv", RESET_FIELDS)
    trigger_scores = TriggerScores(trigger.score_key, trigger.threshold)
    distances = ResetDistances(collector.example_buffer)
    history = {"eval_returns": [], "last_losses": {}, "elapsed": 0.0}

    def write_checkpoint(folder: Path) -> None:
        torch.save(
            {
                "forward_loss": forward.loss.state_dict(),
                "reset_loss": reset.loss.state_dict(),
                "forward_optimizer": forward.optimizer.state_dict(),
                "reset_optimizer": reset.optimizer.state_dict(),
                "collector": collector.state_dict(),
                "history": history,
                "rng": {"torch": torch.get_rng_state(), "numpy": np.random.get_state(), "python": random.getstate()},
            },
            folder / "state.pt",
        )
        for name, rb in (("forward_buffer", forward_rb), ("reset_buffer", reset_rb)):
            if len(rb):  # torchrl cannot dump a buffer that never received data
                rb.dumps(folder / name)

    def checkpoint() -> Path:
        meta = {"task": cfg.task.name, "algo": cfg.algo.name, "seed": int(cfg.seed), "frames": collector.frames}
        return checkpoints.save(collector.frames, write_checkpoint, meta)

    if should_resume(cfg):
        folder = checkpoints.latest()
        state = torch.load(folder / "state.pt", weights_only=False)
        forward.loss.load_state_dict(state["forward_loss"])
        reset.loss.load_state_dict(state["reset_loss"])
        forward.optimizer.load_state_dict(state["forward_optimizer"])
        reset.optimizer.load_state_dict(state["reset_optimizer"])
        for name, rb in (("forward_buffer", forward_rb), ("reset_buffer", reset_rb)):
            if (folder / name).exists():
                rb.loads(folder / name)
        collector.load_state_dict(state["collector"])
        history = state["history"]
        torch.set_rng_state(state["rng"]["torch"])
        np.random.set_state(state["rng"]["numpy"])
        random.setstate(state["rng"]["python"])
        for table in (progress, evals, triggers, diagnostics, resets):
            table.truncate_after(collector.frames)
        log.info("resumed from %s at step %d", folder, collector.frames)
    else:
        # a fresh start: tables left by an earlier attempt that never checkpointed start over
        for table in (progress, evals, triggers, diagnostics, resets):
            table.truncate_after(-1)
        for stale in ("summary.json", "code.jsonl"):
            (run_dir / stale).unlink(missing_ok=True)
        (run_dir / "config.yaml").write_text(OmegaConf.to_yaml(cfg, resolve=True))
    # the code each stretch of the run ran at (a resumed run appends its own line)
    with open(run_dir / "code.jsonl", "a") as f:
        f.write(json.dumps({"from_step": collector.frames, **code_version()}) + "\n")

    loggers = make_loggers(cfg, run_dir)
    h_f, h_r = int(cfg.task.forward_horizon), reset_horizon(cfg)
    curriculum_index = int(cfg.task.curriculum.index)
    heat_up = int(cfg.heat_up)
    ensemble_size = int(cfg.algo.num_members)

    compiled = set(cfg.speed.compile)
    losses_of = {id(agent): torch.compile(agent.loss) if name in compiled else agent.loss
                 for name, agent in (("forward", forward), ("reset", reset))}
    robot = realtime_env(env)
    budget = UpdateBudget()

    def fits(name: str) -> bool:
        """On a real-time robot, whether the update fits in what is left of the control period."""
        return robot is None or budget.fits(name, robot.time_left())

    def update(agent, sample, names) -> dict[str, float]:
        with matmul_products(matmul_precision):
            return _update(agent, sample, names)

    def _update(agent, sample, names) -> dict[str, float]:
        started = time.perf_counter()
        losses = losses_of[id(agent)](sample)
        total = sum(losses[name] for name in names)
        if not torch.isfinite(total):
            path = checkpoint()
            raise TrainingDiverged(
                f"non-finite loss at step {collector.frames} ({', '.join(f'{n}={float(losses[n].detach())}' for n in names)}); "
                f"the last good state is checkpointed in {path}. Lower the learning rates or check the inputs."
            )
        agent.optimizer.zero_grad()
        total.backward()
        agent.optimizer.step()
        agent.targets.step()
        budget.record("forward" if agent is forward else "reset", time.perf_counter() - started)
        return {name: float(losses[name].detach()) for name in names}

    def log_row(elapsed: float) -> dict:
        c = collector.counters
        returns = history["eval_returns"]
        losses = history["last_losses"]
        return {
            "frames": collector.frames, **{k: c[k] for k in PROGRESS_FIELDS if k in c},
            "forward_share": collector.forward_share, "reset_success_rate": collector.reset_success_rate,
            "eval_return": returns[-1] if returns else float("nan"),
            "average_return": float(np.mean(returns)) if returns else float("nan"),
            "steps_per_second": collector.frames / max(elapsed, 1e-9), "skipped_updates": budget.skipped, **losses,
            "protective_stops": safety_counters(env).get("protective_stops", 0),
        }

    # wall time of the steps of each phase once its agent updates (env step, policy, trigger, buffer, update),
    # once both agents made 10 updates: the first ones include one-off costs (with speed.compile, the
    # compile pause and a recompile of the forward loss when the reset agent's first update runs)
    step_time = history.setdefault("step_time", {"forward": [0.0, 0], "reset": [0.0, 0]})
    warm_up_updates = 10
    bar = tqdm(total=int(cfg.total_steps), initial=collector.frames, desc=f"{cfg.task.name}/{cfg.algo.name}",
               unit="step", mininterval=2.0, disable=not cfg.progress_bar, dynamic_ncols=True)
    start = time.perf_counter() - history["elapsed"]
    interrupted = False
    last = time.perf_counter()
    # SIGTERM (a cluster's pre-emption, `kill`) ends the run after the current step, with a checkpoint
    stop_requested: list[int] = []
    try:
        previous_handler = signal.signal(signal.SIGTERM, lambda signum, frame: stop_requested.append(signum))
    except ValueError:  # not the main thread: leave signals alone
        previous_handler = None
    try:
        for batch in collector:
            batch = batch.to(cfg.device)
            phase = DualCollector.phase_of(batch)
            updating = collector.counters[f"{phase}_steps"] > heat_up
            timed = min(collector.counters["forward_steps"], collector.counters["reset_steps"]) > heat_up + warm_up_updates
            if phase == "forward":
                forward_rb.extend(batch.select(*forward_keys, strict=False))
                trigger_scores.add(batch)
                if updating and fits("forward"):
                    out = update(forward, forward_rb.sample(), ("loss_actor", "loss_value"))
                    history["last_losses"].update(loss_forward_actor=out["loss_actor"], loss_forward_critic=out["loss_value"])
            else:
                reset_rb.extend(batch.select(*reset_keys, strict=False))
                if updating and fits("reset"):
                    fallbacks = getattr(reset_rb.sampler, "fallbacks", 0)
                    sample = reset_rb.sample().to(cfg.device)
                    if getattr(reset_rb.sampler, "fallbacks", 0) > fallbacks:
                        # no reset episode has n transitions yet: the release uses the one-step label
                        sample.set("one_step", torch.ones(sample.shape[0], dtype=torch.bool, device=sample.device))
                    if cfg.algo.name == "ours":
                        sample.set("example", collector.example_buffer.sample(sample.shape[0]).to(cfg.device))
                        out = update(reset, sample, ("loss_actor", "loss_classifier"))
                        history["last_losses"].update(loss_reset_actor=out["loss_actor"], loss_reset_critic=out["loss_classifier"])
                    else:
                        out = update(reset, lnt_batch(sample, cfg.algo, ensemble_size), ("loss_actor", "loss_value"))
                        history["last_losses"].update(loss_reset_actor=out["loss_actor"], loss_reset_critic=out["loss_value"])
            frames = collector.frames
            now = time.perf_counter()
            if timed:
                step_time[phase][0] += now - last
                step_time[phase][1] += batch.numel()
            last = now
            bar.update(batch.numel())
            for event in collector.pop_events():
                trigger_scores.add_event(event)
                if event["phase"] == "reset":
                    resets.append(distances.row(event))
                if event["outcome"] == "triggered":
                    obs = event["state"]["observation"].flatten().tolist()
                    triggers.append({"frames": event["frame"], "steps": event["steps"], "value": obs[curriculum_index],
                                     "observation": " ".join(f"{v:.5g}" for v in obs)})
            if frames % int(cfg.eval_every) == 0:
                result = evaluate(eval_env, eval_trigger, forward.actor, reset.actor, horizon=h_f, reset_horizon=h_r,
                                  min_reset_steps=int(cfg.reset.min_steps), gamma=float(cfg.gamma))
                history["eval_returns"].append(result["forward_return"])
                evals.append({"frames": frames, **result})
            if frames % int(cfg.log_every) == 0:
                history["elapsed"] = time.perf_counter() - start
                row = log_row(history["elapsed"])
                progress.append(row)
                fallbacks = getattr(reset_rb.sampler, "fallbacks", "")
                with torch.random.fork_rng(devices=[]):  # the probe's samples leave training's random stream as it was
                    probe = probe_classifier(cfg.algo.name, reset.model, reset.actor, collector.example_buffer,
                                             forward_rb, reset_rb, trigger.threshold)
                if fallbacks != "":
                    reset_rb.sampler.fallbacks = fallbacks  # the probe's own sample does not count
                diagnostics.append({"frames": frames, **trigger_scores.row(), **probe, "sampler_fallbacks": fallbacks})
                for logger in loggers:
                    logger.log_metrics({k: v for k, v in row.items() if k != "frames" and not _isnan(v)}, step=frames)
                bar.set_postfix(sps=f"{row['steps_per_second']:.0f}", manual=row["manual_resets"],
                                ret=f"{row['eval_return']:.2f}", refresh=False)
            if frames % int(cfg.checkpoint_every) == 0:
                history["elapsed"] = time.perf_counter() - start
                checkpoint()
            if stop_requested:
                interrupted = True
                log.warning("SIGTERM at step %d: checkpointing", collector.frames)
                break
    except KeyboardInterrupt:
        interrupted = True
        log.warning("interrupted at step %d: checkpointing", collector.frames)
    except RobotFault as err:  # the robot must not go on (emergency stop, too many protective stops...)
        bar.close()
        history["elapsed"] = time.perf_counter() - start
        path = checkpoint()
        raise RobotStopped(f"{err} The run is checkpointed in {path}; resume=true continues it.") from err
    finally:
        bar.close()
        if previous_handler is not None:
            signal.signal(signal.SIGTERM, previous_handler)
    history["elapsed"] = time.perf_counter() - start
    checkpoint()
    summary = {
        "task": cfg.task.name, "algo": cfg.algo.name, "seed": int(cfg.seed),
        # the threshold the trigger used (ours: algo.threshold when set, else the task's p_thresh)
        "p_thresh": float(trigger.threshold) if cfg.algo.name == "ours" else float(cfg.task.p_thresh),
        "steps": collector.frames, "finished": collector.frames >= int(cfg.total_steps) and not interrupted,
        "average_return": float(np.mean(history["eval_returns"])) if history["eval_returns"] else None,
        "manual_resets": collector.counters["manual_resets"],
        # an episodic agent needs one reset per forward episode (the release logs it as the baseline)
        "episodic_resets": collector.counters["forward_episodes"],
        "resets_saved": collector.counters["forward_episodes"] - collector.counters["manual_resets"],
        "forward_share": collector.forward_share,
        "reset_success_rate": collector.reset_success_rate,
        **success_rate_by_quarter(progress.path),
        "final_eval_return": history["eval_returns"][-1] if history["eval_returns"] else None,
        "evaluations": len(history["eval_returns"]),
        **{k: collector.counters[k] for k in ("triggered_resets", "requested_resets", "successful_resets", "reset_episodes")},
        "skipped_updates": budget.skipped,
        "overruns": getattr(robot, "overruns", 0),
        "protective_stops": safety_counters(env).get("protective_stops", 0),
        "safety": safety_counters(env),
        "seconds": round(history["elapsed"], 1),
        "steps_per_second": round(collector.frames / max(history["elapsed"], 1e-9), 1),
        "step_seconds": {name: (total / count if count else None) for name, (total, count) in step_time.items()},
        "device": str(cfg.device), "matmul_precision": matmul_precision, **code_version(),
        "torch": torch.__version__, "torchrl": torchrl.__version__,
    }
    (run_dir / "summary.json").write_text(json.dumps(summary, indent=2, default=_json_default))
    collector.shutdown()
    eval_env.close()
    for logger in loggers:
        finish = getattr(getattr(logger, "experiment", None), "finish", None)
        if callable(finish):  # wandb: close the run so its files are complete
            finish()
    return summary


def make_loggers(cfg: DictConfig, run_dir: Path) -> list:
    from torchrl.record.loggers import CSVLogger

    loggers = [CSVLogger(exp_name="torchrl", log_dir=str(run_dir / "logs"))]
    if cfg.logger.wandb:
        from torchrl.record.loggers.wandb import WandbLogger

        loggers.append(WandbLogger(
            exp_name=f"{cfg.task.name}-{cfg.algo.name}-seed{cfg.seed}", offline=cfg.logger.wandb_mode != "online",
            save_dir=str(run_dir / "wandb"), project=cfg.logger.project, config=OmegaConf.to_container(cfg, resolve=True),
        ))
    return loggers


def _isnan(value) -> bool:
    return isinstance(value, float) and math.isnan(value)


def _json_default(value):
    if isinstance(value, (np.floating, np.integer)):
        return value.item()
    return float(value)


@hydra.main(version_base="1.3", config_path="conf", config_name="config")
def main(cfg: DictConfig) -> None:
    try:
        summary = train(cfg)
    except (ConfigError, RunFolderBusy, TrainingDiverged, RobotStopped) as err:
        print(f"error: {err}", file=sys.stderr)
        sys.exit({ConfigError: 2, RunFolderBusy: 2, TrainingDiverged: 3}.get(type(err), 4))
    width = max(map(len, summary))
    for key, value in summary.items():
        print(f"{key:<{width}}  {value:.4g}" if isinstance(value, float) else f"{key:<{width}}  {value}")
    print(_in_words(summary))
    print(f"results in {cfg.run_dir}")


def _in_words(summary: dict) -> str:
    """The run's effect in one sentence: resets saved against an episodic agent, and the success trend."""
    def pct(value):
        return "n/a" if value is None or (isinstance(value, float) and math.isnan(value)) else f"{100 * value:.0f}%"

    return (f"{summary['manual_resets']} manual resets where an episodic agent would have needed "
            f"{summary['episodic_resets']} ({summary['resets_saved']} saved); reset success rate "
            f"{pct(summary['reset_success_rate_first_quarter'])} in the first quarter of the run, "
            f"{pct(summary['reset_success_rate_last_quarter'])} in the last.")


if __name__ == "__main__":
    main()
