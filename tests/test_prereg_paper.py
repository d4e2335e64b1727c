"""examples/prereg_paper.py: the paper-schedule pre-registration's runs as its plan states them, and their
tracked copy (a fresh checkout continues them)."""

import importlib.util
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from tests.test_budget_ladder import write_state

SCRIPT = Path(__file__).resolve().parents[1] / "examples" / "prereg_paper.py"
PLAN = Path(__file__).resolve().parents[1] / "docs" / "research" / "preregistration_paper_schedule.md"


def load_script():
    spec = importlib.util.spec_from_file_location("prereg_paper", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # its dataclass looks its module up while the class is made
    spec.loader.exec_module(module)
    return module


def test_list_prints_the_plans_commands_seed_by_seed(capsys):
    module = load_script()
    assert module.main(["--list"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    runs, total = lines[:-1], lines[-1]
    assert len(runs) == 20 and "0 of 20 runs done" in total and "39.6 core-hours in all" in total
    plan = " ".join(PLAN.read_text().replace("\\\n", " ").split())  # shell lines joined
    for i, line in enumerate(runs):
        seed, variant = 400 + i // 2, ("consmac-a", "mappo")[i % 2]
        command = line.split(" h  ", 1)[1]
        assert command.endswith(" --no-progress") and "--resume" not in command
        stated = (
            f"cefc-train highlevel --schedule paper --variant {variant} --seed $K --adversary "
            "adversary_ppo_nearest_group_intercept --threads 1 --out runs/prereg_paper "
            "--policies-dir policies/prereg_paper"
        )
        assert stated in plan  # the plan's own words
        assert command == stated.replace("$K", str(seed)) + " --no-progress"


def test_keep_and_restore_carry_unfinished_runs_across_a_fresh_checkout(tmp_path, capsys):
    module = load_script()
    out, policies = tmp_path / "runs", tmp_path / "policies"
    runs = module.planned_runs(10, out, policies)
    done, compact, full = runs[1], runs[0], runs[2]
    write_state(done.run_dir, 1500, None)
    policies.mkdir()
    for name in (done.policy, done.policy.with_suffix(".json")):
        name.write_bytes(b"exported")
    write_state(compact.run_dir, 1012, 0)
    write_state(full.run_dir, 1030, 5)
    argv = ["--out", str(out), "--policies-dir", str(policies)]
    assert module.main(["--keep", *argv]) == 0
    printed = capsys.readouterr().out
    assert f"kept {done.stem}: done" in printed and f"kept {compact.stem}: iteration 1012" in printed
    assert f"kept {full.stem}: its state at iteration 1030 holds the replay's rows" in printed
    assert {p.name for p in done.kept_dir(policies).iterdir()} == {"config.json", "progress.csv"}
    assert (compact.kept_dir(policies) / "state.pt").is_file() and not full.kept_dir(policies).exists()

    shutil.rmtree(out)  # a fresh checkout: the tracked folder only
    lines = module.kept_runs.restore(runs, policies)
    assert lines == [f"restored {compact.stem}: iteration 1012", f"restored {done.stem}: done"]
    assert module.kept_runs.saved_iteration(compact.run_dir / "state.pt") == 1012
    assert "--resume" in compact.command() and (done.run_dir / "progress.csv").is_file()
    assert module.main(["--list", *argv]) == 0
    assert "1 of 20 runs done" in capsys.readouterr().out
    assert module.kept_runs.restore(runs, policies) == []


@pytest.mark.parametrize(
    "argv, needle",
    [
        (["--seeds", "9"], "--seeds 9: the plan trains at least 10 per method"),
        (["--runs", "0"], "--runs 0: must be >= 1"),
        (["--jobs", "3"], "--jobs: invalid choice: 3"),
        (["--list", "--keep"], "not allowed with argument"),
        (["--policies-dir", "/proc/p"], "--policies-dir /proc/p"),
    ],
)
def test_bad_input_exits_2_with_one_line(argv, needle, tmp_path, capsys):
    module = load_script()
    with pytest.raises(SystemExit) as exit_info:
        module.main([*argv, "--out", str(tmp_path / "runs")])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and needle in err and "Traceback" not in err
    assert not (tmp_path / "runs").exists()


def test_the_tracked_copy_is_not_ignored_by_git():
    module = load_script()
    run = module.planned_runs(10, module.ROOT / module.OUT, module.ROOT / module.POLICIES)[0]
    for path in (run.kept_dir(module.ROOT / module.POLICIES) / "state.pt", run.policy):
        assert subprocess.run(["git", "check-ignore", "-q", str(path)], cwd=module.ROOT).returncode == 1, path
