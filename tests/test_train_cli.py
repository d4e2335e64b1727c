"""cefc-train as a user meets it: bad input ends in one line (exit 2) before anything is written,
runs land under --out (default runs/<command> in the current folder) and never in the shipped
policies/, --init-from fine-tunes a shipped policy on a fresh checkout, --resume needs a run,
--install is the one way into policies/, and model cards carry their provenance."""

import hashlib
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from cefc_mj import paths
from cefc_mj.cli.train import main
from cefc_mj.nn import ATMActor, ATMConfig, load_actor, save_policy
from cefc_mj.provenance import git_commit
from cefc_mj.task.config import TaskConfig

# The smallest run that works: one iteration of 2 envs (c = 3), one torch thread.
TINY = ["--budget", "1", "--envs", "2", "--threads", "1", "--no-progress"]
CEFC_TRAIN = Path(sys.executable).parent / "cefc-train"


@pytest.fixture(autouse=True)
def in_tmp(tmp_path, monkeypatch):
    """Every test runs in its own empty folder, so the default runs/ lands there; one torch thread."""
    monkeypatch.chdir(tmp_path)
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def shipped_policies() -> dict[str, str]:
    return {p.name: sha256(p) for p in sorted(paths.POLICIES_DIR.iterdir()) if p.is_file()}


def files_under(folder: Path) -> list[str]:
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*"))


def usage_error(argv, capsys) -> str:
    """Run the CLI in-process; it must exit 2 with exactly one line on stderr, which is returned."""
    with pytest.raises(SystemExit) as exc:
        main(argv)
    err = capsys.readouterr().err
    assert exc.value.code == 2, err
    assert err.count("\n") == 1 and err.startswith("cefc-train"), err
    return err.strip()


# ---------------------------------------------------------------------------- bad input
LOW = ["lowlevel", "--formation", "3", "--step", "1"]
ROBUST = ["lowlevel", "--formation", "3", "--step", "3", "--init-from", "atm_c3_step3"]


@pytest.mark.parametrize(
    "argv, needle",
    [
        (LOW + ["--budget", "0"], "--budget '0': must be more than zero"),
        (LOW + ["--budget=-5m"], "--budget '-5m': expected iterations"),
        (LOW + ["--budget", "-5m"], "argument --budget: expected one argument"),
        (LOW + ["--budget", "abc"], "--budget 'abc'"),
        (LOW + ["--budget", "1e99it"], "--budget '1e99it'"),
        (LOW + ["--budget", "99999999999it"], "at most 10000000 iterations"),
        (LOW + ["--budget", "99999h"], "at most 30 days"),
        (LOW + ["--envs", "0"], "--envs 0: must be an integer >= 1"),
        (LOW + ["--envs", "100000"], "--envs 100000: must be at most"),
        (LOW + ["--epochs", "0"], "--epochs 0"),
        (LOW + ["--minibatches", "0"], "--minibatches 0"),
        (LOW + ["--envs", "2", "--minibatches", "5000"], "--minibatches 5000: must be at most the 200 env-steps"),
        (LOW + ["--lr", "0"], "--lr 0.0: must be a positive number"),
        (LOW + ["--lr", "nan"], "--lr nan"),
        (LOW + ["--lr", "3"], "--lr 3.0: must be at most"),
        (LOW + ["--threads", "0"], "--threads 0"),
        (LOW + ["--threads", "100000"], "--threads 100000: must be at most"),
        (LOW + ["--seed", "-1"], "--seed -1: must be an integer >= 0"),
        (LOW + ["--density", "0.5"], "--density 0.5"),
        (LOW + ["--density", "-0.1"], "--density -0.1"),
        (ROBUST + ["--deviation", "-0.5"], "--deviation -0.5"),
        (ROBUST + ["--deviation", "nan"], "--deviation nan"),
        # Quadrotor-like dynamics only fine-tune Step 3.
        (LOW + ["--velocity-noise", "0.1"], "--response-time/--velocity-noise (0.0, 0.1)"),
        (LOW + ["--collision-margin", "0.7"], "--collision-margin 0.7: must be in [0, 0.5] m"),
        (LOW + ["--collision-margin", "nan"], "--collision-margin nan"),
        (
            LOW + ["--navigation-weight", "8"],
            "--navigation-weight 8.0: another navigation weight fine-tunes the Step 3",
        ),
        (ROBUST + ["--navigation-weight", "0"], "--navigation-weight 0.0: must be in (0, 50]"),
        (ROBUST + ["--navigation-weight", "inf"], "--navigation-weight inf"),
        (LOW + ["--anchor-periods", "2"], "--anchor-periods 2: longer episodes with anchor redraws fine-tune"),
        (ROBUST + ["--anchor-periods", "0"], "--anchor-periods 0: must be an integer >= 1"),
        (LOW + ["--straggler-fraction", "0.3"], "--straggler-fraction 0.3: starts away from the group fine-tune"),
        (ROBUST + ["--straggler-fraction", "1.5"], "--straggler-fraction 1.5: must be in [0, 1]"),
        (ROBUST + ["--straggler-fraction", "nan"], "--straggler-fraction nan"),
        (["lowlevel-all", "--workers", "0"], "--workers 0"),
        (["lowlevel-all", "--workers", "7"], "--workers 7"),
        (["lowlevel-all", "--seed", "-3"], "--seed -3"),
        (["distill", "--tuples", "10000000000"], "--tuples 10000000000: must be at most"),
        (["distill", "--tuples", "0"], "--tuples 0"),
        (LOW + ["--formation", "9"], "invalid choice: 9"),
        (["lowlevel", "--step", "1"], "required: --formation"),
        (LOW + ["--envs", "two"], "--envs: invalid int value"),
    ],
)
def test_bad_flag_values(argv, needle, tmp_path, capsys):
    assert needle in usage_error(argv, capsys)
    assert files_under(tmp_path) == []  # nothing written, not even the default runs/ folder


