"""Shared test set-up."""

import os
import signal

import pytest

# Headless rendering: MuJoCo's offscreen renderer needs a GL backend before mujoco is first imported
# (the CLIs do the same; .ci/run exports it too).
os.environ.setdefault("MUJOCO_GL", "egl")

# A test run started in the background of a non-interactive shell (`cmd &` without job control,
# nohup under a script) inherits SIGINT ignored, and so would every process it starts: the tests
# that press Ctrl-C on a child would see it shrug. With a handler installed here, children start
# with the default disposition (exec resets handlers, not "ignored"), as under a terminal.
if signal.getsignal(signal.SIGINT) == signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)


@pytest.fixture(autouse=True, scope="session")
def _test_ledger_outside_the_repository(tmp_path_factory):
    """A run that flies a test-block seed appends to the test ledger (cefc_mj/eval/ledger.py): in the
    tests that is a temporary file, never the repository's eval/test_ledger.jsonl (subprocesses inherit
    it)."""
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("CEFC_TEST_LEDGER", str(tmp_path_factory.mktemp("ledger") / "test_ledger.jsonl"))
        yield


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
