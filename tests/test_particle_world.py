"""The batched particle world against a slow, obvious single-env reference, and the env API."""

import math

import numpy as np
import pytest
from pettingzoo.test import parallel_api_test

import cefc_mj
from cefc_mj.env import BatchedCEFCEnv
from cefc_mj.errors import ConfigError
from cefc_mj.sim.particle import ParticleWorld
from cefc_mj.task.config import TaskConfig


def reference_step(cfg, pos, vel, obstacles, accel):
    """One env, one agent at a time, plain Python floats: the documented particle dynamics."""
    pos, vel = [list(p) for p in pos], [list(v) for v in vel]
    collided = [False] * len(pos)
    for i in range(len(pos)):
        vx, vy = vel[i][0] + accel[i][0] * cfg.dt, vel[i][1] + accel[i][1] * cfg.dt
        speed = math.hypot(vx, vy)
        if speed > cfg.speed_max:
            vx, vy = vx * cfg.speed_max / speed, vy * cfg.speed_max / speed
        vel[i] = [vx, vy]
        pos[i] = [pos[i][0] + vx * cfg.dt, pos[i][1] + vy * cfg.dt]
    for i in range(len(pos)):
        for j in range(len(pos)):
            if i != j and math.dist(pos[i], pos[j]) < 2 * cfg.uav_radius:
                collided[i] = True
    contact = cfg.obstacle_radius + cfg.uav_radius
    for i in range(len(pos)):
        dists = [math.dist(pos[i], o) for o in obstacles]
        if not dists:
            continue
        k = int(np.argmin(dists))
        if dists[k] < contact:
            collided[i] = True
            nx, ny = (pos[i][0] - obstacles[k][0]) / dists[k], (pos[i][1] - obstacles[k][1]) / dists[k]
            pos[i] = [obstacles[k][0] + nx * contact, obstacles[k][1] + ny * contact]
            vn = vel[i][0] * nx + vel[i][1] * ny
            if vn < 0:
                vel[i] = [vel[i][0] - vn * nx, vel[i][1] - vn * ny]
    return np.array(pos), np.array(vel), np.array(collided)


def test_batched_world_matches_reference_step_by_step():
    cfg = TaskConfig(n_agents=6, obstacle_density=0.05)
    rng = np.random.default_rng(0)
    b = 4
    world = ParticleWorld(cfg, b)
    # Obstacles right in the agents' way so that contacts happen.
    obstacles = rng.uniform(-1.5, 1.5, (b, cfg.n_obstacles, 2))
    start = rng.uniform(-2, 2, (b, 6, 2))
    world.reset(np.ones(b, bool), start, np.zeros((b, 2)), obstacles)
    ref = [(start[e].copy(), np.zeros((6, 2))) for e in range(b)]
    contacts = 0
    for _ in range(60):
        accel = rng.uniform(-2, 2, (b, 6, 2))
        world.step(accel, np.zeros((b, 2)))
        for e in range(b):
            p, v, c = reference_step(cfg, ref[e][0], ref[e][1], obstacles[e], accel[e])
            ref[e] = (p, v)
            np.testing.assert_allclose(world.agent_pos[e], p, atol=1e-12)
            np.testing.assert_allclose(world.agent_vel[e], v, atol=1e-12)
            assert (world.collisions()[e] == c).all()
            contacts += c.sum()
    assert contacts > 0  # the comparison exercised the contact branch
    assert np.linalg.norm(world.agent_vel, axis=-1).max() <= cfg.speed_max + 1e-12


def test_acceleration_integrates_to_speed_limit():
    cfg = TaskConfig(n_agents=1)
    world = ParticleWorld(cfg, 1)
    world.reset(np.ones(1, bool), np.zeros((1, 1, 2)), np.zeros((1, 2)), np.zeros((1, 0, 2)))
    for _ in range(3):
        world.step(np.array([[[1.0, 0.0]]]), np.zeros((1, 2)))
    assert world.agent_vel[0, 0, 0] == pytest.approx(0.3)
    assert world.agent_pos[0, 0, 0] == pytest.approx(0.01 + 0.02 + 0.03)
    for _ in range(20):
        world.step(np.array([[[2.0, 2.0]]]), np.array([[2.0, 0.0]]))
    assert np.linalg.norm(world.agent_vel[0, 0]) == pytest.approx(1.0)
    assert np.linalg.norm(world.adversary_vel[0]) == pytest.approx(0.75)


