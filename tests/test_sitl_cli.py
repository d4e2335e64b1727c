"""cefc-eval's SITL-M and dropout flags: refused where they do not apply, and flown end to end."""

from __future__ import annotations

import json

import psutil
import pytest

from cefc_mj.cli.eval import main


@pytest.mark.parametrize(
    "argv, needle",
    [
        (["--link-delay", "5"], "--link-delay: applies to SITL-M only"),
        (["--jitter", "2"], "--jitter: applies to SITL-M only"),
        (["--sitl-m", "--link-delay", "-1"], "--link-delay -1"),
        (["--sitl-m", "--jitter", "nan"], "--jitter nan"),
        (["--sitl-m", "--link-delay", "1e9"], "--link-delay 1e+09"),
        (["--sitl-m", "--workers", "2"], "SITL-M episodes fly one at a time"),
        (["--sitl-m", "--backend", "particle", "--protocol", "table3"], "--sitl-m: Table III"),
        (["--drop", "two@5"], "must be K@STEP"),
        (["--drop", "3@100", "--formation", "5"], "k must be in 1..2"),
        (["--drop", "1@1000", "--formation", "5"], "step must be in 1..999"),
        (["--drop", "1@10", "--protocol", "table8"], "--drop: agent dropout is a --protocol single experiment"),
    ],
)
def test_bad_sitl_and_dropout_flags(argv, needle, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as exit_info:
        main(argv)
    err = capsys.readouterr().err.strip()
    assert exit_info.value.code == 2 and len(err.splitlines()) == 1 and needle in err, err
    assert list(tmp_path.iterdir()) == []


def test_single_sitl_m_flies_beside_the_calm_reference(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    before = set(psutil.Process().children(recursive=True))
    assert (
        main(
            [
                "--sitl-m",
                "--formation",
                "5",
                "--steps",
                "20",
                "--episodes",
                "1",
                "--link-delay",
                "5",
                "--json",
                str(tmp_path / "out.json"),
            ]
        )
        == 0
    )
    out = capsys.readouterr().out
    assert "SITL-M" in out and "round trip p50" in out
    rows = json.loads((tmp_path / "out.json").read_text())["rows"]["5"]
    assert set(rows) == {"SITL-M", "SITL-S"}
    sitl = rows["SITL-M"]["episodes_detail"][0]["sitl"]
    assert sitl["decision_latency_ms"]["all"]["count"] > 0 and sitl["malformed"] == 0
    assert rows["SITL-M"]["episodes_detail"][0]["steps"] == 20
    assert set(psutil.Process().children(recursive=True)) <= before, "agent processes survived the run"


def test_lockstep_dropout_reports_before_and_after(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    assert (
        main(
            [
                "--drop",
                "2@10",
                "--policy",
                "student",
                "--formation",
                "6",
                "--backend",
                "particle",
                "--steps",
                "30",
                "--episodes",
                "1",
                "--json",
                str(tmp_path / "out.json"),
            ]
        )
        == 0
    )
    assert "dropout at step 10: before (6 UAVs" in capsys.readouterr().out
    episode = json.loads((tmp_path / "out.json").read_text())["rows"]["6"]["SITL-S"]["episodes_detail"][0]
    assert episode["dropout"]["phases"]["after"]["group_size"] == 4 and len(episode["dropout"]["uavs"]) == 2


def test_table8_sitl_m_row_is_cached_under_its_own_key(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    argv = [
        "--protocol",
        "table8",
        "--sitl-m",
        "--formation",
        "5",
        "--episodes",
        "1",
        "--steps",
        "5",
        "--report-dir",
        str(tmp_path / "r"),
    ]
    assert main(argv) == 0
    report = json.loads((tmp_path / "r" / "table8.json").read_text())
    assert "SITL-M" in report["rows"]["5"] and "SITL-S" in report["rows"]["5"]
    assert "## SITL-M timing" in (tmp_path / "r" / "table8.md").read_text()
    assert (tmp_path / "r" / "table8_sitl.png").stat().st_size > 1000
    sitl = report["rows"]["5"]["SITL-M"]["episodes_detail"][0]["sitl"]
    assert sum(sitl["round_trip_ms"]["histogram"]) == sitl["round_trip_ms"]["all"]["count"] > 0
    capsys.readouterr()
    assert main(argv) == 0
    assert "8 of 8 cells reused" in capsys.readouterr().out


def test_sitl_m_recording_carries_the_timings(tmp_path):
    """Rerun gets per-step SITL-M timings beside F, N, C (the recording is read back)."""
    from cefc_mj.deploy.episode import SitlConfig, run_sitl_episode
    from cefc_mj.eval.runner import EpisodeSpec
    from cefc_mj.viz.rerun_log import close_recording, log_episode, open_recording

    result = run_sitl_episode(EpisodeSpec(formation=5, seed=0, steps=15), SitlConfig(), record=True)
    scalars = result.record.scalars
    for name in ("sitl_decision_latency_ms", "sitl_round_trip_ms", "sitl_command_age_ms"):
        assert scalars[name].shape == (15,) and scalars[name][-1] > 0
    rrd = tmp_path / "sitl.rrd"
    recording = open_recording(rrd_path=rrd, spawn=False, recording_id="sitl")
    log_episode(result.record, recording)
    close_recording(recording)
    from rrd_reader import read_rrd

    paths = set(read_rrd(rrd))
    assert {"/metrics/sitl_round_trip_ms", "/metrics/sitl_command_age_ms"} <= paths, sorted(paths)
