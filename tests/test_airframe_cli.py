"""cefc-eval --airframe: refused up front when it cannot fly, flown (and cached under its file's digest)
when it can."""

from __future__ import annotations

import json

import pytest

from cefc_mj.cli.eval import main
from cefc_mj.eval.runner import EpisodeSpec, airframe_files
from cefc_mj.eval.table8 import cell_key_fields


@pytest.mark.parametrize(
    "argv, needle",
    [
        (["--airframe", "nope"], "unknown airframe 'nope'"),
        (["--airframe", "crazyflie", "--backend", "particle"], "--airframe: the particle backend has no airframe"),
        (["--airframe", "MISSING.xml"], "--airframe MISSING.xml"),
    ],
)
def test_bad_airframe_is_one_line_exit_2(argv, needle, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as exit_info:
        main(argv)
    err = capsys.readouterr().err.strip()
    assert exit_info.value.code == 2 and len(err.splitlines()) == 1 and needle in err, err


def test_crazyflie_flies_a_short_episode(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert (
        main(["--airframe", "crazyflie", "--formation", "5", "--steps", "20", "--episodes", "1", "--json", "out.json"])
        == 0
    )
    episode = json.loads((tmp_path / "out.json").read_text())["rows"]["5"]["SITL-S"]["episodes_detail"][0]
    assert episode["airframe"] == "crazyflie" and episode["steps"] == 20 and episode["diverged"] is None


def test_cell_key_covers_the_airframe_files():
    iris, crazy = EpisodeSpec(formation=5, seed=0), EpisodeSpec(formation=5, seed=0, airframe="crazyflie")
    assert airframe_files(iris) != airframe_files(crazy)
    assert airframe_files(EpisodeSpec(formation=5, seed=0, backend="particle")) is None
    assert cell_key_fields(iris, "p", "c")["airframe"] == airframe_files(iris)
