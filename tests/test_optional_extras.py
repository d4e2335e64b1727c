"""Optional extras end cleanly: without pyrvo, Table III skips ORCA-F with one line naming the extra,
and asking for ORCA-F alone exits 2 with that line before any work (a real cefc-eval process with the
import blocked); without dm-control, `cefc_mj` and the suite's task list still import, while
`suite.load` and `cefc-view` refuse in one line naming the `dm-control` extra; `import cefc_mj` (and a
MuJoCo env) never imports dm_control."""

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


def _run_without_dm_control(tmp_path, *args):
    """`python *args` with dm_control unimportable (a package on PYTHONPATH that raises as a missing one)."""
    blocker = tmp_path / "block" / "dm_control"
    blocker.mkdir(parents=True)
    block = "raise ModuleNotFoundError('dm_control blocked by the test', name='dm_control')\n"
    (blocker / "__init__.py").write_text(block)
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY", "WAYLAND_SOCKET")}
    env["PYTHONPATH"] = os.pathsep.join([str(blocker.parent), os.environ.get("PYTHONPATH", "")])
    return subprocess.run([sys.executable, *args], capture_output=True, text=True, env=env, cwd=tmp_path, timeout=300)


def test_cefc_mj_never_imports_dm_control(tmp_path):
    script = (
        "import sys, cefc_mj\n"
        "env = cefc_mj.make_env(backend='mujoco', n_agents=3, mode='formation', seed=0)\n"
        "env.reset(seed=0)\n"
        "print(sorted(m for m in sys.modules if m.split('.')[0] in ('dm_control', 'dm_env')))\n"
    )
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, cwd=tmp_path, timeout=300)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"


def test_without_dm_control_the_suite_names_the_extra(tmp_path):
    script = (
        "from cefc_mj import suite\n"
        "print(len(suite.TASKS))\n"
        "try:\n"
        "    suite.load('cefc', 'formation_c6')\n"
        "except suite.MissingExtra as e:\n"
        "    print(isinstance(e, ImportError), e)\n"
    )
    out = _run_without_dm_control(tmp_path, "-c", script)
    assert out.returncode == 0, out.stderr
    count, refusal = out.stdout.strip().splitlines()
    assert count == "7" and refusal.startswith("True ") and "pip install -e '.[dm-control]'" in refusal


def test_cefc_view_without_dm_control_exits_2_naming_the_extra(tmp_path):
    out = _run_without_dm_control(tmp_path, "-m", "cefc_mj.cli.view", "formation_c5")
    assert out.returncode == 2
    assert out.stderr.count("\n") == 1 and "pip install -e '.[dm-control]'" in out.stderr, out.stderr
    assert "Traceback" not in out.stderr


if __name__ == "__main__":  # pragma: no cover
    sys.exit(pytest.main([__file__, "-q"]))
