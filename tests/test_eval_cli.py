"""cefc-eval: bad input ends in one clear line with exit code 2; a small particle run writes its JSON."""

import json
import subprocess
import sys

import pytest
import torch

from cefc_mj.cli.eval import main
from cefc_mj.nn.atm import ATMActor, ATMConfig
from cefc_mj.nn.policy_io import save_policy
from cefc_mj.task.config import TaskConfig


@pytest.fixture(scope="module")
def random_policy(tmp_path_factory):
    """An untrained AT-M actor for the low-level layout (the CLI's plumbing, not its skill, is tested)."""
    torch.manual_seed(0)
    path = tmp_path_factory.mktemp("pol") / "random_atm.pt"
    save_policy(ATMActor(ATMConfig.from_task(TaskConfig(n_agents=5, mode="formation"))), path)
    return path


@pytest.fixture(scope="module")
def wrong_shape_policy(tmp_path_factory):
    path = tmp_path_factory.mktemp("pol") / "wrong.pt"
    cfg = TaskConfig(n_agents=5, mode="formation", n_lidar_rays=12)
    save_policy(ATMActor(ATMConfig.from_task(cfg)), path)
    return path


def run_cli(argv, capsys):
    with pytest.raises(SystemExit) as exc:
        main(argv)
    return exc.value.code, capsys.readouterr().err


@pytest.mark.parametrize(
    "argv, needle",
    [
        (["--wind", "-1"], "--wind"),
        (["--deviation", "nan"], "--deviation"),
        (["--formation", "2"], "--formation 2"),
        (["--episodes", "0"], "--episodes"),
        (["--policy", "no_such_policy"], "no_such_policy"),
        (["--json", "{file}/out.json"], "--json"),
        (["--rrd", "{file}/x.rrd"], "--rrd"),
        (["--backend", "particle", "--wind", "3"], "--wind"),
        (["--sitl-m"], "--sitl-m"),
    ],
)
def test_bad_input_one_line_exit_2(argv, needle, capsys, tmp_path):
    (tmp_path / "a_file").write_text("not a folder")
    argv = [a.replace("{file}", str(tmp_path / "a_file")) for a in argv]
    code, err = run_cli(argv, capsys)
    assert code == 2
    lines = [line for line in err.strip().splitlines() if line]
    assert len(lines) == 1 and needle in lines[0] and "Traceback" not in err


def test_checkpoint_for_another_observation_size(wrong_shape_policy, capsys):
    code, err = run_cli(["--backend", "particle", "--formation", "5", "--steps", "5", "--policy", str(wrong_shape_policy)], capsys)
    assert code == 2 and "observations of size 51" in err and len(err.strip().splitlines()) == 1


def test_unknown_flag_value_via_subprocess():
    proc = subprocess.run([sys.executable, "-m", "cefc_mj.cli.eval", "--backend", "bullet"], capture_output=True, text=True)
    assert proc.returncode == 2 and "invalid choice" in proc.stderr and "Traceback" not in proc.stderr


def test_particle_single_run_writes_json_and_png(random_policy, tmp_path, capsys):
    out = tmp_path / "res.json"
    code = main(["--backend", "particle", "--formation", "5", "--steps", "30", "--deviation", "0.3",
                 "--policy", str(random_policy), "--json", str(out), "--png", str(tmp_path / "png")])
    assert code == 0
    data = json.loads(out.read_text())
    assert data["condition"] == "Deviation-0.3" and data["seeds"] == [0]
    rows = data["rows"]["5"]
    assert set(rows) == {"Deviation-0.3", "SITL-S"}
    for cell in rows.values():
        assert 0 <= cell["F"] <= 30 and 0 <= cell["N"] <= 30 and 0 <= cell["C"] <= 100 and cell["episodes"] == 1
    assert list((tmp_path / "png").glob("*.png"))
    assert "Table VIII metrics" in capsys.readouterr().out


def test_rrd_recording_read_back(random_policy, tmp_path):
    """--rrd writes a Rerun file whose entities say what they are."""
    import rerun as rr

    rrd = tmp_path / "run.rrd"
    assert main(["--backend", "particle", "--formation", "5", "--steps", "20", "--policy", str(random_policy),
                 "--rrd", str(rrd)]) == 0
    paths = set()
    for chunk in rr.chunk.RrdReader(rrd).stream().to_chunks():
        paths.add(str(chunk.entity_path))
    expected = {"/world/uav_0", "/world/uav_4/lidar", "/world/obstacles", "/world/anchor", "/metrics/hd_error"}
    assert expected <= paths and "/world/uav_5" not in paths  # five UAVs flew
