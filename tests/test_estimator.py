"""The onboard position estimate (cefc_mj/task/estimator.py): it averages the sensing deviation away
on both backends, is bit-identical to the raw agent without deviation, and restarts per env."""

import numpy as np
import pytest

from cefc_mj.env import BatchedCEFCEnv
from cefc_mj.errors import ConfigError
from cefc_mj.sim.mujoco_world import make_mujoco_world
from cefc_mj.task.config import TaskConfig


def _config(estimator, deviation, **kw):
    return TaskConfig(
        n_agents=5, mode="formation", obstacle_density=0.03, deviation=deviation, position_estimator=estimator, **kw
    )


def _errors(env, steps, rng):
    """Mean |perceived - true| per step [steps] while the agents fly random accelerations."""
    out = []
    for _ in range(steps):
        env.step(rng.uniform(-1.0, 1.0, (env.n_envs, env.n_agents, 2)))
        out.append(np.linalg.norm(env.perceived_pos - env.world.agent_pos, axis=-1).mean())
    return np.array(out)


def test_option_is_validated():
    with pytest.raises(ConfigError, match="position_estimator='kalman'"):
        TaskConfig(position_estimator="kalman")
    assert TaskConfig().position_estimator == "raw"


def test_fused_estimate_averages_the_deviation_away_on_particles():
    errors = {}
    for est in ("raw", "fused"):
        env = BatchedCEFCEnv(_config(est, 0.8), n_envs=16, seed=4)
        env.reset()
        errors[est] = _errors(env, 60, np.random.default_rng(0))
    # raw: every fix is |Normal(0.8, 0.2)| off; fused: a few times smaller once the filter settled
    assert 0.75 < errors["raw"].mean() < 0.85
    assert errors["fused"][:3].mean() > 0.3  # it starts from a single fix ...
    assert errors["fused"][30:].mean() < 0.25 * errors["raw"].mean()  # ... and settles


def test_without_deviation_fused_is_bit_identical_to_raw():
    obs = {}
    for est in ("raw", "fused"):
        env = BatchedCEFCEnv(_config(est, 0.0), n_envs=4, seed=1)
        first = env.reset().copy()
        rng = np.random.default_rng(2)
        steps = [env.step(rng.uniform(-2, 2, (4, 5, 2)))[0].copy() for _ in range(20)]
        obs[est] = np.stack([first, *steps])
    np.testing.assert_array_equal(obs["raw"], obs["fused"])


def test_partial_reset_restarts_only_the_masked_envs():
    env = BatchedCEFCEnv(_config("fused", 0.8), n_envs=2, seed=0)
    env.reset()
    _errors(env, 40, np.random.default_rng(1))
    settled = env.estimate.variance.copy()
    env.reset(mask=np.array([True, False]))
    assert (env.estimate.variance[0] > 10 * settled[0]).all()  # back to one fix's uncertainty
    np.testing.assert_array_equal(env.estimate.variance[1], settled[1])


def test_fused_estimate_tracks_a_quadrotor():
    # the prediction is the drone's own displacement between decisions, from the MuJoCo state
    cfg = _config("fused", 0.8)
    world = make_mujoco_world(cfg, n_envs=1, seed=3)
    env = BatchedCEFCEnv(cfg, n_envs=1, seed=3, world=world)
    env.reset()
    errors = _errors(env, 50, np.random.default_rng(3))
    assert errors[25:].mean() < 0.25
