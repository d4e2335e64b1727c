"""The DDPG adversary (cefc_mj/train/adversary_ddpg.py): config checks, the DDPG update, a run with
its exports, exact resume, the CLI and its Table VI column."""

import json
import re

import numpy as np
import pytest
import torch

from cefc_mj.cli.train import build_parser, main
from cefc_mj.errors import ConfigError
from cefc_mj.eval.highlevel import run_table6
from cefc_mj.eval.highlevel_report import format_highlevel_table
from cefc_mj.game_protocol import game_task
from cefc_mj.nn.adversary_policy import (
    AdversaryNetConfig,
    AdversaryPolicy,
    load_adversary_policy,
    save_adversary_policy,
)
from cefc_mj.nn.highlevel_policy import HighLevelPolicy, save_highlevel_policy
from cefc_mj.nn.registry import GAME_ADVERSARY
from cefc_mj.task.adversary import ADVERSARY_OBS_DIM
from cefc_mj.train.adversary import load_population
from cefc_mj.train.adversary_ddpg import (
    FLAG_OF_FIELD,
    DDPGAdversaryConfig,
    DDPGAdversaryTrainer,
    QCritic,
    ReplayBuffer,
    effective_action,
    soft_update,
    train_ddpg_adversary,
)
from cefc_mj.train.config import Budget

pytestmark = pytest.mark.usefixtures("one_torch_thread")

TINY = {
    "teams": ("rule-urgent",),
    "teams_per_iteration": 1,
    "n_envs": 2,
    "learning_starts": 800,
    "updates_per_iteration": 5,
    "batch_size": 32,
    "replay_capacity": 2000,
    "eval_episodes": 0,
}
"""Two envs of one game: 800 transitions an iteration, so the first flies random actions, the second the actor."""


def _tiny(iterations: int = 2, **kw) -> DDPGAdversaryConfig:
    return DDPGAdversaryConfig(budget=Budget(iterations=iterations), **{**TINY, **kw})


def _trainer(cfg: DDPGAdversaryConfig) -> DDPGAdversaryTrainer:
    population, _, low_level, interval, own = load_population(cfg)
    return DDPGAdversaryTrainer(cfg, population, low_level, interval, own)


@pytest.mark.parametrize(
    "kw, needle",
    [
        ({"tau": 0.0}, "tau=0.0: must be a number in (0, 1]"),
        ({"gamma": 1.5}, "gamma=1.5: must be a number in [0, 1]"),
        ({"actor_lr": -1e-3}, "actor_lr=-0.001"),
        ({"exploration_noise": float("nan")}, "exploration_noise=nan"),
        ({"batch_size": 0}, "batch_size=0: must be an integer in [1, "),
        ({"replay_capacity": 100, "learning_starts": 200}, "learning_starts=200: must be at most the replay's 100"),
        ({"n_envs": 20, "teams_per_iteration": 3}, "teams_per_iteration=3: must divide the 20 envs"),
        ({"action": "jerk"}, "action='jerk'"),  # the PPO adversary's checks, shared
        ({"teams": ()}, "teams=()"),
        ({"collision_weight": -1}, "collision_weight=-1"),
    ],
)
def test_config_refuses_bad_values_up_front(kw, needle):
    with pytest.raises(ConfigError) as e:
        _tiny(**kw)
    assert needle in str(e.value)


def test_config_round_trips_and_names_the_run():
    cfg = _tiny(seed=3)
    assert DDPGAdversaryConfig.from_dict(json.loads(json.dumps(cfg.to_dict()))) == cfg
    assert cfg.name == "adversary_ddpg_seed3" and _tiny().name == "adversary_ddpg"
    assert DDPGAdversaryConfig(budget=Budget(iterations=1)).gamma == 0.95


def test_effective_action_is_what_the_env_flies():
    u = torch.tensor([[3.0, 4.0], [0.3, 0.0], [-5.0, 0.5]])
    vel = effective_action(u, AdversaryNetConfig(action="velocity"))
    r = float(np.hypot(5.0, 0.5))
    torch.testing.assert_close(vel, torch.tensor([[0.6, 0.8], [0.3, 0.0], [-5.0 / r, 0.5 / r]]))
    assert torch.allclose(effective_action(u, AdversaryNetConfig(action="heading")).norm(dim=-1), torch.ones(3))
    assert effective_action(u, AdversaryNetConfig(action="acceleration", accel_max=2.0)).abs().max() == 2.0
    policy = AdversaryPolicy(AdversaryNetConfig(action="velocity"))
    obs = np.zeros((3, ADVERSARY_OBS_DIM), dtype=np.float32)
    np.testing.assert_allclose(
        policy.to_acceleration(vel.numpy(), obs), policy.to_acceleration(u.numpy(), obs), atol=1e-6
    )


