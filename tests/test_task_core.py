"""Task-core functions against hand-computed cases from the paper's formulas."""

import numpy as np
import pytest

from cefc_mj.errors import ConfigError
from cefc_mj.task import rewards as R
from cefc_mj.task.adversary import (
    INTERCEPT_HORIZON,
    STRIKE_LEAD,
    InterceptRule,
    adversary_goal,
)
from cefc_mj.task.config import RewardConfig, TaskConfig
from cefc_mj.task.deviation import sample_deviation
from cefc_mj.task.formation import connected_groups, directed_hausdorff, formation_template, group_formation_error
from cefc_mj.task.lidar import lidar_ranges, lidar_ranges_reference
from cefc_mj.task.observation import build_cefc_observation, build_low_level_observation, cefc_layout, low_level_layout
from cefc_mj.task.scenario import sample_scenario


# ---------------------------------------------------------------- formations
@pytest.mark.parametrize("c", range(3, 16))
def test_template_shape_spacing_and_centre(c):
    t = formation_template(c)
    assert t.shape == (c, 2)
    np.testing.assert_allclose(t.mean(axis=0), 0.0, atol=1e-12)
    d = np.linalg.norm(t[:, None] - t[None], axis=-1) + np.eye(c) * 1e9
    # nearest-neighbour spacing is s = 1 m: the ring has side 1, and for c >= 7 the centre sits at
    # the circumradius (>= 1 m for a hexagon or larger ring)
    assert d.min() == pytest.approx(1.0)


def test_template_c7_is_hexagon_plus_centre():
    t = formation_template(7)
    r = np.linalg.norm(t, axis=-1)
    assert np.sum(r < 1e-9) == 1 and np.allclose(np.sort(r)[1:], 1.0)


def test_template_rejects_c_below_3():
    with pytest.raises(ValueError):
        formation_template(2)


@pytest.mark.parametrize("c", [3, 5, 8])
def test_hausdorff_cases(c):
    t = formation_template(c)
    assert directed_hausdorff(t, t) == 0.0
    shifted = t + np.array([3.0, -2.0])
    assert directed_hausdorff(t, shifted - shifted.mean(0)) == pytest.approx(0.0, abs=1e-12)
    moved = t.copy()
    moved[1] += np.array([0.0, 0.3])  # the moved point is still the nearest to template point 1
    assert directed_hausdorff(t, moved) == pytest.approx(0.3)


def test_hausdorff_is_directed_template_to_points():
    t = np.array([[0.0, 0.0], [1.0, 0.0]])
    points = np.array([[0.0, 0.0], [1.0, 0.0], [5.0, 0.0]])  # an extra far point does not count
    assert directed_hausdorff(t, points) == 0.0
    assert directed_hausdorff(points, t) == 4.0


def test_connected_groups_chain_and_isolated():
    pos = np.array([[[0, 0], [2.5, 0], [5.0, 0], [20, 0], [20, 2.9]]], dtype=float)
    labels = connected_groups(pos, 3.0)
    assert labels.tolist() == [[0, 0, 0, 3, 3]]  # a chain is one group; labels = smallest member


def test_group_formation_error_per_group():
    tri = formation_template(3)
    pos = np.concatenate([tri + [0, 0], tri[:2] + [50, 0]])[None]
    labels = connected_groups(pos, 3.0)
    err, size, centre = group_formation_error(pos, labels)
    assert err[0, 0] == pytest.approx(0.0, abs=1e-12) and size[0, 0] == 3
    np.testing.assert_allclose(centre[0, 3], [50.0 + tri[:2, 0].mean(), tri[:2, 1].mean()])
    assert np.isnan(err[0, 3]) and size[0, 3] == 2  # a pair is not a formation group


# ---------------------------------------------------------------- rewards
def test_collision_reward_three_cases():
    p = RewardConfig()
    d = np.array([[0.1, 0.3, 0.6]])
    cr = R.collision_penalty(d, p)
    np.testing.assert_allclose(cr, [[24 * 0.1 + 3, 8 * 0.2 + 1, 0.0]])


def test_formation_reward_lag():
    r1 = R.formation_reward(np.array([2.0]), np.array([0.0]), 0.3)
    r2 = R.formation_reward(np.array([1.0]), r1, 0.3)
    assert r1[0] == -2.0 and r2[0] == pytest.approx(-1.0 + 0.6)


