"""`cefc-train highlevel --schedule`: the two readings of the paper's training budget
(cefc_mj/train/highlevel_config.py, SCHEDULES). "short" keeps today's defaults; "paper" fixes 1,500
iterations of 20 envs (1,000 pre-training) and ConsMAC 5,000 steps of 2,048 after every 20, refuses
any flag that would change them, and is saved in the run's config (a resumed run keeps it).
"paper-scaled" is "paper" shrunk to --budget Nit in its proportions (the budget ladder's rungs); a
resumed run keeps its N."""

import dataclasses
from pathlib import Path

import pytest

from cefc_mj.cli.train import build_parser, main
from cefc_mj.cli.train_highlevel import parse_budget
from cefc_mj.errors import ConfigError
from cefc_mj.train.config import Budget
from cefc_mj.train.highlevel_config import SCHEDULES, HighLevelConfig, check_resume_schedule, config_from_args
from cefc_mj.train.run_state import check_same_run


def config_of(argv: list[str]) -> HighLevelConfig:
    args = build_parser().parse_args(["highlevel", *argv])
    return config_from_args(args, parse_budget(args.budget))


def test_the_default_is_todays_short_reading():
    cfg = config_of([])
    short = SCHEDULES["short"]
    assert cfg.schedule == "short" and cfg.budget == Budget(iterations=short["iterations"]) == Budget(iterations=75)
    assert (cfg.consmac_every, cfg.consmac_steps, cfg.consmac_batch, cfg.ppo.n_envs) == (1, 200, 2048, 20)
    assert cfg == config_of(["--schedule", "short"])
    # short only names the defaults: flags still change them
    cfg = config_of(["--budget", "300", "--consmac-steps", "5000", "--consmac-every", "20"])
    assert (cfg.budget.iterations, cfg.consmac_steps, cfg.consmac_every, cfg.schedule) == (300, 5000, 20, "short")


def test_paper_is_1500_iterations_of_20_envs_and_5000_consmac_steps_after_every_20():
    cfg = config_of(["--schedule", "paper", "--variant", "mappo", "--seed", "7"])
    assert cfg.schedule == "paper" and cfg.budget == Budget(iterations=1500) and cfg.ppo.n_envs == 20
    assert (cfg.consmac_every, cfg.consmac_steps, cfg.consmac_batch) == (20, 5000, 2048)
    assert cfg.ppo.episodes_per_iteration == 1 and cfg.variant == "mappo" and cfg.seed == 7
    assert [cfg.phase(i, 0.0) for i in (0, 999, 1000, 1499)] == [0, 0, 1, 1]  # 1,000 navigation-only updates
    assert config_of(["--schedule", "paper", "--budget", "1500it", "--consmac-steps", "5000"]) == config_of(
        ["--schedule", "paper"]
    )  # flags that match are fine
    assert HighLevelConfig.from_dict(cfg.to_dict()) == cfg


@pytest.mark.parametrize(
    "flags, needle",
    [
        (["--budget", "75"], "--budget '75it': schedule 'paper' fixes it to 1500 iterations"),
        (["--budget", "2h"], "--budget '7200s'"),
        (["--consmac-steps", "200"], "--consmac-steps 200: schedule 'paper' fixes it to 5000"),
        (["--consmac-every", "1"], "--consmac-every 1:"),
        (["--consmac-batch", "512"], "--consmac-batch 512:"),
        (["--envs", "8"], "--envs 8:"),
        (["--pretrain-share", "0"], "--pretrain-share 0.0:"),
    ],
)
def test_paper_refuses_a_flag_that_changes_its_numbers_before_any_work(flags, needle, tmp_path, capsys):
    out = tmp_path / "runs"
    with pytest.raises(SystemExit) as exit_info:
        main(["highlevel", "--schedule", "paper", "--out", str(out), "--no-progress", *flags])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and needle in err and "Traceback" not in err
    assert not out.exists()


def test_a_paper_run_resumes_only_as_a_paper_run(tmp_path):
    paper = config_of(["--schedule", "paper"])
    check_same_run(paper.to_dict(), paper, Path("state.pt"), free=("budget", "checkpoint_every", "eval_episodes"))
    short = dataclasses.replace(config_of([]), consmac_every=20, consmac_steps=5000)
    with pytest.raises(ConfigError, match="different settings \\(schedule\\)"):
        check_same_run(paper.to_dict(), short, Path("state.pt"), free=("budget", "checkpoint_every", "eval_episodes"))
    saved_before = {k: v for k, v in config_of([]).to_dict().items() if k != "schedule"}  # a run saved before the field
    assert HighLevelConfig.from_dict(saved_before).schedule == "short"


FREE = ("budget", "checkpoint_every", "eval_episodes")


def consmac_steps_in(cfg: HighLevelConfig) -> int:
    """ConsMAC steps the run makes: a round after every iteration i (1-based) with i % consmac_every == 0
    (`HighLevelTrainer.iterate`)."""
    rounds = sum(i % cfg.consmac_every == 0 for i in range(1, cfg.budget.iterations + 1))
    return rounds * cfg.consmac_steps


