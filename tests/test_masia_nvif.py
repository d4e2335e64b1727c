"""The MASIA and NVIF baselines (cefc_mj/nn/obs_comm.py, `--variant masia|nvif`; docs/research/baselines.md).

What they send (the paper's Table IV sizes, the sender's raw local observation), that the PPO loss
never reaches their modules, that their supervised losses learn, and that their policy files train,
load, round-trip and decide on the deployed path with messages of 38 and 102 numbers, over the
SITL-M wire too. Real torch and particle worlds; tiny runs (2 envs, 5 decisions per episode).
"""

import json

import numpy as np
import pytest
import torch

from cefc_mj.cli.train import main
from cefc_mj.deploy import wire
from cefc_mj.errors import ConfigError
from cefc_mj.hierarchy import AgentHierarchy, HierarchicalCEFCEnv, load_low_level
from cefc_mj.nn.consmac import ConsMAC, ConsMACConfig
from cefc_mj.nn.highlevel_policy import VARIANTS, HighLevelPolicy, load_highlevel_policy, save_highlevel_policy
from cefc_mj.nn.obs_comm import ObservationComm, build_comm
from cefc_mj.task.config import TaskConfig
from cefc_mj.task.messages import Inbox
from cefc_mj.task.observation import cefc_layout
from cefc_mj.train.config import Budget, PPOConfig
from cefc_mj.train.highlevel_config import HighLevelConfig
from cefc_mj.train.highlevel_trainer import HighLevelTrainer

TASK = TaskConfig(n_agents=8, mode="cefc", obstacle_density=0.03)
TABLE_IV = {"mappo": 0, "tarmac": 64, "masia": 38, "nvif": 102, "consmac-a": 64, "consmac-o": 64}
"""The paper's Table IV, numbers each agent sends per decision (MAPPO sends nothing)."""
BASELINES = ("masia", "nvif")

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def tiny_config(variant: str, **overrides) -> HighLevelConfig:
    ppo = PPOConfig(n_envs=2, epochs=2, minibatches=2, lr=1e-4, entropy_coef=0.01, update_threads=1)
    settings = dict(
        budget=Budget(iterations=2),
        variant=variant,
        episode_steps=50,
        consmac_steps=3,
        consmac_batch=32,
        ppo=ppo,
        eval_episodes=0,
    )
    settings.update(overrides)
    return HighLevelConfig(**settings)


def trainer_and_rollout(cfg: HighLevelConfig):
    task = cfg.task()
    trainer = HighLevelTrainer(cfg, (load_low_level("navigation", task), load_low_level(cfg.low_level, task)))
    env = HierarchicalCEFCEnv(task, trainer.low_levels[0], n_envs=2, seed=0, adversary_policy=trainer.adversary_policy)
    return trainer, trainer.collect(env)


def random_inbox(d: int, b=2, seed=0) -> tuple[np.ndarray, Inbox]:
    """CEFC observations [b, 8, D] and an inbox of messages of d numbers: agents hear 0 to 7 others."""
    rng = np.random.default_rng(seed)
    count = np.arange(8) % 8  # agent a hears a others
    mask = np.broadcast_to(np.arange(7) < count[:, None], (b, 8, 7)).copy()
    inbox = Inbox(
        messages=(rng.normal(size=(b, 8, 7, d)) * 4 * mask[..., None]).astype(np.float32),
        mask=mask,
        distance=rng.random((b, 8, 7)) * 3 * mask,
        sender=np.where(mask, 0, -1),
        received=mask.sum(-1),
        own=rng.normal(size=(b, 8, d)).astype(np.float32),
    )
    obs = (rng.normal(size=(b, 8, cefc_layout(TASK).size)) * 4).astype(np.float32)
    return obs, inbox


# ---------------------------------------------------------------------------- what is sent
def test_message_sizes_are_the_papers_table_iv():
    assert set(TABLE_IV) == set(VARIANTS)
    for variant, numbers in TABLE_IV.items():
        policy = HighLevelPolicy.build(variant, TASK)
        assert policy.message_dim == numbers, variant
    for variant in BASELINES:
        policy = HighLevelPolicy.build(variant, TASK)
        cfg = policy.comm.cfg
        assert isinstance(policy.comm, ObservationComm) and cfg.obs_dim == 38
        assert cfg.sent_dim == (38 if variant == "masia" else 64 + 38)
        assert policy.selector.cfg.consensus_dim == cfg.feature_dim == 64  # the selector reads z_i / mu_i
        assert not policy.selector.cfg.consensus_gradient


