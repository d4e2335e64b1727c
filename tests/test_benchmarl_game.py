"""BenchMARL on the high-level game (cefc_mj/train/benchmarl_game.py, docs/research/baselines.md "BenchMARL
baselines"): the torchrl env against `HierarchicalCEFCEnv`, tiny MASAC and MAPPO runs exported as
high-level policy files that Table V's evaluator flies, and `cefc-train highlevel-benchmarl`'s checks.

The tests that need BenchMARL skip when the optional `benchmarl` extra is not installed; the command
line's checks (and its one-line refusal without the extra) run everywhere."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from cefc_mj.cli import train_benchmarl as cli_benchmarl
from cefc_mj.cli.train import main
from cefc_mj.train.benchmarl_config import BENCHMARL_EXTRA, BenchMARLConfig, parse_episode_budget

TINY = {"n_envs": 2, "episode_steps": 30, "budget_episodes": 4, "eval_episodes": 2}
"""2 iterations of 2 episodes of 3 decisions."""
TINY_ALGORITHM = {
    "masac": {"masac_updates": 4, "masac_batch": 6},
    "mappo": {"mappo_epochs": 2, "mappo_minibatch": 3},
}


@pytest.fixture(scope="module")
def benchmarl_game():
    """The BenchMARL module (skips without the benchmarl extra)."""
    pytest.importorskip("benchmarl")
    pytest.importorskip("torchrl")
    from cefc_mj.train import benchmarl_game

    return benchmarl_game


def tiny(algorithm: str, **overrides) -> BenchMARLConfig:
    return BenchMARLConfig(algorithm=algorithm, **{**TINY, **TINY_ALGORITHM[algorithm], **overrides})


# ---------------------------------------------------------------------------- config and command line
def test_the_default_run_is_our_trainers_game_and_budget():
    from cefc_mj.hierarchy import DECISION_INTERVAL
    from cefc_mj.nn.registry import GAME_ADVERSARY
    from cefc_mj.train.benchmarl_config import DECISION_INTERVAL as OURS
    from cefc_mj.train.config import Budget
    from cefc_mj.train.highlevel_config import HighLevelConfig

    cfg = BenchMARLConfig()
    trainer = HighLevelConfig(budget=Budget(iterations=75), variant="mappo")
    assert cfg.adversary == GAME_ADVERSARY == trainer.adversary and OURS == DECISION_INTERVAL
    assert cfg.low_level == trainer.low_level and cfg.game_config().task() == trainer.task()
    episodes = trainer.budget.iterations * trainer.ppo.n_envs * trainer.ppo.episodes_per_iteration
    assert cfg.budget_episodes == episodes == 1500 and cfg.n_envs == trainer.ppo.n_envs
    assert (cfg.iterations, cfg.frames_per_batch, cfg.max_frames) == (75, 800, 60000)
    assert cfg.gamma == trainer.ppo.gamma
    assert BenchMARLConfig(seed=2).name == "benchmarl_masac_seed2" and BenchMARLConfig(algorithm="mappo").name == (
        "benchmarl_mappo"
    )
    assert parse_episode_budget("1500ep") == parse_episode_budget(" 1500 ") == 1500


@pytest.mark.parametrize(
    "argv, says",
    [
        (["--envs", "0"], "--envs 0: must be an integer"),
        (["--budget", "30ep"], "--budget 30: must be a multiple of the 20 envs"),
        (["--budget", "75it"], "--budget '75it': expected a number of episodes"),
        (["--updates", "10", "--algorithm", "mappo"], "--updates: a masac setting, not mappo's"),
        (["--episode-steps", "35"], "--episode-steps 35: must be a multiple of 10"),
        (["--adversary", "learned"], "--adversary 'learned': must be a rule"),
    ],
)
def test_bad_flags_one_line_exit_2_before_any_work(argv, says, tmp_path, capsys):
    if "--algorithm" not in argv:
        argv = [*argv, "--algorithm", "masac"]
    with pytest.raises(SystemExit) as stop:
        main(["highlevel-benchmarl", "--out", str(tmp_path / "out"), *argv])
    err = capsys.readouterr().err
    assert stop.value.code == 2 and err.count("\n") == 1 and says in err, err
    assert not (tmp_path / "out").exists()


def test_without_the_extra_one_line_exit_2(monkeypatch, tmp_path, capsys):
    monkeypatch.setattr(cli_benchmarl, "has_benchmarl", lambda: False)
    with pytest.raises(SystemExit) as stop:
        main(["highlevel-benchmarl", "--algorithm", "masac", "--out", str(tmp_path / "out")])
    assert stop.value.code == 2
    assert capsys.readouterr().err == BENCHMARL_EXTRA + "\n"
    assert BENCHMARL_EXTRA == (
        "cefc-train highlevel-benchmarl: needs the benchmarl extra (pip install -e '.[benchmarl]')"
    )
    assert not (tmp_path / "out").exists()


# ---------------------------------------------------------------------------- the torchrl env
def test_env_passes_torchrls_spec_check(benchmarl_game):
    from torchrl.envs.utils import check_env_specs

    env = benchmarl_game.make_game_env(tiny("masac", n_envs=3, budget_episodes=6))
    check_env_specs(env)
    assert env.full_action_spec[("agents", "action")].space.n == 9
    assert env.full_observation_spec[("agents", "observation")].shape == (3, 8, 38)


def test_env_gives_the_hierarchical_games_observations_and_rewards(benchmarl_game):
    """Same seed and anchors: the torchrl env's o_i, state, team reward and done are what
    `HierarchicalCEFCEnv` gives (its observation's selector part x 0.125, R_H summed over the
    decision's 10 steps, times reward_scale, for every agent), and its k-th full reset plays
    iteration_seed(seed, k)."""
    import torch

    from cefc_mj.hierarchy import HierarchicalCEFCEnv
    from cefc_mj.train.mappo import iteration_seed

    cfg = tiny("mappo", n_envs=3, budget_episodes=6, episode_steps=50, seed=7)
    env = benchmarl_game.make_game_env(cfg)
    task, low_level, adversary, _ = benchmarl_game.load_game(cfg)
    game = HierarchicalCEFCEnv(task, low_level, n_envs=3, seed=7, adversary_policy=adversary)
    rng = np.random.default_rng(0)
    for episode in range(2):
        td = env.reset()
        obs = game.reset(seed=iteration_seed(7, episode))
        for decision in range(cfg.decision_steps):
            assert np.array_equal(td["agents", "observation"].numpy(), obs[..., :38] * np.float32(0.125))
            assert np.array_equal(td["state"].numpy(), game.global_state())
            anchors = rng.integers(0, 9, size=(3, 8))
            td["agents", "action"] = torch.from_numpy(anchors)
            td = env.step(td)["next"]
            obs, reward, done, info = game.step(anchors)
            np.testing.assert_allclose(info["low_level_rewards"].sum(0), reward)
            expected = np.repeat((reward * cfg.reward_scale).astype(np.float32)[:, None, None], 8, axis=1)
            assert np.array_equal(td["agents", "reward"].numpy(), expected)
            assert td["done"].reshape(-1).tolist() == td["terminated"].reshape(-1).tolist() == done.tolist()
            assert done.all() == (decision == cfg.decision_steps - 1)
            assert np.isfinite(reward).all() and reward.std() > 0  # three different games
        assert np.array_equal(td["agents", "observation"].numpy(), obs[..., :38] * np.float32(0.125))


def test_exported_selector_acts_as_benchmarls_actor(benchmarl_game, tmp_path):
    """Before any training (random weights): on the game's own observations, the exported HighLevelPolicy's
    anchors (the mode, as Table V flies it) are BenchMARL's deterministic actions, and the logits agree."""
    import torch
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    for algorithm in ("masac", "mappo"):
        cfg = tiny(algorithm, n_envs=4)
        (tmp_path / algorithm).mkdir()
        experiment, _ = benchmarl_game.build_experiment(cfg, tmp_path / algorithm)
        env = benchmarl_game.make_game_env(cfg)
        policy = benchmarl_game.export_actor(experiment, cfg, env.task)
        td = env.reset()
        raw = env.game.reset(seed=123)  # the full CEFC observations [4, 8, 69] that our policy reads
        td["agents", "observation"] = torch.from_numpy(benchmarl_game.selector_observation(raw, env.task, 0.125))
        with set_exploration_type(ExplorationType.DETERMINISTIC), torch.no_grad():
            theirs = experiment.policy(td.clone())["agents", "action"].numpy()
        ours, message = policy.decide(raw, None)
        assert message is None and np.array_equal(ours, theirs) and len(np.unique(ours)) > 1
        logits = benchmarl_game.actor_logits(experiment, td["agents", "observation"])
        with torch.no_grad():
            torch.testing.assert_close(policy.selector(torch.from_numpy(raw), torch.zeros(4, 8, 0)), logits)
        experiment.close()


# ---------------------------------------------------------------------------- training and Table V
@pytest.mark.parametrize("algorithm", ["masac", "mappo"])
def test_tiny_run_exports_a_policy_that_table5_flies(algorithm, benchmarl_game, tmp_path):
    from cefc_mj.nn.highlevel_policy import load_highlevel_policy
    from cefc_mj.seeds import GAME_VALIDATION_SEED

    cfg = tiny(algorithm, seed=1)
    card = benchmarl_game.train_benchmarl(cfg, tmp_path, show_progress=False)
    path = tmp_path / "policies" / f"benchmarl_{algorithm}_seed1.pt"
    assert path.is_file() and path.with_suffix(".json").is_file()
    assert (card["iterations"], card["episodes"], card["frames"]) == (2, 4, 12)
    saved = json.loads(path.with_suffix(".json").read_text())
    assert saved["benchmarl_versions"]["benchmarl"] == "1.5.2" and saved["algorithm"] == algorithm
    assert saved["evaluation"]["protocol"]["seed"] == GAME_VALIDATION_SEED
    assert all(math.isfinite(v) for v in saved["evaluation"]["ours"].values())
    rows = (tmp_path / f"benchmarl_{algorithm}_seed1" / "progress.csv").read_text().splitlines()
    assert len(rows) == 3 and rows[0].startswith("iteration,frames,episodes")
    policy, meta = load_highlevel_policy(path)
    assert policy.variant == "mappo" and policy.comm is None and meta["trainer"] == f"benchmarl-{algorithm}"

    figures = benchmarl_game.evaluate_benchmarl(path, episodes=2, seed=GAME_VALIDATION_SEED)
    assert all(math.isfinite(figures[m]) for m in ("R_H", "R_t", "R_n", "R_e", "E", "F", "C"))
    assert figures["protocol"]["episodes"] == 2 and figures["row"]["policy"] == path.name
    assert figures["R_H"] == pytest.approx(figures["R_t"] + figures["R_n"] + figures["R_e"])


def test_the_command_trains_and_exports(benchmarl_game, tmp_path, capsys):
    out = tmp_path / "runs"
    argv = ["--envs", "2", "--episode-steps", "30", "--budget", "4ep", "--epochs", "2", "--minibatch-size", "3"]
    assert main(["highlevel-benchmarl", "--algorithm", "mappo", *argv, "--eval-episodes", "0", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "benchmarl_mappo: BenchMARL mappo, 2 iterations, 4 episodes (12 frames)" in printed
    card = json.loads((out / "policies" / "benchmarl_mappo.json").read_text())
    assert card["command"].startswith("cefc-train highlevel-benchmarl") and "evaluation" not in card
