"""Test-wide settings: headless MuJoCo and quiet TorchRL logging; the ``one_torch_thread`` fixture."""

import os

import pytest
import torch

os.environ.setdefault("MUJOCO_GL", "disable")
os.environ.setdefault("RL_LOGGING_LEVEL", "WARNING")


@pytest.fixture(scope="module")
def one_torch_thread():
    """Small networks on a shared 2-core machine: one intra-op thread is several times faster.
    A module uses it with ``pytestmark = pytest.mark.usefixtures("one_torch_thread")``."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)
