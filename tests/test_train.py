"""Training stages end to end with CI-sized budgets, resume, distillation, the CLI and Table III."""

import csv
import dataclasses
import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from cefc_mj.cli.train import main
from cefc_mj.errors import ConfigError
from cefc_mj.eval.table3 import PAPER_TABLE3, evaluate_lowlevel_episodes, format_table3, run_table3
from cefc_mj.nn import ATMActor, ATMConfig, load_actor, load_policy, save_policy
from cefc_mj.task.config import TaskConfig
from cefc_mj.train.config import Budget, DistillConfig, LowLevelConfig, PPOConfig
from cefc_mj.train.distill import train_student
from cefc_mj.train.lowlevel import read_state, train_lowlevel
from cefc_mj.train.pipeline import plan

TINY = PPOConfig(n_envs=8, lr=1e-3, update_threads=1)


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def rows(run_dir):
    with (run_dir / "progress.csv").open() as f:
        return list(csv.DictReader(f))


def test_budget_and_config_validation():
    assert Budget.parse("40") == Budget(iterations=40) == Budget.parse("40it")
    assert Budget.parse("90s").seconds == 90 and Budget.parse("1.5h").seconds == 5400
    assert Budget(seconds=100).exhausted(0, 100.0) and not Budget(iterations=3).exhausted(2, 1e9)
    for bad in ("abc", "1.5it", "-3"):
        with pytest.raises(ConfigError, match="budget"):
            Budget.parse(bad)
    with pytest.raises(ConfigError, match="formation"):
        LowLevelConfig(formation=9, step=1, budget=Budget(iterations=1))
    with pytest.raises(ConfigError, match="safe"):
        LowLevelConfig(formation=6, step=1, safe=True, budget=Budget(iterations=1))
    with pytest.raises(ConfigError, match="gamma"):
        LowLevelConfig(formation=6, step=1, budget=Budget(iterations=1), ppo=PPOConfig(gamma=1.5))
    cfg = LowLevelConfig(formation=6, step=3, budget=Budget(seconds=60.0))
    assert LowLevelConfig.from_dict(json.loads(json.dumps(cfg.to_dict()))) == cfg
    assert (cfg.density, cfg.name, cfg.method) == (0.03, "atm_c6_step3", "AT-M-Step3")
    # Fine-tunes of Step 3: sensing deviation makes Robust, quadrotor-like dynamics alone make Quad.
    robust = LowLevelConfig(formation=6, step=3, deviation=0.8, response_time=0.15, budget=Budget(iterations=1))
    quad = LowLevelConfig(formation=6, step=3, response_time=0.15, velocity_noise=0.1, budget=Budget(iterations=1))
    assert (robust.name, robust.method, robust.fine_tune) == ("atm_c6_robust", "AT-M-Robust", True)
    assert (quad.name, quad.method, quad.fine_tune) == ("atm_c6_quad", "AT-M-Quad", True)
    assert not cfg.fine_tune
    with pytest.raises(ConfigError, match="velocity_noise"):
        LowLevelConfig(formation=6, step=1, velocity_noise=0.1, budget=Budget(iterations=1))
    # A collision margin widens both distances of the training reward, nothing else.
    from cefc_mj.train.lowlevel import task_config_for

    wide = task_config_for(dataclasses.replace(quad, collision_margin=0.125))
    plain = task_config_for(quad)
    assert (wide.rewards.safety_distance, wide.rewards.collision_alert_distance) == (0.325, 0.625)
    assert dataclasses.replace(wide, rewards=plain.rewards) == plain
    with pytest.raises(ConfigError, match="collision_margin"):
        LowLevelConfig(formation=6, step=3, collision_margin=-0.1, budget=Budget(iterations=1))
    # A navigation weight changes omega_n of R_L only; alone on Step 3 it is AT-M-Nav, from Step 3.
    nav = LowLevelConfig(formation=6, step=3, navigation_weight=10.0, budget=Budget(iterations=1))
    assert (nav.name, nav.method, nav.source_stages) == ("atm_c6_nav", "AT-M-Nav", ("atm_c6_step3",))
    assert task_config_for(nav).rewards.navigation_weight_low == 10.0
    assert dataclasses.replace(task_config_for(nav), rewards=task_config_for(cfg).rewards) == task_config_for(cfg)
    assert nav.paper_differences() == ["navigation weight omega_n = 10 (paper 4)"] and cfg.paper_differences() == []
    quad_nav = dataclasses.replace(quad, navigation_weight=6.0)
    assert (quad_nav.name, len(quad_nav.paper_differences())) == ("atm_c6_quad", 3)
    for bad in (0.0, -1.0, float("nan"), 51.0, True):
        with pytest.raises(ConfigError, match="navigation_weight"):
            LowLevelConfig(formation=6, step=3, navigation_weight=bad, budget=Budget(iterations=1))
    with pytest.raises(ConfigError, match="navigation_weight"):
        LowLevelConfig(formation=6, step=3, safe=True, navigation_weight=8.0, budget=Budget(iterations=1))
    # Anchor periods lengthen the episode and redraw the anchor every 100 steps; only on a fine-tune.
    periods = dataclasses.replace(nav, anchor_periods=3)
    task = task_config_for(periods)
    assert (task.steps, task.anchor_redraw_steps, periods.name) == (300, 100, "atm_c6_nav")
    assert dataclasses.replace(task, episode_steps=None, anchor_redraw_steps=None) == task_config_for(nav)
    assert task_config_for(nav).anchor_redraw_steps is None
    assert periods.paper_differences()[1].startswith("episodes of 3 anchor periods of 100 steps")
    observed = dataclasses.replace(nav, accel_max=3.5, push_observer_s=2.0)  # recorded in the card, flown by evaluators
    assert observed.paper_differences()[1:] == [
        "action bound 3.5 m/s^2 per axis (ours; the paper states none)",
        "the agent's push observer, time constant 2 s (the paper's agent is memoryless)",
    ]
    assert (task_config_for(observed).accel_max, task_config_for(observed).push_observer_s) == (3.5, 2.0)
    for bad in (0, 21, 2.0, True):
        with pytest.raises(ConfigError, match="anchor_periods"):
            dataclasses.replace(nav, anchor_periods=bad)
    with pytest.raises(ConfigError, match="anchor_periods=2: .*fine-tune"):
        LowLevelConfig(formation=6, step=3, anchor_periods=2, budget=Budget(iterations=1))
    # Stragglers: one agent starts away from the others in a share of the episodes; only on a fine-tune.
    straggling = dataclasses.replace(periods, straggler_fraction=0.3)
    assert (task_config_for(straggling).straggler_fraction, straggling.name) == (0.3, "atm_c6_nav")
    assert task_config_for(periods).straggler_fraction == 0.0
    assert straggling.paper_differences()[2].startswith("in 30% of the episodes one agent starts 3-7 m")
    for bad in (-0.1, 1.1, True, "0.3"):
        with pytest.raises(ConfigError, match="straggler_fraction"):
            dataclasses.replace(nav, straggler_fraction=bad)
    with pytest.raises(ConfigError, match="straggler_fraction=0.2: .*fine-tune"):
        LowLevelConfig(formation=6, step=3, straggler_fraction=0.2, budget=Budget(iterations=1))
    # The LiDAR sees obstacles and UAVs unless asked; an obstacles-only stage has its own name.
    one = Budget(iterations=1)
    blind = [
        LowLevelConfig(formation=6, step=1, lidar_sees_uavs=False, budget=one),
        LowLevelConfig(formation=6, step=3, safe=True, lidar_sees_uavs=False, budget=one),
    ]
    assert [c.name for c in blind] == ["atm_c6_step1_obstacle_lidar", "atm_c6_safe_obstacle_lidar"]
    assert [task_config_for(c).lidar_sees_agents for c in (*blind, quad)] == [False, False, True]
    with pytest.raises(ConfigError, match="lidar_sees_uavs"):
        LowLevelConfig(formation=6, step=1, lidar_sees_uavs=None, budget=one)


