"""BenchMARL on the formation task (cefc_mj/train/benchmarl_formation.py, docs/formation_benchmarl.md): the
torchrl env step by step against `BatchedCEFCEnv`, the exported AT-M actor against BenchMARL's policy,
tiny MADDPG, IPPO, MAPPO and MASAC runs that Table III flies, resuming, and `cefc-train
formation-benchmarl`'s checks.

The tests that need BenchMARL skip when the optional `benchmarl` extra is not installed; the command
line's checks (and its one-line refusal without the extra) run everywhere."""

from __future__ import annotations

import csv
import json
import math

import numpy as np
import pytest

from cefc_mj.cli import train_benchmarl_formation as cli_formation
from cefc_mj.cli.train import main
from cefc_mj.errors import CheckpointError
from cefc_mj.train.benchmarl_config import FORMATION_EXTRA, FormationBenchMARLConfig, parse_frame_budget

TINY = {"n_envs": 2, "episodes_per_iteration": 1, "budget_frames": 400, "eval_episodes": 2, "checkpoint_every": 1}
"""2 iterations of 2 episodes of 100 steps."""
TINY_ALGORITHM = {
    "maddpg": {"updates": 4, "batch_size": 16, "memory_frames": 1000},
    "masac": {"updates": 4, "batch_size": 16, "memory_frames": 1000},
    "ippo": {"epochs": 2, "minibatch_size": 100},
    "mappo": {"epochs": 2, "minibatch_size": 100},
}
TINY_FLAGS = ["--envs", "2", "--episodes-per-iteration", "1", "--checkpoint-every", "1"]
TINY_MADDPG_FLAGS = [*TINY_FLAGS, "--updates", "4", "--batch-size", "16", "--memory", "1000"]


@pytest.fixture(scope="module")
def formation():
    """The BenchMARL formation module (skips without the benchmarl extra)."""
    pytest.importorskip("benchmarl")
    pytest.importorskip("torchrl")
    from cefc_mj.train import benchmarl_formation

    return benchmarl_formation


def tiny(algorithm: str = "maddpg", **overrides) -> FormationBenchMARLConfig:
    return FormationBenchMARLConfig(algorithm=algorithm, **{**TINY, **TINY_ALGORITHM[algorithm], **overrides})


# ---------------------------------------------------------------------------- config and command line
def test_the_task_is_the_atm_stages_and_the_name_table3s():
    from cefc_mj.eval.table3 import MADDPG, MADDPG_FILE, PAPER_TABLE3, POLICY_CHOICES, policy_file_for
    from cefc_mj.train.config import Budget, LowLevelConfig, PPOConfig
    from cefc_mj.train.lowlevel import task_config_for

    for c in (6, 7, 8):
        for step in (1, 2):
            stage = LowLevelConfig(formation=c, step=step, budget=Budget(iterations=1))
            assert FormationBenchMARLConfig(formation=c, step=step).task() == task_config_for(stage)
        assert FormationBenchMARLConfig(formation=c).name == MADDPG_FILE.format(c=c) == policy_file_for(MADDPG, c)
    assert FormationBenchMARLConfig(step=1).task().obstacle_density == 0.0
    assert FormationBenchMARLConfig().task().obstacle_density == 0.03
    assert FormationBenchMARLConfig(algorithm="masac", formation=8, step=1, seed=2).name == (
        "benchmarl_masac_c8_step1_seed2"
    )
    assert POLICY_CHOICES["maddpg"] == MADDPG and PAPER_TABLE3["6"][MADDPG]["F"] == 58.12
    assert PAPER_TABLE3["7"][MADDPG]["N"] == 46.94 and PAPER_TABLE3["6"][MADDPG]["R_L"] is None
    cfg = FormationBenchMARLConfig()
    assert (cfg.frames_per_batch, cfg.gamma) == (6000, PPOConfig().gamma)
    assert parse_frame_budget("300kf") == parse_frame_budget(" 300000 ") == parse_frame_budget("300000f") == 300_000
    assert parse_frame_budget("3mf") == 3_000_000


