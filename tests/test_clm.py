"""The CL-M baseline: a curriculum over obstacle densities for one low-level MAPPO stage. Bad
curriculums fail up front (ConfigError, CLI exit 2); a run visits every phase in order, logs each
iteration's density, resumes in the phase it was in (and never goes back to an easier one), records
the curriculum in its model card; Table III gets a CL-M row when a clm_c{c} policy exists."""

import csv
import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from cefc_mj.cli.train import main
from cefc_mj.errors import ConfigError
from cefc_mj.eval.table3 import PAPER_TABLE3, format_table3, run_table3
from cefc_mj.nn import ATMActor, ATMConfig, load_actor, save_policy
from cefc_mj.task.config import TaskConfig
from cefc_mj.train.config import Budget, LowLevelConfig, PPOConfig
from cefc_mj.train.lowlevel import read_state, train_lowlevel
from cefc_mj.train.mappo import MAPPO
from cefc_mj.train.pipeline import plan

# The smallest runs that learn something: 2 envs, one epoch, one torch thread.
TINY_PPO = PPOConfig(n_envs=2, epochs=1, minibatches=1, update_threads=1)
TINY_CLI = ["--envs", "2", "--epochs", "1", "--minibatches", "1", "--threads", "1", "--no-progress"]
CEFC_TRAIN = Path(sys.executable).parent / "cefc-train"


@pytest.fixture(autouse=True)
def in_tmp(tmp_path, monkeypatch):
    """Each test in its own folder (default runs/ lands there), one torch thread."""
    monkeypatch.chdir(tmp_path)
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def logged(run_dir: Path) -> list[tuple[int, int, float]]:
    """(iteration, curriculum_phase, obstacle_density) of every row of a run's progress.csv."""
    with (run_dir / "progress.csv").open(newline="") as f:
        return [
            (int(r["iteration"]), int(r["curriculum_phase"]), float(r["obstacle_density"])) for r in csv.DictReader(f)
        ]


def clm(curriculum=(0.0, 0.02, 0.05), iterations=3, formation=3) -> LowLevelConfig:
    return LowLevelConfig(
        formation=formation,
        step=1,
        curriculum=curriculum,
        budget=Budget(iterations=iterations),
        ppo=TINY_PPO,
        checkpoint_every=1,
    )


# ---------------------------------------------------------------------------- configuration
def test_config_names_the_stage_and_round_trips():
    cfg = clm()
    assert (cfg.name, cfg.method, cfg.density) == ("clm_c3", "CL-M", 0.0)
    assert LowLevelConfig.from_dict(json.loads(json.dumps(cfg.to_dict()))) == cfg  # JSON lists back to a tuple
    assert clm(curriculum=[0, 0.01]).curriculum == (0.0, 0.01)
    # Equal shares of the budget: 4 phases over 8 iterations, or over 100 s (whichever is further on).
    eight = clm(curriculum=(0.0, 0.01, 0.02, 0.03), iterations=8)
    assert [eight.curriculum_phase(i, 0.0) for i in range(9)] == [0, 0, 1, 1, 2, 2, 3, 3, 3]
    timed = LowLevelConfig(formation=3, step=1, curriculum=(0.0, 0.01, 0.02, 0.03), budget=Budget(seconds=100.0))
    assert [timed.curriculum_phase(1000, s) for s in (0.0, 24.9, 25.0, 60.0, 99.0, 500.0)] == [0, 0, 1, 2, 3, 3]
    assert LowLevelConfig(formation=3, step=1, budget=Budget(iterations=1)).curriculum is None


@pytest.mark.parametrize(
    "changes, needle",
    [
        ({"curriculum": (0.0, 0.5)}, "curriculum=0,0.5: density 0.5 is not in [0, 0.2]"),
        ({"curriculum": (0.0, float("nan"))}, "density nan"),
        ({"curriculum": (-0.01, 0.02)}, "density -0.01"),
        ({"curriculum": (0.03, 0.01)}, "must not decrease"),
        ({"curriculum": (0.03,)}, "must be 2 to 20"),
        ({"curriculum": tuple([0.01] * 21)}, "must be 2 to 20"),
        ({"curriculum": "0,0.01"}, "must be 2 to 20"),
        ({"curriculum": (0.0, True)}, "density True"),
        ({"curriculum": (0.0, 0.01), "step": 2}, "use it with step 1"),
        ({"curriculum": (0.0, 0.01), "obstacle_density": 0.01}, "leave obstacle_density unset"),
        ({"curriculum": (0.0, 0.01, 0.02), "budget": Budget(iterations=2)}, "3 phases need a budget of at least 3"),
    ],
)
def test_bad_curriculum_is_one_line_config_error(changes, needle):
    kwargs = {"formation": 3, "step": 1, "budget": Budget(iterations=3), **changes}
    with pytest.raises(ConfigError) as exc:
        LowLevelConfig(**kwargs)
    assert needle in str(exc.value) and "\n" not in str(exc.value)


