"""ORCA-F (cefc_mj.baselines.orca) on the particle world: ORCA keeps agents off each other and off
the cylinders where the bare preferred velocity would collide, and the formation controller reaches
the template and the anchor in free space."""

import numpy as np
import pytest

pytest.importorskip("pyrvo", reason="ORCA-F needs the RVO2 binding: pip install 'pyrvo>=0.4.3'")

from cefc_mj.baselines.orca import (  # noqa: E402
    OrcaConfig,
    OrcaFormationPolicy,
    cylinder_polygon,
    evaluate_orca,
    evaluate_orca_episodes,
)
from cefc_mj.env import BatchedCEFCEnv  # noqa: E402
from cefc_mj.errors import ConfigError  # noqa: E402
from cefc_mj.task.config import TaskConfig  # noqa: E402
from cefc_mj.task.formation import directed_hausdorff, formation_template  # noqa: E402


def _scene(n_agents, starts, anchor, obstacles, steps=150):
    """A one-env formation game with the given starts [N, 2], anchor [2] and obstacles [K, 2]."""
    density = len(obstacles) / 400.0  # the arena is 20 m x 20 m: round(density * 400) = K
    cfg = TaskConfig(n_agents=n_agents, mode="formation", obstacle_density=density, episode_steps=steps)
    env = BatchedCEFCEnv(cfg, n_envs=1, seed=0)
    env.reset()
    obstacles = np.asarray(obstacles, dtype=float).reshape(1, -1, 2)
    env.world.reset(np.ones(1, bool), np.asarray(starts, dtype=float)[None], np.zeros((1, 2)), obstacles)
    env.obstacles[:] = obstacles
    env.anchor[:] = anchor
    return cfg, env


def _fly(env, act, steps):
    """Fly `steps` steps; returns (any collision flagged, min UAV-UAV distance, min UAV-obstacle distance)."""
    collided, min_agents, min_obstacle = False, np.inf, np.inf
    n = env.n_agents
    for _ in range(steps):
        env.step(act(env))
        pos = env.world.agent_pos[0]
        collided |= bool(env.world.collisions().any())
        d = np.linalg.norm(pos[:, None] - pos[None], axis=-1) + np.eye(n) * 99
        min_agents = min(min_agents, d.min())
        if env.obstacles.shape[1]:
            min_obstacle = min(min_obstacle, np.linalg.norm(pos[:, None] - env.obstacles[0][None], axis=-1).min())
    return collided, min_agents, min_obstacle


def _bare(policy):
    """The same formation controller without ORCA: u = clip(5 (v_pref - v), +-2)."""

    def act(env):
        pref = policy.preferred_velocity(env.world.agent_pos, env.anchor, env.t == 0)
        return np.clip(5.0 * (pref - env.world.agent_vel), -2.0, 2.0)

    return act


def test_cylinder_polygon_contains_the_cylinder_counterclockwise():
    poly = cylinder_polygon([1.0, -2.0], 0.4, 16)
    rel = poly - [1.0, -2.0]
    x, y = rel[:, 0], rel[:, 1]
    assert 0.5 * (x * np.roll(y, -1) - np.roll(x, -1) * y).sum() > 0  # counterclockwise
    mid = 0.5 * (rel + np.roll(rel, -1, axis=0))  # edge midpoints: the closest points of the edges
    np.testing.assert_allclose(np.linalg.norm(mid, axis=-1), 0.4)


def test_orca_flies_around_an_obstacle_in_the_way():
    # a triangle of 3 agents at x = -4 heading for an anchor at x = +4, a cylinder straight between
    starts = formation_template(3) + [-4.0, 0.0]
    cfg, env = _scene(3, starts, [4.0, 0.0], [[0.0, 0.0]])
    policy = OrcaFormationPolicy(cfg)
    collided, min_agents, min_obstacle = _fly(env, policy.act, 150)
    assert not collided
    assert min_obstacle > cfg.obstacle_radius + cfg.uav_radius and min_agents > 2 * cfg.uav_radius
    assert np.linalg.norm(env.world.agent_pos[0].mean(0) - env.anchor[0]) < 1.0  # got there all the same
    # control: the bare formation controller hits the cylinder
    cfg, env = _scene(3, starts, [4.0, 0.0], [[0.0, 0.0]])
    assert _fly(env, _bare(OrcaFormationPolicy(cfg)), 150)[0]


