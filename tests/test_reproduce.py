"""`python -m cefc_mj.cli.reproduce`: a report re-flown by its own command gives the same numbers; a
changed number or a changed policy file is reported, never passed."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

from cefc_mj.cli.reproduce import (
    compare,
    flew_legacy_acceleration,
    legacy_command,
    legacy_names,
    main,
    redirected,
)

pytestmark = pytest.mark.usefixtures("one_torch_thread")
ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def small_report(tmp_path_factory):
    folder = tmp_path_factory.mktemp("t3")
    path = folder / "t3.json"
    command = ["--backend", "particle", "--protocol", "table3", "--formation", "6", "--episodes", "3", "--steps", "10"]
    done = subprocess.run(
        [sys.executable, "-m", "cefc_mj.cli.eval", *command, "--json", str(path)], capture_output=True
    )
    assert done.returncode == 0, done.stderr.decode()
    return path


def test_a_report_reproduces_and_a_changed_number_does_not(small_report, tmp_path, capsys):
    assert main([str(small_report)]) == 0
    assert "reproduced bit for bit" in capsys.readouterr().out
    report = json.loads(small_report.read_text())
    report["6"]["Student"]["F"] += 1.0  # one number off
    tampered = tmp_path / "t3.json"
    tampered.write_text(json.dumps(report))
    assert main([str(tampered)]) == 1
    assert "/6/Student/F" in capsys.readouterr().out


def test_a_changed_policy_file_is_named_not_compared(tmp_path, capsys):
    report = {
        "protocol": {"command": "cefc-eval --protocol table5", "adversary": {"policy": "x.pt", "sha256": "0" * 64}}
    }
    (tmp_path / "r.json").write_text(json.dumps(report))
    assert main([str(tmp_path / "r.json"), "--root", str(tmp_path)]) == 1
    assert "cannot reproduce" in capsys.readouterr().out


def test_bad_input_exits_2(tmp_path, capsys):
    (tmp_path / "r.json").write_text(json.dumps({"protocol": {}}))
    assert main([str(tmp_path / "r.json")]) == 2
    assert main([str(tmp_path / "missing.json")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and "no cefc-eval command" in err[0]


def test_outputs_are_redirected_and_timing_is_not_compared(tmp_path):
    args = redirected(["--protocol", "table8", "--report-dir", "eval/reports", "--json=a/b.json"], tmp_path)
    assert args == [
        "--protocol",
        "table8",
        "--report-dir",
        str(tmp_path / "reports"),
        "--json",
        str(tmp_path / "b.json"),
    ]
    old = {"rows": [{"F": 1.0, "wall_s": 3.0}, {"condition": "SITL-M", "F": 2.0}], "provenance": {"git_commit": "a"}}
    new = {"rows": [{"F": 1.0, "wall_s": 4.0}, {"condition": "SITL-M", "F": 5.0}], "provenance": {"git_commit": "b"}}
    assert compare(old, new) == (1, [])
    assert compare(old, {**new, "rows": [{"F": 1.5}, new["rows"][1]]})[1] == ["/rows/0/F: 1.0 != 1.5"]
    table8_old = {"rows": {"5": {"SITL-S": {"F": 1.0}, "SITL-M": {"F": 2.0, "retention": 1.0}}}}
    table8_new = {"rows": {"5": {"SITL-S": {"F": 1.0}, "SITL-M": {"F": 3.0, "retention": 0.9}}}}
    assert compare(table8_old, table8_new) == (1, [])
    table8_new["rows"]["5"]["SITL-S"]["F"] = 1.25
    assert compare(table8_old, table8_new)[1] == ["/rows/5/SITL-S/F: 1.0 != 1.25"]


def test_a_report_of_the_earlier_acceleration_interface_is_re_flown_under_its_new_name(tmp_path):
    """Reports written before `--offboard acceleration` became PX4's (no "accel_max" recorded) flew
    what is now "acceleration-assisted"; later reports (with "accel_max", even None) are PX4's."""
    shipped = json.loads((ROOT / "eval/reports/mujoco_ft/acceleration_nav/table8.json").read_text())
    assert flew_legacy_acceleration(shipped)
    assert not flew_legacy_acceleration({**shipped, "accel_max": None})
    assert not flew_legacy_acceleration(json.loads((ROOT / "eval/reports/table8.json").read_text()))  # velocity
    args = ["--protocol", "table8", "--offboard", "acceleration", "--guard", "off"]
    assert legacy_command(args) == ["--protocol", "table8", "--offboard", "acceleration-assisted", "--guard", "off"]
    assert legacy_command(["--offboard=acceleration"]) == ["--offboard=acceleration-assisted"]
    new = {
        "offboard": "acceleration-assisted",
        "accel_max": None,
        "cells": [{"spec": {"offboard": "acceleration-assisted"}}],
    }
    old = {"offboard": "acceleration", "cells": [{"spec": {"offboard": "acceleration"}}]}
    assert compare(old, legacy_names(new)) == (0, [])  # renamed back; the added None setting is no difference
    assert compare(old, {**legacy_names(new), "accel_max": 3.5})[1] == ["/accel_max: only in the new report"]