def test_navigation_rewards():
    pos = np.array([[[1.0, 0.0], [3.0, 0.0]]])
    assert R.anchor_navigation_reward(pos, np.array([[2.0, 4.0]]))[0] == pytest.approx(-4.0)
    targets = np.array([[[1.0, 0.0], [1.0, 3.0]]])
    urgency = np.array([[1.0, 0.5]])
    # agent 0: 0*1 + 3*0.5 ; agent 1: 2*1 + sqrt(13)*0.5
    expected = -(1.5 + 2.0 + 0.5 * np.sqrt(13))
    assert R.target_navigation_reward(pos, targets, urgency)[0] == pytest.approx(expected)


def test_task_reward_and_urgency_decay():
    err = np.array([[0.5, 2.0, np.nan]])
    size = np.array([[4, 3, 0]])
    centre = np.array([[[8.0, 8.0], [8.5, 8.0], [0, 0]]])
    targets = np.array([[[8.0, 8.0], [-8.0, -8.0]]])
    cov = R.target_coverage(err, size, centre, targets, 1.0, 3.0)
    assert cov.tolist() == [[4.0, 0.0]]  # the second group is not in formation
    urgency = np.array([[1.0, 1.0]])
    assert R.task_reward(cov, urgency)[0] == 4.0
    np.testing.assert_allclose(R.update_urgency(urgency, cov, 0.003), [[1 - 0.012, 1.0]])
    assert R.update_urgency(np.array([[0.001]]), np.array([[4.0]]), 0.003)[0, 0] == 0.0


def test_evasion_reward():
    pos = np.array([[[0.0, 0.0], [0.0, 1.5], [0.0, 5.0]]])
    assert R.evasion_reward(pos, np.array([[0.0, 0.5]]), 2.0)[0] == pytest.approx(-(1.5 + 1.0))