class _Swap(OrcaFormationPolicy):
    """Agents 0 and 1 want to trade places head-on (agent 2 stays put): a test of agent-agent ORCA."""

    def preferred_velocity(self, pos, anchor, new_episode):
        goal = np.array([[2.0, 0.0], [-2.0, 0.0], [0.0, 3.0]])
        return np.clip(goal - pos, -1.0, 1.0)


def test_orca_agents_avoid_each_other():
    starts = [[-2.0, 0.0], [2.0, 0.0], [0.0, 3.0]]
    cfg, env = _scene(3, starts, [0.0, 3.0], [])
    collided, min_agents, _ = _fly(env, _Swap(cfg).act, 80)
    assert not collided and min_agents > 2 * cfg.uav_radius
    pos = env.world.agent_pos[0]
    assert np.linalg.norm(pos[0] - [2.0, 0.0]) < 0.3 and np.linalg.norm(pos[1] - [-2.0, 0.0]) < 0.3  # swapped
    # control: flown straight at each other they collide
    cfg, env = _scene(3, starts, [0.0, 3.0], [])
    swap = _Swap(cfg)
    collided, min_agents, _ = _fly(
        env,
        lambda e: np.clip(
            5.0 * (swap.preferred_velocity(e.world.agent_pos[0], None, None)[None] - e.world.agent_vel), -2.0, 2.0
        ),
        80,
    )
    assert collided and min_agents < 2 * cfg.uav_radius


def test_orca_reaches_formation_and_anchor_in_free_space():
    per_episode = evaluate_orca_episodes(6, episodes=4, seed=1, steps=100, density=0.0)
    assert sorted(per_episode) == ["C", "F", "N", "R_L", "R_L_agents"] and all(
        v.shape == (4,) for v in per_episode.values()
    )
    assert (per_episode["C"] == 0).all()
    assert (per_episode["F"] > 90).all() and (per_episode["N"] > 40).all()
    # and the final shape is the template
    cfg = TaskConfig(n_agents=6, mode="formation", episode_steps=100)
    env = BatchedCEFCEnv(cfg, n_envs=2, seed=5)
    env.reset(seed=5)
    policy = OrcaFormationPolicy(cfg)
    for _ in range(100):
        env.step(policy.act(env))
    pos = env.world.agent_pos
    hd = directed_hausdorff(np.broadcast_to(formation_template(6), (2, 6, 2)), pos - pos.mean(1, keepdims=True))
    assert (hd < 0.2).all()
    assert (np.linalg.norm(pos.mean(1) - env.anchor, axis=-1) < 0.3).all()


def test_evaluate_orca_table3_keys_and_new_episodes_rebuild_the_simulators():
    result = evaluate_orca(6, episodes=3, seed=0, steps=10, density=0.05)
    assert sorted(result) == ["C", "F", "N", "R_L", "R_L_agents"] and all(np.isfinite(v) for v in result.values())
    cfg = TaskConfig(n_agents=6, mode="formation", obstacle_density=0.05, episode_steps=5)
    env = BatchedCEFCEnv(cfg, n_envs=2, seed=0)
    env.reset(seed=0)
    policy = OrcaFormationPolicy(cfg)
    policy.act(env)
    first = list(policy._sims)
    policy.act(env)
    assert all(a is b for a, b in zip(first, policy._sims))  # same episode: kept
    env.reset(seed=1)
    policy.act(env)
    np.testing.assert_array_equal(policy._obstacles, env.obstacles)
    assert all(a is not b for a, b in zip(first, policy._sims))  # new obstacles: rebuilt


def test_orca_rejects_bad_settings():
    with pytest.raises(ConfigError, match="mode"):
        OrcaFormationPolicy(TaskConfig(n_agents=6))
    with pytest.raises(ConfigError, match="obstacle_sides"):
        OrcaConfig(obstacle_sides=2)
    with pytest.raises(ConfigError, match="time_horizon"):
        OrcaConfig(time_horizon=0.0)
    with pytest.raises(ConfigError, match="formation"):
        evaluate_orca(2)
    env = BatchedCEFCEnv(TaskConfig(n_agents=4, mode="formation"), n_envs=1)
    with pytest.raises(ConfigError, match="env"):
        OrcaFormationPolicy(TaskConfig(n_agents=5, mode="formation")).act(env)