@pytest.mark.parametrize(
    "argv, says",
    [
        (["--envs", "0"], "--envs 0: must be an integer"),
        (["--budget", "6100"], "--budget 6100: must be a multiple of the 6000 frames"),
        (["--budget", "75it"], "--budget '75it': expected a number of frames"),
        (["--formation", "9"], "--formation 9: must be an integer in [3, 8]"),
        (["--step", "3"], "--step 3: must be 1 (no obstacles) or 2"),
        (["--epochs", "3"], "--epochs: a setting of ippo, mappo, not maddpg's"),
        (["--updates", "3", "--algorithm", "mappo"], "--updates: a setting of maddpg, masac, not mappo's"),
        (["--anneal-frames", "10", "--algorithm", "masac"], "--anneal-frames: a setting of maddpg, not masac's"),
        (["--reward-scale", "0"], "--reward-scale 0.0: must be a number in (0, 1e+06]"),
    ],
)
def test_bad_flags_one_line_exit_2_before_any_work(argv, says, tmp_path, capsys):
    with pytest.raises(SystemExit) as stop:
        main(["formation-benchmarl", "--out", str(tmp_path / "out"), *argv])
    err = capsys.readouterr().err
    assert stop.value.code == 2 and err.count("\n") == 1 and says in err, err
    assert not (tmp_path / "out").exists()


def test_without_the_extra_one_line_exit_2(monkeypatch, tmp_path, capsys):
    monkeypatch.setattr(cli_formation, "has_benchmarl", lambda: False)
    with pytest.raises(SystemExit) as stop:
        main(["formation-benchmarl", "--out", str(tmp_path / "out")])
    assert stop.value.code == 2
    assert capsys.readouterr().err == FORMATION_EXTRA + "\n"
    assert FORMATION_EXTRA == (
        "cefc-train formation-benchmarl: needs the benchmarl extra (pip install -e '.[benchmarl]')"
    )
    assert not (tmp_path / "out").exists()


# ---------------------------------------------------------------------------- the torchrl env
def test_env_passes_torchrls_spec_check(formation):
    from torchrl.envs.utils import check_env_specs

    env = formation.make_formation_env(tiny(n_envs=3, formation=7, budget_frames=600))
    check_env_specs(env)
    assert env.full_action_spec[("agents", "action")].shape == (3, 7, 2)
    assert env.full_observation_spec[("agents", "observation")].shape == (3, 7, env.env.layout.size)


@pytest.mark.parametrize("step", [1, 2])
def test_formation_env_steps_as_the_projects_env(formation, step):
    """The equivalence test: same seed, same actions (some outside the action box) -> the torchrl env's
    observations, global states, rewards (each agent's learning reward of our MAPPO trainer, times
    reward_scale), dones and episode metrics F, N, C are exactly `BatchedCEFCEnv`'s, over two
    batches of episodes (its k-th full reset plays iteration_seed(seed, k)) and a partial reset."""
    import torch

    from cefc_mj.env import BatchedCEFCEnv
    from cefc_mj.train.config import PPOConfig
    from cefc_mj.train.rollout import agent_rewards, iteration_seed

    cfg = tiny(n_envs=3, step=step, seed=7, reward_scale=0.01, budget_frames=600)
    env = formation.make_formation_env(cfg)
    task = cfg.task()
    ours = BatchedCEFCEnv(task, n_envs=3, seed=7)
    rng = np.random.default_rng(0)
    for episode in range(2):
        td = env.reset()
        obs = ours.reset(seed=iteration_seed(7, episode))
        for t in range(task.steps):
            assert np.array_equal(td["agents", "observation"].numpy(), obs)
            assert np.array_equal(td["state"].numpy(), ours.global_state())
            actions = rng.uniform(-3.0, 3.0, size=(3, task.n_agents, 2)).astype(np.float32)
            td["agents", "action"] = torch.from_numpy(actions)
            td = env.step(td)["next"]
            obs, reward, done, info = ours.step(actions.astype(np.float64))
            own = agent_rewards(
                PPOConfig().collision_credit,
                reward,
                info["reward_terms"]["R_c"],
                ours.agent_collision_penalty,
                task.rewards,
            )
            assert np.array_equal(td["agents", "reward"].numpy(), (own * np.float32(0.01))[..., None])
            assert td["done"].reshape(-1).tolist() == td["terminated"].reshape(-1).tolist() == done.tolist()
            assert not td["truncated"].any() and done.all() == (t == task.steps - 1)
            metrics = ours.episode_metrics()
            for m in ("F", "N", "C"):
                assert np.array_equal(td[m].reshape(-1).numpy(), metrics[m].astype(np.float32)), m
        for m in ("F", "N", "C"):
            assert np.array_equal(td[m].reshape(-1).numpy(), info["metrics"][m].astype(np.float32))
        assert np.array_equal(td["agents", "observation"].numpy(), obs)
        assert own.std() > 0 and len({tuple(o.ravel()) for o in obs}) == 3  # three different episodes
    mask = np.array([True, False, True])
    reset_td = env.reset(env.full_done_spec.zero().update({"_reset": torch.from_numpy(mask)[:, None]}))
    assert np.array_equal(reset_td["agents", "observation"].numpy()[mask], ours.reset(mask)[mask])