def test_response_time_is_a_first_order_lag_behind_the_commanded_velocity():
    """tau = 0.1 s at dt = 0.1 s: v moves half-way to the commanded velocity each step."""
    cfg = TaskConfig(n_agents=1, response_time=0.1)
    world = ParticleWorld(cfg, 1)
    world.reset(np.ones(1, bool), np.zeros((1, 1, 2)), np.zeros((1, 2)), np.zeros((1, 0, 2)))
    commanded, expected = 0.0, 0.0
    for t in range(12):
        accel = 2.0 if t < 4 else 0.0  # the commanded velocity ramps to 0.8 m/s and holds
        world.step(np.array([[[accel, 0.0]]]), np.zeros((1, 2)))
        commanded += accel * cfg.dt
        expected += 0.5 * (commanded - expected)
        assert world.agent_vel[0, 0, 0] == pytest.approx(expected)
    assert 0.79 < world.agent_vel[0, 0, 0] < 0.8  # converged from below, never overshooting


def test_velocity_noise_kicks_have_the_configured_spread_and_follow_the_seed():
    def velocities(seed):
        env = BatchedCEFCEnv(TaskConfig(n_agents=4, mode="formation", velocity_noise=0.08), n_envs=50, seed=seed)
        env.reset(seed=seed)
        env.step(np.zeros((50, 4, 2)))  # from rest with zero action: the velocity is the kick alone
        return env.world.agent_vel.copy()

    v = velocities(3)
    assert v.std() == pytest.approx(0.08, rel=0.1) and abs(v.mean()) < 0.01
    np.testing.assert_array_equal(v, velocities(3))
    assert not np.array_equal(v, velocities(4))


def test_particle_only_settings_are_refused_by_mujoco():
    with pytest.raises(ConfigError, match="response_time"):
        cefc_mj.make_world("mujoco", TaskConfig(n_agents=3, response_time=0.1))


def test_uniform_deviation_sampling_draws_each_env_its_own_level():
    env = BatchedCEFCEnv(
        TaskConfig(n_agents=4, mode="formation", deviation=0.8, deviation_sampling="uniform"), n_envs=64, seed=0
    )
    env.reset()
    first = env.env_deviation.copy()
    assert ((first >= 0) & (first <= 0.8)).all() and first.std() > 0.15
    env.step(np.zeros((64, 4, 2)))
    offset = np.linalg.norm(env.perceived_pos - env.world.agent_pos, axis=-1).mean(axis=1)  # [B]
    assert np.corrcoef(offset, first)[0, 1] > 0.9  # each env perceives with its own level
    env.reset(mask=np.arange(64) < 32)
    assert (env.env_deviation[32:] == first[32:]).all() and (env.env_deviation[:32] != first[:32]).all()


def test_collision_reward_scores_true_clearance_under_deviation():
    """Two agents 0.4 m apart (touching) are penalised whatever their noisy LiDAR shows."""
    from cefc_mj.task.rewards import collision_penalty

    cfg = TaskConfig(n_agents=3, mode="formation", deviation=0.8)
    env = BatchedCEFCEnv(cfg, n_envs=8, seed=0)
    env.reset()
    start = np.array([[0.0, 0.0], [0.4, 0.0], [0.0, 3.0]]) + np.array([4.0, -8.0])
    env.world.reset(np.ones(8, bool), np.repeat(start[None], 8, 0), np.zeros((8, 2)), env.obstacles + 50.0)
    env.step(np.zeros((8, 3, 2)))
    true_penalty = collision_penalty(env.world.lidar(env.world.agent_pos).min(-1), cfg.rewards)
    np.testing.assert_allclose(env.agent_collision_penalty, true_penalty)
    assert (true_penalty[:, :2] > 0).all()
    assert not np.allclose(env.lidar, env.true_lidar)  # the observation is noisy, the reward is not


def rollout(seed, mode="cefc", steps=50, **kw):
    env = BatchedCEFCEnv(TaskConfig(n_agents=6, mode=mode, obstacle_density=0.03, **kw), n_envs=3, seed=seed)
    rng = np.random.default_rng(seed)
    trace = [env.reset()]
    for _ in range(steps):
        obs, reward, done, info = env.step(rng.uniform(-2, 2, (3, 6, 2)))
        trace += [obs.copy(), reward, env.world.agent_pos.copy()]
    return trace


@pytest.mark.parametrize("mode", ["cefc", "formation"])
def test_same_seed_same_rollout(mode):
    a, b, c = rollout(7, mode, deviation=0.5), rollout(7, mode, deviation=0.5), rollout(8, mode, deviation=0.5)
    assert all(np.array_equal(x, y) for x, y in zip(a, b))
    assert not all(np.array_equal(x, y) for x, y in zip(a, c))


