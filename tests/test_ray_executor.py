"""Ray as an executor: Table VIII grids and multi-seed training sweeps on a Ray cluster.

A real one-CPU Ray head (`ray start --head`, bound to 127.0.0.1) serves the --address tests; one
test starts its own local instance through the CLI and interrupts it. Every Ray process of this
module runs with its own RAY_TMPDIR, so the teardown can tell whether any of them outlived the
tests; the token Ray requires comes from the environment, so nothing is written to ~/.ray.
"""

from __future__ import annotations

import json
import os
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

ray = pytest.importorskip("ray")
psutil = pytest.importorskip("psutil")

from cefc_mj.cli.eval import main as eval_main  # noqa: E402
from cefc_mj.cli.train import main as train_main  # noqa: E402
from cefc_mj.eval.table8 import load_cells  # noqa: E402
from cefc_mj.executors import RAY_MISSING  # noqa: E402

RAY_ENV = ("RAY_TMPDIR", "RAY_AUTH_TOKEN", "RAY_AUTH_MODE", "RAY_USAGE_STATS_ENABLED", "RAY_ADDRESS")
# one c, the 7 conditions, one seed; 150 steps give non-zero F and C to compare
# without the separation guard, so that some cells collide and C travels through the cache too
TABLE8 = ["--protocol", "table8", "--formation", "5", "--episodes", "1", "--steps", "150", "--guard", "off"]
SWEEP = [
    "lowlevel",
    "--formation",
    "3",
    "--step",
    "1",
    "--budget",
    "2it",
    "--envs",
    "2",
    "--threads",
    "1",
    "--no-progress",
]


def ray_processes(tmp: str) -> list:
    """Live processes (not zombies) of this module's Ray runs, told by their RAY_TMPDIR or a path in it."""
    found = []
    for proc in psutil.process_iter(["pid", "cmdline", "environ", "status"]):
        info = proc.info
        if info["pid"] == os.getpid() or info["status"] == psutil.STATUS_ZOMBIE:
            continue
        if tmp in " ".join(info["cmdline"] or []) or (info["environ"] or {}).get("RAY_TMPDIR") == tmp:
            found.append(proc)
    return found


@pytest.fixture(scope="module")
def ray_tmp():
    """A short RAY_TMPDIR (Ray's socket paths must stay under 108 bytes) and a token in the environment;
    afterwards the environment is restored and no process of this module's Ray runs may remain."""
    saved = {name: os.environ.get(name) for name in RAY_ENV}
    tmp = tempfile.mkdtemp(prefix="cefc-ray-", dir="/tmp")
    os.environ.update(RAY_TMPDIR=tmp, RAY_AUTH_TOKEN=secrets.token_hex(32), RAY_USAGE_STATS_ENABLED="0")
    os.environ.pop("RAY_ADDRESS", None)
    yield tmp
    for name, value in saved.items():
        if value is None:
            os.environ.pop(name, None)
        else:
            os.environ[name] = value
    deadline = time.monotonic() + 15
    while (left := ray_processes(tmp)) and time.monotonic() < deadline:
        time.sleep(0.5)
    for proc in left:  # ours (they run under our RAY_TMPDIR): end them, then fail
        proc.kill()
    shutil.rmtree(tmp, ignore_errors=True)
    assert not left, f"Ray processes outlived the tests: {[' '.join(p.info['cmdline'] or [])[:80] for p in left]}"


@pytest.fixture(scope="module")
def ray_head(ray_tmp):
    """A one-CPU Ray head on 127.0.0.1 (`ray start --head --block`); yields its HOST:PORT."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    log = Path(ray_tmp) / "head.log"
    with open(log, "w") as fh:
        head = subprocess.Popen(
            [
                str(Path(sys.executable).parent / "ray"),
                "start",
                "--head",
                "--node-ip-address",
                "127.0.0.1",
                "--port",
                str(port),
                "--num-cpus",
                "1",
                "--include-dashboard",
                "false",
                "--disable-usage-stats",
                "--block",
            ],
            stdout=fh,
            stderr=subprocess.STDOUT,
            start_new_session=True,
            # a driver that names an --address uses token authentication only when RAY_AUTH_MODE=token is
            # set before ray is imported, which this process is past: a cluster without tokens
            env={**os.environ, "RAY_AUTH_MODE": "disabled"},
        )
    try:
        deadline = time.monotonic() + 90
        while "Ray runtime started" not in log.read_text():
            assert head.poll() is None and time.monotonic() < deadline, log.read_text()[-2000:]
            time.sleep(0.3)
        yield f"127.0.0.1:{port}"
    finally:
        head.send_signal(signal.SIGTERM)  # --block: the head stops the processes it started
        try:
            head.wait(timeout=30)
        except subprocess.TimeoutExpired:
            head.kill()


def cells(report_dir: Path) -> dict[str, dict]:
    """The cell file's rows by key, without the wall-clock time (the only field that may differ)."""
    rows = load_cells(report_dir / "table8_cells_mujoco.jsonl")
    return {key: {k: v for k, v in row.items() if k != "wall_s"} for key, row in rows.items()}


