"""No collision at spawn: every pair of start positions keeps two UAV radii plus a margin
(TaskConfig.start_min_spacing), which covers a quadrotor's tilted footprint and the first decision
step, so neither backend counts a contact in an episode's first step.

The MuJoCo check flies the closest starts of 10,000 layouts per c with the worst action (every UAV
accelerating at a_max towards its nearest neighbour); a pair 0.5038 m apart, which the old 0.5 m
rule allowed, is shown to touch under the same action, so the check can fail."""

from __future__ import annotations

import numpy as np
import pytest

from cefc_mj import make_world
from cefc_mj.env import BatchedCEFCEnv
from cefc_mj.errors import ConfigError
from cefc_mj.task.config import TaskConfig
from cefc_mj.task.scenario import Scenario, sample_scenario

LAYOUTS = 10_000
FORMATIONS = (3, 4, 5, 6, 7, 8)


def _config(c: int, **kw) -> TaskConfig:
    return TaskConfig(n_agents=c, mode="formation", obstacle_density=0.03, **kw)


def _min_pair_distance(pos: np.ndarray) -> np.ndarray:
    """[B] smallest distance between two agents of each layout [B, N, 2]."""
    d = np.linalg.norm(pos[:, :, None] - pos[:, None], axis=-1)
    d[:, np.arange(pos.shape[1]), np.arange(pos.shape[1])] = np.inf
    return d.min(axis=(1, 2))


def _towards_nearest(pos: np.ndarray, accel_max: float) -> np.ndarray:
    """[B, N, 2] the worst first action: each UAV at a_max (per axis) towards its nearest neighbour."""
    d = np.linalg.norm(pos[:, :, None] - pos[:, None], axis=-1)
    d[:, np.arange(pos.shape[1]), np.arange(pos.shape[1])] = np.inf
    nearest = np.take_along_axis(pos, d.argmin(-1)[..., None], axis=1)
    return accel_max * np.sign(nearest - pos)


@pytest.mark.parametrize("c", FORMATIONS)
def test_starts_keep_contact_distance_plus_margin(c):
    cfg = _config(c)
    assert cfg.start_min_spacing >= 2 * cfg.uav_radius + 0.057
    starts = sample_scenario(cfg, np.random.default_rng(c), LAYOUTS).agent_pos
    assert _min_pair_distance(starts).min() >= cfg.start_min_spacing


@pytest.mark.parametrize("c", FORMATIONS)
def test_particle_world_counts_no_contact_in_the_first_step(c):
    cfg = _config(c)
    env = BatchedCEFCEnv(cfg, n_envs=LAYOUTS, seed=c)
    env.reset()
    env.step(_towards_nearest(env.world.agent_pos.copy(), cfg.accel_max))
    assert not env.world.collisions().any()


def _fly_first_step(cfg: TaskConfig, starts: np.ndarray) -> np.ndarray:
    """Collisions [B, N] of MuJoCo quadrotors from `starts` [B, N, 2] after one worst-case decision step."""
    n = starts.shape[0]
    world = make_world("mujoco", cfg, n_envs=n, seed=0)
    env = BatchedCEFCEnv(cfg, n_envs=n, seed=0, world=world)
    far = np.tile([[9.0, 9.0]], (n, 1))  # keep the obstacles and the anchor out of the way
    obstacles = np.zeros((n, cfg.n_obstacles, 2))
    obstacles[:] = np.stack([np.linspace(-9.0, 9.0, cfg.n_obstacles), np.full(cfg.n_obstacles, -9.0)], -1)
    env.reset(
        scenario=Scenario(
            agent_pos=starts,
            adversary_pos=far.copy(),
            obstacles=obstacles,
            targets=np.zeros((n, 0, 2)),
            anchor=far.copy(),
        )
    )
    env.step(_towards_nearest(starts, cfg.accel_max))
    return world.collisions()


@pytest.mark.parametrize("c", (5, 8))
def test_mujoco_closest_starts_do_not_touch(c):
    cfg = _config(c)
    starts = sample_scenario(cfg, np.random.default_rng(100 + c), LAYOUTS).agent_pos
    closest = np.argsort(_min_pair_distance(starts))[:8]
    assert not _fly_first_step(cfg, starts[closest]).any()


def test_mujoco_contact_distance_exceeds_two_radii():
    """What the margin is for: two quadrotors 0.5038 m apart (the old rule allowed 0.5) touch in their
    first step under the worst action; 0.6 m apart they do not."""
    cfg = _config(3)
    starts = np.array([[[0.0, 0.0], [0.5038, 0.0], [0.0, 1.5]], [[0.0, 0.0], [0.6, 0.0], [0.0, 1.5]]])
    collided = _fly_first_step(cfg, starts)
    assert collided[0, :2].all() and not collided[1].any()


def test_spacing_below_two_radii_is_refused():
    with pytest.raises(ConfigError, match="start_min_spacing"):
        TaskConfig(start_min_spacing=0.4)
