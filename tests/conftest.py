import functools
import os

import pytest
import torch

os.environ.setdefault("RL_WARNINGS", "0")
# off-screen rendering through libEGL (Mesa's software rasterizer on machines without a GPU); read
# by mujoco when it is first imported, so it is set before any test module imports torchrl
os.environ.setdefault("MUJOCO_GL", "egl")

if os.environ.get("PYTEST_XDIST_WORKER"):
    # `pytest -n 2` (the README's command): two workers on two cores, so each worker's torch runs one thread
    # whatever a run asks for (two threads in each of two workers spin against each other: several times
    # slower). A test about the thread count itself calls the original, `torch.set_num_threads.__wrapped__`.
    @functools.wraps(torch.set_num_threads)
    def _one_thread(n: int) -> None:
        _one_thread.__wrapped__(1)

    torch.set_num_threads = _one_thread


@pytest.fixture(autouse=True)
def _seed_and_threads():
    torch.manual_seed(0)
    torch.set_num_threads(min(2, os.cpu_count() or 1))
    yield
