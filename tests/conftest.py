import os

import pytest
import torch

os.environ.setdefault("RL_WARNINGS", "0")
# off-screen rendering through libEGL (Mesa's software rasterizer on machines without a GPU); read
# by mujoco when it is first imported, so it is set before any test module imports torchrl
os.environ.setdefault("MUJOCO_GL", "egl")


@pytest.fixture(autouse=True)
def _seed_and_threads():
    torch.manual_seed(0)
    torch.set_num_threads(min(2, os.cpu_count() or 1))
    yield