def test_reset_by_mask_only_touches_masked_envs():
    env = BatchedCEFCEnv(TaskConfig(n_agents=4, mode="formation"), n_envs=3, seed=0)
    env.reset()
    for _ in range(5):
        env.step(np.ones((3, 4, 2)))
    before = env.world.agent_pos.copy()
    env.reset(mask=np.array([False, True, False]))
    assert np.array_equal(env.world.agent_pos[[0, 2]], before[[0, 2]])
    assert not np.array_equal(env.world.agent_pos[1], before[1])
    assert env.t.tolist() == [5, 0, 5]


def test_episode_metrics_at_end():
    env = BatchedCEFCEnv(TaskConfig(n_agents=5, mode="formation", episode_steps=20), n_envs=2, seed=1)
    env.reset()
    for t in range(20):
        obs, reward, done, info = env.step(np.zeros((2, 5, 2)))
        assert done.all() == (t == 19)
    m = info["metrics"]
    assert set(m) == {"F", "N", "C", "E", "E_agents"} and all(v.shape == (2,) for v in m.values())
    assert ((0 <= m["F"]) & (m["F"] <= 20) & (0 <= m["C"]) & (m["C"] <= 100)).all()
    with pytest.raises(ConfigError, match="reset"):
        env.step(np.zeros((2, 5, 2)))


def test_formation_metric_counts_a_held_template():
    """Agents placed exactly on Delta_5 at the anchor, zero action: F = N = all steps, C = 0."""
    from cefc_mj.task.formation import formation_template

    cfg = TaskConfig(n_agents=5, mode="formation", episode_steps=10)
    env = BatchedCEFCEnv(cfg, n_envs=1, seed=0)
    env.reset()
    anchor = env.anchor.copy()
    env.world.reset(np.ones(1, bool), (formation_template(5) + anchor[0])[None], np.zeros((1, 2)), env.obstacles)
    for _ in range(10):
        obs, reward, done, info = env.step(np.zeros((1, 5, 2)))
    assert info["metrics"]["F"][0] == 10 and info["metrics"]["N"][0] == 10 and info["metrics"]["C"][0] == 0
    assert info["reward_terms"]["R_f"][0] == pytest.approx(0.0, abs=1e-9)


@pytest.mark.parametrize("mode", ["cefc", "formation"])
def test_pettingzoo_parallel_api(mode):
    parallel_api_test(cefc_mj.make_env(n_agents=5, mode=mode, obstacle_density=0.03, seed=0), num_cycles=150)


def test_pettingzoo_infos_hold_true_state():
    env = cefc_mj.make_env(n_agents=3, mode="formation", deviation=0.5, seed=0)
    obs, infos = env.reset(seed=3)
    assert env.agents == ["uav_0", "uav_1", "uav_2"]
    assert env.action_space("uav_0").shape == (2,)
    np.testing.assert_array_equal(infos["uav_1"]["position"], env.batched.world.agent_pos[0, 1])
    obs, rew, term, trunc, infos = env.step({a: np.array([1.0, 0.0]) for a in env.agents})
    assert infos["uav_0"]["velocity"][0] == pytest.approx(0.1)


@pytest.mark.parametrize("n", range(3, 16))
def test_observations_finite_and_documented_shape(n):
    env = cefc_mj.make_env(n_agents=n, obstacle_density=0.03, seed=n)
    obs, _ = env.reset(seed=n)
    for _ in range(5):
        obs, *_ = env.step({a: env.action_space(a).sample() for a in env.agents})
    expected = 6 + 4 + 5 * 7 + 24  # the 7 nearest neighbours within 3 m, whatever N is
    assert all(o.shape == (expected,) and np.isfinite(o).all() for o in obs.values())


@pytest.mark.parametrize(
    "kwargs, name",
    [
        (dict(backend="bullet"), "backend"),
        (dict(n_agents=0), "n_agents"),
        (dict(obstacle_density=-0.1), "obstacle_density"),
        (dict(obstacle_density=1.0), "obstacle_density"),
        (dict(deviation=float("nan")), "deviation"),
        (dict(wind=-1.0), "wind"),
        (dict(mode="formation", n_agents=2), "n_agents"),
        (dict(obstacle_densty=0.1), "obstacle_densty"),
    ],
)
def test_bad_input_names_the_argument(kwargs, name):
    with pytest.raises(ValueError, match=name):
        cefc_mj.make_env(**kwargs)


def test_nan_action_is_rejected():
    env = cefc_mj.make_env(n_agents=3, seed=0)
    env.reset(seed=0)
    with pytest.raises(ValueError, match="NaN"):
        env.step({a: np.array([np.nan, 0.0]) for a in env.agents})
