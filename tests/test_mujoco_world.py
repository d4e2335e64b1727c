"""MuJoCo world: physics checked against physics (hover, tracking, wind drag), LiDAR against exact
ray-circle distances and the particle world, contacts, determinism, divergence and bad input."""

from __future__ import annotations

import math

import numpy as np
import pytest

from cefc_mj.errors import ConfigError, SimulationDiverged
from cefc_mj.sim.mujoco_world import MujocoWorld, MujocoWorldConfig
from cefc_mj.sim.wind import WindConfig
from cefc_mj.sim.world import World
from cefc_mj.task.lidar import lidar_ranges

G = 9.81
MASS = 1.5
ALL = np.ones(1, dtype=bool)


def single_drone(wind=None, **config):
    world = MujocoWorld(MujocoWorldConfig(**config), n_envs=1, n_agents=1, n_obstacles=0, with_adversary=False, wind=wind, seed=3)
    world.reset(ALL, np.zeros((1, 1, 2)), np.zeros((1, 2)), np.zeros((1, 0, 2)))
    return world


def fly(world, accel, steps):
    """Hold accel [2] for `steps` decision steps; return per-step positions [steps, 3] and tilts [steps]."""
    a = np.broadcast_to(np.asarray(accel, dtype=float), (1, world.n_agents, 2))
    positions, tilts = [], []
    for _ in range(steps):
        world.step(a, np.zeros((1, 2)))
        positions.append(world.drone_positions[0, 0].copy())
        tilts.append(world.tilt_deg()[0, 0])
    return np.array(positions), np.array(tilts)


# ----------------------------------------------------------------------------- flight physics
def test_hover_holds_position_with_weight_shared_by_the_motors():
    world = single_drone()
    start = world.drone_positions[0, 0].copy()
    positions, _ = fly(world, (0.0, 0.0), 200)  # 20 s
    assert np.linalg.norm(positions - start, axis=1).max() < 0.05
    np.testing.assert_allclose(world.motor_thrusts[0, 0], MASS * G / 4, rtol=0.01)


def test_tracking_an_acceleration_setpoint():
    world = single_drone()
    positions, tilts = fly(world, (0.25, 0.0), 20)  # 2 s
    v_at_2s = world.agent_vel[0, 0, 0]
    # the cascade answers with ~0.25 s of delay (attitude P 6.5, rate P 0.15): once the setpoint
    # returns to 0 the delayed response completes; the calm-air speed then holds (no damping)
    settle, settle_tilts = fly(world, (0.0, 0.0), 5)
    v = world.agent_vel[0, 0]
    assert v[0] == pytest.approx(0.5, rel=0.10)
    assert abs(v[1]) < 1e-6
    assert 0.8 * 0.5 < v_at_2s < v[0]
    assert max(tilts.max(), settle_tilts.max()) <= 45.0
    assert np.abs(np.concatenate([positions, settle])[:, 2] - 2.0).max() < 0.10


def test_speed_limits_hold_at_full_acceleration():
    world = MujocoWorld(MujocoWorldConfig(), n_envs=1, n_agents=1, n_obstacles=0, seed=0)
    world.reset(ALL, np.zeros((1, 1, 2)), np.array([[0.0, 5.0]]), np.zeros((1, 0, 2)))
    speeds, adversary_speeds = [], []
    for _ in range(30):
        world.step(np.full((1, 1, 2), 2.0), np.array([[-2.0, 2.0]]))
        speeds.append(np.linalg.norm(world.agent_vel[0, 0]))
        adversary_speeds.append(np.linalg.norm(world.adversary_vel[0]))
    assert max(speeds) < 1.0 * 1.03 and speeds[-1] == pytest.approx(1.0, abs=0.02)
    assert max(adversary_speeds) < 0.75 * 1.03 and adversary_speeds[-1] == pytest.approx(0.75, abs=0.02)
    assert world.tilt_deg().max() < 45.0


