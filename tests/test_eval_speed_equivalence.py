"""The evaluation-loop speed-ups change no number: compiled LiDAR, cached free-space pass, policy path.

- the compiled LiDAR (cefc_mj.sim.raycast: mju_rayGeom on the geoms near each drone) equals the
  per-drone `mj_multiRay` path bit for bit, on random layouts with tilted, displaced drones, UAV-UAV
  beams and origins inside obstacles or other UAVs;
- ATMActor caches F_a(d_free) only without gradients, and recomputes it after a weight update;
- `ATMActor.deterministic_actions` (what run_episode calls) equals `Policy.act` and the forward as
  it was before (nn.Module calls, F_a(d_free) recomputed) bit for bit;
- a 300-step c = 8 Table VIII episode flies the same trajectory, bit for bit, with the new loop and
  with the loop as it was before.
"""

from __future__ import annotations

import mujoco
import numpy as np
import pytest
import torch

from cefc_mj import make_world
from cefc_mj.env import BatchedCEFCEnv
from cefc_mj.eval.runner import EpisodeSpec, load_policy_for, run_episode
from cefc_mj.sim.mujoco_world import MujocoWorld, MujocoWorldConfig
from cefc_mj.sim.raycast import MJU_RAY_GEOM

pytestmark = pytest.mark.skipif(MJU_RAY_GEOM is None, reason="mju_rayGeom not found in the MuJoCo library")


def before_actions(policy):
    """The policy path before the speed-ups: module calls, F_a(d_free) recomputed (as Policy.act was)."""
    a = policy.actor

    def act(obs):
        with torch.no_grad():
            obs_t = torch.as_tensor(obs, dtype=torch.float32)
            f = a.formation(obs_t.index_select(-1, a.formation_index))
            mean = a.output(f + (a.obstacle(a.lidar_input(obs_t)) - a.obstacle(a.free_lidar)))
            return a.to_acceleration(mean, obs_t).numpy()

    return act


@pytest.mark.parametrize("sees_agents", [True, False])
def test_compiled_lidar_equals_mj_multiray_bit_for_bit(sees_agents):
    rng = np.random.default_rng(7)
    world = MujocoWorld(MujocoWorldConfig(), n_envs=2, n_agents=8, n_obstacles=12, seed=0, with_adversary=True,
                        lidar_sees_agents=sees_agents)
    assert world._lidar_compiled
    hits = uav_hits = inside = 0
    for _ in range(12):
        agents = rng.uniform(-2.5, 2.5, (2, 8, 2))
        world.reset(np.ones(2, bool), agents, rng.uniform(-2, 2, (2, 2)), rng.uniform(-6, 6, (2, 12, 2)))
        for qpos, *_ in world._views:  # off the flight altitude and tilted: the footprints are not circles at z = 2
            qpos[:, 2] += rng.uniform(-0.08, 0.08, len(qpos))
            q = rng.normal(size=(len(qpos), 4))
            q[:, 0] += 4.0
            qpos[:, 3:] = q / np.linalg.norm(q, axis=1, keepdims=True)
        for model, data in zip(world.models, world.datas):
            mujoco.mj_forward(model, data)
        origins = world.agent_pos + rng.normal(0.0, 0.5, (2, 8, 2))  # perceived positions, some inside things
        world._lidar_compiled = True
        compiled = world.lidar(origins)
        world._lidar_compiled = False
        reference = world.lidar(origins)
        assert np.array_equal(compiled, reference)
        hits += int((reference < world.lidar_range).sum())
        inside += int((reference == 0).all(-1).sum())
        if sees_agents:  # beams that hit a UAV: they read longer when the footprints are hidden
            world._ray_group[2] = 0
            blind = world.lidar(origins)
            world._ray_group[2] = 1
            uav_hits += int((blind > reference).sum())
    assert hits > 500 and inside > 0
    assert uav_hits > 50 or not sees_agents


