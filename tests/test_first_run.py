"""A first run that works, and failures that say so.

- SITL-M on a cold numba cache (every kernel compiled by this run) flies as it does warm: the
  simulator compiles before any agent starts, so no agent times out while it waits.
- Agents lost mid-flight, or agents that cannot start, end the run with one line per cause, the cell
  marked, and a non-zero exit code; nothing prints a zero as if it were a measurement.
- The README's Table V command on two worker processes finishes (no fork-after-threads deadlock), and
  a pool that stops making progress ends with one line, not a hang.
"""

from __future__ import annotations

import dataclasses
import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import psutil
import pytest

from cefc_mj import executors, paths
from cefc_mj.cli import eval_single
from cefc_mj.cli.eval import main
from cefc_mj.cli.eval_common import EXIT_NOT_A_RESULT
from cefc_mj.nn.registry import GAME_ADVERSARY

REPO = Path(__file__).resolve().parent.parent


def _cold_env(tmp_path: Path) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("NUMBA_")}
    env["NUMBA_CACHE_DIR"] = str(tmp_path / "numba")  # empty: every kernel is compiled by this run
    return env


def test_sitl_m_on_a_cold_numba_cache_flies_as_warm(tmp_path):
    """The README's SITL-M command with nothing compiled yet: retention >= 90 % for c = 6 seed 0 and
    exit 0 (before the simulator warmed its kernels, its first steps compiled for tens of seconds and
    every agent left at its 5 s heartbeat: F = N = 0 printed as a result)."""
    out_json = tmp_path / "sitl.json"
    cmd = [sys.executable, "-m", "cefc_mj.cli.eval", "--sitl-m", "--formation", "6", "--episodes", "1"]
    start = time.monotonic()
    done = subprocess.run(
        [*cmd, "--json", str(out_json)],
        cwd=tmp_path,
        env=_cold_env(tmp_path),
        capture_output=True,
        text=True,
        timeout=600,
    )
    wall = time.monotonic() - start
    assert done.returncode == 0, done.stderr[-3000:]
    assert "compiling numba kernels" in done.stderr  # the cache really was cold
    cell = json.loads(out_json.read_text())["rows"]["6"]["SITL-M"]
    assert cell["valid"] and cell["faults"] == [], cell["faults"]
    assert cell["retention"] >= 0.90, (cell["retention"], wall)


def _sitl_with_agents(monkeypatch, agent_code: str) -> None:
    """Fly cefc-eval's SITL-M episodes with `agent_code` (python -c) as the agents' command."""
    original = eval_single.sitl_config

    def with_command(*args, **kwargs):
        config = original(*args, **kwargs)
        return dataclasses.replace(config, agent_command=(sys.executable, "-c", agent_code), startup_timeout_s=60.0)

    monkeypatch.setattr(eval_single, "sitl_config", with_command)


# the real agent, except that each agent process dies when its 5th sensor packet arrives
AGENTS_DIE_IN_FLIGHT = (
    "import os, sys\n"
    "from cefc_mj.deploy import agent\n"
    "act = agent.Agent._act\n"
    "agent.Agent._act = lambda self, packet, t: os._exit(1) if packet['seq'] >= 5 else act(self, packet, t)\n"
    "sys.exit(agent.main(sys.argv[1:]))\n"
)


