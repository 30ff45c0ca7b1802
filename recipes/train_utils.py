"""The recipe's helpers, by concept (this module re-exports them for scripts written against it):

- ``config_checks``: ``validate`` and the other configuration checks;
- ``agents``: the networks, the forward and reset agents, the trigger;
- ``buffers``: the replay buffers and what they keep;
- ``learner``: the collector and the agents' updates;
- ``records``: the run's tables, loggers, progress bar and summary;
- ``task_envs``: the task's envs, evaluation, the real-time robot's update budget and safety counters;
- ``run_files``: checkpoints, the training state, CSV tables, the code version;
- the CPU speed settings: ``torchrl_reset.accel``.
"""
from __future__ import annotations

from agents import *  # noqa: F401,F403
from buffers import *  # noqa: F401,F403
from config_checks import *  # noqa: F401,F403
from learner import *  # noqa: F401,F403
from records import *  # noqa: F401,F403
from run_files import *  # noqa: F401,F403
from task_envs import *  # noqa: F401,F403
from torchrl_reset_envs import make_env  # noqa: F401
