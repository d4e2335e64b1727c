"""The evaluation-loop speed-ups change no number: compiled LiDAR, cached free-space pass, policy path.

- the compiled LiDAR (cefc_mj.sim.raycast: mju_rayGeom on the geoms near each drone) equals the
  per-drone `mj_multiRay` path bit for bit, on random layouts with tilted, displaced drones, UAV-UAV
  beams and origins inside obstacles or other UAVs;
- ATMActor caches F_a(d_free) only without gradients, and recomputes it after a weight update;
- `ATMActor.deterministic_actions` (what run_episode calls, the compiled kernel of
  cefc_mj.nn.inference) is `Policy.act`, agrees with the torch forward to float32 rounding, follows
  weight updates, and gives a row the same bits whatever batch it is in;
- the kernel does exactly the arithmetic it documents: a numpy float32 reference that multiplies
  and adds in input order gives the same bits (so no fused multiply-add, no reordering: the same
  actions on every CPU);
- a 300-step c = 8 Table VIII episode flies the same trajectory, bit for bit, with the compiled
  LiDAR and with per-drone mj_multiRay.
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


TORCH_TOLERANCE = 2e-5  # m/s^2: the kernel against torch's forward (float32 sums in another order, tanh within 4e-7)


def before_actions(policy):
    """The torch forward: module calls, F_a(d_free) recomputed (as Policy.act was before the kernel)."""
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
    world = MujocoWorld(
        MujocoWorldConfig(),
        n_envs=2,
        n_agents=8,
        n_obstacles=12,
        seed=0,
        with_adversary=True,
        lidar_sees_agents=sees_agents,
    )
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
        np.testing.assert_allclose(changed, before_actions(policy)(obs), rtol=0, atol=TORCH_TOLERANCE)
        actor.load_state_dict(state, assign=True)  # new parameter objects
        assert np.array_equal(actor.deterministic_actions(obs), first)
        with torch.no_grad():
            actor.formation[0].weight.data = actor.formation[0].weight.data * 0.5  # new storage, same parameter
        halved = actor.deterministic_actions(obs)
        assert not np.array_equal(halved, first)
        np.testing.assert_allclose(halved, before_actions(policy)(obs), rtol=0, atol=TORCH_TOLERANCE)
    finally:
        actor.load_state_dict(state)


@pytest.mark.parametrize("choice, formation", [("atm", 5), ("atm", 8), ("safe", 8), ("student", 8)])
def test_deterministic_actions_are_policy_act_batch_invariant_and_close_to_torch(choice, formation):
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
        np.testing.assert_allclose(actions, before(obs), rtol=0, atol=TORCH_TOLERANCE)
        assert np.array_equal(actions.astype(np.float64), policy.act(obs))
        rows = obs.reshape(-1, policy.obs_dim)  # one row at a time (a SITL-M agent) = the whole batch
        alone = np.concatenate([policy.actor.deterministic_actions(rows[i : i + 1]) for i in range(len(rows))])
        assert np.array_equal(alone, actions.reshape(-1, 2))


def _reference_actions(actor, obs: np.ndarray) -> np.ndarray:
    """The kernel's documented arithmetic in numpy float32, one operation at a time: each output
    b_j + x_0 w_0j + x_1 w_1j + ... (a multiply, then an add, in input order), the rational tanh."""
    from cefc_mj.nn import inference as k

    f32 = np.float32

    def tanh(x):
        x = np.clip(x, -k._TANH_CLAMP, k._TANH_CLAMP)
        x2 = x * x
        p = x2 * k._A13 + k._A11
        for c in (k._A9, k._A7, k._A5, k._A3, k._A1):
            p = x2 * p + c
        q = x2 * k._B6 + k._B4
        for c in (k._B2, k._B0):
            q = x2 * q + c
        return np.where(np.abs(x) < k._TANH_TINY, x, x * p / q)

    def mlp(x, seq, tanh_last):
        linears = [m for m in seq if isinstance(m, torch.nn.Linear)]
        for n, m in enumerate(linears):
            w, b = m.weight.detach().numpy().T.astype(f32), m.bias.detach().numpy().astype(f32)
            out = np.broadcast_to(b, (len(x), len(b))).copy()
            for i in range(w.shape[0]):
                out = out + x[:, i : i + 1] * w[i]
            x = tanh(out) if n < len(linears) - 1 or tanh_last else out
        return x

    cfg = actor.cfg
    obs = obs.astype(f32)
    d = obs[:, actor.lidar_slice]
    if cfg.safe:
        d = np.where(d < f32(cfg.lidar_range - 1e-6), d - f32(cfg.safe_margin), d)
    free = mlp(np.full((1, d.shape[1]), cfg.lidar_range, f32), actor.obstacle, True)
    f = mlp(obs[:, actor.formation_index.numpy()], actor.formation, True)
    head = mlp(f + (mlp(d, actor.obstacle, True) - free), actor.output, False)
    if cfg.action == "velocity":
        head = f32(cfg.velocity_gain) * (head - obs[:, actor.velocity_slice])
    return np.clip(head, -f32(cfg.accel_max), f32(cfg.accel_max))


@pytest.mark.parametrize("choice", ["atm", "safe", "student"])
def test_kernel_does_exactly_the_documented_arithmetic(choice):
    policy = load_policy_for(choice, 8)
    obs = np.random.default_rng(11).uniform(-1.0, 3.0, (9, policy.obs_dim)).astype(np.float32)
    obs[0, policy.actor.lidar_slice] = policy.actor.cfg.lidar_range
    assert np.array_equal(policy.actor.deterministic_actions(obs), _reference_actions(policy.actor, obs))


def test_tanh32_is_within_4e7_of_tanh():
    from cefc_mj.nn.inference import tanh32

    x = np.concatenate([np.linspace(-10.0, 10.0, 20001), [0.0, 1e-30, -3e-4, 5e-4]]).astype(np.float32)
    got = np.array([tanh32(v) for v in x], dtype=np.float64)
    assert np.abs(got - np.tanh(x.astype(np.float64))).max() < 4e-7


def test_table8_episode_is_bit_identical_with_either_lidar():
    """300 decision steps, c = 8: drone positions after every step, compiled LiDAR vs per-drone mj_multiRay."""
    spec = EpisodeSpec(formation=8, seed=0, steps=300, guard=False)  # the policy alone, as flown by hand below
    config = spec.task_config()
    policy = load_policy_for("atm", 8)
    torch.set_num_threads(1)
    trajectories = []
    for variant in ("now", "before"):
        world = make_world("mujoco", config, seed=spec.seed)
        world._lidar_compiled = variant == "now"
        env = BatchedCEFCEnv(config, n_envs=1, seed=spec.seed, world=world)
        act = policy.actor.deterministic_actions
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
