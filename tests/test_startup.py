"""Start-up of the numba kernels (cefc_mj/jit.py): compiled once, cached on disk, announced when cold.

Every test runs fresh Python processes against a cache folder of its own, so what the user's cache
holds does not matter and the user's cache is never touched.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from cefc_mj.jit import COMPILE_NOTICE

PACKAGE_DIR = Path(__file__).resolve().parent.parent / "cefc_mj"

# A 10-step episode: metrics and final state, to the last bit. The particle world runs the task
# kernels and the LiDAR kernel; MuJoCo (Wind-8) the task kernels and the cascade (run_physics).
EPISODE = """
import json, sys
from cefc_mj.eval.runner import EpisodeSpec, run_episode
backend = sys.argv[1]
spec = EpisodeSpec(formation=5, seed=0, steps=10, backend=backend, wind=8.0 if backend == "mujoco" else 0.0)
result = run_episode(spec, record=True)
print(json.dumps({"F": result.F, "N": result.N, "C": result.C,
                  "pos": result.record.agent_pos[-1].tobytes().hex(),
                  "vel": result.record.agent_vel[-1].tobytes().hex()}))
"""
COMPILED = {
    "particle": ("kernels.neighbours_kernel", "kernels.formation_error_kernel", "lidar._lidar_kernel"),
    "mujoco": ("kernels.neighbours_kernel", "kernels.formation_error_kernel", "cascade.run_physics"),
}

# One small kernel: enough to see where its machine code is cached.
ONE_KERNEL = """
import numpy as np
from cefc_mj.task.kernels import groups_kernel
labels = np.zeros((1, 3), dtype=np.int64)
groups_kernel(np.array([[[0.0, 0.0], [0.5, 0.0], [5.0, 0.0]]]), 1.0, labels)
print(labels.tolist())
"""


def _env(**overrides: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("NUMBA_") and k != "XDG_CACHE_HOME"}
    env.update(overrides)
    return env


def _run(code: str, env: dict[str, str], *args: str, timeout: float = 300) -> subprocess.CompletedProcess:
    out = subprocess.run([sys.executable, "-c", code, *args], env=env, capture_output=True, text=True, timeout=timeout)
    assert out.returncode == 0, out.stderr[-2000:]
    return out


def _cached(folder: Path, stem: str) -> list[Path]:
    return sorted(folder.rglob(f"{stem}*.nbi"))


@pytest.mark.parametrize("backend", ["particle", pytest.param("mujoco", marks=pytest.mark.slow)])
def test_cold_cache_is_announced_warm_cache_is_silent_and_results_are_identical(tmp_path, backend):
    """First process compiles (one notice line) and fills the cache; the second loads it, says
    nothing, and flies the same episode to the last bit. (MuJoCo: ~25 s of compiling the cascade.)"""
    env = _env(NUMBA_CACHE_DIR=str(tmp_path / "numba"))
    cold = _run(EPISODE, env, backend)
    assert cold.stderr.count(COMPILE_NOTICE) == 1, cold.stderr
    for stem in COMPILED[backend]:
        assert _cached(tmp_path / "numba", stem), stem
    warm = _run(EPISODE, env, backend)
    assert COMPILE_NOTICE not in warm.stderr, warm.stderr
    assert json.loads(warm.stdout) == json.loads(cold.stdout)


def test_notice_once_only_for_cefc_mj_kernels_and_above_a_progress_bar(monkeypatch, capsys):
    """The listener numba calls on each compile: the user's own numba code says nothing, a
    cefc_mj kernel prints the line once, and a running tqdm bar is redrawn below it."""
    from types import SimpleNamespace

    from numba.core import event
    from tqdm import tqdm

    from cefc_mj import jit

    monkeypatch.setattr(jit.compile_notice, "announced", False)

    def compile_of(module: str) -> event.Event:
        py_func = SimpleNamespace(__module__=module)
        return event.Event(
            "numba:compile", event.EventStatus.START, data={"dispatcher": SimpleNamespace(py_func=py_func)}
        )

    jit.compile_notice.on_start(compile_of("my_numba_code"))
    assert capsys.readouterr().err == ""
    with tqdm(total=2, desc="episodes", file=sys.stderr) as bar:
        jit.compile_notice.on_start(compile_of("cefc_mj.control.cascade"))
        jit.compile_notice.on_start(compile_of("cefc_mj.task.kernels"))
        bar.update(1)
    err = capsys.readouterr().err
    assert err.count(COMPILE_NOTICE) == 1
    assert f"{COMPILE_NOTICE}\n" in err  # on a line of its own, not glued to the bar


def _read_only_package(code: str, env: dict[str, str], read_only: list[Path]) -> subprocess.CompletedProcess:
    """Run `code` with the package folder (and `read_only`) mounted read-only, in a private mount
    namespace (the rest of the machine keeps its writable tree)."""
    mounts = " && ".join(f"mount --bind {p} {p} && mount -o remount,ro,bind {p}" for p in [PACKAGE_DIR, *read_only])
    script = f'{mounts} && exec {sys.executable} -c "$CODE"'
    out = subprocess.run(
        ["unshare", "-m", "sh", "-c", script], env={**env, "CODE": code}, capture_output=True, text=True, timeout=300
    )
    assert out.returncode == 0, out.stderr[-2000:]
    return out


@pytest.fixture
def can_mount_read_only(tmp_path):
    if shutil.which("unshare") is None:
        pytest.skip("unshare is not installed")
    probe = tmp_path / "probe"
    probe.mkdir()
    try:
        out = subprocess.run(
            [
                "unshare",
                "-m",
                "sh",
                "-c",
                f"mount --bind {probe} {probe} && mount -o remount,ro,bind {probe} && ! touch {probe}/x",
            ],
            capture_output=True,
            timeout=30,
        )
    except (OSError, subprocess.TimeoutExpired):
        pytest.skip("unshare does not run here")
    if out.returncode != 0:
        pytest.skip("no permission to make a read-only mount (needs root or user namespaces)")


def test_read_only_install_caches_in_the_user_cache_folder(tmp_path, can_mount_read_only):
    home = tmp_path / "home"
    home.mkdir()
    env = _env(HOME=str(home))
    cold = _read_only_package(ONE_KERNEL, env, [])
    assert cold.stdout.strip() == "[[0, 0, 2]]"
    assert COMPILE_NOTICE in cold.stderr
    assert _cached(home / ".cache" / "numba", "kernels.groups_kernel")
    warm = _read_only_package(ONE_KERNEL, env, [])
    assert COMPILE_NOTICE not in warm.stderr, warm.stderr


def test_read_only_install_and_home_fall_back_to_the_temp_folder(tmp_path, can_mount_read_only):
    """numba alone would refuse to import a cache=True function here (no writable folder)."""
    home, temp = tmp_path / "home", tmp_path / "tmp"
    home.mkdir()
    temp.mkdir()
    env = _env(HOME=str(home), TMPDIR=str(temp))
    cold = _read_only_package(ONE_KERNEL, env, [home])
    assert cold.stdout.strip() == "[[0, 0, 2]]"
    assert COMPILE_NOTICE in cold.stderr
    assert not any(home.iterdir())
    cached = _cached(temp, "kernels.groups_kernel")
    assert cached and cached[0].relative_to(temp).parts[0].startswith("cefc-mj-numba-")
    warm = _read_only_package(ONE_KERNEL, env, [home])
    assert COMPILE_NOTICE not in warm.stderr, warm.stderr


def test_processes_compiling_into_one_cold_cache_at_once(tmp_path):
    """SITL-M's agents, a pool's workers, two users' runs: several processes may compile the same kernel
    into one empty cache at the same moment. numba writes each cache file to a temporary name and
    renames it into place, so every process gets the right result and a later process loads it."""
    env = _env(NUMBA_CACHE_DIR=str(tmp_path / "numba"))
    racing = [
        subprocess.Popen([sys.executable, "-c", ONE_KERNEL], env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
        for _ in range(4)
    ]
    outputs = [p.communicate(timeout=300) for p in racing]
    assert [p.returncode for p in racing] == [0] * 4, [err[-2000:] for _, err in outputs]
    assert {out.decode().strip() for out, _ in outputs} == {"[[0, 0, 2]]"}
    assert _cached(tmp_path / "numba", "kernels.groups_kernel")
    later = _run(ONE_KERNEL, env)
    assert COMPILE_NOTICE not in later.stderr and later.stdout.strip() == "[[0, 0, 2]]", later.stderr