def test_adversary_rules():
    pos = np.array([[[0, 0], [1, 0], [0, 1], [10, 10], [10.5, 10], [10, 10.5], [11, 10.5], [5.0, -6]]], dtype=float)
    _, size, centre = group_formation_error(pos, connected_groups(pos, 3.0))
    adv = np.array([[5.0, -5.0]])
    np.testing.assert_allclose(adversary_goal("r_nearest", adv, pos, size, centre)[0], [5, -6])
    np.testing.assert_allclose(adversary_goal("nearest_group", adv, pos, size, centre)[0], pos[0, :3].mean(0))
    np.testing.assert_allclose(adversary_goal("r_largest", adv, pos, size, centre)[0], pos[0, 3:7].mean(0))
    # the strike rule: the lone agent 1 m away is within 3 m, so it is chased instead of the group...
    np.testing.assert_allclose(adversary_goal("nearest_group_strike", adv, pos, size, centre)[0], [5, -6])
    # ... and from 3.2 m away it is not: the nearest group of >= 3 again
    far = np.array([[5.0, -2.8]])
    np.testing.assert_allclose(adversary_goal("nearest_group_strike", far, pos, size, centre)[0], pos[0, :3].mean(0))
    # the member rule is not lured by the lone agent: it chases the group, and strikes at the group's
    # nearest member once one is within 3 m
    labels = connected_groups(pos, 3.0)
    np.testing.assert_allclose(
        adversary_goal("nearest_group_member", adv, pos, size, centre, labels)[0], pos[0, :3].mean(0)
    )
    close = np.array([[1.5, -1.5]])  # 2.1 m from agent 0, 1.6 m from agent 1: the nearest member
    np.testing.assert_allclose(adversary_goal("nearest_group_member", close, pos, size, centre, labels)[0], [1, 0])
    with pytest.raises(ValueError, match="group labels"):
        adversary_goal("nearest_group_member", adv, pos, size, centre)
    # the intercept rule aims ahead: at the group's centre plus its mean velocity times the time the
    # adversary needs to get there (at most INTERCEPT_HORIZON), and at a member within STRIKE_DISTANCE
    # plus STRIKE_LEAD of its velocity; like the member rule it is not lured by the lone agent
    vel = np.zeros_like(pos)
    vel[0, :3] = [0.0, 1.0]  # the nearest group flies north at 1 m/s, the others stand
    vel[0, 7] = [1.0, 0.0]  # the lone UAV flies east
    for at in (adv, np.array([[-3.0, -3.0]])):  # 1 m from the lone UAV; 4.2 m from every UAV
        reach = np.linalg.norm(pos[0, :3].mean(0) - at[0]) / 0.75
        assert reach > INTERCEPT_HORIZON  # the lead is capped
        np.testing.assert_allclose(
            adversary_goal("nearest_group_intercept", at, pos, size, centre, labels, vel, 0.75)[0],
            pos[0, :3].mean(0) + [0.0, INTERCEPT_HORIZON],
        )
    near = np.array([[0.3, 0.2]])  # agent 0 is the nearest member, within reach
    np.testing.assert_allclose(
        adversary_goal("nearest_group_intercept", near, pos, size, centre, labels, vel, 0.75)[0],
        pos[0, 0] + [0.0, STRIKE_LEAD],
    )
    np.testing.assert_allclose(  # standing UAVs: the member rule's goal
        adversary_goal("nearest_group_intercept", close, pos, size, centre, labels, 0 * vel, 0.75)[0], [1, 0]
    )
    with pytest.raises(ValueError, match="velocities"):
        adversary_goal("nearest_group_intercept", adv, pos, size, centre, labels)
    # the variants of the intercept family (InterceptRule; its defaults are the named rule)
    moving = (labels, vel, 0.75)
    for at in (adv, near, close):
        np.testing.assert_array_equal(
            adversary_goal(InterceptRule(), at, pos, size, centre, *moving),
            adversary_goal("nearest_group_intercept", at, pos, size, centre, *moving),
        )
    ahead = InterceptRule(horizon=1.0, strike_lead=0.0)
    np.testing.assert_allclose(adversary_goal(ahead, near, pos, size, centre, *moving)[0], pos[0, 0])
    no_strike = InterceptRule(strike_distance=None)  # the group's centre + its velocity x the time to get there
    reach = np.linalg.norm(pos[0, :3].mean(0) - near[0]) / 0.75
    np.testing.assert_allclose(
        adversary_goal(no_strike, near, pos, size, centre, *moving)[0], pos[0, :3].mean(0) + [0.0, reach]
    )
    # striking at any UAV: the lone one 1 m away lures it (aimed 1.5 s ahead of it); striking at any
    # UAV of a group of >= 3 does not, and the member rule's goal is kept
    any_uav, grouped = InterceptRule(strike_at="any"), InterceptRule(strike_at="grouped")
    np.testing.assert_allclose(adversary_goal(any_uav, adv, pos, size, centre, *moving)[0], [5 + STRIKE_LEAD, -6])
    np.testing.assert_array_equal(
        adversary_goal(grouped, adv, pos, size, centre, *moving),
        adversary_goal("nearest_group_intercept", adv, pos, size, centre, *moving),
    )
    for bad in ({"horizon": -1.0}, {"strike_distance": 0.0}, {"strike_lead": float("nan")}, {"strike_at": "lone"}):
        with pytest.raises(ValueError, match=next(iter(bad))):
            InterceptRule(**bad)
    # no group of 3: the nearest-group rule falls back to the nearest agent
    lone = pos[:, [0, 7]]
    _, size, centre = group_formation_error(lone, connected_groups(lone, 3.0))
    np.testing.assert_allclose(adversary_goal("nearest_group", adv, lone, size, centre)[0], [5, -6])


# ---------------------------------------------------------------- lidar
def test_lidar_matches_analytic_ray_circle():
    # One obstacle of radius 0.4 at (2, 0): the +x beam reads 1.6; a beam at angle a hits at
    # t = 2 cos a - sqrt(0.16 - 4 sin^2 a).
    ranges = lidar_ranges(np.zeros((1, 1, 2)), np.array([[[2.0, 0.0]]]), 0.4, np.zeros((1, 1, 2)), 0.25, 360, 3.0)
    a = np.deg2rad(np.arange(360))
    hit = 0.16 - 4 * np.sin(a) ** 2 >= 0
    hit &= np.cos(a) > 0
    expected = np.where(hit, 2 * np.cos(a) - np.sqrt(np.clip(0.16 - 4 * np.sin(a) ** 2, 0, None)), 3.0)
    np.testing.assert_allclose(ranges[0, 0], expected, atol=1e-12)
    assert ranges[0, 0, 0] == pytest.approx(1.6)


def test_lidar_kernel_matches_reference_and_sees_agents():
    rng = np.random.default_rng(3)
    origins = rng.uniform(-3, 3, (3, 6, 2))
    obstacles = rng.uniform(-4, 4, (3, 10, 2))
    for see in (True, False):
        fast = lidar_ranges(origins, obstacles, 0.4, origins, 0.25, 24, 3.0, see)
        slow = lidar_ranges_reference(origins, obstacles, 0.4, origins, 0.25, 24, 3.0, see)
        np.testing.assert_allclose(fast, slow, atol=1e-12)
    two = np.array([[[0.0, 0.0], [1.0, 0.0]]])
    r = lidar_ranges(two, np.zeros((1, 0, 2)), 0.4, two, 0.25, 4, 3.0, True)
    assert r[0, 0, 0] == pytest.approx(0.75) and r[0, 1, 2] == pytest.approx(0.75)
    assert r[0, 0, 1] == 3.0  # never its own disc


