"""Obstacle layouts: the "clear-start" option is bit-identical to the original sampler, and the
paper-faithful "paper" layout puts obstacles between the swarm and its anchor far more often
(docs/research/layouts.md)."""

import hashlib

import numpy as np
import pytest

from cefc_mj.env import BatchedCEFCEnv
from cefc_mj.errors import ConfigError
from cefc_mj.task.config import TaskConfig
from cefc_mj.task.scenario import (
    START_DISC_MARGIN,
    Scenario,
    near_path_fraction,
    obstacle_near_path,
    sample_obstacles,
    sample_scenario,
)

# sha256 of sample_scenario(cfg, default_rng(123), 32) (agent_pos, adversary_pos, obstacles, targets,
# anchor as little-endian float64), computed with the sampler as it was before obstacle_layout existed
# (and before the start spacing grew to 0.6 m, hence start_min_spacing=0.5).
CLEAR_START_DIGESTS = [
    (
        dict(n_agents=6, mode="formation", obstacle_density=0.05),
        "cb4020120fa7df8bef7eb478b45637d746a15a67e1cbfc0a80d4c11b51e22a7f",
    ),
    (
        dict(n_agents=8, mode="cefc", obstacle_density=0.03),
        "6147806e2f2d03fc1cf57097fc4145082f6889e4489c9edd8075bd4dd0cea706",
    ),
    (
        dict(n_agents=3, mode="formation", obstacle_density=0.0),
        "d28100f98f61bb815043bb9c37fe088eba42cd62392c80ad4c54a277ed7e85f3",
    ),
]


def _digest(scenario: Scenario) -> str:
    h = hashlib.sha256()
    for a in (scenario.agent_pos, scenario.adversary_pos, scenario.obstacles, scenario.targets, scenario.anchor):
        h.update(np.ascontiguousarray(a, dtype="<f8").tobytes())
    return h.hexdigest()


# ---------------------------------------------------------------- the option
def test_layout_option_validated_and_round_trips():
    assert TaskConfig().obstacle_layout == "paper"
    with pytest.raises(ConfigError, match="obstacle_layout='uniform'"):
        TaskConfig(obstacle_layout="uniform")
    cfg = TaskConfig(obstacle_layout="paper", obstacle_density=0.05)
    assert TaskConfig.from_dict(cfg.to_dict()) == cfg
    # configs saved before the field existed load with the old behaviour
    old = cfg.to_dict()
    del old["obstacle_layout"]
    assert TaskConfig.from_dict(old).obstacle_layout == "clear-start"


@pytest.mark.parametrize("kwargs,digest", CLEAR_START_DIGESTS)
def test_clear_start_is_bit_identical_to_the_original_sampler(kwargs, digest):
    explicit = TaskConfig(**kwargs, obstacle_layout="clear-start", start_min_spacing=0.5)
    assert _digest(sample_scenario(explicit, np.random.default_rng(123), 32)) == digest


# ---------------------------------------------------------------- the paper layout
@pytest.mark.parametrize("mode", ["formation", "cefc"])
def test_paper_layout_rejects_only_overlaps(mode):
    cfg = TaskConfig(n_agents=8, mode=mode, obstacle_density=0.05, obstacle_layout="paper")
    sc = sample_scenario(cfg, np.random.default_rng(1), 400)
    obs, k = sc.obstacles, cfg.n_obstacles
    assert obs.shape == (400, k, 2)
    assert np.abs(obs).max() <= cfg.arena_half_size - cfg.obstacle_radius  # wholly inside the arena
    od = np.linalg.norm(obs[:, :, None] - obs[:, None], axis=-1) + np.eye(k) * 99
    assert od.min() >= 2 * cfg.obstacle_radius + cfg.obstacle_min_gap
    to_start = np.linalg.norm(obs[:, :, None] - sc.agent_pos[:, None], axis=-1)
    assert to_start.min() >= cfg.uav_radius + cfg.obstacle_radius + START_DISC_MARGIN
    assert np.linalg.norm(obs - sc.anchor[:, None], axis=-1).min() >= cfg.anchor_clearance
    if mode == "cefc":
        assert np.linalg.norm(obs[:, :, None] - sc.targets[:, None], axis=-1).min() >= cfg.anchor_clearance
    # the start square is no longer kept free: some obstacles stand inside the old keep-out square
    old_keep_out = cfg.start_half_size + cfg.obstacle_radius + cfg.uav_radius
    assert (np.abs(obs).max(-1) <= old_keep_out).any()
    # same draw order as clear-start: starts, targets and anchor come out the same
    ref = sample_scenario(
        TaskConfig(n_agents=8, mode=mode, obstacle_density=0.05, obstacle_layout="clear-start"),
        np.random.default_rng(1),
        400,
    )
    np.testing.assert_array_equal(sc.agent_pos, ref.agent_pos)
    np.testing.assert_array_equal(sc.anchor, ref.anchor)
    np.testing.assert_array_equal(sc.targets, ref.targets)


def test_paper_layout_needs_the_starts():
    cfg = TaskConfig(n_agents=4, mode="formation", obstacle_density=0.05, obstacle_layout="paper")
    with pytest.raises(ConfigError, match="start positions"):
        sample_obstacles(cfg, np.random.default_rng(0), np.zeros((2, 2)), np.zeros((2, 0, 2)))


def test_paper_layout_anchor_redraws_keep_clear_of_obstacles():
    cfg = TaskConfig(
        n_agents=6,
        mode="formation",
        obstacle_density=0.05,
        obstacle_layout="paper",
        anchor_redraw_steps=1,
        episode_steps=20,
    )
    env = BatchedCEFCEnv(cfg, n_envs=32, seed=3)
    env.reset()
    anchors = [env.anchor.copy()]
    for _ in range(19):
        env.step(np.zeros((32, 6, 2)))
        anchors.append(env.anchor.copy())
        assert np.linalg.norm(env.obstacles - env.anchor[:, None], axis=-1).min() >= cfg.anchor_clearance
    assert len({a.tobytes() for a in anchors}) == 20  # it really was redrawn every step