def test_bad_output_folders(tmp_path, capsys):
    a_file = tmp_path / "a_file"
    a_file.write_text("x")
    for argv, needle in (
        (LOW + ["--out", str(a_file)], "is a file, not a folder"),
        (LOW + ["--out", str(a_file / "runs")], "is a file, not a folder"),
        (LOW + ["--policies-dir", str(a_file / "pol")], "--policies-dir"),
        (LOW + ["--policies-dir", str(paths.POLICIES_DIR)], "written only with --install"),
        (LOW + ["--out", str(paths.POLICIES_DIR / "runs")], "inside the shipped policies folder"),
        # /proc passes os.access for root; only a real probe file shows that nothing can be written there
        (LOW + ["--out", "/proc/forbidden/runs"], "/proc is not writable"),
        (LOW + ["--policies-dir", "/proc"], "/proc is not writable"),
    ):
        assert needle in usage_error(argv, capsys)
    assert files_under(tmp_path) == ["a_file"]


@pytest.mark.skipif(os.geteuid() == 0, reason="root may write into any folder")
def test_unwritable_folder(tmp_path, capsys):
    locked = tmp_path / "locked"
    locked.mkdir(mode=0o500)
    try:
        assert "is not writable" in usage_error(LOW + ["--out", str(locked / "runs")], capsys)
        assert "is not writable" in usage_error(LOW + ["--policies-dir", str(locked)], capsys)
    finally:
        locked.chmod(0o700)


def test_bad_init_from(tmp_path, capsys):
    junk = tmp_path / "junk.pt"
    junk.write_bytes(b"not a checkpoint")
    wide = tmp_path / "wide.pt"  # 9 neighbour slots: another observation size than the stage's 7
    save_policy(ATMActor(ATMConfig.from_task(TaskConfig(n_agents=3, mode="formation", max_neighbours=9))), wide)
    step3 = ["lowlevel", "--formation", "3", "--step", "3"]
    for argv, needle in (
        (step3 + ["--init-from", "no_such_policy"], "--init-from: no policy 'no_such_policy'"),
        (step3 + ["--init-from", str(tmp_path / "missing.pt")], "--init-from: no policy"),
        (step3 + ["--init-from", str(junk)], "not a readable checkpoint"),
        (step3 + ["--init-from", str(wide)], "made for observations of size 73, this env gives 63"),
        (step3 + ["--init-from", "atm_student"], "made for another network: hidden 256 (this stage: 128)"),
        (LOW + ["--init-from", "atm_c3_step3"], "starts from random weights"),
        (step3, "or start from a trained policy with --init-from atm_c3_step3"),  # fresh clone, no runs/
        (step3 + ["--safe"], "no training state at runs/lowlevel/atm_c3_step3/state.pt"),
    ):
        assert needle in usage_error(argv, capsys)
    assert files_under(tmp_path) == ["junk.pt", "wide.pt"]