def test_lidar_origin_inside_obstacle_reads_zero():
    r = lidar_ranges(np.zeros((1, 1, 2)), np.array([[[0.1, 0.0]]]), 0.4, np.zeros((1, 1, 2)), 0.25, 8, 3.0)
    assert (r == 0).all()


# ---------------------------------------------------------------- observation
@pytest.mark.parametrize("n", range(3, 16))
def test_observation_shapes_finite(n):
    cfg = TaskConfig(n_agents=n, obstacle_density=0.03)
    rng = np.random.default_rng(n)
    sc = sample_scenario(cfg, rng, 2)
    lidar = np.full((2, n, 24), 3.0)
    vel = rng.normal(size=(2, n, 2))
    obs = build_cefc_observation(
        cfg, sc.agent_pos, vel, sc.targets, np.ones((2, 2)), sc.adversary_pos, np.zeros((2, 2)), lidar
    )
    assert obs.shape == (2, n, cefc_layout(cfg).size) and np.isfinite(obs).all()
    low_cfg = TaskConfig(n_agents=n, mode="formation")
    low = build_low_level_observation(low_cfg, sc.agent_pos, vel, sc.anchor, lidar)
    assert low.shape == (2, n, low_level_layout(low_cfg).size) and np.isfinite(low).all()


def test_paper_observation_is_38_numbers_for_8_agents():
    layout = cefc_layout(TaskConfig(n_agents=8))
    assert layout["neighbours"].stop == 38
    assert low_level_layout(TaskConfig(n_agents=8, mode="formation")).size == 63


def test_neighbours_sorted_masked_and_padded():
    cfg = TaskConfig(n_agents=4, mode="formation")
    pos = np.array([[[0, 0], [2.0, 0], [0, 1.0], [0, 10.0]]])
    vel = np.zeros((1, 4, 2))
    vel[0, 2] = [0.5, 0.0]
    obs = build_low_level_observation(cfg, pos, vel, np.zeros((1, 2)), np.full((1, 4, 24), 3.0))
    lay = low_level_layout(cfg)
    neigh = obs[0, 0, lay["neighbours"]].reshape(-1, 4)
    mask = obs[0, 0, lay["neighbour_mask"]]
    np.testing.assert_allclose(neigh[0], [0, 1, 0.5, 0])  # nearest first, relative velocity
    np.testing.assert_allclose(neigh[1], [2, 0, 0, 0])
    assert mask.tolist() == [1, 1, 0, 0, 0, 0, 0] and (neigh[2:] == 0).all()  # far agent and padding


# ---------------------------------------------------------------- scenario
def test_scenario_constraints():
    # the "clear-start" sampler; the paper layout's own rules: tests/test_scenario_layouts.py
    cfg = TaskConfig(n_agents=8, obstacle_density=0.05, obstacle_layout="clear-start")
    sc = sample_scenario(cfg, np.random.default_rng(0), 16)
    assert sc.obstacles.shape == (16, 20, 2) and sc.targets.shape == (16, 2, 2)
    starts = sc.agent_pos
    d = np.linalg.norm(starts[:, :, None] - starts[:, None], axis=-1) + np.eye(8) * 9
    assert d.min() >= 0.5 and np.abs(starts).max() <= 2.0
    assert (np.abs(sc.obstacles).max(-1) > 2.0 + 0.4 + 0.25).all()
    od = np.linalg.norm(sc.obstacles[:, :, None] - sc.obstacles[:, None], axis=-1) + np.eye(20) * 9
    assert od.min() >= 0.8 + 0.5
    assert (np.linalg.norm(sc.obstacles - sc.anchor[:, None], axis=-1) >= 2.0).all()
    assert (np.abs(sc.targets) == 8).all() and (sc.targets[:, 0] != sc.targets[:, 1]).any(-1).all()


def test_scenario_too_dense_fails_fast():
    with pytest.raises(ConfigError, match="obstacle_density"):
        TaskConfig(obstacle_density=0.5)
    # passes the up-front coverage check, but the anchor's clearance leaves no room: bounded retries
    cfg = TaskConfig(obstacle_density=0.2, anchor_clearance=12.0)
    with pytest.raises(ConfigError, match="obstacle_density"):
        sample_scenario(cfg, np.random.default_rng(0), 2)


