"""The agent's push observer (cefc_mj/task/push_observer.py): its estimate on a double integrator with
a known push, and, on real quadrotors in MuJoCo's wind through PX4's acceleration interface, that a
drone whose command is AT-M's velocity loop towards rest (u = 5 (0 - v), the policy's action head)
holds its place with it and drifts downwind without it."""

import dataclasses

import numpy as np
import pytest

from cefc_mj.env import BatchedCEFCEnv
from cefc_mj.errors import ConfigError
from cefc_mj.sim.mujoco_world import MujocoWorldConfig, make_mujoco_world
from cefc_mj.sim.wind import WindConfig
from cefc_mj.task.config import TaskConfig
from cefc_mj.task.push_observer import PushObserver
from cefc_mj.train.config import Budget, LowLevelConfig

GAIN = 5.0
"""AT-M's velocity-loop gain (ATMConfig.velocity_gain): u = GAIN (v* - v)."""


def test_on_a_double_integrator_the_estimate_converges_to_the_push_and_cancels_it():
    dt, push = 0.1, np.array([1.5, -0.7])
    observer = PushObserver(1, 1, time_constant=0.5, dt=dt, accel_max=2.0)
    velocity = np.zeros((1, 1, 2))
    observer.reset(np.ones(1, bool), velocity)
    speeds = []
    for _ in range(60):  # 6 s: twelve time constants
        sent = observer.setpoint(-GAIN * velocity)
        velocity = velocity + (sent + push) * dt  # what moves the drone: its setpoint and the push
        observer.update(velocity)
        speeds.append(np.linalg.norm(velocity))
    np.testing.assert_allclose(observer.push[0, 0], push, rtol=1e-4)
    assert speeds[-1] < 1e-3 < max(speeds)  # pushed at first, then held
    observer.reset(np.ones(1, bool), velocity)
    assert not observer.push.any()


def test_a_push_beyond_the_bound_is_cancelled_only_up_to_it():
    observer = PushObserver(1, 1, time_constant=0.1, dt=0.1, accel_max=2.0)
    velocity = np.zeros((1, 1, 2))
    observer.reset(np.ones(1, bool), velocity)
    for _ in range(20):
        sent = observer.setpoint(np.array([[[1.0, 0.0]]]))
        velocity = velocity + (sent + np.array([3.0, 0.0])) * 0.1
        observer.update(velocity)
    assert np.array_equal(observer.setpoint(np.zeros((1, 1, 2)))[0, 0], [-2.0, 0.0])


def drift(push_observer_s: float, steps: int = 100) -> tuple[float, float, np.ndarray]:
    """Three Iris in a steady 5 m/s wind towards +x, PX4's acceleration interface, every agent's
    command the velocity loop towards rest for `steps` decisions: (largest distance moved over the
    second half, largest final speed, final estimates)."""
    task = TaskConfig(n_agents=3, mode="formation", obstacle_density=0.0, push_observer_s=push_observer_s)
    steady = WindConfig(mean_speed=5.0, speed_sigma=0.0, direction=0.0)
    world = make_mujoco_world(task, n_envs=1, wind=steady, seed=3, config=MujocoWorldConfig(offboard="acceleration"))
    env = BatchedCEFCEnv(task, world=world, seed=3)
    env.reset()
    for k in range(steps):
        if k == steps // 2:
            half_way = world.agent_pos.copy()
        env.step(-GAIN * world.agent_vel)
    moved = np.linalg.norm(world.agent_pos - half_way, axis=-1).max()
    speed = np.linalg.norm(world.agent_vel, axis=-1).max()
    return moved, speed, None if env.push_observer is None else env.push_observer.push.copy()


def test_in_steady_wind_5_a_drone_flying_to_rest_holds_with_the_observer_and_drifts_without():
    # The push at 5 m/s, measured at the hold (docs/px4_interface.md): 1.81 m/s^2, inside the 2 m/s^2 bound.
    # Measured: 1.74 m at 0.35 m/s without (push / GAIN), 0.002 m at 0.001 m/s with, estimate 1.83 m/s^2.
    moved, speed, _ = drift(0.0)
    assert moved > 1.2 and speed > 0.25, (moved, speed)  # the loop balances the push at 1.81 / 5 m/s downwind
    moved, speed, push = drift(0.5)
    assert moved < 0.05 and speed < 0.02, (moved, speed)
    assert np.all(np.abs(push[0, :, 0] - 1.81) < 0.1) and np.all(np.abs(push[0, :, 1]) < 0.05), push


def test_the_observer_is_a_recorded_setting_checked_up_front():
    with pytest.raises(ConfigError, match="push_observer_s"):
        TaskConfig(push_observer_s=-1.0)
    with pytest.raises(ConfigError, match="push_observer_s"):
        LowLevelConfig(formation=6, step=1, budget=Budget(iterations=1), push_observer_s=0.5)
    calm = TaskConfig(n_agents=3, mode="formation")
    assert BatchedCEFCEnv(calm).push_observer is None  # the paper's memoryless agent by default
    assert BatchedCEFCEnv(dataclasses.replace(calm, push_observer_s=0.5)).push_observer is not None