def test_masia_sends_exactly_the_senders_unscaled_local_observation_and_nvif_ends_with_it():
    layout = cefc_layout(TASK)
    for variant in BASELINES:
        policy = HighLevelPolicy.build(variant, TASK, seed=3)
        d = policy.message_dim
        obs, inbox = random_inbox(d)
        # o_i: the targets, adversary and neighbour parts of the env's observation, as the env gives them
        o = np.concatenate([obs[..., layout[p]] for p in ("targets", "adversary", "neighbours")], axis=-1)
        assert o.shape == (2, 8, 38)
        index, message = policy.decide(obs, inbox)
        assert message.shape == (2, 8, d) and index.shape == (2, 8)
        np.testing.assert_array_equal(message[..., -38:], o)
        out = policy.comm(*policy.comm_inputs(torch.as_tensor(obs), inbox))
        if variant == "masia":
            np.testing.assert_array_equal(message, o)
            assert out.estimate.shape == (2, 8, 28)  # g_hat_i: ConsMAC-O's global state
        else:  # the first 64 numbers are the latent's mean, which the selector reads
            torch.testing.assert_close(torch.as_tensor(message[..., :64]), out.feature, rtol=0, atol=0)
            assert out.estimate is None
        assert out.consensus is out.feature and out.feature.shape == (2, 8, 64)
        # the feature aggregates the neighbours' messages: changing a received one changes it
        moved = Inbox(inbox.messages * 2 + inbox.mask[..., None], *list(vars(inbox).values())[1:])
        other = policy.comm(*policy.comm_inputs(torch.as_tensor(obs), moved))
        heard = torch.as_tensor(inbox.mask.any(-1))
        assert not torch.allclose(other.feature[heard], out.feature[heard])
        torch.testing.assert_close(other.feature[~heard], out.feature[~heard], rtol=0, atol=0)
        # empty slots are never read
        garbage = Inbox(np.where(inbox.mask[..., None], inbox.messages, np.nan), *list(vars(inbox).values())[1:])
        same = policy.comm(*policy.comm_inputs(torch.as_tensor(obs), garbage))
        torch.testing.assert_close(same.feature, out.feature, rtol=0, atol=0)


def test_configs_are_checked_up_front():
    with pytest.raises(ConfigError, match="message_content='raw'"):
        ConsMACConfig.from_task(TASK, message_content="raw")
    with pytest.raises(ConfigError, match="kl_weight=-1"):
        ConsMACConfig.from_task(TASK, message_content="latent+observation", kl_weight=-1)
    with pytest.raises(ConfigError, match="ablates ConsMAC"):
        ConsMACConfig.from_task(TASK, message_content="observation", ablation="wo-com")
    with pytest.raises(ConfigError, match="build_comm"):
        ConsMAC(ConsMACConfig.from_task(TASK, message_content="observation"))
    assert isinstance(build_comm(ConsMACConfig.from_task(TASK)), ConsMAC)
    for variant in BASELINES:  # ConsMAC's ablations stay ConsMAC's
        with pytest.raises(ConfigError, match="needs variant consmac-a or consmac-o"):
            HighLevelPolicy.build(variant, TASK, ablation="wo-com")
        with pytest.raises(ConfigError, match="needs variant consmac-a or consmac-o"):
            tiny_config(variant, ablation="wt-rl")
    assert tiny_config("masia").name == "cihrl_masia" and tiny_config("nvif", seed=2).name == "cihrl_nvif_seed2"
    assert tiny_config("nvif", pretrain_share=0.0).name == "cihrl_nvif_dt"