def test_pipeline_plan_splits_the_budget():
    stages = plan(Budget(seconds=1000.0), formations=(6, 3), workers=1)
    names = [s.name for s in stages]
    assert names[:4] == ["atm_c6_step1", "atm_c6_step2", "atm_c6_step3", "atm_c6_safe"] and names[-1] == "atm_student"
    total = sum(s.budget.seconds for s in stages)
    assert total == pytest.approx(1000.0)
    c6 = sum(s.budget.seconds for s in stages if s.lowlevel and s.lowlevel.formation == 6)
    c3 = sum(s.budget.seconds for s in stages if s.lowlevel and s.lowlevel.formation == 3)
    assert c6 == pytest.approx(2 * c3)  # small formations get half
    two = plan(Budget(seconds=1000.0), formations=(6, 7), workers=2)
    assert sum(s.budget.seconds for s in two if s.lowlevel and s.lowlevel.formation == 6) == pytest.approx(940.0)


def test_every_stage_trains_and_exports(tmp_path):
    out, pol = tmp_path / "runs", tmp_path / "policies"
    # Steps 1 and 2 start from scratch: the return must improve within a few iterations.
    for step in (1, 2):
        cfg = LowLevelConfig(formation=3, step=step, budget=Budget(iterations=6), ppo=TINY)
        card = train_lowlevel(cfg, out, pol, show_progress=False, evaluate=False)
        r = [float(row["reward_per_step"]) for row in rows(out / cfg.name)]
        assert len(r) == 6 and card["iterations"] == 6 and card["agent_steps"] == 6 * 8 * 100 * 3
        assert sum(r[-3:]) / 3 > r[0] + 20, r
        assert json.loads((pol / f"{cfg.name}.json").read_text())["config"]["step"] == step
    step1, _ = load_actor(pol / "atm_c3_step1.pt")
    step2, _ = load_actor(pol / "atm_c3_step2.pt")
    # A Step 1 whose LiDAR sees obstacles only (so reads nothing without them) has its own name; the
    # policy file says which LiDAR, and the evaluator flies each policy with its own.
    blind = LowLevelConfig(formation=3, step=1, lidar_sees_uavs=False, budget=Budget(iterations=1), ppo=TINY)
    assert train_lowlevel(blind, out, pol, show_progress=False, evaluate=False)["name"] == "atm_c3_step1_obstacle_lidar"
    assert (step1.cfg.lidar_sees_agents, load_actor(pol / f"{blind.name}.pt")[0].cfg.lidar_sees_agents) == (True, False)
    for name, sees in (("atm_c3_step1_obstacle_lidar", False), ("atm_c3_step1", True)):
        policy, nearest = load_policy(name, pol), []
        act = policy.act
        policy.act = lambda obs, p=policy, act=act: nearest.append(obs[..., p.actor.lidar_slice].min()) or act(obs)
        evaluate_lowlevel_episodes(policy, 3, density=0.0, episodes=2, steps=3)
        assert (min(nearest) < 3.0) == sees, (name, min(nearest))

    # Step 3 starts from the merge (checked through its first update's inputs) and moves the policy.
    cfg3 = LowLevelConfig(formation=3, step=3, budget=Budget(iterations=2), ppo=TINY)
    card3 = train_lowlevel(cfg3, out, pol, show_progress=False, evaluate=False)
    assert card3["init"]["critic"] == "atm_c3_step2"
    step3, _ = load_actor(pol / "atm_c3_step3.pt")
    for module, parent in (("formation", step1), ("obstacle", step2), ("output", step1)):
        moved = [
            (p - q).abs().max().item()
            for p, q in zip(getattr(step3, module).parameters(), getattr(parent, module).parameters())
        ]
        assert 0 < max(moved) < 0.2, module  # fine-tuned from its parent, not re-initialised
    assert float(rows(out / "atm_c3_step3")[-1]["approx_kl"]) > 0

    cfg_safe = LowLevelConfig(formation=3, step=3, safe=True, budget=Budget(iterations=2), ppo=TINY)
    train_lowlevel(cfg_safe, out, pol, show_progress=False, evaluate=False)
    safe = load_policy("atm_c3_safe", pol)
    assert safe.safe and not load_policy("atm_c3_step3", pol).safe
    assert read_state(out / "atm_c3_safe" / "state.pt")["origin"]["actor"] == "atm_c3_step3"
    cfg_quad = LowLevelConfig(
        formation=3, step=3, response_time=0.15, velocity_noise=0.1, budget=Budget(iterations=1), ppo=TINY
    )
    assert train_lowlevel(cfg_quad, out, pol, show_progress=False, evaluate=False)["init"]["actor"] == "atm_c3_step3"
    assert json.loads((pol / "atm_c3_quad.json").read_text())["task"]["velocity_noise"] == 0.1