def test_replay_is_a_ring_and_round_trips():
    replay = ReplayBuffer(5, obs_dim=3)
    for start in (0, 3):  # 3 then 3 more: the oldest one is overwritten
        rows = torch.arange(start, start + 3, dtype=torch.float32)
        replay.add(rows[:, None].expand(3, 3), rows[:, None].expand(3, 2), rows, rows[:, None].expand(3, 3) + 1)
    assert replay.size == 5 and replay.pos == 1
    assert sorted(replay.rewards.tolist()) == [1, 2, 3, 4, 5]
    copy = ReplayBuffer(5, obs_dim=3)
    copy.load_state_dict(replay.state_dict())
    g1, g2 = torch.Generator().manual_seed(0), torch.Generator().manual_seed(0)
    for a, b in zip(replay.sample(8, g1), copy.sample(8, g2)):
        torch.testing.assert_close(a, b, rtol=0, atol=0)


def test_soft_update_moves_targets_by_tau():
    net = AdversaryNetConfig(observes_goal=False)
    online, target = QCritic(net, 16), QCritic(net, 16)
    before = [p.clone() for p in target.parameters()]
    soft_update(target, online, 0.1)
    for old, new, p in zip(before, target.parameters(), online.parameters()):
        torch.testing.assert_close(new, old + 0.1 * (p - old))


def test_critic_loss_falls_on_a_fixed_batch_and_targets_follow_by_tau():
    trainer = _trainer(_tiny())
    g = torch.Generator().manual_seed(0)
    obs, next_obs = torch.rand(256, ADVERSARY_OBS_DIM, generator=g), torch.rand(256, ADVERSARY_OBS_DIM, generator=g)
    actions = effective_action(torch.randn(256, 2, generator=g), trainer.actor.cfg)
    rewards = obs[:, 6] - actions[:, 0]  # something the critic can fit
    old_target = [p.clone() for p in trainer.actor_target.parameters()]
    first = trainer.update_step(obs, actions, rewards, next_obs)
    for old, new, p in zip(old_target, trainer.actor_target.parameters(), trainer.actor.parameters()):
        torch.testing.assert_close(new, (1 - trainer.cfg.tau) * old + trainer.cfg.tau * p)
    losses = [trainer.update_step(obs, actions, rewards, next_obs)["critic_loss"] for _ in range(150)]
    assert np.mean(losses[-10:]) < 0.2 * first["critic_loss"]
    assert trainer.updates == 151


def test_run_writes_folder_policy_and_card_and_resumes_exactly(tmp_path):
    """1 iteration, then --resume to 2, ends exactly where 2 straight iterations do (weights, targets,
    optimizers, replay); the exported file loads as any adversary policy."""
    straight = train_ddpg_adversary(_tiny(2), tmp_path / "a", tmp_path / "a" / "policies", show_progress=False)
    train_ddpg_adversary(_tiny(1), tmp_path / "b", tmp_path / "b" / "policies", show_progress=False)
    resumed = train_ddpg_adversary(
        _tiny(2), tmp_path / "b", tmp_path / "b" / "policies", resume=True, show_progress=False
    )
    assert straight["iterations"] == resumed["iterations"] == 2 and resumed["gradient_steps"] == 10
    run = tmp_path / "a" / "adversary_ddpg"
    assert {"config.json", "progress.csv", "state.pt"} <= {p.name for p in run.iterdir()}
    assert json.loads((run / "config.json").read_text())["adversary"]["replay_capacity"] == 2000
    rows = (run / "progress.csv").read_text().splitlines()
    assert len(rows) == 3 and "critic_loss" in rows[0]
    a, _ = load_adversary_policy(tmp_path / "a" / "policies" / "adversary_ddpg.pt")
    b, meta = load_adversary_policy(tmp_path / "b" / "policies" / "adversary_ddpg.pt")
    assert meta["algorithm"] == "ddpg" and meta["iterations"] == 2
    for x, y in zip(a.state_dict().values(), b.state_dict().values()):
        torch.testing.assert_close(x, y, rtol=0, atol=0)
    sa = torch.load(run / "state.pt", weights_only=False)["trainer"]
    sb = torch.load(tmp_path / "b" / "adversary_ddpg" / "state.pt", weights_only=False)["trainer"]
    for part in ("critic", "actor_target", "critic_target", "replay"):
        for key, value in sa[part].items():
            assert torch.equal(torch.as_tensor(value), torch.as_tensor(sb[part][key])), (part, key)
    assert sa["counters"]["updates"] == sb["counters"]["updates"] == 10
    with pytest.raises(ConfigError, match="different settings"):
        train_ddpg_adversary(
            _tiny(3, tau=0.01), tmp_path / "b", tmp_path / "b" / "policies", resume=True, show_progress=False
        )