def test_free_space_pass_is_cached_only_without_gradients():
    policy = load_policy_for("atm", 8)
    actor = policy.actor
    with torch.no_grad():
        fresh = actor.obstacle(actor.free_lidar)
        assert torch.equal(actor.free_features(), fresh)
        assert actor.free_features() is actor.free_features()  # computed once
    with torch.enable_grad():  # training: computed afresh, with gradients to the obstacle module
        assert actor.free_features().requires_grad
    layer = actor.obstacle[0]
    with torch.no_grad():
        layer.bias.add_(0.01)  # an optimizer step: in place
        try:
            assert torch.equal(actor.free_features(), actor.obstacle(actor.free_lidar))
            assert not torch.equal(actor.free_features(), fresh)
        finally:
            layer.bias.sub_(0.01)


def test_deterministic_actions_follow_weight_updates_and_replacements():
    policy = load_policy_for("atm", 8)
    actor = policy.actor
    obs = np.random.default_rng(3).uniform(-1.0, 3.0, (1, 8, policy.obs_dim)).astype(np.float32)
    first = actor.deterministic_actions(obs)
    state = {k: v.clone() for k, v in actor.state_dict().items()}
    try:
        with torch.no_grad():  # in place, as an optimizer step: the obstacle module and the output layer
            actor.obstacle[2].weight.mul_(1.5)
            actor.output[4].bias.add_(0.3)
        changed = actor.deterministic_actions(obs)
        assert not np.array_equal(changed, first)
        assert np.array_equal(changed, before_actions(policy)(obs))
        actor.load_state_dict(state, assign=True)  # new parameter objects
        assert np.array_equal(actor.deterministic_actions(obs), first)
        with torch.no_grad():
            actor.formation[0].weight.data = actor.formation[0].weight.data * 0.5  # new storage, same parameter
        assert np.array_equal(actor.deterministic_actions(obs), before_actions(policy)(obs))
    finally:
        actor.load_state_dict(state)


@pytest.mark.parametrize("choice, formation", [("atm", 5), ("atm", 8), ("safe", 8), ("student", 8)])
def test_deterministic_actions_equal_policy_act_bit_for_bit(choice, formation):
    policy = load_policy_for(choice, formation)
    before = before_actions(policy)
    rng = np.random.default_rng(formation)
    lidar = policy.actor.lidar_slice
    for shape in ((1, formation), (3, formation), (formation,)):
        obs = rng.uniform(-1.0, 3.0, shape + (policy.obs_dim,)).astype(np.float32)
        free = rng.uniform(size=shape) < 0.5
        obs[..., lidar][free] = policy.actor.cfg.lidar_range  # rows that see nothing
        actions = policy.actor.deterministic_actions(obs)
        assert actions.dtype == np.float32
        assert np.array_equal(actions, before(obs))
        assert np.array_equal(actions.astype(np.float64), policy.act(obs))


def test_table8_episode_is_bit_identical_to_the_loop_before():
    """300 decision steps, c = 8: drone positions after every step, new loop vs the loop before."""
    spec = EpisodeSpec(formation=8, seed=0, steps=300)
    config = spec.task_config()
    policy = load_policy_for("atm", 8)
    torch.set_num_threads(1)
    trajectories = []
    for variant in ("now", "before"):
        world = make_world("mujoco", config, seed=spec.seed)
        world._lidar_compiled = variant == "now"
        env = BatchedCEFCEnv(config, n_envs=1, seed=spec.seed, world=world)
        act = policy.actor.deterministic_actions if variant == "now" else before_actions(policy)
        obs = env.reset()
        positions = []
        for _ in range(spec.steps):
            obs, _, _, info = env.step(act(obs))
            positions.append(world.drone_positions[0].copy())
        trajectories.append((np.array(positions), {k: float(v[0]) for k, v in env.episode_metrics().items()}))
    (now, metrics_now), (before, metrics_before) = trajectories
    assert np.array_equal(now, before)
    assert metrics_now == metrics_before
    result = run_episode(spec, policy=policy)  # the user path flies the same episode
    assert (result.F, result.N, result.C) == (metrics_now["F"], metrics_now["N"], metrics_now["C"])
