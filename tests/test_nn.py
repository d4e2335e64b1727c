"""AT-M network, student, policy files and the evaluators' loading API."""

import numpy as np
import pytest
import torch

from cefc_mj.errors import CheckpointError, ConfigError
from cefc_mj.nn import ATMActor, ATMConfig, Critic, load_actor, load_policy, merge_step3, save_policy
from cefc_mj.nn.atm import FORMATION_PARTS
from cefc_mj.nn.policy_io import POLICY_FORMAT
from cefc_mj.task.config import TaskConfig
from cefc_mj.task.observation import low_level_layout

TASK = TaskConfig(n_agents=6, mode="formation")
LAYOUT = low_level_layout(TASK)


def random_obs(b=4, n=6, seed=0, free_lidar=False):
    g = torch.Generator().manual_seed(seed)
    obs = torch.randn(b, n, LAYOUT.size, generator=g)
    obs[..., LAYOUT["lidar"]] = 3.0 if free_lidar else torch.rand(b, n, 24, generator=g) * 3.0
    return obs


def test_shapes_and_input_routing():
    actor = ATMActor(ATMConfig.from_task(TASK))
    assert actor.cfg.obs_dim == 63
    assert actor(random_obs()).shape == (4, 6, 2)
    assert actor.formation[0].in_features == 39  # anchor 2 + own velocity 2 + neighbours 28 + mask 7
    assert actor.obstacle[0].in_features == 24
    assert len([m for m in actor.formation if isinstance(m, torch.nn.Linear)]) == 3
    assert len([m for m in actor.output if isinstance(m, torch.nn.Linear)]) == 3
    student = ATMActor(ATMConfig.from_task(TASK, hidden=256))
    assert student.formation[0].out_features == 256 and student(random_obs()).shape == (4, 6, 2)
    critic = Critic(100)
    assert critic(torch.zeros(5, 7, 100)).shape == (5, 7)


def test_obstacle_module_is_silent_in_free_space_and_only_it_reads_lidar():
    torch.manual_seed(0)
    actor = ATMActor(ATMConfig.from_task(TASK))
    torch.nn.init.normal_(actor.output[-1].weight)  # make the output sensitive
    free, seen = random_obs(free_lidar=True), random_obs(free_lidar=False)
    before_free, before_seen = actor(free).detach(), actor(seen).detach()
    with torch.no_grad():
        for p in actor.obstacle.parameters():
            p.add_(torch.randn_like(p))
    # F_a(d_free) - F_a(d_free) = 0 up to float rounding; with obstacles in sight the output moves.
    assert (actor(free) - before_free).abs().max() < 1e-4
    assert (actor(seen) - before_seen).abs().max() > 1e-2
    # The formation module reads only its parts: changing the LiDAR of `free` obs changes nothing else.
    f_in = free.index_select(-1, actor.formation_index)
    parts = torch.cat([free[..., LAYOUT[p]] for p in FORMATION_PARTS], dim=-1)
    assert torch.equal(f_in, parts)


def test_safe_transform_shortens_only_beams_that_see_something():
    actor = ATMActor(ATMConfig.from_task(TASK, safe=True))
    obs = torch.zeros(1, 1, 63)
    obs[..., LAYOUT["lidar"]] = torch.tensor([3.0, 1.0, 0.1] + [3.0] * 21)
    d = actor.lidar_input(obs)[0, 0]
    assert d[:3].tolist() == pytest.approx([3.0, 0.8, -0.1])
    plain = ATMActor(ATMConfig.from_task(TASK))
    assert torch.equal(plain.lidar_input(obs), obs[..., LAYOUT["lidar"]])


def test_velocity_head_tracks_the_commanded_velocity():
    actor = ATMActor(ATMConfig.from_task(TASK, action="velocity", velocity_gain=5.0))
    obs = torch.zeros(1, 2, 63)
    obs[0, :, LAYOUT["own_velocity"]] = torch.tensor([[0.5, 0.0], [0.0, 0.0]])
    command = torch.tensor([[[0.6, -0.2], [1.0, 0.0]]])
    accel = actor.to_acceleration(command, obs)
    assert accel[0, 0].tolist() == pytest.approx([0.5, -1.0])  # 5 * (v* - v)
    assert accel[0, 1].tolist() == pytest.approx([2.0, 0.0])  # clipped to accel_max
    raw = ATMActor(ATMConfig.from_task(TASK, action="acceleration"))
    assert raw.to_acceleration(command * 3, obs)[0, 1].tolist() == pytest.approx([2.0, 0.0])


def test_merge_step3_takes_modules_from_the_right_parents():
    torch.manual_seed(1)
    s1, s2 = ATMActor(ATMConfig.from_task(TASK)), ATMActor(ATMConfig.from_task(TASK))
    merged = merge_step3(s1, s2)
    for name, p in merged.state_dict().items():
        source = s2 if name.startswith("obstacle.") else s1
        assert torch.equal(p, source.state_dict()[name]), name
    # In free space the merged policy acts exactly like Step 1.
    assert torch.allclose(merged(random_obs(free_lidar=True)), s1(random_obs(free_lidar=True)))


