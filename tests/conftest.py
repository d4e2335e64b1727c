"""Shared test set-up."""

import os

import pytest

# Headless rendering: MuJoCo's offscreen renderer needs a GL backend before mujoco is first imported
# (the CLIs do the same; .ci/run exports it too).
os.environ.setdefault("MUJOCO_GL", "egl")


@pytest.fixture
def one_torch_thread():
    """Small networks: one torch thread is faster than two fighting over a loaded machine, and does
    not oversubscribe a shared CPU. Modules use it with `pytestmark = pytest.mark.usefixtures(...)`."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture
def strict_rerun():
    """Make Rerun raise on data it cannot log instead of warning and dropping it."""
    import rerun as rr

    before = rr.strict_mode()
    rr.set_strict_mode(True)
    yield
    rr.set_strict_mode(before)