def test_resume_reproduces_the_uninterrupted_run(tmp_path):
    ppo = PPOConfig(n_envs=4, epochs=2, update_threads=1)
    full = LowLevelConfig(formation=3, step=2, budget=Budget(iterations=3), ppo=ppo, checkpoint_every=1)
    train_lowlevel(full, tmp_path / "a", tmp_path / "pa", show_progress=False, evaluate=False)
    # The same run killed after 2 iterations (its last checkpoint), then resumed with the full budget.
    cut = LowLevelConfig(formation=3, step=2, budget=Budget(iterations=2), ppo=ppo, checkpoint_every=1)
    train_lowlevel(cut, tmp_path / "b", tmp_path / "pb", show_progress=False, evaluate=False)
    with pytest.raises(ConfigError, match="--resume"):
        train_lowlevel(full, tmp_path / "b", tmp_path / "pb", show_progress=False, evaluate=False)
    train_lowlevel(full, tmp_path / "b", tmp_path / "pb", resume=True, show_progress=False, evaluate=False)
    a = read_state(tmp_path / "a" / "atm_c3_step2" / "state.pt")["trainer"]
    b = read_state(tmp_path / "b" / "atm_c3_step2" / "state.pt")["trainer"]
    for part in ("actor", "critic", "value_norm"):
        for k in a[part]:
            assert torch.equal(a[part][k], b[part][k]), (part, k)
    assert a["counters"]["iteration"] == b["counters"]["iteration"] == 3
    ra, rb = rows(tmp_path / "a" / "atm_c3_step2"), rows(tmp_path / "b" / "atm_c3_step2")
    assert [r["episode_return"] for r in ra] == [r["episode_return"] for r in rb]
    # Resuming a finished run trains nothing more and re-exports it with its last logged figures.
    card = train_lowlevel(full, tmp_path / "b", tmp_path / "pb", resume=True, show_progress=False, evaluate=False)
    assert card["iterations"] == 3 and card["last_iteration"]["iteration"] == 3
    assert len(rows(tmp_path / "b" / "atm_c3_step2")) == 3
    other = LowLevelConfig(formation=3, step=2, budget=Budget(iterations=3), ppo=PPOConfig(n_envs=5))
    with pytest.raises(ConfigError, match="different settings"):
        train_lowlevel(other, tmp_path / "b", tmp_path / "pb", resume=True, show_progress=False, evaluate=False)
    # Thread counts are how a run executes, not what it learns: a resume may change them.
    threads = LowLevelConfig(formation=3, step=2, budget=Budget(iterations=3), ppo=replace(ppo, update_threads=2))
    assert (
        train_lowlevel(threads, tmp_path / "b", tmp_path / "pb", resume=True, show_progress=False, evaluate=False)[
            "iterations"
        ]
        == 3
    )