def test_cli_trains_exports_a_card_with_the_population_evaluation(tmp_path, capsys):
    out = tmp_path / "runs"
    argv = [
        "adversary-ddpg",
        "--budget",
        "1it",
        "--envs",
        "2",
        "--teams-per-iteration",
        "1",
        "--teams",
        "rule-urgent",
        "--learning-starts",
        "0",
        "--updates",
        "3",
        "--batch-size",
        "16",
        "--replay",
        "1000",
        "--eval-episodes",
        "1",
        "--out",
        str(out),
        "--no-progress",
    ]
    assert main(argv) == 0
    card = json.loads((out / "policies" / "adversary_ddpg.json").read_text())
    assert card["name"] == "adversary_ddpg" and "DDPG" in card["method"] and card["gradient_steps"] == 3
    assert card["network"]["action"] == "heading" and card["network"]["observes_goal"] is False
    assert card["config"]["gamma"] == 0.95 and "git_commit" in card
    row = card["evaluation"]["per_team"]["rule-urgent"]
    assert set(row) == {"ours", "rule_nearest_group", "E_ratio"}
    assert "against the DDPG adversary / the nearest-group rule" in capsys.readouterr().out


@pytest.mark.parametrize(
    "argv, needle",
    [
        (["--tau", "0"], "--tau 0.0: must be a number in (0, 1]"),
        (["--batch-size", "0"], "--batch-size 0: must be an integer in [1, "),
        (["--noise", "-1"], "--noise -1.0: must be a number in (0, 5]"),
        (["--teams-per-iteration", "3"], "--teams-per-iteration 3: must divide the 20 envs"),
        (["--learning-starts", "200000"], "--learning-starts 200000: must be at most the replay's 100000"),
        (["--teams", "no_such_policy"], "--teams: "),
        (["--budget", "0"], "--budget '0': must be more than zero"),
        (["--updates", "many"], "argument --updates: invalid int value"),
    ],
)
def test_cli_bad_input_exits_2_with_one_line_and_writes_nothing(argv, needle, tmp_path, capsys):
    out = tmp_path / "runs"
    with pytest.raises(SystemExit) as e:
        main(["adversary-ddpg", "--out", str(out), *argv])
    assert e.value.code == 2
    err = capsys.readouterr().err.strip()
    assert needle in err and len(err.splitlines()) == 1
    assert not out.exists()


def test_cli_help_states_the_configs_defaults():
    sub = next(a for a in build_parser()._actions if a.dest == "command").choices["adversary-ddpg"]
    defaults = DDPGAdversaryConfig(budget=Budget(iterations=1))
    for action in sub._actions:
        if action.dest in FLAG_OF_FIELD and action.dest not in ("teams", "seed"):
            shown = re.search(r"\(default ([-+.\w]+)", action.help.replace("\n", " "))
            value = getattr(defaults, action.dest)
            assert shown, action.dest
            assert shown.group(1) == value if isinstance(value, str) else float(shown.group(1)) == value, action.dest


def test_table6_flies_the_ddpg_adversary_once_trained_and_else_says_how(tmp_path):
    policies = tmp_path / "policies"
    policies.mkdir()
    save_highlevel_policy(
        HighLevelPolicy.build("mappo", game_task(), seed=0),
        policies / "cihrl_mappo.pt",
        meta={"name": "cihrl_mappo", "decision_interval": 10},
    )
    for seed, name in enumerate(("adversary_ppo", "adversary_ppo_nearest_group_member", GAME_ADVERSARY)):
        save_adversary_policy(AdversaryPolicy(AdversaryNetConfig(), seed=seed), policies / f"{name}.pt")
    without = run_table6(episodes=1, policies_dir=policies, policy="cihrl_mappo")
    assert "DDPG" not in without["rows"]
    note = [line for line in format_highlevel_table(without).splitlines() if "adversary_ddpg" in line]
    assert len(note) == 1 and "not trained yet" in note[0] and "cefc-train adversary-ddpg --install" in note[0]
    save_adversary_policy(
        AdversaryPolicy(AdversaryNetConfig(observes_goal=False), seed=1), policies / "adversary_ddpg.pt"
    )
    result = run_table6(episodes=1, policies_dir=policies, policy="cihrl_mappo")
    assert list(result["rows"])[:4] == ["PPO", "PPO (previous generation)", "PPO (first generation)", "DDPG"]
    assert not result["protocol"]["missing"]
    assert result["rows"]["DDPG"]["adversary_record"]["policy"] == "adversary_ddpg.pt"
    assert result["rows"]["DDPG"]["paper"] == {"R_t": 161.97, "R_e": -82.43, "E": 6.42}
