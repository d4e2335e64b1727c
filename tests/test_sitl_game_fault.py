"""examples/sitl_game_fault.py: an agent killed in the middle of a SITL-M game (real processes,
particle world here for speed): its vehicle holds, the game finishes, no agent process is left
(`ps`); bad input exits 2 with one line before anything starts."""

import subprocess
import sys
from pathlib import Path

SCRIPT = Path(__file__).resolve().parents[1] / "examples" / "sitl_game_fault.py"


def run(*args):
    return subprocess.run([sys.executable, str(SCRIPT), *args], capture_output=True, text=True, timeout=300)


def test_killed_agent_holds_and_leaves_no_process():
    out = run("--backend", "particle", "--uav", "1", "--step", "100", "--seed", "3")
    assert out.returncode == 0, out.stdout + out.stderr
    text = out.stdout
    assert "400 steps" in text and "'event': 'fault_kill'" in text and "'event': 'offboard_loss_hold'" in text
    assert "agent processes left after the game (ps): 0" in text
    speed = float(text.split("its speed is at most ")[1].split(" m/s")[0])
    assert speed < 0.1


def test_bad_input_is_one_line_and_exit_2():
    for args in (["--uav", "8"], ["--step", "0"], ["--step", "400"], ["--action", "pause"]):
        out = run(*args)
        assert out.returncode == 2 and out.stdout == "" and len(out.stderr.strip().splitlines()) == 1, args