# ---------------------------------------------------------------------------- what trains them
@pytest.mark.parametrize("variant", BASELINES)
def test_the_ppo_loss_never_reaches_their_modules(variant):
    trainer, ro = trainer_and_rollout(tiny_config(variant))
    comm = trainer.policy.comm
    assert ro.comm_inputs == () and ro.senders is None and not ro.consensus.requires_grad
    assert ro.consensus.shape == (5, 2, 8, 64)
    rl_params = {id(p) for group in trainer.policy_opt.param_groups for p in group["params"]}
    supervised = {id(p) for p in trainer.consmac_opt.param_groups[0]["params"]}
    assert all(id(p) not in rl_params and id(p) in supervised for p in comm.parameters())
    flat = lambda x: x.reshape(-1, *x.shape[2:])[:4]  # noqa: E731
    # even handed the live inputs, the policy terms give the module no gradient (the selector detaches)
    logp, entropy = trainer.policy_terms(flat(ro.obs), flat(ro.consensus), (), flat(ro.actions))
    (-(logp * torch.randn(logp.shape)).mean() - entropy.mean()).backward()
    assert all(p.grad is None for p in comm.parameters())
    assert all(p.grad is not None for p in trainer.policy.selector.parameters())
    trainer.policy.zero_grad(set_to_none=True)
    # the consensus the policy acts on is cut from the module's graph, though the module's output is live
    obs = ro.obs[0]
    d = comm.cfg.sent_dim
    inputs = (
        obs,
        torch.zeros(2, 8, d),
        torch.zeros(2, 8, 7, d),
        torch.zeros(2, 8, 7, dtype=torch.bool),
        torch.zeros(2, 8, 7),
    )
    consensus, out = trainer.policy.consensus(inputs, (2, 8))
    assert not consensus.requires_grad and out.feature.requires_grad
    trainer.policy.selector.evaluate(obs, consensus, ro.actions[0])[0].sum().backward()
    assert all(p.grad is None for p in comm.parameters())
    trainer.policy.zero_grad(set_to_none=True)
    # a whole PPO update leaves the module bit for bit as it was and moves the selector
    before = {k: v.clone() for k, v in comm.state_dict().items()}
    selector = {k: v.clone() for k, v in trainer.policy.selector.state_dict().items()}
    trainer.update(ro)
    assert all(torch.equal(v, before[k]) for k, v in comm.state_dict().items())
    assert not all(torch.equal(v, selector[k]) for k, v in trainer.policy.selector.state_dict().items())
    # the supervised step is what moves it, on the replay of messages at the sent size
    assert trainer.replay.data["messages"].shape[1:] == (7, TABLE_IV[variant])
    assert trainer.replay.data["label"].shape[1:] == ((28,) if variant == "masia" else (0,))
    stats = trainer.train_consmac(3)
    assert np.isfinite(stats["consmac_loss"]) and stats["replay_size"] == 80
    assert not all(torch.equal(v, before[k]) for k, v in comm.state_dict().items())


@pytest.mark.parametrize("variant", BASELINES)
def test_the_supervised_loss_falls_on_a_fixed_small_batch(variant):
    trainer, _ = trainer_and_rollout(tiny_config(variant))
    comm = trainer.policy.comm
    batch = {k: v[:64].clone() for k, v in trainer.replay.data.items()}
    assert batch["mask"].any()  # some agents heard others

    def loss() -> float:
        with torch.no_grad():
            return float(comm.supervised_loss(batch, generator=torch.Generator().manual_seed(7)))

    before = loss()
    opt = torch.optim.Adam(comm.parameters(), lr=3e-3)
    generator = torch.Generator().manual_seed(0)
    for _ in range(300):
        opt.zero_grad()
        comm.supervised_loss(batch, generator=generator).backward()
        opt.step()
    after = loss()
    assert after < 0.3 * before, (before, after)


# ---------------------------------------------------------------------------- files and the deployed path
@pytest.mark.parametrize("variant", BASELINES)
def test_a_policy_file_round_trips(variant, tmp_path):
    policy = HighLevelPolicy.build(variant, TASK, seed=5)
    path = save_highlevel_policy(policy, tmp_path / "p.pt", meta={"variant": variant})
    loaded, meta = load_highlevel_policy(path)
    assert loaded.variant == variant == meta["variant"] and loaded.comm.cfg == policy.comm.cfg
    assert loaded.selector.cfg == policy.selector.cfg and loaded.message_dim == TABLE_IV[variant]
    obs, inbox = random_inbox(policy.message_dim, seed=1)
    a, m = policy.decide(obs, inbox)
    b, n = loaded.decide(obs, inbox)
    np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(m, n)


