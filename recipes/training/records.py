"""What a run writes while it trains: its tables, loggers and progress bar, and its summary at the end.

``progress.csv`` (training metrics every ``log_every`` steps), ``eval.csv`` (one row per evaluation),
``triggers.csv`` (the state before each triggered reset), ``diagnostics.csv`` and ``resets.csv``
(``diagnostics.py``), torchrl's CSV logs (and optionally wandb), and ``summary.json`` (the paper's
Table 1 metrics).
"""
from __future__ import annotations

import json
import logging
import math
import time
from pathlib import Path

import numpy as np
import torch
import torchrl
from omegaconf import DictConfig, OmegaConf
from tqdm import tqdm

from torchrl_reset_recipes.training.buffers import fallback_count, restore_fallback_count
from torchrl_reset_recipes.training.run_spec import RunSpec
from torchrl_reset_recipes.training.agents import forward_head, reset_head
from torchrl_reset_recipes.training.learner import LEARNER_FIELDS, learner_fields
from torchrl_reset_recipes.training.diagnostics import DIAGNOSTIC_FIELDS, RESET_FIELDS, ResetDistances, TriggerScores, probe_classifier
from torchrl_reset_recipes.training.run_folder import CsvTable, code_version, processor_name, reset_outcomes_by_quarter
from torchrl_reset_recipes.training.task_envs import realtime_env, safety_counters

log = logging.getLogger("torchrl_reset.train")

__all__ = ["PROGRESS_FIELDS", "EVAL_FIELDS", "TRIGGER_FIELDS", "RunRecord", "make_loggers"]

PROGRESS_FIELDS = [
    "frames", "forward_steps", "reset_steps", "forward_episodes", "reset_episodes", "manual_resets",
    "triggered_resets", "requested_resets", "successful_resets", "forward_share", "reset_success_rate",
    "eval_return", "average_return", "steps_per_second", "loss_forward_actor", "loss_forward_critic",
    "loss_reset_actor", "loss_reset_critic", "skipped_updates", "protective_stops",
    "irrecoverable_forward", "irrecoverable_reset",
    # the policies' saturation over the log window: the share of their noiseless action components beyond 0.99 of
    # the bound (normalised coordinates) on the steps they took, and the mean |pre-activation| (the tanh's input)
    "forward_saturation", "forward_preact_abs", "reset_saturation", "reset_preact_abs",
    # triggered resets whose stopped state already passed the env's at-initial-state check (so far)
    "triggers_at_initial_state",
    # on a real-time robot: steps called after the control period ended (so far), and each agent's updates as a
    # fraction of Algorithm 1's count (one per step of its phase past heat-up)
    "overruns", "forward_updates_achieved", "reset_updates_achieved",
    # learner.mode=async, over the log window: the learner's lag and the weights' age (steps), the queue's deepest,
    # the seconds waited at episode boundaries (all 0 in sync)
    *LEARNER_FIELDS,
]
EVAL_FIELDS = ["frames", "forward_return", "forward_steps", "triggered", "reset_success", "reset_steps"]
TRIGGER_FIELDS = ["frames", "steps", "value", "irrecoverable", "at_initial_state", "observation"]
# the steps of each phase are timed once both agents made this many updates: the first ones include
# one-off costs (with speed.compile, the compile pause and a recompile of the forward loss)
WARM_UP_UPDATES = 10


def make_loggers(cfg: DictConfig, run_dir: Path) -> list:
    """torchrl's CSV logger in ``run_dir/logs``; with ``logger.wandb``, also wandb (offline by default)."""
    from torchrl.record.loggers import CSVLogger

    loggers = [CSVLogger(exp_name="torchrl", log_dir=str(run_dir / "logs"))]
    if cfg.logger.wandb:
        from torchrl.record.loggers.wandb import WandbLogger

        loggers.append(WandbLogger(
            exp_name=f"{cfg.task.name}-{cfg.algo.name}-seed{cfg.seed}", offline=cfg.logger.wandb_mode != "online",
            save_dir=str(run_dir / "wandb"), project=cfg.logger.project, config=OmegaConf.to_container(cfg, resolve=True),
        ))
    return loggers