def test_student_reproduces_teachers_on_held_out_observations(tmp_path):
    # Teachers with non-trivial outputs (a trained-size output layer), one per formation.
    torch.manual_seed(0)
    for c in (3, 4):
        teacher = ATMActor(ATMConfig.from_task(TaskConfig(n_agents=c, mode="formation")))
        torch.nn.init.orthogonal_(teacher.output[-1].weight, 1.0)
        save_policy(teacher, tmp_path / "teachers" / f"atm_c{c}_step3.pt")
    cfg = DistillConfig(
        budget=Budget(iterations=1000), formations=(3, 4), tuples_per_formation=4000, lr=1e-3, hidden=128, seed=0
    )
    card = train_student(
        cfg,
        tmp_path / "pol",
        tmp_path / "runs",
        show_progress=False,
        evaluate=False,
        teachers_dir=tmp_path / "teachers",
    )
    err = card["held_out_error"]
    # Stated error: on held-out episodes the student's MSE is below 40 % of the teachers' action
    # variance for every formation (an untrained student scores about 100 %).
    assert err["held_rel/c3"] < 0.4 and err["held_rel/c4"] < 0.4, err
    first = rows(tmp_path / "runs" / "atm_student")[0]
    assert float(first["loss"]) > float(rows(tmp_path / "runs" / "atm_student")[-1]["loss"])
    assert load_policy("atm_student", tmp_path / "pol").actor.cfg.hidden == 128