def test_deviation_distribution():
    rng = np.random.default_rng(0)
    delta = sample_deviation(rng, 0.8, (2000, 10))
    mag = np.linalg.norm(delta, axis=-1).ravel()
    assert mag.mean() == pytest.approx(0.8, rel=0.02) and mag.std() == pytest.approx(0.2, rel=0.05)
    angle = np.arctan2(delta[..., 1], delta[..., 0]).ravel()
    hist, _ = np.histogram(angle, bins=8, range=(-np.pi, np.pi))
    assert hist.min() > 0.9 * hist.mean()
    assert (sample_deviation(rng, 0.0, (3, 4)) == 0).all()


# ---------------------------------------------------------------- compiled kernels vs references
def test_kernels_match_numpy_references():
    from reference_impl import (
        connected_groups_reference,
        group_formation_error_reference,
        low_level_observation_reference,
        neighbour_features_reference,
    )

    from cefc_mj.task.observation import neighbour_features

    rng = np.random.default_rng(5)
    for n in (3, 5, 8, 12):
        pos = rng.uniform(-4, 4, (20, n, 2))
        vel = rng.normal(size=(20, n, 2))
        labels = connected_groups(pos, 3.0)
        np.testing.assert_array_equal(labels, connected_groups_reference(pos, 3.0))
        for lab in (labels, np.zeros_like(labels)):
            err, size, centre = group_formation_error(pos, lab)
            ref_err, ref_size = group_formation_error_reference(pos, lab)
            np.testing.assert_allclose(err, ref_err, atol=1e-12)
            np.testing.assert_array_equal(size, ref_size)
        for slots in (n - 1, n + 3):
            f, m = neighbour_features(pos, vel, slots, 3.0)
            rf, rm = neighbour_features_reference(pos, vel, slots, 3.0)
            np.testing.assert_allclose(f, rf, atol=1e-12)
            np.testing.assert_array_equal(m, rm)
        # the whole observation, bit for bit, with one anchor per env and one per agent
        cfg = TaskConfig(n_agents=n)
        lidar = rng.uniform(0.0, 3.0, (20, n, cfg.n_lidar_rays))
        for anchor in (rng.uniform(-5, 5, (20, 2)), rng.uniform(-5, 5, (20, n, 2))):
            obs = build_low_level_observation(cfg, pos, vel, anchor, lidar)
            ref = low_level_observation_reference(
                pos, vel, anchor, lidar, cfg.neighbour_slots, cfg.observation_distance
            )
            assert obs.dtype == np.float32 and obs.tobytes() == ref.tobytes()


@pytest.mark.parametrize("backend", ["particle", "mujoco"])
def test_rule_adversary_goes_around_obstacles_when_asked(backend):
    """An obstacle right on the line to the adversary's goal: the default rule flies through it,
    the avoiding one keeps uav_radius + obstacle_radius from its centre and still gets there."""
    from cefc_mj import make_world
    from cefc_mj.env import BatchedCEFCEnv

    def fly(avoid: bool) -> tuple[float, float]:
        task = TaskConfig(
            n_agents=3,
            mode="cefc",
            obstacle_density=1 / 400,
            adversary="r_nearest",  # one obstacle
            adversary_avoids_obstacles=avoid,
            episode_steps=200,
        )
        env = BatchedCEFCEnv(task, n_envs=1, seed=0, world=make_world(backend, task, 1, seed=0))
        env.reset()
        w = env.world
        agents = np.array([[[0.0, -6.0], [0.5, -6.0], [0.0, -6.5]]])
        adversary = np.array([[0.05, 2.0]])  # the obstacle at the origin lies on its way to the agents
        env.obstacles[:] = 0.0
        w.reset(np.ones(1, bool), agents, adversary, env.obstacles)
        closest = np.inf
        for _ in range(140):
            env.step(np.zeros((1, 3, 2)))  # the agents hover; the adversary chases the nearest one
            closest = min(closest, float(np.linalg.norm(w.adversary_pos[0])))
        return closest, float(np.linalg.norm(w.adversary_pos[0] - w.agent_pos[0, 0]))

    keep_out = 0.4 + 0.25
    straight_closest, _ = fly(False)
    around_closest, final_gap = fly(True)
    assert straight_closest < 0.2
    assert around_closest >= keep_out - 0.05 and final_gap < 1.0
    with pytest.raises(ConfigError, match="adversary_avoids_obstacles"):
        TaskConfig(adversary_avoids_obstacles="yes")