def test_wind_drag_matches_the_rotor_drag_formula():
    # one physics step from a level hover at rest: the relative airspeed is exactly -wind
    wind = WindConfig(mean_speed=8.0, speed_sigma=0.0, direction=0.3)
    world = single_drone(wind=wind, decision_dt=0.002)
    w = world.wind_vector[0]
    assert np.linalg.norm(w) == pytest.approx(8.0) and math.atan2(w[1], w[0]) == pytest.approx(0.3)
    omega = world.motor_speeds[0, 0].copy()
    world.step(np.zeros((1, 1, 2)), np.zeros((1, 2)))
    c_rd = world.airframe.rotor_drag_coefficient
    # Gazebo's motor model: per rotor -|omega| c_rd v_perp; the rotor speeds are the lagged state of this step
    expected = -c_rd * np.abs(world.motor_speeds[0, 0]).sum() * (np.zeros(3) - w)
    np.testing.assert_allclose(world.drag_forces[0, 0, :3], expected, rtol=1e-9)
    # about 0.56 N per m/s at hover (facts file), and it accelerates the drone accordingly
    assert np.linalg.norm(expected) == pytest.approx(4 * c_rd * omega.mean() * 8.0, rel=1e-3)
    assert np.linalg.norm(expected) / 8.0 == pytest.approx(0.556, abs=0.01)
    accel = world.drone_velocities[0, 0, :2] / 0.002
    np.testing.assert_allclose(accel, expected[:2] / MASS, rtol=0.01)


def test_strong_wind_drifts_the_drone_downwind_at_held_altitude():
    direction = 0.3
    world = single_drone(wind=WindConfig(mean_speed=8.0, direction=direction))
    downwind = np.array([math.cos(direction), math.sin(direction)])
    positions, speeds, tilts = [], [], []
    for _ in range(50):  # 5 s, zero setpoint
        p, t = fly(world, (0.0, 0.0), 1)
        positions.append(p[0])
        tilts.append(t[0])
        speeds.append(np.linalg.norm(world.agent_vel[0, 0]))
    positions = np.array(positions)
    drift = positions[-1, :2]
    assert drift @ downwind > 2.0
    assert abs(drift @ np.array([-downwind[1], downwind[0]])) < 0.1 * (drift @ downwind)
    assert np.abs(positions[:, 2] - 2.0).max() < 0.15
    # the offboard interface holds the speed at its limit on average; each 0.5 s redraw of the
    # wind (a step of up to ~2 m/s^2 in push) overshoots it for a few tenths of a second
    assert np.mean(speeds[25:]) < 1.15
    assert max(tilts) < 45.0


def test_wind_redraws_every_half_second_around_the_mean():
    world = single_drone(wind=WindConfig(mean_speed=5.0, direction=1.0))
    speeds = []
    for _ in range(40):
        fly(world, (0.0, 0.0), 5)
        speeds.append(np.linalg.norm(world.wind_vector[0]))
    speeds = np.array(speeds)
    assert len(np.unique(speeds)) == len(speeds)
    assert speeds.mean() == pytest.approx(5.0, abs=0.5) and speeds.std() == pytest.approx(1.0, abs=0.4)


# ----------------------------------------------------------------------------- LiDAR
LAYOUT_AGENTS = np.array([[[0.0, 0.0], [1.2, 0.3], [-0.6, -1.5]]])
LAYOUT_OBSTACLES = np.array([[[2.0, 0.0], [0.0, 2.2], [-1.7, 1.1], [1.0, -2.0], [9.0, 9.0]]])


def analytic_ranges(origin, circles, n_rays, max_range):
    """Nearest ray-circle intersection per beam: solve |o + t u - c| = r for the smaller root t >= 0."""
    out = np.full(n_rays, max_range)
    for k in range(n_rays):
        u = np.array([math.cos(2 * math.pi * k / n_rays), math.sin(2 * math.pi * k / n_rays)])
        for centre, radius in circles:
            oc = origin - centre
            b = u @ oc
            disc = b * b - (oc @ oc - radius**2)
            if disc >= 0 and -b - math.sqrt(disc) >= 0:
                out[k] = min(out[k], -b - math.sqrt(disc))
    return out


