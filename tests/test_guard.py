"""The agents' separation guard (cefc_mj/task/guard.py): the rule on one observation row, a head-on
encounter of two real MuJoCo quadrotors, and every evaluator applying it when the game asks."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from cefc_mj import make_world
from cefc_mj.errors import ConfigError
from cefc_mj.eval.runner import EpisodeSpec, run_episode
from cefc_mj.task.config import TaskConfig
from cefc_mj.task.guard import NEIGHBOUR_DISTANCE, guard_actions, guarded
from cefc_mj.task.observation import build_low_level_observation

CFG = TaskConfig(n_agents=2, mode="formation", obstacle_density=0.0)
SLOTS, RAYS = CFG.neighbour_slots, CFG.n_lidar_rays


def _row(pos, vel, lidar=None):
    """Observations [1, N, D] of agents at pos [N, 2] with velocities vel [N, 2], anchor at the origin."""
    pos, vel = np.asarray(pos, float)[None], np.asarray(vel, float)[None]
    lidar = np.full((1, pos.shape[1], RAYS), CFG.lidar_range) if lidar is None else np.asarray(lidar, float)[None]
    cfg = TaskConfig(n_agents=pos.shape[1], mode="formation", obstacle_density=0.0)
    return build_low_level_observation(cfg, pos, vel, np.zeros((1, 2)), lidar)


def _guard(obs, actions):
    return guard_actions(obs, np.asarray(actions, np.float32), SLOTS, RAYS, CFG.dt, CFG.accel_max)


def test_nothing_near_returns_the_policys_action_bit_for_bit():
    obs = _row([[0.0, 0.0], [3.0, 0.0]], [[1.0, 0.0], [-1.0, 0.0]])  # 3 m apart: beyond the guard's range
    actions = np.array([[[2.0, 0.3], [-1.7, 0.1]]], np.float32)
    out = _guard(obs, actions)
    assert out.dtype == np.float32 and np.array_equal(out, actions)


def test_a_closing_neighbour_is_braked_for_and_a_receding_one_is_not():
    closing = _guard(_row([[0.0, 0.0], [0.9, 0.0]], [[0.8, 0.0], [-0.8, 0.0]]), [[[2.0, 0.5], [-2.0, 0.5]]])
    assert closing[0, 0, 0] == -2.0 and closing[0, 1, 0] == 2.0  # both brake as hard as the clip allows
    assert closing[0, 0, 1] == closing[0, 1, 1] == np.float32(0.5)  # sideways is left alone
    receding = [[[-2.0, 0.0], [2.0, 0.0]]]
    assert np.array_equal(
        _guard(_row([[0.0, 0.0], [0.9, 0.0]], [[-0.8, 0.0], [0.8, 0.0]]), receding), np.asarray(receding, np.float32)
    )


def test_a_masked_slot_is_ignored():
    obs = _row([[0.0, 0.0], [0.9, 0.0]], [[0.8, 0.0], [-0.8, 0.0]])
    mask_at = 4 + 4 * SLOTS
    obs[0, 0, mask_at] = 0.0  # agent 0 no longer hears agent 1
    out = _guard(obs, [[[2.0, 0.0], [-2.0, 0.0]]])
    assert out[0, 0, 0] == 2.0 and out[0, 1, 0] == 2.0


def test_a_lidar_hit_ahead_is_braked_for():
    lidar = np.full((1, RAYS), CFG.lidar_range)
    lidar[0, 0] = 0.6  # beam 0 points along +x: an obstacle's surface 0.6 m ahead
    obs = _row([[0.0, 0.0]], [[0.8, 0.0]], lidar)
    out = guard_actions(obs, np.array([[[2.0, 0.0]]], np.float32), SLOTS, RAYS, CFG.dt, CFG.accel_max)
    assert out[0, 0, 0] == -2.0
    obs_behind = _row([[0.0, 0.0]], [[-0.8, 0.0]], lidar)  # flying away from it
    assert (
        guard_actions(obs_behind, np.array([[[-2.0, 0.0]]], np.float32), SLOTS, RAYS, CFG.dt, CFG.accel_max)[0, 0, 0]
        == -2.0
    )


def test_guarded_is_the_policy_itself_unless_asked():
    def act(obs):
        return np.zeros(obs.shape[:2] + (2,), np.float32)

    assert guarded(act, CFG) is act
    assert guarded(act, TaskConfig(n_agents=2, mode="formation", separation_guard=True)) is not act
    with pytest.raises(ConfigError, match="separation_guard"):
        TaskConfig(n_agents=2, mode="formation", separation_guard="yes")


def _fly_at_a_hovering_one(guard: bool) -> tuple[float, bool]:
    """Two MuJoCo quadrotors 4 m apart: UAV 0 is commanded at full acceleration towards UAV 1, whose
    policy asks to hover, for 6 s. Returns (closest centre distance, whether they touched)."""
    cfg = TaskConfig(n_agents=2, mode="formation", obstacle_density=0.0, separation_guard=guard)
    world = make_world("mujoco", cfg, n_envs=1, seed=0)
    world.reset(
        np.ones(1, bool), np.array([[[-2.0, 0.0], [2.0, 0.0]]]), np.zeros((1, 2)), np.zeros((1, world.n_obstacles, 2))
    )
    act = guarded(lambda obs: np.array([[[2.0, 0.0], [0.0, 0.0]]], np.float32), cfg)
    closest, touched = np.inf, False
    for _ in range(60):
        pos, vel = world.agent_pos, world.agent_vel
        obs = build_low_level_observation(cfg, pos, vel, np.zeros((1, 2)), world.lidar(pos))
        world.step(act(obs), np.zeros((1, 2)))
        closest = min(closest, float(np.linalg.norm(world.agent_pos[0, 0] - world.agent_pos[0, 1])))
        touched |= bool(world.collisions().any())
    return closest, touched


def test_a_quadrotor_flown_at_a_hovering_one_touches_it_without_the_guard_and_stops_short_with_it():
    """Closing at the speed limit (1 m/s). (Two UAVs head-on at full speed, 2 m/s closing, need more
    room to stop than the guard's 1.6 m range: the guard does not claim to separate them.)"""
    closest, touched = _fly_at_a_hovering_one(guard=False)
    assert touched and closest < 2 * CFG.uav_radius + 0.02  # the rotor discs touch at about 0.5 m
    closest, touched = _fly_at_a_hovering_one(guard=True)
    assert not touched and closest > NEIGHBOUR_DISTANCE


def test_the_episode_runner_flies_the_guard_when_the_spec_asks(monkeypatch):
    import cefc_mj.task.guard as guard_module

    calls = []
    real = guard_module.guard_actions
    monkeypatch.setattr(guard_module, "guard_actions", lambda *a, **k: calls.append(1) or real(*a, **k))
    run_episode(EpisodeSpec(formation=5, seed=0, steps=20, guard=False))
    assert calls == []
    assert run_episode(EpisodeSpec(formation=5, seed=0, steps=20)).steps == 20  # on by default
    assert len(calls) == 20


def test_a_sitl_m_agent_guards_its_own_row_when_the_game_asks():
    """The agent process's decision (cefc_mj.deploy.agent) is the guarded policy on its row."""
    from cefc_mj.deploy.agent import Agent
    from cefc_mj.eval.runner import load_policy_for

    cfg = TaskConfig(n_agents=5, mode="formation", separation_guard=True)
    agent = Agent("tcp://127.0.0.1:9", 0, "atm", None, 1.0, None, False)  # nothing listens: sends are dropped
    try:
        assert agent._welcome({"uav": 0, "task": cfg.to_dict(), "formation": 5, "heartbeat_timeout_s": 1.0}) is None
        # heading for the anchor 6 m ahead, a neighbour 1.2 m ahead coming the other way
        obs = _row(
            [[-6.0, 0.0], [-4.8, 0.0], [-6.0, 1.0], [-7.0, 0.0], [-6.0, -1.0]],
            [[0.9, 0.0], [-0.9, 0.0], [0.9, 0.0], [0.9, 0.0], [0.9, 0.0]],
        )[:, :1]
        plain = load_policy_for("atm", 5).act(obs)
        expected = guard_actions(obs, plain, cfg.neighbour_slots, cfg.n_lidar_rays, cfg.dt, cfg.accel_max)
        assert not np.array_equal(expected, plain)  # the guard acts on this row
        assert np.array_equal(agent.act(obs), expected)
    finally:
        agent.sock.close(0)


@pytest.mark.parametrize("protocol", ["table3", "table5"])
def test_cli_refuses_the_guard_where_it_does_not_apply(protocol):
    result = subprocess.run(
        [sys.executable, "-m", "cefc_mj.cli.eval", "--backend", "particle", "--protocol", protocol, "--guard", "on"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert result.returncode == 2 and "--guard" in result.stderr and "Traceback" not in result.stderr