@pytest.mark.parametrize("n, pretrain", [(3, 2), (75, 50), (300, 200), (1497, 998)])
def test_paper_scaled_keeps_the_papers_proportions_at_n_iterations(n, pretrain):
    cfg = config_of(["--schedule", "paper-scaled", "--budget", f"{n}it", "--variant", "mappo", "--seed", "301"])
    paper = config_of(["--schedule", "paper"])
    assert cfg.schedule == "paper-scaled" and cfg.paper_updates == n and cfg.budget == Budget(iterations=n)
    assert (cfg.consmac_every, cfg.consmac_steps, cfg.consmac_batch, cfg.ppo.n_envs) == (20, 5000, 2048, 20)
    assert cfg.ppo == paper.ppo and cfg.pretrain_share == paper.pretrain_share
    assert [cfg.phase(i, 0.0) for i in (pretrain - 1, pretrain, n - 1)] == [0, 1, 1]  # 2N/3 navigation-only
    assert HighLevelConfig.from_dict(cfg.to_dict()) == cfg
    assert paper.paper_updates is None and config_of([]).paper_updates is None


def test_paper_scaled_at_75_gives_consmac_the_short_schedules_15000_steps():
    scaled = config_of(["--schedule", "paper-scaled", "--budget", "75it"])
    assert consmac_steps_in(scaled) == 3 * 5000 == consmac_steps_in(config_of([])) == 75 * 200
    assert consmac_steps_in(config_of(["--schedule", "paper"])) == 75 * 5000  # the paper's 375,000
    assert consmac_steps_in(config_of(["--schedule", "paper-scaled", "--budget", "300it"])) == 15 * 5000


@pytest.mark.parametrize(
    "flags, needle",
    [
        ([], "--budget left out: schedule 'paper-scaled' needs --budget Nit"),
        (["--budget", "76"], "--budget 76: schedule 'paper-scaled' needs N iterations"),
        (["--budget", "0"], "--budget"),
        (["--budget", "1500"], "the paper's 1500 are schedule 'paper'"),
        (["--budget", "1503"], "--budget 1503:"),
        (["--budget", "2h"], "--budget 7200s: schedule 'paper-scaled' needs --budget Nit"),
        (["--budget", "75", "--consmac-steps", "200"], "--consmac-steps 200: schedule 'paper-scaled' fixes it to 5000"),
        (["--budget", "75", "--envs", "8"], "--envs 8:"),
        (["--budget", "75", "--pretrain-share", "0"], "--pretrain-share 0.0:"),
    ],
)
def test_paper_scaled_refuses_a_bad_n_or_a_changed_number_before_any_work(flags, needle, tmp_path, capsys):
    out = tmp_path / "runs"
    with pytest.raises(SystemExit) as exit_info:
        main(["highlevel", "--schedule", "paper-scaled", "--out", str(out), "--no-progress", *flags])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and needle in err and "Traceback" not in err
    assert not out.exists()


def test_paper_updates_belongs_to_paper_scaled_only():
    with pytest.raises(ConfigError, match="paper_updates=75: is for schedule 'paper-scaled' only"):
        dataclasses.replace(config_of([]), paper_updates=75)
    with pytest.raises(ConfigError, match="paper_updates=75: is for schedule 'paper-scaled' only"):
        dataclasses.replace(config_of(["--schedule", "paper"]), paper_updates=75)
    scaled = config_of(["--schedule", "paper-scaled", "--budget", "75it"])
    with pytest.raises(ConfigError, match="budget='300it': schedule 'paper-scaled' fixes it to 75 iterations"):
        dataclasses.replace(scaled, budget=Budget(iterations=300))  # the budget is N itself


def test_a_paper_scaled_run_resumes_only_at_its_own_n(tmp_path):
    state = Path("state.pt")
    short = config_of(["--schedule", "paper-scaled", "--budget", "75it"])
    check_resume_schedule(short.to_dict(), short, state)  # the same N: fine
    check_same_run(short.to_dict(), short, state, free=FREE)
    longer = config_of(["--schedule", "paper-scaled", "--budget", "300it"])
    with pytest.raises(ConfigError, match="scaled to 75 iterations, not 300 .*cannot be extended.*another --out"):
        check_resume_schedule(short.to_dict(), longer, state)
    with pytest.raises(ConfigError, match="different settings \\(paper_updates\\)"):
        check_same_run(short.to_dict(), longer, state, free=FREE)  # the generic check catches it too
    paper = config_of(["--schedule", "paper"])
    with pytest.raises(ConfigError, match="different settings \\(schedule, paper_updates\\)"):
        check_same_run(short.to_dict(), paper, state, free=FREE)  # nor continued as the paper's 1,500
    saved_before = {k: v for k, v in paper.to_dict().items() if k != "paper_updates"}  # saved before the field
    assert HighLevelConfig.from_dict(saved_before) == paper
    check_resume_schedule(saved_before, paper, state)