def test_exported_actor_acts_as_benchmarls_policy(formation, tmp_path):
    """Before any training (random weights), for every algorithm: on the task's own observations, the
    exported AT-M actor's actions (what Table III flies) are BenchMARL's deterministic actions as the env
    applies them (clipped to the action box)."""
    import torch

    from cefc_mj.nn.policy_io import Policy

    for algorithm in TINY_ALGORITHM:
        cfg = tiny(algorithm, formation=7)
        (tmp_path / algorithm).mkdir()
        experiment, _ = formation.build_experiment(cfg, tmp_path / algorithm)
        env = formation.make_formation_env(cfg)
        obs = env.env.reset(seed=123).copy()
        actor = formation.export_actor(experiment, cfg, env.task)
        ours = Policy(actor, {}, "probe").act(obs)
        theirs = formation.deterministic_actions(experiment, torch.from_numpy(obs)).numpy()
        limit = cfg.task().accel_max
        if algorithm == "maddpg":  # its actor projects onto the action box; the others' mean is clipped by the env
            assert np.abs(theirs).max() <= limit
        np.testing.assert_allclose(ours, np.clip(theirs, -limit, limit), atol=1e-5)
        assert len(np.unique(ours.round(4))) > 10
        experiment.close()


# ---------------------------------------------------------------------------- training, Table III, resuming
def test_maddpg_smoke_trains_saves_reloads_and_flies_table3(formation, tmp_path, capsys):
    """`cefc-train formation-benchmarl` with a tiny budget, then `cefc-eval --protocol table3` flies the
    file: one Table III episode."""
    from cefc_mj.cli.eval import main as eval_main
    from cefc_mj.nn.policy_io import load_policy
    from cefc_mj.seeds import FORMATION_VALIDATION_SEED

    out = tmp_path / "runs"
    argv = ["formation-benchmarl", "--budget", "400", *TINY_MADDPG_FLAGS, "--eval-episodes", "2", "--no-progress"]
    assert main([*argv, "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "benchmarl_maddpg_c6: BenchMARL maddpg, c = 6, 2 iterations, 400 frames (2400 agent-steps)" in printed
    path = out / "policies" / "benchmarl_maddpg_c6.pt"
    card = json.loads(path.with_suffix(".json").read_text())
    assert card["command"].startswith("cefc-train formation-benchmarl") and card["frames"] == 400
    assert card["benchmarl_versions"]["benchmarl"] == "1.5.2" and card["agent_steps_per_s"] > 0
    assert card["validation"]["protocol"]["seed"] == FORMATION_VALIDATION_SEED
    assert card["validation"]["paper"] == {"R_L": None, "F": 58.12, "N": 4.26, "C": None}
    assert all(math.isfinite(card["validation"]["ours"][m]) for m in ("R_L", "F", "N", "C"))
    policy = load_policy(path)
    assert policy.meta["trainer"] == "benchmarl-maddpg" and policy.obs_dim == 63

    report = tmp_path / "table3.json"
    code = eval_main(
        ["--backend", "particle", "--protocol", "table3", "--policy", str(path), "--formation", "6"]
        + ["--episodes", "1", "--json", str(report)]
    )
    assert code == 0
    row = json.loads(report.read_text())["6"]["benchmarl_maddpg_c6"]
    assert row["policy"] == path.name and len(row["per_episode"]["F"]) == 1
    assert all(math.isfinite(row[m]) for m in ("R_L", "F", "N", "C"))


def test_table3_flies_maddpg_as_the_papers_row(formation, tmp_path):
    """The `maddpg` alias: the MADDPG row of each c from benchmarl_maddpg_c<c>.pt, beside the paper's."""
    from cefc_mj.eval.table3 import format_table3, run_table3

    formation.train_formation(tiny(eval_episodes=0), tmp_path, show_progress=False)
    result = run_table3([6], episodes=1, policy="maddpg", policies_dir=tmp_path / "policies")
    row = result["6"]["MADDPG"]
    assert row["seeds"][0]["policy"] == "benchmarl_maddpg_c6.pt" and row["paper"]["F"] == 58.12
    assert "MADDPG" in format_table3(result) and "58.12" in format_table3(result)


@pytest.mark.parametrize("algorithm", ["ippo", "mappo", "masac"])
def test_the_other_algorithms_train_and_export(algorithm, formation, tmp_path):
    from cefc_mj.nn.policy_io import load_policy

    card = formation.train_formation(tiny(algorithm, formation=7, eval_episodes=1), tmp_path, show_progress=False)
    assert (card["iterations"], card["frames"], card["agent_steps"]) == (2, 400, 2800)
    path = tmp_path / "policies" / f"benchmarl_{algorithm}_c7.pt"
    assert load_policy(path).meta["trainer"] == f"benchmarl-{algorithm}"
    assert math.isfinite(card["validation"]["ours"]["F"]) and card["validation"]["paper"] is None


def test_a_run_resumes_from_its_checkpoint(formation, tmp_path, capsys):
    out = tmp_path / "runs"
    base = ["formation-benchmarl", *TINY_MADDPG_FLAGS, "--eval-episodes", "0", "--no-progress", "--out", str(out)]
    assert main([*base, "--budget", "400"]) == 0
    with pytest.raises(SystemExit) as stop:  # a second run into the same folder
        main([*base, "--budget", "400"])
    assert stop.value.code == 2 and "already holds a run; pass --resume" in capsys.readouterr().err
    with pytest.raises(SystemExit) as stop:  # a resumed run keeps its settings
        main([*base, "--budget", "600", "--resume", "--gamma", "0.9"])
    assert stop.value.code == 2 and "made with different settings (gamma)" in capsys.readouterr().err
    with pytest.raises(SystemExit) as stop:
        main([*base[:-1], str(tmp_path / "elsewhere"), "--budget", "600", "--resume"])
    assert stop.value.code == 2 and "--resume: no run to continue" in capsys.readouterr().err

    assert main([*base, "--budget", "600", "--resume"]) == 0
    card = json.loads((out / "policies" / "benchmarl_maddpg_c6.json").read_text())
    assert (card["iterations"], card["frames"], card["resumed"]) == (3, 600, True)
    with (out / "benchmarl_maddpg_c6" / "progress.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert [int(r["frames"]) for r in rows] == [200, 400, 600] and [r["iteration"] for r in rows] == ["1", "2", "3"]


def test_a_damaged_benchmarl_checkpoint_is_skipped_and_none_left_is_one_line(formation, tmp_path):
    """--resume reads BenchMARL's checkpoints through the project's one weights-only reader: a torn or
    foreign newest checkpoint is passed over, and with nothing readable left the error is one line."""
    import fractions

    import torch

    folder = tmp_path / "run" / "benchmarl" / "checkpoints"
    folder.mkdir(parents=True)
    torch.save({"state": {"total_frames": 400}}, folder / "checkpoint_400.pt")
    whole = (folder / "checkpoint_400.pt").read_bytes()
    (folder / "checkpoint_600.pt").write_bytes(whole[: len(whole) // 2])  # torn while being written
    # newest: a pickle naming a global the weights-only unpickler refuses (never run, passed over)
    torch.save({"state": {"total_frames": 800, "code": fractions.Fraction(1, 3)}}, folder / "checkpoint_800.pt")
    path, state = formation.readable_checkpoint(tmp_path / "run")
    assert path.name == "checkpoint_400.pt" and state == {"total_frames": 400}
    (folder / "checkpoint_400.pt").write_text("not a checkpoint\n")
    torch.save({"weights": torch.zeros(2)}, folder / "checkpoint_200.pt")  # no "state": another file
    with pytest.raises(CheckpointError) as error:
        formation.readable_checkpoint(tmp_path / "run")
    assert "\n" not in str(error.value) and "no readable BenchMARL checkpoint" in str(error.value)
