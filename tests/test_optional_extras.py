"""Optional extras end cleanly: without pyrvo, Table III skips ORCA-F with one line naming the extra,
and asking for ORCA-F alone exits 2 with that line before any work (a real cefc-eval process with the
import blocked)."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest


def _run_without_pyrvo(tmp_path, *args):
    blocker = tmp_path / "block"
    blocker.mkdir()
    (blocker / "pyrvo.py").write_text("raise ImportError('pyrvo blocked by the test')\n")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(blocker), os.environ.get("PYTHONPATH", "")])}
    return subprocess.run(
        [sys.executable, "-m", "cefc_mj.cli.eval", *args],
        capture_output=True,
        text=True,
        env=env,
        cwd=tmp_path,
        timeout=300,
    )


def test_table3_without_pyrvo_skips_orca_with_a_note(tmp_path):
    out = _run_without_pyrvo(
        tmp_path,
        "--backend",
        "particle",
        "--protocol",
        "table3",
        "--formation",
        "6",
        "--episodes",
        "1",
        "--steps",
        "5",
        "--json",
        str(tmp_path / "t3.json"),
    )
    assert out.returncode == 0, out.stderr
    assert "Traceback" not in out.stderr
    notes = [line for line in out.stderr.splitlines() if "ORCA-F" in line]
    assert len(notes) == 1 and "pip install -e '.[baselines]'" in notes[0], out.stderr
    assert "AT-M-Step3" in out.stdout
    assert '"ORCA-F"' not in (tmp_path / "t3.json").read_text()


def test_orca_alone_without_pyrvo_exits_2_before_work(tmp_path):
    report = tmp_path / "t3.json"
    out = _run_without_pyrvo(
        tmp_path,
        "--backend",
        "particle",
        "--protocol",
        "table3",
        "--policy",
        "orca",
        "--formation",
        "6",
        "--episodes",
        "1",
        "--steps",
        "5",
        "--json",
        str(report),
    )
    assert out.returncode == 2
    assert out.stderr.strip().count("\n") == 0 and "pip install -e '.[baselines]'" in out.stderr
    assert "Traceback" not in out.stderr and not report.exists()


def test_pyrvo_available_reflects_the_install():
    from cefc_mj.baselines.orca import pyrvo_available

    try:
        import pyrvo  # noqa: F401
    except ImportError:
        assert not pyrvo_available()
    else:
        assert pyrvo_available()


if __name__ == "__main__":  # pragma: no cover
    sys.exit(pytest.main([__file__, "-q"]))
