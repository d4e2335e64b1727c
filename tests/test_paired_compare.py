"""`python -m cefc_mj.eval.paired`: two Table VIII reports compared seed by seed."""

import json

import pytest

from cefc_mj.eval.paired import compare, main


def report(policy: str, figures: dict) -> dict:
    """A table8.json with per-episode details: figures[(c, condition)] = [(F, N, C) per seed]."""
    rows: dict = {}
    for (c, condition), episodes in figures.items():
        rows.setdefault(str(c), {})[condition] = {
            "valid": True,
            "episodes_detail": [{"seed": 100 + k, "F": f, "N": n, "C": col} for k, (f, n, col) in enumerate(episodes)],
        }
    return {"policy": policy, "rows": rows}


def test_a_consistent_gain_is_better_and_noise_is_undecided(tmp_path, capsys):
    calm = [(900.0 + k, 700.0, 0.0) for k in range(12)]
    before = report("nav", {(6, "SITL-S"): calm, (6, "Wind-5"): [(400.0 + k, 20.0, 0.1) for k in range(12)]})
    after = report(
        "mujoco",
        {
            (6, "SITL-S"): calm,
            (6, "Wind-5"): [(700.0 + k, 300.0 + (-1) ** k, 0.1 + 0.01 * (-1) ** k) for k in range(12)],
        },
    )
    (row_calm, row_wind) = compare(before, after)
    assert row_wind["verdict_keeps"] == "better" and row_wind["p_keeps_holm"] < 0.01
    assert row_wind["after_keeps"] > 60 > 30 > row_wind["before_keeps"]
    assert row_wind["verdict_C"].startswith("undecided")
    assert row_calm["verdict_keeps"] == "-"
    worse = compare(after, before)[1]
    assert worse["verdict_keeps"] == "worse"
    a, b = tmp_path / "a.json", tmp_path / "b.json"
    a.write_text(json.dumps(before))
    b.write_text(json.dumps(after))
    assert main([str(a), str(b), "--md", str(tmp_path / "out.md")]) == 0
    assert "(better)" in (tmp_path / "out.md").read_text() and "| 6 | Wind-5 |" in capsys.readouterr().out


@pytest.mark.parametrize("args, message", [(["missing.json", "x.json"], "no such report")])
def test_bad_input_is_one_line_exit_2(args, message, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main(args) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1