@pytest.mark.parametrize(
    "argv, needle",
    [
        (["--curriculum", "0,0.5"], "--curriculum 0,0.5: density 0.5 is not in [0, 0.2] per m^2"),
        (["--curriculum", "0.03,0"], "--curriculum 0.03,0: densities must not decrease"),
        (["--curriculum", "0.01"], "--curriculum 0.01: must be 2 to 20"),
        (["--curriculum", "0,abc"], "argument --curriculum: '0,abc': expected comma-separated densities"),
        (["--curriculum", "0,,0.01"], "expected comma-separated densities"),
        (["--budget", "3"], "4 phases need a budget of at least 4 iterations, got 3"),
        (["--formation", "9"], "invalid choice: 9"),
        (["--resume"], "--resume: no run to continue"),
    ],
)
def test_cli_bad_input_exits_2_before_writing(argv, needle, tmp_path, capsys):
    base = ["clm", "--formation", "3", "--budget", "4"]
    with pytest.raises(SystemExit) as exc:
        main(base + argv + TINY_CLI)
    err = capsys.readouterr().err
    assert exc.value.code == 2 and err.count("\n") == 1 and err.startswith("cefc-train"), err
    assert needle in err
    assert not (tmp_path / "runs" / "clm" / "clm_c3" / "state.pt").exists()