def test_cli_bad_input_is_one_line_and_exit_2(tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        main(["lowlevel", "--formation", "9", "--step", "1"])
    assert e.value.code == 2
    capsys.readouterr()
    common = ["--out", str(tmp_path / "runs"), "--policies-dir", str(tmp_path / "pol")]
    for argv, pattern in (
        (["lowlevel", "--formation", "6", "--step", "1", "--budget", "soon"], "--budget"),
        (["lowlevel", "--formation", "6", "--step", "1", "--safe"], "--safe"),
        (["lowlevel", "--formation", "6", "--step", "3"], "train that stage first"),
        (["distill", "--formations", "3", "--teachers-dir", str(tmp_path)], "no policy"),
    ):
        with pytest.raises(SystemExit) as e:
            main(argv + common)
        assert e.value.code == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith("cefc-train: error:") and pattern in err and "\n" not in err, err
    assert list(tmp_path.iterdir()) == []  # checked before anything was written


def test_cli_lowlevel_runs_and_reports(tmp_path, capsys):
    argv = [
        "lowlevel",
        "--formation",
        "3",
        "--step",
        "1",
        "--budget",
        "1",
        "--envs",
        "2",
        "--no-progress",
        "--out",
        str(tmp_path / "runs"),
        "--policies-dir",
        str(tmp_path / "pol"),
    ]
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert "atm_c3_step1: 1 iterations" in out and "Table III protocol" in out
    card = json.loads((tmp_path / "pol" / "atm_c3_step1.json").read_text())
    assert {
        "config",
        "seed",
        "git_commit",
        "versions",
        "command",
        "train_wall_clock_s",
        "agent_steps",
        "table3",
    } <= set(card)
    assert set(card["table3"]["ours"]) == {"R_L", "R_L_agents", "F", "N", "C"}


def test_table3_rows_keyed_like_the_paper(tmp_path):
    torch.manual_seed(0)
    save_policy(ATMActor(ATMConfig.from_task(TaskConfig(n_agents=6, mode="formation"))), tmp_path / "atm_c6_step3.pt")
    blind = TaskConfig(n_agents=6, mode="formation", lidar_sees_agents=False)
    save_policy(ATMActor(ATMConfig.from_task(blind)), tmp_path / "atm_c6_step1_obstacle_lidar.pt")
    result = run_table3([6], episodes=3, seed=0, policies_dir=tmp_path, json_path=tmp_path / "t3.json")
    # the obstacles-only Step 1 stands beside the paper's Step 1 row
    assert result["6"]["AT-M-Step1 (obstacle LiDAR)"]["paper"] == PAPER_TABLE3["6"]["AT-M-Step1"]
    row = result["6"]["AT-M-Step3"]
    assert set(row) >= {"R_L", "F", "N", "C", "paper"} and 0 <= row["F"] <= 100 and 0 <= row["C"] <= 100
    assert row["paper"] == {"R_L": -96.0, "F": 49.72, "N": 36.66, "C": 0.78}
    assert "6/AT-M-Step1 (atm_c6_step1.pt)" in result["protocol"]["missing"]
    assert json.loads((tmp_path / "t3.json").read_text())["6"]["AT-M-Step3"]["F"] == row["F"]
    text = format_table3(result)
    assert "AT-M-Step3" in text and "missing policies" in text
    with pytest.raises(ConfigError):
        run_table3([9], policies_dir=tmp_path)


def test_table3_maddpg_row_is_the_mean_and_spread_over_training_seeds(tmp_path):
    """The MADDPG row flies every training seed's file and reports over seeds, not one seed's episodes."""
    from cefc_mj.eval.table3 import MADDPG

    task = TaskConfig(n_agents=6, mode="formation")
    for i, name in enumerate(["benchmarl_maddpg_c6", "benchmarl_maddpg_c6_seed2", "benchmarl_maddpg_c6_seed1"]):
        torch.manual_seed(i)
        save_policy(ATMActor(ATMConfig.from_task(task)), tmp_path / f"{name}.pt")
    torch.manual_seed(9)  # another scenario's file: not a seed of this row
    save_policy(ATMActor(ATMConfig.from_task(task)), tmp_path / "benchmarl_maddpg_c6_step1_seed1.pt")
    result = run_table3([6], episodes=3, seed=0, policy="maddpg", policies_dir=tmp_path)
    row = result["6"][MADDPG]
    assert [s["seed"] for s in row["seeds"]] == [0, 1, 2] and row["training_seeds"] == 3
    assert [s["policy"] for s in row["seeds"]][1] == "benchmarl_maddpg_c6_seed1.pt"
    means = {m: [] for m in ("R_L", "F", "N", "C")}
    for name in ("benchmarl_maddpg_c6", "benchmarl_maddpg_c6_seed1", "benchmarl_maddpg_c6_seed2"):
        episodes = evaluate_lowlevel_episodes(load_policy(tmp_path / f"{name}.pt"), 6, episodes=3, seed=0)
        for m in means:
            means[m].append(float(episodes[m].mean()))
    for m, values in means.items():
        assert row[m] == pytest.approx(np.mean(values)) and row[f"{m}_std"] == pytest.approx(np.std(values, ddof=1))
    assert len(set(means["R_L"])) == 3  # three different policies, so the spread is not zero
    assert len(row["per_episode"]["F"]) == 9 and row["paper"]["F"] == 58.12
    assert "MADDPG (3 seeds)" in format_table3(result) and "training seeds" in format_table3(result)


def test_shipped_paper_table3_matches_the_shared_transcription():
    path = Path(__file__).resolve().parents[2] / "shared" / "reference" / "paper_tables.json"
    if not path.is_file():
        pytest.skip("the project's shared reference folder is not next to this checkout")
    shared = json.loads(path.read_text())["table3_atm_mpe"]
    assert PAPER_TABLE3["6"]["AT-M-Step3"] == {"R_L": -96.0, "F": 49.72, "N": 36.66, "C": 0.78}
    for c, rows_c in PAPER_TABLE3.items():
        for method, row in rows_c.items():
            assert [row[k] for k in ("R_L", "F", "N", "C")] == shared[c][method], (c, method)


def test_agent_collision_credit_splits_the_team_collision_term():
    import numpy as np

    from cefc_mj.nn import Critic
    from cefc_mj.train.mappo import MAPPO

    task = TaskConfig(n_agents=5, mode="formation", obstacle_density=0.05)
    actor = ATMActor(ATMConfig.from_task(task))
    trainer = MAPPO(task, PPOConfig(n_envs=6), actor, Critic(5 * 28 + 63), seed=0)
    env = trainer.env
    env.reset(seed=1)
    rng = np.random.default_rng(0)
    for _ in range(30):  # fly around randomly until some agents are near something
        obs, reward, _, info = env.step(rng.uniform(-2, 2, (6, 5, 2)))
    terms, w = info["reward_terms"], task.rewards
    per_agent = trainer.agent_rewards(reward, terms["R_c"], env.agent_collision_penalty, w)
    shared = w.formation_weight * terms["R_f"] + w.navigation_weight_low * terms["R_n"]
    # sum_i (shared - 100 CR_i) = N shared + 100 R_c, because R_c = -sum_i CR_i.
    np.testing.assert_allclose(per_agent.sum(1), 5 * shared + w.collision_weight * terms["R_c"], rtol=1e-4, atol=1e-2)
    assert (terms["R_c"] < 0).any()  # the check above is not vacuous
    team = MAPPO(task, PPOConfig(n_envs=6, collision_credit="team"), actor, Critic(5 * 28 + 63), seed=0)
    np.testing.assert_allclose(
        team.agent_rewards(reward, terms["R_c"], env.agent_collision_penalty, w),
        np.repeat(reward[:, None], 5, 1),
        rtol=1e-6,
    )