def test_init_from_across_action_bounds_records_the_bound(tmp_path, capsys):
    """The action bound is a stated parameter: a stage trains at --accel-max (validated before any
    work), starts from a policy trained at another bound when the network is the same, and its card
    and policy file record the bound."""
    for bad in ("0", "-1", "12", "nan"):
        assert "--accel-max" in usage_error(ROBUST + ["--deviation", "0.5", "--accel-max", bad] + TINY, capsys)
    assert files_under(tmp_path) == []
    shipped, _ = load_actor(paths.POLICIES_DIR / "atm_c3_step3.pt")
    assert shipped.cfg.accel_max == 2.0
    assert main(ROBUST + ["--deviation", "0.5", "--accel-max", "3.5"] + TINY) == 0
    out = tmp_path / "runs" / "lowlevel" / "policies"
    card = json.loads((out / "atm_c3_robust.json").read_text())
    assert card["config"]["accel_max"] == 3.5 and card["task"]["accel_max"] == 3.5
    assert card["init_from"]["name"] == "atm_c3_step3" and "--accel-max 3.5" in card["command"]
    tuned, _ = load_actor(out / "atm_c3_robust.pt")
    assert tuned.cfg.accel_max == 3.5
    moved = max((p - q).abs().max().item() for p, q in zip(tuned.parameters(), shipped.parameters()))
    assert 0 < moved < 0.05, moved  # fine-tuned from the 2 m/s^2 weights, not re-initialised
    obs = torch.zeros(1, shipped.cfg.obs_dim)
    big = torch.full((1, 2), 10.0)
    assert tuned.to_acceleration(big, obs).max().item() == 3.5 and shipped.to_acceleration(big, obs).max().item() == 2.0


def test_resume_without_a_run_names_the_folder(tmp_path, capsys):
    for argv, folder in (
        (LOW + ["--resume"], "runs/lowlevel/atm_c3_step1"),
        (ROBUST + ["--deviation", "0.5", "--resume", "--out", "mine"], "mine/atm_c3_robust"),
        (["distill", "--resume"], "runs/distill/atm_student"),
        (["lowlevel-all", "--resume"], "runs/lowlevel-all"),
    ):
        assert f"--resume: no run to continue in {folder}" in usage_error(argv, capsys)
    assert files_under(tmp_path) == []
    # The other way round: a pipeline that has begun is continued only with --resume.
    stage = tmp_path / "runs" / "lowlevel-all" / "atm_c6_step1"
    stage.mkdir(parents=True)
    (stage / "state.pt").write_bytes(b"")
    assert "already holds runs of a pipeline (atm_c6_step1)" in usage_error(["lowlevel-all"], capsys)


def test_distill_without_teachers(tmp_path, capsys):
    err = usage_error(["distill", "--formations", "3", "--teachers-dir", str(tmp_path)], capsys)
    assert "no policy 'atm_c3_step3'" in err and files_under(tmp_path) == []