def test_agents_lost_in_flight_are_not_a_result(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    _sitl_with_agents(monkeypatch, AGENTS_DIE_IN_FLIGHT)
    before = set(psutil.Process().children(recursive=True))
    code = main(
        ["--sitl-m", "--formation", "3", "--steps", "40", "--episodes", "1", "--json", str(tmp_path / "out.json")]
    )
    captured = capsys.readouterr()
    assert code == EXIT_NOT_A_RESULT, captured.err
    faults = [line for line in captured.err.splitlines() if line.startswith("cefc-eval: fault: ")]
    # (the simulator notices the exit at the next step it polls, 5 or 6)
    assert any(re.search(r"UAVs 0-2: agent process exited at step [56] ", line) for line in faults), captured.err
    assert any("failsafe hold" in line for line in faults), captured.err
    assert "NOT A MEASUREMENT" in captured.out  # the cell is marked in the table
    cell = json.loads((tmp_path / "out.json").read_text())["rows"]["3"]["SITL-M"]
    assert cell["valid"] is False and cell["faults"]
    assert json.loads((tmp_path / "out.json").read_text())["rows"]["3"]["SITL-S"]["valid"] is True
    assert set(psutil.Process().children(recursive=True)) <= before, "agent processes survived the run"


def test_agents_that_cannot_start_end_the_run_in_one_line(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    _sitl_with_agents(monkeypatch, "import sys; sys.exit(7)")
    code = main(
        ["--sitl-m", "--formation", "3", "--steps", "20", "--episodes", "1", "--json", str(tmp_path / "out.json")]
    )
    err = capsys.readouterr().err.strip().splitlines()
    assert code == EXIT_NOT_A_RESULT
    assert err[-1].startswith("cefc-eval: error: the agent processes exited with code 7 during startup"), err
    assert not (tmp_path / "out.json").exists()


def _game_home(tmp_path: Path) -> Path:
    """A CEFC_MJ_HOME with the shipped data and three of Table V's policy files (two rows)."""
    home = tmp_path / "home"
    (home / "policies").mkdir(parents=True)
    for name in ("assets", "controllers", "eval"):
        (home / name).symlink_to(paths.PROJECT_ROOT / name)
    keep = ("atm_student", GAME_ADVERSARY, "cihrl_consmac_a", "cihrl_mappo", "cihrl_mappo_seed1")
    for name in keep:
        for suffix in (".pt", ".json"):
            source = paths.POLICIES_DIR / f"{name}{suffix}"
            if source.exists():
                (home / "policies" / source.name).symlink_to(source)
    return home


def test_table5_cli_on_two_workers_finishes(tmp_path):
    """`cefc-eval --protocol table5 --workers 2` through the real CLI start-up (its parent has run torch
    by then): a forked pool deadlocked here with both workers at 0 s of CPU."""
    env = dict(os.environ, CEFC_MJ_HOME=str(_game_home(tmp_path)))
    argv = ["--backend", "particle", "--protocol", "table5", "--episodes", "2", "--seed", "200", "--workers", "2"]
    done = subprocess.run(
        [sys.executable, "-m", "cefc_mj.cli.eval", *argv, "--report-dir", str(tmp_path / "reports")],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    rows = json.loads((tmp_path / "reports" / "table5.json").read_text())["rows"]
    assert set(rows) == {"MAPPO+AT-M", "CI-HRL"}
    assert list(rows["MAPPO+AT-M"]["training_seeds"]["seeds"]) == [0, 1]
    report = (tmp_path / "reports" / "table5.md").read_text()  # the Markdown table, a one-seed row included
    assert "| MAPPO+AT-M | 2 | " in report and "| **CI-HRL** | 1 | " in report


def _stop_self(_item) -> None:
    os.kill(os.getpid(), signal.SIGSTOP)


def test_a_pool_that_makes_no_progress_ends_in_one_line(monkeypatch):
    monkeypatch.setattr(executors, "STALL_POLL_S", 0.2)
    before = set(psutil.Process().children(recursive=True))
    start = time.monotonic()
    with pytest.raises(executors.WorkersStalled, match=r"used no CPU for \d+ s with 2 job\(s\) pending"):
        list(executors.map_unordered(_stop_self, [1, 2], executors.ExecutorConfig(workers=2), stall_timeout_s=2.0))
    assert time.monotonic() - start < 60
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline and set(psutil.Process().children(recursive=True)) - before:
        time.sleep(0.1)
    assert not set(psutil.Process().children(recursive=True)) - before, "stalled workers survived"