class RunRecord:
    """The run's tables and counters of what happened; ``history`` travels in every checkpoint."""

    def __init__(self, spec: RunSpec, run_dir: Path, collector, trigger) -> None:
        cfg = spec.cfg
        self.spec, self.cfg, self.run_dir, self.collector, self.trigger = spec, cfg, run_dir, collector, trigger
        self.progress = CsvTable(run_dir / "progress.csv", PROGRESS_FIELDS)
        self.evals = CsvTable(run_dir / "eval.csv", EVAL_FIELDS)
        self.triggers = CsvTable(run_dir / "triggers.csv", TRIGGER_FIELDS)
        self.diagnostics = CsvTable(run_dir / "diagnostics.csv", DIAGNOSTIC_FIELDS)
        self.resets = CsvTable(run_dir / "resets.csv", RESET_FIELDS)
        self.trigger_scores = TriggerScores(trigger.score_key, trigger.threshold)
        self.distances = ResetDistances(collector.example_buffer)
        self.history = {"eval_returns": [], "last_losses": {}, "elapsed": 0.0}
        self.curriculum_index = int(cfg.task.curriculum.index)
        self.heat_up = int(cfg.heat_up)
        self.heads = {"forward": forward_head(spec), "reset": reset_head(spec)}  # each measures its saturation
        self.window = Saturation.empty()  # this log window's counts, per phase
        self.last_window = {}  # the last log row's saturation entries

    @property
    def tables(self) -> tuple[CsvTable, ...]:
        return self.progress, self.evals, self.triggers, self.diagnostics, self.resets

    def begin(self, history: dict | None) -> None:
        """Continue from a checkpoint's ``history`` (rows written after it are dropped), or start afresh."""
        replaced = None  # the last step logged after the checkpoint by the process that stopped (run again now)
        if history is not None:
            self.history = history
            dropped = [table.truncate_after(self.collector.frames) for table in self.tables]
            replaced = max((d for d in dropped if d is not None), default=None)
            if replaced is not None:
                log.warning("resuming at step %d: the rows logged after this checkpoint by the process that stopped "
                            "(to step %d) are dropped; those steps are run again", self.collector.frames, replaced)
        else:
            # a fresh start: tables left by an earlier attempt that never checkpointed start over
            for table in self.tables:
                table.truncate_after(-1)
            for stale in ("summary.json", "code.jsonl"):
                (self.run_dir / stale).unlink(missing_ok=True)
            (self.run_dir / "config.yaml").write_text(OmegaConf.to_yaml(self.cfg, resolve=True))
        # the code each stretch of the run ran at (a resumed run appends its own line); the summary
        # names this stretch's, read now: the work tree may change while the run goes on
        self.code = code_version()
        stretch = {"from_step": self.collector.frames, **self.code}
        if replaced is not None:  # the lost stretch, kept on record: steps from_step to this one ran twice
            stretch["replaces_to_step"] = replaced
        with open(self.run_dir / "code.jsonl", "a") as f:
            f.write(json.dumps(stretch) + "\n")
        self.loggers = make_loggers(self.cfg, self.run_dir)
        # wall time of the steps of each phase once its agent updates (env step, policy, trigger, buffer, update)
        self.step_time = self.history.setdefault("step_time", {"forward": [0.0, 0], "reset": [0.0, 0]})
        # how often the system entered an irrecoverable state (the env's latched "irrecoverable" flag turned
        # on: the cliff tasks' ditch) in a forward and in a reset step; how the last forward episode ended
        self.irrecoverable = self.history.setdefault("irrecoverable", {"forward": 0, "reset": 0})
        # the saturation counts of the run's last quarter (the summary's)
        self.late_saturation = self.history.setdefault("late_saturation", Saturation.empty())
        # this log window's counts: saved with the checkpoint, so a window that a stop cuts in two is whole
        self.window = self.history.setdefault("saturation_window", Saturation.empty())
        self.history.setdefault("last_forward_end", "")
        # triggers that stopped the forward agent at a state the env's at-initial-state check already passed (a run
        # resumed from a checkpoint written before this count existed counts from its resume)
        self.history.setdefault("triggers_at_initial_state", 0)
        self.history.setdefault("updates", {"forward": 0, "reset": 0})  # the updates each agent made
        self.bar = tqdm(total=int(self.cfg.total_steps), initial=self.collector.frames,
                        desc=f"{self.cfg.task.name}/{self.cfg.algo.name}", unit="step", mininterval=2.0,
                        disable=not self.cfg.progress_bar, dynamic_ncols=True)
        self._start = time.perf_counter() - self.history["elapsed"]
        self._last = time.perf_counter()

    def mark_time(self) -> None:
        self.history["elapsed"] = time.perf_counter() - self._start

    def step(self, batch, phase: str) -> None:
        """After each collected step: its trigger score, its time, the progress bar, the collector's events."""
        counters = self.collector.counters
        if phase == "forward":
            self.trigger_scores.add(batch)
        now = time.perf_counter()
        if min(counters["forward_steps"], counters["reset_steps"]) > self.heat_up + WARM_UP_UPDATES:
            self.step_time[phase][0] += now - self._last
            self.step_time[phase][1] += batch.numel()
        self._last = now
        self.bar.update(batch.numel())
        preactivation = batch.get("action_preactivation", None)
        if preactivation is not None:
            counts = self.heads[phase].saturation(preactivation)
            Saturation.add(self.window[phase], counts)
            if self.collector.frames > 0.75 * int(self.cfg.total_steps):
                Saturation.add(self.late_saturation[phase], counts)
        before, after = _flags(batch)
        if after is not None:
            self.irrecoverable[phase] += int((after & ~before).sum())
        for event in self.collector.pop_events():
            self.trigger_scores.add_event(event)
            # the env's flag in the state the event names (the collector copies it: learner.event_keys)
            flag = event["state"].get("irrecoverable", None)
            flag = int(flag) if flag is not None else ""
            if event["phase"] == "forward":
                self.history["last_forward_end"] = event["outcome"]
            if event["phase"] == "reset":
                self.resets.append({**self.distances.row(event), "started_by": self.history["last_forward_end"],
                                    "irrecoverable": flag})
            if event["outcome"] == "triggered":
                obs = event["state"]["observation"].flatten().tolist()
                at_start = event["state"].get("reset_success", None)
                at_start = int(at_start) if at_start is not None else ""
                self.history["triggers_at_initial_state"] += at_start or 0
                self.triggers.append({"frames": event["frame"], "steps": event["steps"],
                                      "value": obs[self.curriculum_index], "irrecoverable": flag,
                                      "at_initial_state": at_start, "observation": " ".join(f"{v:.5g}" for v in obs)})

    def evaluation(self, result: dict) -> None:
        self.history["eval_returns"].append(result["forward_return"])
        self.evals.append({"frames": self.collector.frames, **result})

    def log(self, learner, env) -> None:
        """A ``progress.csv`` row, a ``diagnostics.csv`` row, the loggers and the progress bar."""
        self.mark_time()
        c, frames = self.collector.counters, self.collector.frames
        returns = self.history["eval_returns"]
        row = {
            "frames": frames, **{k: c[k] for k in PROGRESS_FIELDS if k in c},
            "forward_share": self.collector.forward_share, "reset_success_rate": self.collector.reset_success_rate,
            "eval_return": returns[-1] if returns else float("nan"),
            "average_return": float(np.mean(returns)) if returns else float("nan"),
            "steps_per_second": frames / max(self.history["elapsed"], 1e-9), "skipped_updates": learner.budget.skipped,
            **self.history["last_losses"], "protective_stops": safety_counters(env).get("protective_stops", 0),
            "irrecoverable_forward": self.irrecoverable["forward"], "irrecoverable_reset": self.irrecoverable["reset"],
            **Saturation.fields(self.window), "triggers_at_initial_state": self.history["triggers_at_initial_state"],
            "overruns": getattr(realtime_env(env), "overruns", 0),
            **{f"{phase}_updates_achieved": float("nan") if value is None else value
               for phase, value in learner.updates_achieved().items()},
            **learner_fields(learner),
        }
        self.last_window = Saturation.fields(self.window)
        self.window = self.history["saturation_window"] = Saturation.empty()
        self.progress.append(row)
        scores = {"frames": frames, **self.trigger_scores.row()}
        if hasattr(learner, "request_probe"):  # learner.mode=async: the buffers are the learner process's
            learner.request_probe(lambda probe: self.diagnostics.append({**scores, **probe}))
        else:
            self.diagnostics.append({**scores, **diagnostic_probe(self.spec, learner, self.collector.example_buffer,
                                                                  self.trigger.threshold, frames)})
        for logger in self.loggers:
            logger.log_metrics({k: v for k, v in row.items() if k != "frames" and not _isnan(v)}, step=frames)
        self.bar.set_postfix(sps=f"{row['steps_per_second']:.0f}", manual=row["manual_resets"],
                             ret=f"{row['eval_return']:.2f}", refresh=False)

    def close(self) -> None:
        self.bar.close()

    def summary(self, *, finished: bool, learner, env, robot, matmul_precision: str) -> dict:
        """The paper's Table 1 metrics and what the run ran on, written to ``summary.json``."""
        cfg, collector, history = self.cfg, self.collector, self.history
        c, returns = collector.counters, history["eval_returns"]
        quarters = reset_outcomes_by_quarter(self.resets.path, collector.frames, c["reset_episodes"])
        summary = {
            "task": cfg.task.name, "algo": cfg.algo.name, "seed": int(cfg.seed),
            # ours: the threshold the trigger used (algo.threshold when set, else the task's p_thresh); LNT: the
            # task's p_thresh, which it does not use (the report groups runs by it); the threshold it used:
            "p_thresh": float(self.trigger.threshold) if self.spec.kind.scores_probability else float(cfg.task.p_thresh),
            "trigger_threshold": float(self.trigger.threshold),  # ours: p_thresh (a probability); LNT: Q_thresh
            "steps": collector.frames, "finished": finished,
            "average_return": float(np.mean(returns)) if returns else None,
            "manual_resets": c["manual_resets"],
            # an episodic agent needs one reset per forward episode (the release logs it as the baseline)
            "episodic_resets": c["forward_episodes"],
            "resets_saved": c["forward_episodes"] - c["manual_resets"],
            # the release's "baseline hard reset" counter: one per H_f calls of the forward agent's step,
            # triggered ones included (the tasks never end by themselves); it counts no reset for forward
            # episodes the trigger cut short, where the count above counts one each
            "baseline_hard_resets": (c["forward_steps"] + c["triggered_resets"]) // int(cfg.task.forward_horizon),
            "forward_share": collector.forward_share,
            "reset_success_rate": collector.reset_success_rate,
            **_quarter_rates(quarters),
            "reset_episodes_by_quarter": quarters,
            "final_eval_return": returns[-1] if returns else None,
            "evaluations": len(returns),
            **{k: c[k] for k in ("triggered_resets", "requested_resets", "successful_resets", "reset_episodes")},
            # of the triggered resets, those that stopped the forward agent at a state that already passed the
            # env's at-initial-state check (the reset episode after one succeeds once its minimum steps are done)
            "triggers_at_initial_state": history["triggers_at_initial_state"],
            "skipped_updates": learner.budget.skipped,
            # per agent, the updates made as a fraction of Algorithm 1's count (one per step of its phase past
            # heat-up); below 1 on a real-time robot where updates did not fit in the control period
            "updates_achieved": learner.updates_achieved(),
            # learner.mode and, for async, the lag, the weights' age, the queue's depth and the waits
            "learner": learner.stats_summary() if hasattr(learner, "stats_summary") else {"mode": "sync"},
            "overruns": getattr(robot, "overruns", 0),
            "control_period": robot.control_period_stats() if hasattr(robot, "control_period_stats") else None,
            "protective_stops": safety_counters(env).get("protective_stops", 0),
            "safety": safety_counters(env),
            # entries into an irrecoverable state (over the cliff, into the ditch), in forward and in reset steps
            "irrecoverable": dict(self.irrecoverable),
            # the policies' saturation (progress.csv's columns) over the last log window and the last quarter
            "saturation": {"last_window": self.last_window, "last_quarter": Saturation.fields(self.late_saturation)},
            "seconds": round(history["elapsed"], 1),
            "steps_per_second": round(collector.frames / max(history["elapsed"], 1e-9), 1),
            "step_seconds": {name: (total / count if count else None) for name, (total, count) in self.step_time.items()},
            # what decides the float rounding, and so where two runs of one seed part: the processor, the
            # product precision and the number of torch threads
            "device": str(cfg.device), "processor": processor_name(), "matmul_precision": matmul_precision,
            "torch_threads": torch.get_num_threads(), **self.code,
            "torch": torch.__version__, "torchrl": torchrl.__version__,
        }
        (self.run_dir / "summary.json").write_text(json.dumps(summary, indent=2, default=_json_default))
        for logger in self.loggers:
            finish = getattr(getattr(logger, "experiment", None), "finish", None)
            if callable(finish):  # wandb: close the run so its files are complete
                finish()
        return summary


