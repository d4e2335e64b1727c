"""Every benchmark in benchmarks/ runs: its `--smoke` mode (tiny sizes, one round, the same code path)
as a real subprocess, exit code 0 and its ratio line printed. Keeps the benchmarks from rotting as the
code they time changes (a few seconds each once the numba kernels are cached)."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from cefc_mj.sim.mujoco_world import AUTO_ACTUATORS_MAX_DRONES

ROOT = Path(__file__).resolve().parent.parent
BENCHMARKS = ROOT / "benchmarks"

CASES = {
    "mujoco": (
        ["bench_mujoco.py", "--smoke", "--before"],
        [
            r"eval loop \(   now\): +RTF +[\d.]+ +loop / raw mj_step = [\d.]+",
            r"eval loop \(before\): +RTF +[\d.]+ +loop / raw mj_step = [\d.]+",
            r"speed-up now / before: x[\d.]+",
        ],
    ),
    "mujoco-swarm": (
        ["bench_mujoco.py", "--smoke", "--steps", "0", "--sweep", "8", "--scaling"],
        [
            r"(?m)^ +8 +[\d.]+ +[\d.]+ +[\d.]+ +[\d.]+ +1\.00 ",
            r"8 drones .*external / actuators x[\d.]+ .*auto -> actuators",
            rf"{AUTO_ACTUATORS_MAX_DRONES + 1} drones .*external / actuators x[\d.]+ .*auto -> external",
        ],
    ),
    "mujoco-training": (
        ["bench_mujoco_training.py", "--smoke"],
        [r"mujoco / particle: [\d.]+ +W=2 / W=1: x[\d.]+ on 2 cores"],
    ),
    "particle": (["bench_particle.py", "--smoke"], [r"(?m)^ +4 +[\d,]+ +[\d,]+ +[\d.]+x$"]),
    "consmac": (["bench_consmac.py", "--smoke"], [r"new / old: [\d.]+"]),
    "highlevel": (["bench_highlevel.py", "--smoke"], [r"full decision +[\d.]+ us = [\d.]+ x the low level alone"]),
    "highlevel-training": (
        ["bench_highlevel_training.py", "--smoke"],
        [
            r"consmac-a: .*ConsMAC step old [\d.]+ ms, new [\d.]+ ms \([\d.]+x\)",
            r"paper schedule: iteration [\d.]+ s \(old [\d.]+ s, [\d.]+x\); whole run [\d.]+ core-hours",
            r"(?s)mappo: .*paper schedule: iteration [\d.]+ s; whole run [\d.]+ core-hours",
            r"paper-scaled 300 schedule: iteration [\d.]+ s \(old [\d.]+ s, [\d.]+x\); whole run [\d.]+ core-hours",
        ],
    ),
    "rerun": (["bench_rerun.py", "--smoke"], [r"overhead vs a \d+ s episode at +\d+x real time .*: +[\d.]+ %"]),
}


def test_every_benchmark_has_a_smoke_case():
    covered = {args[0] for args, _ in CASES.values()}
    assert covered == {p.name for p in BENCHMARKS.glob("bench_*.py")}


@pytest.mark.parametrize("case", sorted(CASES))
def test_benchmark_smoke_runs_and_prints_its_ratio(case):
    args, patterns = CASES[case]
    env = dict(os.environ, MUJOCO_GL=os.environ.get("MUJOCO_GL", "egl"), OMP_NUM_THREADS="1")
    proc = subprocess.run(
        [sys.executable, str(BENCHMARKS / args[0]), *args[1:]],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, f"{' '.join(args)} exited {proc.returncode}:\n{proc.stdout}\n{proc.stderr[-3000:]}"
    for pattern in patterns:
        assert re.search(pattern, proc.stdout), f"{' '.join(args)}: no line matching {pattern!r} in:\n{proc.stdout}"