# ---------------------------------------------------------------------------- real runs
def test_init_from_shipped_policy_then_resume(tmp_path, capsys):
    """AT-M-Robust on a fresh checkout: the actor starts from the shipped Step 3 policy, the critic
    fresh; everything lands under runs/lowlevel; --resume continues it."""
    shipped = paths.POLICIES_DIR / "atm_c3_step3.pt"
    argv = ROBUST + ["--deviation", "0.5"] + TINY
    assert main(argv) == 0
    assert "atm_c3_robust: 1 iterations" in capsys.readouterr().out
    out = tmp_path / "runs" / "lowlevel"
    assert sorted(p.name for p in (out / "policies").iterdir()) == ["atm_c3_robust.json", "atm_c3_robust.pt"]

    card = json.loads((out / "policies" / "atm_c3_robust.json").read_text())
    assert card["init_from"] == {
        "path": "policies/atm_c3_step3.pt",
        "sha256": sha256(shipped),
        "name": "atm_c3_step3",
        "iterations": card["init_from"]["iterations"],
    }
    assert card["init"]["critic"].startswith("fresh") and card["method"] == "AT-M-Robust"
    assert card["differs_from_paper"] == ["sensing deviation up to 0.5 m (fixed)"]
    assert {"numpy", "numba", "mujoco", "torch", "python", "cpu", "code_version"} <= set(card["versions"])
    assert card["git_commit"] == git_commit() and card["command"].startswith("cefc-train lowlevel --formation 3")
    run_config = json.loads((out / "atm_c3_robust" / "config.json").read_text())
    assert run_config == {
        "stage": card["config"],
        "task": card["task"],
        "init": card["init"],
        "command": card["command"],
    }
    # The actor was fine-tuned from the shipped weights: moved by one update, but not re-initialised.
    start, _ = load_actor(shipped)
    tuned, _ = load_actor(out / "policies" / "atm_c3_robust.pt")
    moved = max((p - q).abs().max().item() for p, q in zip(tuned.parameters(), start.parameters()))
    assert 0 < moved < 0.05, moved

    # A second start on the same --out must say --resume; --resume with another --init-from file is refused.
    assert "pass --resume" in usage_error(argv, capsys)
    other = ["--init-from", str(paths.POLICIES_DIR / "atm_c3_safe.pt")]
    assert "resume it without --init-from" in usage_error(argv + ["--resume"] + other, capsys)
    assert main(ROBUST[:-2] + ["--deviation", "0.5", "--resume"] + TINY[2:] + ["--budget", "2"]) == 0
    assert json.loads((out / "policies" / "atm_c3_robust.json").read_text())["iterations"] == 2

    # AT-M-Nav: the same fine-tune with another omega_n, here on episodes of two anchor periods, trained
    # with both and saying so on its card.
    assert (
        main(ROBUST + ["--navigation-weight", "10", "--anchor-periods", "2", "--straggler-fraction", "0.5"] + TINY) == 0
    )
    card = json.loads((out / "policies" / "atm_c3_nav.json").read_text())
    assert (card["method"], card["task"]["rewards"]["navigation_weight_low"]) == ("AT-M-Nav", 10.0)
    assert (card["task"]["episode_steps"], card["task"]["anchor_redraw_steps"]) == (200, 100)
    assert (card["task"]["straggler_fraction"], card["config"]["straggler_fraction"]) == (0.5, 0.5)
    assert card["differs_from_paper"] == [
        "navigation weight omega_n = 10 (paper 4)",
        "episodes of 2 anchor periods of 100 steps, the anchor redrawn at each (paper: one anchor per episode)",
        "in 50% of the episodes one agent starts 3-7 m from the others (paper: every agent in the start square)",
    ]


def test_interrupted_before_the_first_checkpoint_resumes_exactly(tmp_path, monkeypatch, capsys):
    """Ctrl-C during the first iteration: the state written at the start lets --resume finish the
    run, and it ends where an uninterrupted run ends."""
    from cefc_mj.train.mappo import MAPPO

    assert main(LOW + TINY + ["--out", "whole"]) == 0
    iterate = MAPPO.iterate

    def interrupted(self):
        raise KeyboardInterrupt

    monkeypatch.setattr(MAPPO, "iterate", interrupted)
    assert main(LOW + TINY + ["--out", "cut"]) == 130
    assert "--resume continues from the last checkpoint" in capsys.readouterr().err
    monkeypatch.setattr(MAPPO, "iterate", iterate)
    assert main(LOW + TINY + ["--out", "cut", "--resume"]) == 0
    whole, _ = load_actor(tmp_path / "whole" / "policies" / "atm_c3_step1.pt")
    resumed, _ = load_actor(tmp_path / "cut" / "policies" / "atm_c3_step1.pt")
    assert all(torch.equal(a, b) for a, b in zip(whole.state_dict().values(), resumed.state_dict().values()))


