"""examples/anchor_approach.py: the split of Table VIII's anchor periods adds up to the env's own N
and stays under its bound, on a real particle episode flown by the shipped policy; --png draws a
picture per episode; bad input exits 2 with one line."""

import importlib.util
import subprocess
import sys
from pathlib import Path

import pytest

from cefc_mj.eval.runner import TABLE8_ANCHOR_REDRAW, TABLE8_STEPS, load_policy_for

SCRIPT = Path(__file__).resolve().parents[1] / "examples" / "anchor_approach.py"


def load_script():
    spec = importlib.util.spec_from_file_location("anchor_approach", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.usefixtures("one_torch_thread")
def test_the_anchor_periods_count_the_same_steps_as_the_metric_n():
    periods, n = load_script().anchor_periods(5, 0, "particle", load_policy_for("atm", 5))
    assert len(periods) == TABLE8_STEPS // TABLE8_ANCHOR_REDRAW
    assert sum(p["inside"] for p in periods) == n > 0
    for p in periods:
        assert 0 <= p["reach"] <= TABLE8_ANCHOR_REDRAW and 0.0 <= p["stays"] <= 1.0
        assert p["inside"] <= p["bound"] <= TABLE8_ANCHOR_REDRAW  # nothing beats flying straight at the limit
        if p["reach"] < TABLE8_ANCHOR_REDRAW:  # arrived: it moved no faster than the 1 m/s speed limit allows
            assert p["start"] < 1.0 or 0.0 < p["approach"] <= 1.0 + 1e-9


@pytest.mark.usefixtures("one_torch_thread")
def test_png_draws_one_picture_per_episode(tmp_path, capsys):
    assert load_script().main(["--formations", "5", "--seeds", "2", "--policy", "nav", "--png", str(tmp_path)]) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c5_seed0.png", "c5_seed1.png"]
    for p in tmp_path.iterdir():
        assert p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "bound" in capsys.readouterr().out


@pytest.mark.parametrize(
    "argv, needle",
    [
        (["--formations", "9"], "--formations [9]"),
        (["--seeds", "0"], "--seeds 0"),
        (["--seed", "-1"], "--seed -1"),
        (["--policy", "no_such_policy", "--formations", "5"], "--policy no_such_policy"),
        (["--png", "/proc/no_such_dir"], "--png /proc/no_such_dir: cannot write there"),
    ],
)
def test_bad_input_exits_2_with_one_line(argv, needle):
    run = subprocess.run([sys.executable, str(SCRIPT), *argv], capture_output=True, text=True, timeout=120)
    assert run.returncode == 2 and run.stdout == ""
    assert needle in run.stderr and len(run.stderr.strip().splitlines()) == 1
