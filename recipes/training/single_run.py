"""One training run's pieces, built: Algorithm 1's set-up (lines 1-4) for ``recipes/train.py``."""
from __future__ import annotations

import gc
import logging
import random
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig

from torchrl_reset_recipes.training.agents import make_forward_agent, make_reset_agent
from torchrl_reset_recipes.training.buffers import make_buffers
from torchrl_reset_recipes.training.learner import Learner, make_collector
from torchrl_reset_recipes.training.records import RunRecord
from torchrl_reset_recipes.training.run_spec import RunSpec
from torchrl_reset_recipes.training.checkpoints import Checkpoints, TrainingState
from torchrl_reset_recipes.training.streams import RandomStreams
from torchrl_reset_recipes.training.task_envs import EVAL_SEED_OFFSET, evaluate, make_task_env, realtime_env, task_dimensions

from torchrl_reset import DualCollector
from torchrl_reset.accel import choose_matmul_precision, retain_freed_memory

__all__ = ["TrainingDiverged", "RobotStopped", "seed_process", "set_up_process", "TrainingRun", "build_run",
           "set_up_frozen"]

log = logging.getLogger("torchrl_reset.train")


class TrainingDiverged(RuntimeError):
    """A loss became NaN or infinite; the last good state was checkpointed."""


class RobotStopped(RuntimeError):
    """The robot reported a fault the run must not go on through; the run was checkpointed."""


def seed_process(seed: int) -> None:
    """Seeds torch's, numpy's and Python's global generators, as a run does before it builds anything."""
    torch.manual_seed(seed)
    np.random.seed(seed)
    random.seed(seed)


def set_up_process(spec: RunSpec) -> str:
    """Torch threads, the ``speed.*`` settings and the seeds; returns the CPU product precision chosen."""
    torch.set_num_threads(spec.threads)
    accelerate = bool(spec["speed.accelerate"])
    if accelerate and spec["speed.retain_memory"]:
        retain_freed_memory()
    # a setting of CPU products: with the networks on another device it changes nothing
    on_cpu = torch.device(spec.cfg.device).type == "cpu"
    precision = choose_matmul_precision(spec["speed.matmul_precision"] if on_cpu and accelerate else "ieee")
    seed_process(int(spec.cfg.seed))
    logging.getLogger("torchrl").setLevel(logging.WARNING)
    return precision


@dataclass
class TrainingRun:
    """One run's pieces: its agents, envs, collector, buffers, training state, records and learner."""

    spec: RunSpec
    forward: object
    reset: object
    env: object
    trigger: object
    eval_env: object
    eval_trigger: object
    collector: DualCollector
    forward_rb: object
    reset_rb: object
    state: TrainingState
    record: RunRecord
    learner: Learner
    robot: object
    matmul_precision: str
    streams: RandomStreams  # the actor's and the learner's random streams (learner.streams)

    @property
    def cfg(self) -> DictConfig:
        return self.spec.cfg

    def evaluation(self) -> dict:
        """One forward and one reset episode without noise."""
        spec = self.spec
        return evaluate(self.eval_env, self.eval_trigger, self.forward.actor, self.reset.actor,
                        horizon=spec.forward_horizon, reset_horizon=spec.reset_horizon,
                        min_reset_steps=int(spec.cfg.reset.min_steps), gamma=float(spec.cfg.gamma))

    def after_step(self, batch, phase: str) -> None:
        """The step's record, then the evaluation, log row and checkpoint that fall on this step."""
        self.record.step(batch, phase)
        cfg, frames = self.cfg, self.collector.frames
        before = frames - batch.numel()

        def due(every) -> bool:
            return frames // int(every) > before // int(every)

        evaluate, checkpoint = due(cfg.eval_every), due(cfg.checkpoint_every)
        if self.robot is not None and (evaluate or checkpoint):
            # both take longer than a control period (a checkpoint waits for an async learner's debt): the arm is
            # held meanwhile instead of running on its last command, and the next step starts a fresh period
            self.robot.hold()
        if evaluate:
            self.record.evaluation(self.evaluation())
        if due(cfg.log_every):
            self.record.log(self.learner, self.env)
        if checkpoint:
            self.checkpoint()

    def checkpoint(self):
        self.record.mark_time()
        return self.state.save()

    def finish(self, interrupted: bool) -> dict:
        """The last checkpoint and the summary; closes the envs."""
        self.checkpoint()
        finished = self.collector.frames >= int(self.cfg.total_steps) and not interrupted
        summary = self.record.summary(finished=finished, learner=self.learner, env=self.env, robot=self.robot,
                                      matmul_precision=self.matmul_precision)
        self.collector.shutdown()
        self.eval_env.close()
        return summary


def build_run(spec: RunSpec, matmul_precision: str) -> TrainingRun:
    """Algorithm 1, lines 1-4, for one run (resumed from its checkpoint when ``resume`` says so)."""
    cfg = spec.cfg
    run_dir = Path(cfg.run_dir)
    obs_dim, action_spec = task_dimensions(cfg)
    forward = make_forward_agent(spec, obs_dim, action_spec)  # pi_f and Q
    reset = make_reset_agent(spec, obs_dim, action_spec)  # pi_r and the classifiers C_i (LNT: the Q_i)
    for agent in (forward, reset):
        agent.loss.to(cfg.device)
        # the loss moves the networks' parameters in place but only its own copies of their buffers
        # (the tanh module's action bounds, the ensemble's priors): the modules that act keep theirs
        agent.actor.to(cfg.device)
        agent.model.to(cfg.device)
    env, trigger = make_task_env(spec, reset)  # the trigger watches every forward action
    eval_env, eval_trigger = make_task_env(spec, reset, for_eval=True)
    collector = make_collector(spec, env, forward, reset)  # S* lives in the collector
    eval_env.set_seed(int(cfg.seed) + EVAL_SEED_OFFSET)
    forward_rb, reset_rb = make_buffers(spec)

    checkpoints = Checkpoints(run_dir / "checkpoints", keep=int(cfg.keep_checkpoints),
                              keep_states_every=spec["keep_states_every"])
    streams = RandomStreams(spec["learner.streams"], int(cfg.seed))  # after collector.set_seed: the actor's as shared
    state = TrainingState(checkpoints, cfg,
                          forward, reset, collector, forward_rb, reset_rb, eval_env, streams)
    record = RunRecord(spec, run_dir, collector, trigger)
    if spec.resume:
        folder = state.load()
        record.begin(state.history)
        log.info("resumed from %s at step %d", folder, collector.frames)
    else:
        checkpoints.started_fresh()
        record.begin(None)
    state.history = record.history
    robot = realtime_env(env)
    learner = Learner(spec, forward, reset, forward_rb, reset_rb, collector, matmul_precision, robot,
                      last_losses=record.history["last_losses"], updates=record.history["updates"])
    return TrainingRun(spec, forward, reset, env, trigger, eval_env, eval_trigger, collector, forward_rb, reset_rb, state,
               record, learner, robot, matmul_precision, streams)


@contextmanager
def set_up_frozen(robot):
    """On a real-time arm, the objects built at set-up (the imported modules, the networks, the environment: about
    400,000 in a UR3 run) leave the cyclic garbage collector while the run acts: a full collection over them took
    150-250 ms, several control periods (the overruns of results/learner-off-the-loop); objects made later are
    collected as before, and all return to the collector afterwards. Elsewhere it does nothing."""
    if robot is None:
        yield
        return
    gc.collect()
    gc.freeze()
    try:
        yield
    finally:
        gc.unfreeze()