def test_interrupted_before_any_checkpoint_says_to_start_again(tmp_path, monkeypatch, capsys):
    """Ctrl-C before a run has written its first state (the adversary's imitation phase, say): the
    hint is to run the command again, not a --resume that would find nothing."""
    from cefc_mj.train import run_state

    def interrupted(*_):
        raise KeyboardInterrupt

    monkeypatch.setattr(run_state, "run_state_path", interrupted)
    assert main(LOW + TINY + ["--out", "early"]) == 130
    err = capsys.readouterr().err
    assert "no checkpoint was written yet: run the same command again (without --resume)" in err, err


def test_install_copies_into_the_shipped_folder(tmp_path, monkeypatch, capsys):
    """--install is the opt-in way into policies/; here policies/ is a stand-in folder."""
    fake_shipped = tmp_path / "shipped"
    fake_shipped.mkdir()
    shutil.copy(paths.POLICIES_DIR / "atm_c3_step3.pt", fake_shipped)
    monkeypatch.setattr(paths, "POLICIES_DIR", fake_shipped)
    safe = ["lowlevel", "--formation", "3", "--step", "3", "--safe", "--init-from", "atm_c3_step3"] + TINY
    assert "written only with --install" in usage_error(safe + ["--policies-dir", str(fake_shipped)], capsys)
    assert sorted(p.name for p in fake_shipped.iterdir()) == ["atm_c3_step3.pt"]

    assert main(safe + ["--install"]) == 0
    assert "installed atm_c3_safe" in capsys.readouterr().out
    exported = tmp_path / "runs" / "lowlevel" / "policies"
    for name in ("atm_c3_safe.pt", "atm_c3_safe.json"):
        assert (fake_shipped / name).read_bytes() == (exported / name).read_bytes()
    assert load_actor(fake_shipped / "atm_c3_safe.pt")[0].cfg.safe
    assert not [p for p in fake_shipped.iterdir() if p.name.startswith(".")]  # no temp files left


def git_status() -> set[str] | None:
    """`git status --porcelain` lines of the checkout (None outside one), without Python sources and
    docs: a training run writes neither, and others may be editing them in a shared working tree."""
    status = subprocess.run(
        ["git", "--no-optional-locks", "-C", str(paths.PROJECT_ROOT), "status", "--porcelain"],
        capture_output=True,
        text=True,
    )
    if status.returncode != 0:
        return None
    return {line for line in status.stdout.splitlines() if not line.endswith((".py", ".md"))}


def test_default_run_leaves_the_repository_unchanged(tmp_path):
    """A real `cefc-train` process with default folders, started outside the checkout: its files
    go to ./runs/lowlevel, git sees no change and every shipped policy keeps its bytes."""
    if not CEFC_TRAIN.is_file():
        pytest.skip("cefc-train is not installed next to this python")
    git_before = git_status()
    if git_before is None:
        pytest.skip("not a git checkout")
    policies_before = shipped_policies()
    run = subprocess.run([str(CEFC_TRAIN), *LOW, *TINY], cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    assert files_under(tmp_path / "runs" / "lowlevel" / "policies") == ["atm_c3_step1.json", "atm_c3_step1.pt"]
    assert (tmp_path / "runs" / "lowlevel" / "atm_c3_step1" / "state.pt").is_file()
    assert git_status() == git_before
    assert shipped_policies() == policies_before


def test_version(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["--version"])
    out = capsys.readouterr().out
    assert exc.value.code == 0 and out.startswith("cefc-train ") and out.count("\n") == 1
    assert all(lib in out for lib in ("python", "numpy", "numba", "mujoco", "torch"))


def test_subprocess_bad_input(tmp_path):
    if not CEFC_TRAIN.is_file():
        pytest.skip("cefc-train is not installed next to this python")
    for argv in ([*LOW, "--budget=-5m"], [*LOW, "--seed", "-1"]):
        bad = subprocess.run([str(CEFC_TRAIN), *argv], cwd=tmp_path, capture_output=True, text=True, timeout=120)
        assert bad.returncode == 2 and bad.stderr.count("\n") == 1 and bad.stderr.startswith("cefc-train: error:")
        assert "Traceback" not in bad.stderr and bad.stdout == ""
    assert files_under(tmp_path) == []