def test_cli_bad_curriculum_in_a_real_process(tmp_path):
    if not CEFC_TRAIN.is_file():
        pytest.skip("cefc-train is not installed next to this python")
    bad = subprocess.run(
        [str(CEFC_TRAIN), "clm", "--formation", "6", "--curriculum", "0,0.3"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert bad.returncode == 2 and bad.stderr.count("\n") == 1 and "Traceback" not in bad.stderr
    assert "--curriculum 0,0.3" in bad.stderr and list(tmp_path.iterdir()) == []


def test_lowlevel_all_does_not_train_clm():
    assert not [s.name for s in plan(Budget(seconds=1000.0), workers=2) if "clm" in s.name]


# ---------------------------------------------------------------------------- training
def test_cli_run_visits_every_phase_and_the_card_records_the_curriculum(tmp_path, capsys):
    argv = ["clm", "--formation", "6", "--curriculum", "0,0.02,0.05", "--budget", "3"] + TINY_CLI
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert "clm_c6: 3 iterations (0: 1 it, 0.02: 1 it, 0.05: 1 it)" in out and "Table III protocol" in out
    run_dir = tmp_path / "runs" / "clm" / "clm_c6"
    assert logged(run_dir) == [(1, 0, 0.0), (2, 1, 0.02), (3, 2, 0.05)]
    card = json.loads((tmp_path / "runs" / "clm" / "policies" / "clm_c6.json").read_text())
    assert (card["name"], card["method"], card["init"]["actor"]) == ("clm_c6", "CL-M", "random")
    assert card["config"]["curriculum"] == [0.0, 0.02, 0.05] and card["config"]["step"] == 1
    assert card["curriculum"]["phases"] == [
        {"density": 0.0, "iterations": 1},
        {"density": 0.02, "iterations": 1},
        {"density": 0.05, "iterations": 1},
    ]
    assert card["table3"]["paper"] == PAPER_TABLE3["6"]["CL-M"] == {"R_L": -90.79, "F": 48.8, "N": 38.94, "C": 0.78}
    assert json.loads((run_dir / "config.json").read_text())["stage"]["curriculum"] == [0.0, 0.02, 0.05]
    assert read_state(run_dir / "state.pt")["curriculum"] == {"phase": 2, "iterations": [1, 1, 1]}


def test_resume_in_the_middle_phase_continues_there(tmp_path, monkeypatch):
    cfg = clm()
    train_lowlevel(cfg, tmp_path / "whole", tmp_path / "pw", show_progress=False, evaluate=False)

    # The same run, interrupted after its first iteration (the last checkpoint), then resumed.
    iterate, flown = MAPPO.iterate, []

    def recorded(self):
        flown.append((self.iteration, self.task_cfg.obstacle_density, self.env.config.obstacle_density))
        return iterate(self)

    def interrupted_after_one(self):
        if self.iteration == 1:
            raise KeyboardInterrupt
        return recorded(self)

    monkeypatch.setattr(MAPPO, "iterate", interrupted_after_one)
    with pytest.raises(KeyboardInterrupt):
        train_lowlevel(cfg, tmp_path / "cut", tmp_path / "pc", show_progress=False, evaluate=False)
    state = read_state(tmp_path / "cut" / "clm_c3" / "state.pt")
    assert state["trainer"]["counters"]["iteration"] == 1 and state["curriculum"]["iterations"] == [1, 0, 0]

    monkeypatch.setattr(MAPPO, "iterate", recorded)
    flown.clear()
    card = train_lowlevel(cfg, tmp_path / "cut", tmp_path / "pc", resume=True, show_progress=False, evaluate=False)
    assert flown == [(1, 0.02, 0.02), (2, 0.05, 0.05)]  # re-entered phase 1, then phase 2
    assert logged(tmp_path / "cut" / "clm_c3") == [(1, 0, 0.0), (2, 1, 0.02), (3, 2, 0.05)]
    assert [p["iterations"] for p in card["curriculum"]["phases"]] == [1, 1, 1]
    whole, _ = load_actor(tmp_path / "pw" / "clm_c3.pt")
    resumed, _ = load_actor(tmp_path / "pc" / "clm_c3.pt")
    for (name, a), b in zip(whole.state_dict().items(), resumed.state_dict().values()):
        assert torch.equal(a, b), name  # exactly the uninterrupted run

    # A larger budget moves the phase boundaries (iteration 3 of 5 is in phase 1), but training
    # stays at the hardest density it reached.
    flown.clear()
    longer = clm(iterations=5)
    card = train_lowlevel(longer, tmp_path / "cut", tmp_path / "pc", resume=True, show_progress=False, evaluate=False)
    assert [density for _, density, _ in flown] == [0.05, 0.05]
    assert [p["iterations"] for p in card["curriculum"]["phases"]] == [1, 1, 3]
    other = clm(curriculum=(0.0, 0.01, 0.05))
    with pytest.raises(ConfigError, match="different settings.*curriculum"):
        train_lowlevel(other, tmp_path / "cut", tmp_path / "pc", resume=True, show_progress=False, evaluate=False)


# ---------------------------------------------------------------------------- Table III
def test_table3_has_a_clm_row_when_a_clm_policy_exists(tmp_path):
    torch.manual_seed(0)
    actor = ATMActor(ATMConfig.from_task(TaskConfig(n_agents=6, mode="formation")))
    with_clm = tmp_path / "with"
    save_policy(actor, with_clm / "clm_c6.pt")
    shutil.copy(with_clm / "clm_c6.pt", with_clm / "atm_c6_step3.pt")  # the same network as an AT-M row
    result = run_table3([6], episodes=2, steps=20, seed=0, policies_dir=with_clm)
    row, atm = result["6"]["CL-M"], result["6"]["AT-M-Step3"]
    assert row["policy"] == "clm_c6.pt" and row["paper"] == {"R_L": -90.79, "F": 48.8, "N": 38.94, "C": 0.78}
    # Evaluated exactly like the AT-M rows: same episodes, same numbers for the same weights.
    assert all(row[m] == atm[m] for m in ("R_L", "F", "N", "C")) and len(row["per_episode"]["F"]) == 2
    assert not [m for m in result["protocol"]["missing"] if "CL-M" in m]
    text = format_table3(result)
    assert "CL-M" in text and "48.80" in text
    assert list(run_table3([6], episodes=2, steps=20, policies_dir=with_clm, policy="clm")["6"]) == ["CL-M"]

    without = tmp_path / "without"
    save_policy(actor, without / "atm_c6_step3.pt")
    result = run_table3([6], episodes=2, steps=20, seed=0, policies_dir=without)
    assert "CL-M" not in result["6"]
    assert "6/CL-M (clm_c6.pt: train it with cefc-train clm --formation 6)" in result["protocol"]["missing"]