def layout_world(sees_agents=True):
    world = MujocoWorld(MujocoWorldConfig(), n_envs=1, n_agents=3, n_obstacles=5, n_lidar_rays=36,
                        lidar_sees_agents=sees_agents, seed=0)
    world.reset(ALL, LAYOUT_AGENTS, np.array([[0.0, 1.0]]), LAYOUT_OBSTACLES)  # adversary near agent 0: never seen
    return world


def test_lidar_equals_analytic_ray_circle_distances():
    ranges = layout_world().lidar(LAYOUT_AGENTS)
    for i in range(3):
        circles = [(c, 0.4) for c in LAYOUT_OBSTACLES[0]] + [(LAYOUT_AGENTS[0, j], 0.25) for j in range(3) if j != i]
        np.testing.assert_allclose(ranges[0, i], analytic_ranges(LAYOUT_AGENTS[0, i], circles, 36, 3.0), atol=0.01)
    assert (ranges < 3.0).any() and (ranges == 3.0).any()


@pytest.mark.parametrize("sees_agents", [True, False])
def test_lidar_equals_the_particle_world_lidar(sees_agents):
    rng = np.random.default_rng(1)
    origins = LAYOUT_AGENTS + rng.normal(0, 0.3, LAYOUT_AGENTS.shape)  # perceived positions
    origins[0, 2] = LAYOUT_OBSTACLES[0, 0] + 0.1  # inside an obstacle: reads 0 in both worlds
    ranges = layout_world(sees_agents).lidar(origins)
    particle = lidar_ranges(origins, LAYOUT_OBSTACLES, 0.4, LAYOUT_AGENTS, 0.25, 36, 3.0, sees_agents)
    np.testing.assert_allclose(ranges, particle, atol=0.01)
    assert (ranges[0, 2] == 0).all() and (ranges < 3.0).sum() > 10


def test_obstacles_move_at_reset_per_env():
    world = MujocoWorld(MujocoWorldConfig(), n_envs=2, n_agents=1, n_obstacles=1, n_lidar_rays=4, seed=0)
    origin = np.zeros((2, 1, 2))
    world.reset(np.ones(2, bool), origin, np.full((2, 2), 5.0), np.array([[[1.5, 0.0]], [[0.0, 2.0]]]))
    ranges = world.lidar(origin)
    np.testing.assert_allclose(ranges[0, 0], [1.1, 3.0, 3.0, 3.0], atol=1e-9)
    np.testing.assert_allclose(ranges[1, 0], [3.0, 1.6, 3.0, 3.0], atol=1e-9)
    world.reset(np.array([True, False]), origin, np.full((2, 2), 5.0), np.array([[[-2.5, 0.0]], [[9.0, 9.0]]]))
    np.testing.assert_allclose(world.lidar(origin)[:, 0], [[3.0, 3.0, 2.1, 3.0], [3.0, 1.6, 3.0, 3.0]], atol=1e-9)


# ----------------------------------------------------------------------------- contacts
def test_contacts_with_obstacles_and_uavs_are_collisions_adversary_is_not():
    world = MujocoWorld(MujocoWorldConfig(), n_envs=1, n_agents=4, n_obstacles=1, seed=0)
    agents = np.array([[[0.0, 0.0], [-3.0, 3.0], [-1.5, 3.0], [3.0, -3.0]]])
    world.reset(ALL, agents, np.array([[3.0, -3.0]]), np.array([[[1.5, 0.0]]]))  # adversary on top of agent 3
    hits = np.zeros(4, dtype=bool)
    accel = np.zeros((1, 4, 2))
    accel[0, 0] = (1.0, 0.0)   # into the obstacle
    accel[0, 1] = (1.0, 0.0)   # towards agent 2
    accel[0, 2] = (-1.0, 0.0)  # towards agent 1
    for _ in range(20):
        world.step(accel, np.zeros((1, 2)))
        hits |= world.collisions()[0]
    assert hits.tolist() == [True, True, True, False]
    assert world.agent_pos[0, 0, 0] < 1.5 - 0.4  # the obstacle stopped it