# ---------------------------------------------------------------------------- bad flags
@pytest.mark.parametrize(
    "argv, needle",
    [
        (["--executor", "ray"], "--executor ray: only --protocol table8"),
        (["--protocol", "table8", "--address", "127.0.0.1:6379"], "add --executor ray"),
        (["--protocol", "table8", "--executor", "ray", "--address", "head"], "--address head: expected HOST:PORT"),
        (["--protocol", "table8", "--executor", "ray", "--address", "head:0"], "--address head:0: expected HOST:PORT"),
        (["--protocol", "table8", "--executor", "ray", "--address", "a b:1"], "expected HOST:PORT"),
        (["--protocol", "table8", "--executor", "ray", "--address", "h:6379", "--workers", "2"], "drop --workers"),
        (["--protocol", "table8", "--executor", "dask"], "invalid choice: 'dask'"),
    ],
)
def test_bad_eval_flags_exit_2_with_one_line(argv, needle, capsys):
    with pytest.raises(SystemExit) as exit_:
        eval_main(argv)
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and needle in err and err.count("\n") == 1, err


@pytest.mark.parametrize(
    "argv, needle",
    [
        (["--seeds", "0,1", "--install"], "--install: a --seeds sweep"),
        (["--seeds", "0,1", "--seed", "3"], "--seed 3: give either --seed"),
        (["--seeds", "0,x"], "--seeds 0,x: expected comma-separated seeds"),
        (["--seeds", "1,1"], "a seed is listed twice"),
        (["--executor", "ray"], "--executor ray: runs the seeds of a sweep; add --seeds"),
        (["--seeds", "0,1", "--address", "h:6379"], "add --executor ray"),
        (["--seeds", "0,1", "--executor", "ray", "--address", "h:x"], "--address h:x: expected HOST:PORT"),
    ],
)
def test_bad_sweep_flags_exit_2_with_one_line(argv, needle, tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_:
        train_main(SWEEP + ["--out", str(tmp_path / "out")] + argv)
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and needle in err and err.count("\n") == 1, err
    assert list(tmp_path.iterdir()) == []


def test_ray_missing_is_one_line(monkeypatch, tmp_path, capsys):
    monkeypatch.setitem(sys.modules, "ray", None)  # as if the ray extra were not installed
    with pytest.raises(SystemExit) as exit_:
        eval_main(TABLE8 + ["--executor", "ray", "--report-dir", str(tmp_path / "r")])
    assert exit_.value.code == 2 and capsys.readouterr().err == f"cefc-eval: error: {RAY_MISSING}\n"
    with pytest.raises(SystemExit) as exit_:
        train_main(SWEEP + ["--seeds", "0,1", "--executor", "ray", "--out", str(tmp_path / "o")])
    assert exit_.value.code == 2 and capsys.readouterr().err == f"cefc-train: error: {RAY_MISSING}\n"


# ---------------------------------------------------------------------------- Table VIII
def test_table8_on_a_ray_cluster_matches_the_local_pool_and_resumes(ray_head, tmp_path, capsys):
    local, remote = tmp_path / "local", tmp_path / "ray"
    assert eval_main(TABLE8 + ["--workers", "2", "--report-dir", str(local)]) == 0
    expected = cells(local)
    assert len(expected) == 7 and any(row["F"] > 0 for row in expected.values())
    assert any(row["C"] > 0 for row in expected.values())

    # a run interrupted after 3 episodes, killed mid-line: the rerun on Ray flies only the other 4
    remote.mkdir()
    cell_file = remote / "table8_cells_mujoco.jsonl"
    lines = (local / cell_file.name).read_text().splitlines()
    cell_file.write_text("\n".join(lines[:3]) + '\n{"key": "tor')
    capsys.readouterr()
    assert eval_main(TABLE8 + ["--executor", "ray", "--address", ray_head, "--report-dir", str(remote)]) == 0
    out = capsys.readouterr().out
    assert f"on the Ray cluster at {ray_head}" in out and "3 of 7 cells reused" in out
    assert cells(remote) == expected  # cell for cell: the same keys and the same numbers
    assert len(cell_file.read_text().splitlines()) == 8  # 7 rows and the torn line, each on its own line
    # everything cached: nothing to fly, so no Ray connection is even made
    assert eval_main(TABLE8 + ["--executor", "ray", "--address", "127.0.0.1:1", "--report-dir", str(remote)]) == 0
    assert "7 of 7 cells reused" in capsys.readouterr().out
    # episodes to fly and no head at the address: one line, at once (Ray alone would retry for minutes)
    nowhere = ["--executor", "ray", "--address", "127.0.0.1:1"]
    assert eval_main(TABLE8 + nowhere + ["--report-dir", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err.splitlines()
    assert err[-1].startswith("cefc-eval: error: --address 127.0.0.1:1: no Ray head answers there")


def test_ctrl_c_stops_the_local_ray_instance(ray_tmp, tmp_path):
    """Without --address a Ray instance is started here; Ctrl-C (SIGINT to the process group, as a
    terminal sends it) ends the command with 130 and takes every Ray process with it."""
    # 35 episodes: far more than can finish between the first task starting and the Ctrl-C, however
    # fast an episode flies
    argv = [
        "--protocol",
        "table8",
        "--formation",
        "5",
        "--episodes",
        "5",
        "--steps",
        "1000",
        "--executor",
        "ray",
        "--report-dir",
        str(tmp_path / "r"),
    ]
    proc = subprocess.Popen(
        [sys.executable, "-m", "cefc_mj.cli.eval", *argv],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    seen: dict[int, tuple[psutil.Process, str]] = {}  # every descendant seen: (process, command line)
    try:
        deadline = time.monotonic() + 90
        while not any("_fly_cell" in cmdline for _, cmdline in seen.values()):  # an episode is flying
            assert proc.poll() is None and time.monotonic() < deadline, "no Ray task started"
            for child in psutil.Process(proc.pid).children(recursive=True):
                try:
                    seen[child.pid] = (child, " ".join(child.cmdline()))
                except psutil.Error:
                    continue
            time.sleep(0.3)
        assert {"gcs_server", "raylet"} <= {p.name() for p, _ in seen.values() if p.is_running()}
        os.killpg(proc.pid, signal.SIGINT)
        out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 130, err
    assert "interrupted; finished episodes are kept" in err and "Traceback" not in err
    time.sleep(1)
    alive = [cmdline[:80] for p, cmdline in seen.values() if p.is_running() and p.status() != psutil.STATUS_ZOMBIE]
    assert not alive, alive


# ---------------------------------------------------------------------------- training sweeps
def test_two_seed_sweep_on_ray_writes_two_seed_folders(ray_head, tmp_path, capsys):
    from cefc_mj.nn.policy_io import safe_torch_load

    out = tmp_path / "sweep"
    assert train_main(SWEEP + ["--seeds", "0,1", "--executor", "ray", "--address", ray_head, "--out", str(out)]) == 0
    for k in (0, 1):
        assert (out / f"seed{k}" / "atm_c3_step1" / "state.pt").is_file()
        card = json.loads((out / "policies" / f"atm_c3_step1_s{k}.json").read_text())
        assert card["name"] == f"atm_c3_step1_s{k}" and card["seed"] == k and card["iterations"] == 2
    files = [safe_torch_load(out / "policies" / f"atm_c3_step1_s{k}.pt") for k in (0, 1)]
    assert [f["meta"]["name"] for f in files] == ["atm_c3_step1_s0", "atm_c3_step1_s1"]
    assert files[0]["sha256"] != files[1]["sha256"]  # the weights' digest: two distinct policies

    # seed 1 of the sweep is the run `--seed 1` makes: the same stage and game. (Not bit for bit: Ray
    # sets OMP_NUM_THREADS in its workers, which moves MKL to another code path; docs/scaling.md.)
    assert train_main(SWEEP + ["--seed", "1", "--out", str(tmp_path / "single")]) == 0
    single = json.loads((tmp_path / "single" / "atm_c3_step1" / "config.json").read_text())
    swept = json.loads((out / "seed1" / "atm_c3_step1" / "config.json").read_text())
    assert (swept["stage"], swept["task"], swept["init"]) == (single["stage"], single["task"], single["init"])

    # each seed resumes its own folder, here on the local executor
    capsys.readouterr()
    assert train_main(SWEEP + ["--seeds", "0,1", "--resume", "--budget", "3it", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "atm_c3_step1_s0: 3 iterations" in printed and "atm_c3_step1_s1: 3 iterations" in printed
    with pytest.raises(SystemExit) as exit_:  # started already: refused without --resume
        train_main(SWEEP + ["--seeds", "1,2", "--out", str(out)])
    assert exit_.value.code == 2 and "seed1/atm_c3_step1 already holds a run" in capsys.readouterr().err