def test_policy_file_round_trip_and_name_resolution(tmp_path):
    torch.manual_seed(2)
    actor = ATMActor(ATMConfig.from_task(TASK, safe=True))
    save_policy(actor, tmp_path / "atm_c6_safe.pt", meta={"formation": 6})
    policy = load_policy("atm_c6_safe", policies_dir=tmp_path)
    assert policy.name == "atm_c6_safe" and policy.safe and policy.meta == {"formation": 6}
    obs = random_obs().numpy()
    actions = policy.act(obs)
    assert actions.shape == (4, 6, 2) and np.abs(actions).max() <= 2.0
    with torch.no_grad():
        expected = actor.to_acceleration(actor(torch.from_numpy(obs)), torch.from_numpy(obs)).numpy()
    np.testing.assert_allclose(actions, expected, atol=1e-6)
    np.testing.assert_array_equal(policy.act(obs), actions)  # deterministic
    with pytest.raises(ConfigError, match="obs"):
        policy.act(obs[..., :10])
    with pytest.raises(CheckpointError, match="no policy"):
        load_policy("atm_c9_step3", policies_dir=tmp_path)
    # a bare name is looked up in the policies folder; a missing path is never replaced by a policy
    # of the same file name there
    assert load_policy("atm_c6_safe", policies_dir=tmp_path).name == "atm_c6_safe"
    with pytest.raises(CheckpointError, match="no policy file 'elsewhere/atm_c6_safe.pt'"):
        load_policy("elsewhere/atm_c6_safe.pt", policies_dir=tmp_path)


class Evil:
    """A pickled object of a non-allowlisted class: weights_only refuses to build it."""


def test_bad_files_raise_one_line_checkpoint_errors(tmp_path):
    actor = ATMActor(ATMConfig.from_task(TASK))
    good = save_policy(actor, tmp_path / "good.pt")

    payload = torch.load(good, weights_only=True)
    payload["state_dict"]["output.4.bias"] += 1.0  # edit a weight, keep the stored digest
    torch.save(payload, tmp_path / "edited.pt")
    payload = torch.load(good, weights_only=True)
    payload["net"]["hidden"] = 64  # describe another shape than the weights have
    torch.save(payload, tmp_path / "reshaped.pt")
    (tmp_path / "garbage.pt").write_bytes(b"not a checkpoint at all")
    (tmp_path / "truncated.pt").write_bytes(good.read_bytes()[:500])
    torch.save({"format": "something-else"}, tmp_path / "foreign.pt")

    torch.save({"format": POLICY_FORMAT, "obj": Evil()}, tmp_path / "evil.pt")
    for name, pattern in (
        ("edited", "SHA-256"),
        ("reshaped", "do not fit"),
        ("garbage", "not a readable"),
        ("truncated", "not a readable"),
        ("foreign", "not an AT-M policy"),
        ("evil", "not a readable"),
        ("missing", "no such"),
    ):
        with pytest.raises(CheckpointError, match=pattern) as err:
            load_actor(tmp_path / f"{name}.pt")
        assert "\n" not in str(err.value), name
    with pytest.raises(CheckpointError, match="size 63"):
        load_actor(good, obs_dim=70)


@pytest.mark.parametrize("name", ["atm_c6_step3", "atm_c8_safe", "atm_student"])
def test_loading_skips_init_and_acts_bit_for_bit_like_a_fully_built_actor(name):
    """load_policy builds the network without its (orthogonal) initialisers; the loaded policy must
    act exactly like the network built and initialised the ordinary way, then given the same weights."""
    from cefc_mj.nn.policy_io import resolve_policy_path, safe_torch_load

    rng_before = torch.get_rng_state()
    policy = load_policy(name)
    assert torch.equal(torch.get_rng_state(), rng_before)  # no initialiser drew a random number
    assert not any(t.is_meta for t in [*policy.actor.parameters(), *policy.actor.buffers()])
    payload = safe_torch_load(resolve_policy_path(name))
    reference = ATMActor(ATMConfig.from_dict(payload["net"]))  # ordinary construction, init included
    reference.load_state_dict(payload["state_dict"])
    reference.eval()
    for key, value in reference.state_dict().items():
        assert torch.equal(policy.actor.state_dict()[key], value), key
    obs = random_obs(b=8, n=6, seed=5)
    obs[..., LAYOUT["lidar"]] = torch.where(obs[..., LAYOUT["lidar"]] > 2.0, 3.0, obs[..., LAYOUT["lidar"]])
    for batch in (obs, obs[0]):  # [B, N, D] and one env's [N, D]
        expected = reference.deterministic_actions(batch.numpy()).astype(np.float64)
        actions = policy.act(batch.numpy())
        assert actions.dtype == np.float64 and np.array_equal(actions, expected)
        with torch.no_grad():  # and the torch forward, to float32 rounding
            np.testing.assert_allclose(actions, reference.to_acceleration(reference(batch), batch).numpy(), atol=2e-5)
