"""Rerun helpers for the tests: read a recording back (rerun 0.41: `RrdReader`, one Arrow batch per
chunk), and a headless `rerun --save` listener standing where a viewer would."""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
from rerun.chunk import RrdReader


def read_rrd(path: Path) -> dict[str, dict[str, dict]]:
    """entity -> component -> {step: value} (key None for static data)."""
    out: dict[str, dict[str, dict]] = {}
    for chunk in RrdReader(path).stream().to_chunks():
        batch = chunk.to_record_batch()
        steps = batch.column("step").to_pylist() if "step" in batch.schema.names else [None] * batch.num_rows
        entity = out.setdefault(chunk.entity_path, {})
        for field, column in zip(batch.schema, batch.columns):
            if (field.metadata or {}).get(b"rerun:kind") == b"data":
                entity.setdefault(field.name, {}).update(zip(steps, column.to_pylist()))
    return out


def port_open(port: int) -> bool:
    with socket.socket() as s:
        return s.connect_ex(("127.0.0.1", port)) == 0


def _wait_until_file_settles(path: Path, quiet_s: float = 1.0, limit_s: float = 15.0) -> None:
    """Return once `path`'s size has not changed for `quiet_s` (or after `limit_s` in all)."""
    deadline, last, quiet_since = time.monotonic() + limit_s, -1, time.monotonic()
    while time.monotonic() < deadline:
        size = path.stat().st_size if path.exists() else -1
        if size != last:
            last, quiet_since = size, time.monotonic()
        elif time.monotonic() - quiet_since >= quiet_s:
            return
        time.sleep(0.1)


@contextlib.contextmanager
def rerun_listener(port: int, path: Path):
    """`rerun --port PORT --save PATH` listening while the block runs (skips the test without the
    rerun CLI or with the port taken); afterwards SIGINT, on which it finishes the file. `rerun` is
    a Python wrapper around the native binary: both get the signal, as from a terminal's Ctrl-C (its
    own process group), and whatever does not exit within 20 s is killed, never left behind."""
    rerun_cli = shutil.which("rerun") or str(Path(sys.executable).with_name("rerun"))
    if not Path(rerun_cli).exists():
        pytest.skip("the rerun CLI is not installed")
    if port_open(port):
        pytest.skip(f"port {port} is taken (a Rerun viewer is running)")
    server = subprocess.Popen(
        [rerun_cli, "--port", str(port), "--save", str(path)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )
    try:
        for _ in range(100):
            if port_open(port):
                break
            assert server.poll() is None, "rerun --save exited"
            time.sleep(0.1)
        else:
            pytest.fail(f"rerun --save did not open port {port} within 10 s")
        # The port opens before the server is surely storing: one run in about ten lost the first
        # (static) entity of a recording sent at once. A moment's grace, then the block runs.
        time.sleep(1.0)
        yield server
        # The sender's flush returns once the data is sent, not once the server has stored it: one CI
        # run in about twenty lost the last step to the SIGINT below. Wait until the file stops growing.
        _wait_until_file_settles(path)
    finally:
        os.killpg(server.pid, signal.SIGINT)
        try:
            server.wait(timeout=20)
        finally:
            if server.poll() is None:
                os.killpg(server.pid, signal.SIGKILL)
                server.wait()
