"""Environments for torchrl-reset, installed under the import name ``torchrl_reset_envs``.

(The folder is ``envs/`` in the repository; it is installed as ``torchrl_reset_envs`` so that it
never shadows a user project's own ``envs`` package.)
"""
from .chain import ChainEnv

__all__ = ["ChainEnv"]