# ----------------------------------------------------------------------------- determinism
def run_episode(seed):
    world = MujocoWorld(MujocoWorldConfig(), n_envs=2, n_agents=3, n_obstacles=2, wind=WindConfig(mean_speed=3.0), seed=seed)
    rng = np.random.default_rng(0)
    world.reset(np.ones(2, bool), rng.uniform(-2, 2, (2, 3, 2)), np.array([[0.0, 6.0], [0.0, -6.0]]), np.array([[[4.0, 4.0], [-4.0, 4.0]]] * 2))
    for _ in range(10):
        world.step(rng.uniform(-2, 2, (2, 3, 2)), rng.uniform(-2, 2, (2, 2)))
    return np.stack([d.qpos.copy() for d in world.datas])


def test_same_seed_same_trajectory_bit_for_bit():
    a, b = run_episode(11), run_episode(11)
    assert np.array_equal(a, b)
    assert not np.array_equal(a, run_episode(12))  # the seed drives the wind


# ----------------------------------------------------------------------------- protocol, divergence, bad input
def test_is_a_world():
    world = single_drone()
    assert isinstance(world, World)
    assert world.dt == 0.1 and world.n_envs == 1 and world.n_agents == 1
    assert world.adversary_pos.shape == (1, 2) and world.collisions().shape == (1, 1)


def test_nan_state_and_flipped_drone_raise_simulation_diverged():
    world = single_drone()
    world.datas[0].qvel[0] = np.nan
    with pytest.raises(SimulationDiverged, match="env 0: uav 0 state became NaN/inf at t = 0.000 s"):
        world.step(np.zeros((1, 1, 2)), np.zeros((1, 2)))
    world.reset(ALL, np.zeros((1, 1, 2)), np.zeros((1, 2)), np.zeros((1, 0, 2)))
    world.datas[0].qpos[3:7] = (math.cos(1.0), math.sin(1.0), 0.0, 0.0)  # rolled 115 degrees
    with pytest.raises(SimulationDiverged, match="uav 0 flipped"):
        world.step(np.zeros((1, 1, 2)), np.zeros((1, 2)))


@pytest.mark.parametrize("make, message", [
    (lambda: WindConfig(mean_speed=-1.0), "wind.mean_speed must be a finite number >= 0"),
    (lambda: WindConfig(mean_speed=3.0, speed_sigma=-0.1), "wind.speed_sigma must be >= 0"),
    (lambda: MujocoWorld(MujocoWorldConfig(airframe="hexa"), 1, 1, 0), "unknown airframe 'hexa'"),
    (lambda: MujocoWorld(MujocoWorldConfig(params="hexa"), 1, 1, 0), "unknown parameter file 'hexa'"),
    (lambda: MujocoWorld(MujocoWorldConfig(physics_dt=0.004), 1, 1, 0), "physics_dt must be <= 0.002"),
    (lambda: MujocoWorld(MujocoWorldConfig(rate_loop_hz=200), 1, 1, 0), "rate_loop_hz must be >= 250"),
    (lambda: MujocoWorld(MujocoWorldConfig(position_loop_hz=300), 1, 1, 0), "position_loop_hz = 300 must divide"),
    (lambda: MujocoWorld(MujocoWorldConfig(), 1, 1, -1), "n_obstacles must be an integer >= 0"),
])
def test_bad_configuration_is_one_clear_line(make, message):
    with pytest.raises(ConfigError, match=message) as info:
        make()
    assert "\n" not in str(info.value)


def test_bad_arrays_are_rejected():
    world = single_drone()
    with pytest.raises(ConfigError, match=r"agent_accel must have shape \[1, 1, 2\]"):
        world.step(np.zeros((1, 2)), np.zeros((1, 2)))
    with pytest.raises(ConfigError, match="agent_pos contains NaN"):
        world.reset(ALL, np.full((1, 1, 2), np.nan), np.zeros((1, 2)), np.zeros((1, 0, 2)))
    with pytest.raises(ConfigError, match=r"obstacles must have shape \[1, 0, 2\]"):
        world.reset(ALL, np.zeros((1, 1, 2)), np.zeros((1, 2)), np.zeros((1, 3, 2)))
