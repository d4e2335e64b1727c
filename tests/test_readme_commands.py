"""The README's cheap commands leave a checkout's tracked files untouched.

Each command runs as a user would, in the root of a fresh clone, but shortened (fewer steps, c, seeds)
so the whole set takes a minute. The clone is the data root (CEFC_MJ_HOME), so a command that wrote
into the shipped policies/, eval/ or assets/ would show in the clone's `git status`. Every command is
checked to still be in the README, so the list cannot drift from what users read.
"""

from __future__ import annotations

import os
import shlex
import shutil
import subprocess
import sys

import pytest

from cefc_mj import paths

README = (paths.PROJECT_ROOT / "README.md").read_text() if (paths.PROJECT_ROOT / "README.md").is_file() else ""

# (the command as the README writes it, the extra flags that make it cheap)
COMMANDS = [
    ("cefc-eval --wind 8 --deviation 0.5", "--formation 5 --steps 20"),
    ("cefc-eval --protocol table8 --workers 2", "--formation 5 --episodes 1 --steps 5"),
    ("cefc-eval --backend particle --protocol table3", "--formation 6 --episodes 2"),
    ("cefc-eval --formation 6 --episodes 1 --rrd run.rrd --png plots/", "--steps 5"),
    ("cefc-train lowlevel --formation 6 --step 3 --init-from atm_c6_step3", "--budget 1it --envs 4 --threads 1"),
    (
        "cefc-train lowlevel --formation 6 --step 1 --budget 150it --out runs/mine --policies-dir my_policies",
        "--budget 1it --envs 4 --threads 1",
    ),
    ("cefc-train lowlevel --formation 6 --step 3 --backend mujoco --budget 20it", "--budget 1it --envs 2 --threads 1"),
]


@pytest.fixture(scope="module")
def clone(tmp_path_factory):
    if shutil.which("git") is None or not (paths.PROJECT_ROOT / ".git").exists():
        pytest.skip("needs git and a git checkout")
    dest = tmp_path_factory.mktemp("readme") / "clone"
    subprocess.run(["git", "clone", "-q", str(paths.PROJECT_ROOT), str(dest)], check=True)
    return dest


def _run(command: str, extra: str, cwd) -> subprocess.CompletedProcess:
    argv = shlex.split(command) + shlex.split(extra)
    module = {"cefc-eval": "cefc_mj.cli.eval", "cefc-train": "cefc_mj.cli.train"}[argv[0]]
    env = {**os.environ, "CEFC_MJ_HOME": str(cwd), "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    return subprocess.run(
        [sys.executable, "-m", module, *argv[1:]], cwd=cwd, env=env, capture_output=True, text=True, timeout=600
    )


@pytest.mark.parametrize("command, extra", COMMANDS, ids=[c for c, _ in COMMANDS])
def test_readme_command_leaves_tracked_files_alone(command, extra, clone):
    assert command in " ".join(README.replace("\\\n", " ").split()), f"no longer in the README: {command}"
    done = _run(command, extra, clone)
    assert done.returncode == 0, f"{command} {extra}: exit {done.returncode}\n{done.stderr[-2000:]}"
    status = subprocess.run(
        ["git", "status", "--porcelain", "--untracked-files=no"], cwd=clone, capture_output=True, text=True, check=True
    ).stdout
    assert status == "", f"{command} changed tracked files:\n{status}"