TINY = [
    "highlevel",
    "--envs",
    "2",
    "--epochs",
    "2",
    "--minibatches",
    "2",
    "--episode-steps",
    "50",
    "--consmac-steps",
    "3",
    "--consmac-batch",
    "32",
    "--eval-episodes",
    "1",
    "--threads",
    "1",
    "--no-progress",
    "--budget",
    "2",
]


@pytest.mark.parametrize("variant", BASELINES)
def test_cli_trains_a_policy_that_loads_and_decides_on_the_deployed_path(variant, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main(TINY + ["--variant", variant]) == 0
    path = tmp_path / "runs" / "highlevel" / "policies" / f"cihrl_{variant}.pt"
    card = json.loads(path.with_suffix(".json").read_text())
    d = TABLE_IV[variant]
    assert card["name"] == f"cihrl_{variant}" and card["method"].startswith(f"{variant.upper()}+AT-M")
    assert card["messages"]["numbers"] == d and "o_i" in card["messages"]["content"]
    assert ("global state" if variant == "masia" else "KL") in card["messages"]["trained_by"]
    assert card["messages"]["rl_gradient"] == "none (stop-gradient)"
    assert card["consmac_training"]["steps"] == 6 and "evaluation" in card
    fit = card["consmac_training"]["label_fit"]  # MASIA estimates the global state; NVIF has no such label
    assert (fit["loss"] > 0 and fit["mean_guess_loss"] > 0) if variant == "masia" else fit is None
    policy, meta = load_highlevel_policy(path)
    assert meta["variant"] == variant and policy.message_dim == d

    # one agent's deployed decision (traced) is decide() on its row, bit for bit, for 0, 2 and 7 messages
    decider = policy.agent_decider()
    obs, inbox = random_inbox(d, b=1, seed=2)
    for agent in (0, 2, 7):
        one = Inbox(*(a[:, agent : agent + 1] for a in vars(inbox).values()))
        index, message = decider(obs[:, agent : agent + 1], one)
        ref_index, ref_message = policy.decide(obs[:, agent : agent + 1], one)
        assert (index == ref_index).all() and (message == ref_message).all() and message.shape == (1, 1, d)

    # a SITL-M agent: its message crosses the wire at d numbers, and an inbox of such messages decides
    task = TaskConfig(n_agents=8, mode="cefc")
    agent = AgentHierarchy(policy, load_low_level("atm_student", task), task)
    anchor, sent = agent.decide(obs[0, 0])
    frame = wire.encode({"type": "message", "seq": 0, "uav": 0, "latency_ms": 0.0, "anchor": anchor, "message": sent})
    got = wire.decode(frame, wire.AGENT_TO_SIM)
    wire.check_message(got, d, 9)
    np.testing.assert_array_equal(got["message"], sent)
    rows = [(1, 0.5, got["message"]), (3, 2.5, got["message"] * 0.5)]
    box = wire.decode(wire.encode({"type": "inbox", "seq": 1, "dim": d, "rows": rows}), wire.SIM_TO_AGENT)
    wire.check_inbox(box, d, 8, 0, 3.0)
    anchor, sent = agent.decide(obs[0, 1], box["sender"], box["distance"], box["messages"])
    assert 0 <= anchor < 9 and sent.shape == (d,)
    np.testing.assert_array_equal(sent[-38:], policy.comm.local_observation(torch.as_tensor(obs[0, 1])).numpy())


def test_a_checkpointed_nvif_trainer_continues_exactly(tmp_path):
    """NVIF's reparameterisation noise comes from the trainer's generator, which the state holds."""
    cfg = tiny_config("nvif", pretrain_share=0.5)
    task = cfg.task()
    low_levels = (load_low_level("navigation", task), load_low_level(cfg.low_level, task))
    straight = HighLevelTrainer(cfg, low_levels)
    for _ in range(2):
        straight.iterate()
    first = HighLevelTrainer(cfg, low_levels)
    first.iterate()
    torch.save(first.state_dict(), tmp_path / "state.pt")
    resumed = HighLevelTrainer(cfg, low_levels)
    resumed.load_state_dict(torch.load(tmp_path / "state.pt", weights_only=True))
    resumed.iterate()
    for (name, x), y in zip(straight.policy.state_dict().items(), resumed.policy.state_dict().values()):
        assert torch.equal(x, y), name
    assert resumed.replay.data["label"].shape == (cfg.replay_capacity, 0)
