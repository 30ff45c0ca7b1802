"""Small hand-set networks whose outputs are known in closed form."""
from __future__ import annotations


import torch
from tensordict.nn import TensorDictModule
from torch import nn

from torchrl_reset import EnsembleValueOperator


def linear_logit_ensemble(slopes, biases=None, action_dim: int = 1, action_slopes=None) -> EnsembleValueOperator:
    """An ensemble with 1-d observations whose member i returns ``-slopes[i] * x + biases[i]`` for x >= 0.

    Hidden sizes (1, 1): h0 = relu(x), h1 = relu(h0 + action_slopes[i] * a), logit = -slope * h1 + bias;
    the action is ignored unless ``action_slopes`` is given. No prior, so the logits are exactly these numbers.
    """
    k = len(slopes)
    biases = [0.0] * k if biases is None else biases
    ens = EnsembleValueOperator(1, action_dim, num_members=k, hidden_sizes=(1, 1), prior_scale=0.0)
    with torch.no_grad():
        ens.weight_0.fill_(1.0)
        ens.bias_0.zero_()
        ens.weight_1.fill_(1.0)
        ens.bias_1.zero_()
        ens.action_weight.zero_()
        if action_slopes is not None:
            ens.action_weight.copy_(torch.tensor(action_slopes, dtype=torch.float32).view(k, 1, 1).expand_as(ens.action_weight))
        ens.weight_2.copy_(-torch.tensor(slopes, dtype=torch.float32).view(k, 1, 1))
        ens.bias_2.copy_(torch.tensor(biases, dtype=torch.float32).view(k, 1))
    return ens


class ConstantActor(nn.Module):
    def __init__(self, value: float, action_dim: int = 1):
        super().__init__()
        self.bias = nn.Parameter(torch.full((action_dim,), float(value)))

    def forward(self, observation):
        return self.bias.expand(*observation.shape[:-1], self.bias.shape[0]) + 0 * observation[..., :1]


def constant_actor(value: float, action_dim: int = 1) -> TensorDictModule:
    return TensorDictModule(ConstantActor(value, action_dim), in_keys=["observation"], out_keys=["action"])


#: the main job's settings shrunk to a few hundred steps of tiny networks, one torch thread (the test workers'
#: runs are held to one by conftest.py; this holds the processes they start too: learners, train.py commands)
QUICK_TINY = ["preset=quick", "task=ball_in_cup_catch", "hidden_sizes=[16,16]", "heat_up=40", "task.forward_horizon=20",
              "reset.batch_size=16", "forward.batch_size=16", "eval_every=100", "log_every=50", "checkpoint_every=100",
              "progress_bar=false", "total_steps=200", "threads=1"]


def quick_config(run_dir, *overrides):
    """The recipe's configuration with :data:`QUICK_TINY` and ``overrides``, its run folder ``run_dir``."""
    from torchrl_reset_recipes.training.hydra_config import compose

    return compose([*QUICK_TINY, f"run_dir={run_dir}", *overrides])