@pytest.mark.timeout(60)
@pytest.mark.parametrize("mode", ["formation", "cefc"])
@pytest.mark.parametrize("density", [0.03, 0.05, 0.28])
def test_paper_layout_samples_without_hanging_for_8_agents(mode, density):
    # 0.28 is about the densest the up-front coverage check accepts (112 obstacles)
    cfg = TaskConfig(n_agents=8, mode=mode, obstacle_density=density, obstacle_layout="paper")
    sc = sample_scenario(cfg, np.random.default_rng(0), 1000 if density <= 0.05 else 100)
    assert np.isfinite(sc.obstacles).all() and sc.obstacles.shape[1] == cfg.n_obstacles


# ---------------------------------------------------------------- how often the path is obstructed
def test_obstacle_near_path_geometry():
    r = 0.4
    sc = Scenario(
        agent_pos=np.array([[[-0.5, 0.0], [0.5, 0.0], [0.0, 0.5]]] * 4),  # start centre (0, 1/6)
        adversary_pos=np.zeros((4, 2)),
        obstacles=np.array([[[2.0, 1 / 6 + 1.4]], [[2.0, 1 / 6 + 1.45]], [[-1.3, 1 / 6]], [[5.0 + 1.35, 1 / 6]]]),
        targets=np.zeros((4, 0, 2)),
        anchor=np.array([[5.0, 1 / 6]] * 4),
    )
    # beside the middle: surface 1.0 m away (in), 1.05 m (out); behind the start: 1.3 - 0.4 = 0.9 (in);
    # past the anchor: 1.35 - 0.4 = 0.95 (in, the segment's end cap counts)
    assert obstacle_near_path(sc, r, 1.0).tolist() == [True, False, True, True]
    assert obstacle_near_path(sc, r, 0.5).tolist() == [False, False, False, False]


# Bands around the measured fractions (docs/research/layouts.md: 5000 layouts, seed 0) wide enough for
# 2000 layouts of another seed (binomial std about 1 point).
@pytest.mark.parametrize(
    "density,clear_band,paper_band",
    [
        (0.05, (0.015, 0.07), (0.19, 0.31)),  # Table III: measured 3.8 % and 24.7 % for c = 6
        (0.03, (0.005, 0.05), (0.11, 0.21)),  # Table VIII / training: measured 2.4 % and 15.7 %
    ],
)
def test_paper_layout_obstructs_the_path_tens_of_percent(density, clear_band, paper_band):
    clear = near_path_fraction(
        TaskConfig(n_agents=6, mode="formation", obstacle_density=density, obstacle_layout="clear-start"), 2000, seed=7
    )
    paper = near_path_fraction(
        TaskConfig(n_agents=6, mode="formation", obstacle_density=density, obstacle_layout="paper"), 2000, seed=7
    )
    assert clear_band[0] <= clear <= clear_band[1], clear
    assert paper_band[0] <= paper <= paper_band[1], paper
    assert paper > 4 * clear


def test_near_path_fraction_rejects_bad_count():
    with pytest.raises(ConfigError, match="n_layouts"):
        near_path_fraction(TaskConfig(), 0)


# ---------------------------------------------------------------- stragglers (a training scenario)
def test_stragglers_start_out_of_sight_and_leave_the_default_stream_alone():
    base = dict(n_agents=5, mode="formation", obstacle_density=0.03)
    plain = sample_scenario(TaskConfig(**base), np.random.default_rng(7), 400)
    none = sample_scenario(TaskConfig(**base, straggler_fraction=0.0), np.random.default_rng(7), 400)
    assert _digest(plain) == _digest(none)  # 0 draws nothing: the paper's starts keep their stream
    cfg = TaskConfig(**base, straggler_fraction=0.5)
    sc = sample_scenario(cfg, np.random.default_rng(7), 400)
    gap = np.linalg.norm(sc.agent_pos[:, -1:] - sc.agent_pos[:, :-1], axis=-1).min(-1)  # [B]
    radius = np.linalg.norm(sc.agent_pos[:, -1], axis=-1)
    moved = (np.abs(sc.agent_pos[:, -1]) > cfg.start_half_size).any(-1)  # outside the start square
    assert 0.4 < moved.mean() < 0.6
    assert (gap[moved] >= cfg.observation_distance).all()
    assert (radius[moved] >= 3.0).all() and (radius[moved] <= 7.0).all()
    assert (np.abs(sc.agent_pos[~moved]) <= cfg.start_half_size).all()  # the others start as before
    # obstacles keep clear of the straggler's start disc too
    clearance = np.linalg.norm(sc.obstacles - sc.agent_pos[:, -1:], axis=-1).min(-1)
    assert clearance.min() >= cfg.obstacle_radius + cfg.uav_radius + START_DISC_MARGIN - 1e-9
    all_moved = sample_scenario(TaskConfig(**base, straggler_fraction=1.0), np.random.default_rng(0), 50)
    assert (np.linalg.norm(all_moved.agent_pos[:, -1:] - all_moved.agent_pos[:, :-1], axis=-1) >= 3.0).all()


@pytest.mark.parametrize("bad", [-0.1, 1.5, float("nan")])
def test_straggler_fraction_is_validated(bad):
    with pytest.raises(ConfigError, match="straggler_fraction"):
        TaskConfig(n_agents=5, mode="formation", straggler_fraction=bad)