class Saturation:
    """Counts of the policies' saturation per phase: ``[saturated components, components, sum |u|]``."""

    @staticmethod
    def empty() -> dict:
        return {"forward": [0, 0, 0.0], "reset": [0, 0, 0.0]}

    @staticmethod
    def add(counts: list, new: tuple) -> None:
        for i, value in enumerate(new):
            counts[i] += value

    @staticmethod
    def fields(window: dict) -> dict:
        """``<phase>_saturation`` and ``<phase>_preact_abs`` (NaN where the phase took no step)."""
        out = {}
        for phase, (saturated, components, total) in window.items():
            out[f"{phase}_saturation"] = saturated / components if components else float("nan")
            out[f"{phase}_preact_abs"] = total / components if components else float("nan")
        return out


def _quarter_rates(quarters: dict) -> dict:
    """The share of the reset episodes that got back, in the first and in the last quarter (None where none ended
    or the counts are unknown)."""
    def rate(q):
        return q["successful_resets"] / q["reset_episodes"] if q["reset_episodes"] else None

    return {f"reset_success_rate_{name}_quarter": rate(quarters[name]) for name in ("first", "last")}


def diagnostic_probe(spec, learner, examples, threshold: float, frames: int) -> dict:
    """The reset model on examples, reset replay and forward replay (``diagnostics.csv``'s probe columns) and the
    reset sampler's fallback count, from the learner's buffers; its samples leave the training streams as they were.
    With ``learner.streams=separate`` its samples come from a generator of its own, seeded by the run's seed and
    the step (the same in one process and in two); with the shared stream, from a copy of it (every committed run)."""
    reset_rb = learner.reset_rb
    count = fallback_count(reset_rb)
    with torch.random.fork_rng(devices=[]):
        if spec["learner.streams"] == "separate":
            torch.manual_seed(int(spec.cfg.seed) * 1_000_003 + int(frames))
        probe = probe_classifier(spec.kind, learner.reset.model, learner.reset.actor, examples, learner.forward_rb,
                                 reset_rb, threshold)
    restore_fallback_count(reset_rb, count)  # the probe's own sample does not count
    return {**probe, "sampler_fallbacks": "" if count is None else count}


def _isnan(value) -> bool:
    return isinstance(value, float) and math.isnan(value)


def _json_default(value):
    if isinstance(value, (np.floating, np.integer)):
        return value.item()
    return float(value)


def _flags(batch) -> tuple:
    """The env's latched ``irrecoverable`` flag before and after the step(s) in ``batch`` (one per row), or
    ``(None, None)`` for an env without it."""
    before, after = batch.get("irrecoverable", None), batch.get(("next", "irrecoverable"), None)
    if before is None or after is None:
        return None, None
    return before.reshape(-1).bool(), after.reshape(-1).bool()
