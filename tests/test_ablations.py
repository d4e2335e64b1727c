"""The paper's Fig. 7 ablations of ConsMAC (one flag each, `ConsMACConfig.ablation`), the TarMAC
baseline's end-to-end messages, and the supervised update's fast attention (cefc_mj/nn/consmac.py,
cefc_mj/nn/highlevel_policy.py, cefc_mj/train/highlevel.py).

Each ablation is checked to change only what it names: the same seed gives the same parameters as
ConsMAC, and with the named input neutralised (empty inbox, zero memory, zero distance code) the
ablated and the plain module agree exactly. Tiny trainer runs (2 envs, 5 decisions) keep the file
well under a minute on one core.
"""

import numpy as np
import pytest
import torch

from cefc_mj import paths
from cefc_mj.cli.train import main
from cefc_mj.errors import ConfigError
from cefc_mj.hierarchy import HierarchicalCEFCEnv, load_low_level
from cefc_mj.nn.consmac import ABLATIONS, ConsMAC, ConsMACConfig
from cefc_mj.nn.highlevel_policy import HighLevelPolicy, load_highlevel_policy, save_highlevel_policy
from cefc_mj.task.config import TaskConfig
from cefc_mj.task.messages import Inbox
from cefc_mj.train.config import Budget, PPOConfig
from cefc_mj.train.highlevel_config import HighLevelConfig
from cefc_mj.train.highlevel_trainer import HighLevelTrainer

TASK = TaskConfig(n_agents=8, mode="cefc", obstacle_density=0.03)
ABLATED = [a for a in ABLATIONS if a != "none"]

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def net(ablation="none", variant="A", seed=0) -> ConsMAC:
    return ConsMAC(ConsMACConfig.from_task(TASK, variant=variant, ablation=ablation), seed=seed)


def inputs(cfg: ConsMACConfig, b=3, seed=0, neighbours=(0, 1, 7)):
    """Random ConsMAC inputs [b, 8, ...]; agent rows cycle through `neighbours` received messages."""
    g = torch.Generator().manual_seed(seed)
    n, k, d = cfg.n_agents, cfg.n_agents - 1, cfg.sent_dim
    obs = torch.randn(b, n, cfg.env_obs_dim, generator=g) * 4
    own = torch.randn(b, n, d, generator=g)
    messages = torch.randn(b, n, k, d, generator=g)
    count = torch.tensor([neighbours[i % len(neighbours)] for i in range(n)])
    mask = (torch.arange(k) < count[:, None]).expand(b, n, k).clone()
    distance = torch.rand(b, n, k, generator=g) * 3
    return obs, own, messages * mask.unsqueeze(-1), mask, distance * mask


def same(a, b, atol=0.0):
    torch.testing.assert_close(a, b, atol=atol, rtol=0.0 if atol == 0 else 1e-5)


def tiny_config(variant="consmac-a", **overrides) -> HighLevelConfig:
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


# ---------------------------------------------------------------------------- the fast attention
@pytest.mark.parametrize("residual", [True, False])
def test_the_fast_attention_equals_the_reference_math_with_0_1_and_7_neighbours(residual):
    module = ConsMAC(ConsMACConfig.from_task(TASK, residual=residual), seed=3)
    torch.nn.init.normal_(module.attention.out.weight)  # a large attention contribution
    args = list(inputs(module.cfg, b=4, seed=1))
    args[2] = torch.where(args[3].unsqueeze(-1), args[2], torch.tensor(float("nan")))  # garbage in empty slots
    args[4] = torch.where(args[3], args[4], torch.tensor(50.0))  # finite: cos(w d) of inf has no gradient
    outs, grads = [], []
    for fast in (False, True):
        module.zero_grad()
        out = module(*args, fast=fast)
        (out.estimate.square().sum() + out.message.sum()).backward()
        outs.append(out)
        grads.append({k: p.grad.clone() for k, p in module.named_parameters()})
    ref, new = outs
    for name in ("message", "estimate", "memory", "attention"):
        assert torch.isfinite(getattr(new, name)).all()
        same(getattr(new, name), getattr(ref, name), atol=1e-5)
    for k in grads[0]:
        same(grads[1][k], grads[0][k], atol=1e-4)
    # rows without a neighbour: weights exactly 0, message exactly the memory's (LayerNorm or 0)
    lonely = ~args[3].any(-1)
    assert lonely.any() and (new.attention[lonely] == 0).all()
    same(new.message[lonely], module.norm(new.memory)[lonely] if residual else torch.zeros_like(new.message[lonely]))


# ---------------------------------------------------------------------------- each flag changes only what it names
def test_every_ablation_keeps_consmacs_parameters_and_initialisation():
    plain = net().state_dict()
    for ablation in ABLATED:
        ablated = net(ablation).state_dict()
        assert list(ablated) == list(plain)
        for k, v in ablated.items():
            if (
                ablation == "consmac-g"
                and k.startswith(("attention.key.", "attention.value."))
                and k.endswith("weight")
            ):
                assert v.shape == (64, 16 + 64)  # its keys are the 16 numbers of g_hat plus the distance code
            elif ablation != "consmac-g":
                assert torch.equal(v, plain[k]), (ablation, k)


def test_wo_com_receives_nothing():
    plain, ablated = net(), net("wo-com")
    obs, own, messages, mask, distance = inputs(ablated.cfg)
    out = ablated(obs, own, messages, mask, distance)
    other = ablated(obs, own, torch.randn_like(messages), torch.ones_like(mask), torch.rand_like(distance) * 3)
    same(out.message, other.message)
    same(out.estimate, other.estimate)
    assert (out.attention == 0).all()
    # with an empty inbox it is ConsMAC itself
    empty = plain(obs, own, messages, torch.zeros_like(mask), distance)
    same(out.message, empty.message)
    same(out.estimate, empty.estimate)
    assert not torch.allclose(plain(obs, own, messages, mask, distance).message, out.message)


def test_wo_mem_forgets_the_previous_memory_state():
    plain, ablated = net(), net("wo-mem")
    obs, own, messages, mask, distance = inputs(ablated.cfg)
    out = ablated(obs, own, messages, mask, distance)
    same(out.message, ablated(obs, torch.randn_like(own) * 5, messages, mask, distance).message)
    same(out.message, plain(obs, torch.zeros_like(own), messages, mask, distance).message)
    # it still reads the observation and the inbox
    assert not torch.allclose(out.message, ablated(obs + 1, own, messages, mask, distance).message)
    assert not torch.allclose(out.message, ablated(obs, own, torch.randn_like(messages), mask, distance).message)


def test_wo_de_ignores_neighbour_distances_given_the_same_messages():
    plain, ablated = net(), net("wo-de")
    obs, own, messages, mask, distance = inputs(ablated.cfg)
    out = ablated(obs, own, messages, mask, distance)
    same(out.message, ablated(obs, own, messages, mask, torch.rand_like(distance) * 3).message)
    assert not torch.allclose(out.message, ablated(obs, own, torch.randn_like(messages), mask, distance).message)
    # ConsMAC with a distance encoder that outputs zeros is the ablation
    plain.distance_encoder.forward = lambda d: torch.zeros(*d.shape, plain.cfg.distance_dim)
    same(out.message, plain(obs, own, messages, mask, distance).message)


@pytest.mark.parametrize("variant", ["A", "O"])
def test_consmac_g_sends_its_estimate_at_the_label_size(variant):
    ablated = net("consmac-g", variant=variant)
    cfg = ablated.cfg
    assert cfg.sent_dim == cfg.global_dim == (16 if variant == "A" else 28)
    obs, own, messages, mask, distance = inputs(cfg)
    for with_estimate in (True, False):  # the estimate is the message, so it is always computed
        out = ablated(obs, own, messages, mask, distance, with_estimate=with_estimate)
        assert out.message.shape == (3, 8, cfg.global_dim)
        same(out.message, out.estimate)
    assert ablated.initial_message(3, 8).shape == (3, 8, cfg.global_dim)
    with pytest.raises(ConfigError, match="own_message: expected shape"):
        ablated(obs, torch.zeros(3, 8, 64), messages, mask, distance)
    policy = HighLevelPolicy.build("consmac-o" if variant == "O" else "consmac-a", TASK, ablation="consmac-g")
    assert policy.message_dim == cfg.global_dim and policy.selector.cfg.consensus_dim == cfg.global_dim


def test_bad_ablations_are_refused_with_one_line():
    with pytest.raises(ConfigError, match="ablation='wo-x'"):
        ConsMACConfig.from_task(TASK, ablation="wo-x")
    with pytest.raises(ConfigError, match="must fit the memory"):
        ConsMACConfig.from_task(TASK, variant="O", ablation="consmac-g", message_dim=16)
    for variant in ("mappo", "tarmac"):
        with pytest.raises(ConfigError, match="needs variant consmac-a or consmac-o"):
            HighLevelPolicy.build(variant, TASK, ablation="wo-com")
        with pytest.raises(ConfigError, match="needs variant consmac-a or consmac-o"):
            tiny_config(variant, ablation="wt-rl")


def test_run_names_never_collide():
    names = {tiny_config(v).name for v in ("consmac-a", "consmac-o", "mappo", "tarmac")}
    for variant in ("consmac-a", "consmac-o"):
        for ablation in ABLATED:
            for seed in (0, 1):
                names.add(tiny_config(variant, ablation=ablation, seed=seed).name)
    assert len(names) == 4 + 2 * len(ABLATED) * 2
    assert tiny_config(ablation="wo-com", seed=2).name == "cihrl_consmac_a_wo_com_seed2"
    assert tiny_config(ablation="consmac-g").name == "cihrl_consmac_a_consmac_g"


# ---------------------------------------------------------------------------- the RL loss: wt-rl, CI-HRL, TarMAC
def test_wt_rl_lets_the_ppo_loss_into_consmac_and_ci_hrl_does_not():
    for ablation in ("none", "wt-rl"):
        trainer, ro = trainer_and_rollout(tiny_config(ablation=ablation))
        comm = trainer.policy.comm
        flat = lambda x: x.reshape(-1, *x.shape[2:])[:4]  # noqa: E731
        logp, entropy = trainer.policy_terms(
            flat(ro.obs), flat(ro.consensus), tuple(flat(x) for x in ro.comm_inputs), flat(ro.actions)
        )
        (-(logp * torch.randn(logp.shape)).mean() - entropy.mean()).backward()
        grads = [p.grad for p in comm.parameters()]
        if ablation == "none":
            assert all(g is None for g in grads) and ro.comm_inputs == ()
        else:
            assert any(g is not None and g.abs().sum() > 0 for g in grads)
        trainer.policy.zero_grad(set_to_none=True)
        before = {k: v.clone() for k, v in comm.state_dict().items()}
        trainer.update(ro)
        changed = not all(torch.equal(v, before[k]) for k, v in comm.state_dict().items())
        assert changed == (ablation == "wt-rl")
        if ablation == "wt-rl":  # ConsMAC's own optimizer took those steps, and still trains on eq. (11)
            assert trainer.consmac_opt.state and all(p not in trainer.policy_opt.state for p in comm.parameters())
            stats = trainer.train_consmac(3)
            assert np.isfinite(stats["consmac_loss"])


def test_tarmacs_messages_get_gradient_from_the_receivers_ppo_loss():
    trainer, ro = trainer_and_rollout(tiny_config("tarmac"))
    assert ro.senders is not None and ro.senders.shape == (5, 2, 8, 7)
    t, b = ro.logp.shape[:2]
    flat = lambda x: x.reshape(t * b, *x.shape[2:])  # noqa: E731
    previous = [flat(torch.cat([x[:1], x[:-1]])) for x in ro.comm_inputs]
    previous[0] = previous[0].clone().requires_grad_(True)  # the senders' observations one decision earlier
    fresh = flat(torch.cat([torch.ones_like(ro.episode_end[:1]), ro.episode_end[:-1]]))
    mask = flat(ro.comm_inputs[3])
    sender = flat(ro.senders)
    logp, _ = trainer.policy_terms(
        flat(ro.obs),
        flat(ro.consensus),
        tuple(flat(x) for x in ro.comm_inputs),
        flat(ro.actions),
        (tuple(previous), sender, fresh),
    )
    # Recomputed live at the same weights, the inbox is the one the agents acted on.
    same(logp, flat(ro.logp), atol=1e-5)
    # One receiver's loss reaches the observation of another agent that sent to it, a decision earlier.
    row, receiver = [int(i) for i in torch.nonzero(mask.any(-1) & ~fresh[:, None])[0]]
    j = int(sender[row, receiver][mask[row, receiver]][0])
    assert j != receiver
    logp[row, receiver].backward()
    assert previous[0].grad[row, j].abs().sum() > 0
    others = [a for a in range(8) if a != receiver and a not in sender[row, receiver].tolist()]
    assert all(previous[0].grad[row, a].abs().sum() == 0 for a in others)
    assert previous[0].grad[fresh].abs().sum() == 0  # nothing was sent before an episode's first decision
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in trainer.policy.comm.parameters())
    trainer.policy.zero_grad(set_to_none=True)
    # CI-HRL: no RL gradient anywhere near its messages, whatever the caller passes.
    ci, ro_ci = trainer_and_rollout(tiny_config())
    assert ro_ci.senders is None
    logp, _ = ci.policy_terms(
        flat(ro_ci.obs), flat(ro_ci.consensus), (), flat(ro_ci.actions), (tuple(previous), sender, fresh)
    )
    logp.sum().backward()
    assert all(p.grad is None for p in ci.policy.comm.parameters())
    # a whole tarmac update runs and moves its communication module
    before = {k: v.clone() for k, v in trainer.policy.comm.state_dict().items()}
    stats = trainer.update(ro)
    assert np.isfinite(stats["policy_loss"])
    assert not all(torch.equal(v, before[k]) for k, v in trainer.policy.comm.state_dict().items())


def test_consmac_g_and_wo_com_train_through_the_channel():
    for ablation in ("consmac-g", "wo-com"):
        trainer, ro = trainer_and_rollout(tiny_config(ablation=ablation))
        assert trainer.replay.data["messages"].shape[-1] == trainer.policy.message_dim
        if ablation == "consmac-g":
            assert ro.consensus.shape[-1] == 16
        trainer.update(ro)
        assert np.isfinite(trainer.train_consmac(3)["consmac_loss"])


# ---------------------------------------------------------------------------- files and the command line
@pytest.mark.parametrize("ablation", ABLATIONS)
def test_policy_files_round_trip_every_ablation(ablation, tmp_path):
    policy = HighLevelPolicy.build("consmac-a", TASK, seed=4, ablation=ablation)
    path = save_highlevel_policy(policy, tmp_path / "p.pt", meta={"ablation": ablation})
    loaded, meta = load_highlevel_policy(path)
    assert loaded.ablation == ablation and meta["ablation"] == ablation
    assert loaded.selector.cfg == policy.selector.cfg and loaded.comm.cfg == policy.comm.cfg
    d = policy.message_dim
    rng = np.random.default_rng(0)
    mask = rng.random((2, 8, 7)) < 0.5
    inbox = Inbox(
        messages=(rng.normal(size=(2, 8, 7, d)) * mask[..., None]).astype(np.float32),
        mask=mask,
        distance=rng.random((2, 8, 7)) * 3 * mask,
        sender=np.where(mask, 0, -1),
        received=mask.sum(-1),
        own=rng.normal(size=(2, 8, d)).astype(np.float32),
    )
    obs = rng.normal(size=(2, 8, policy.selector.cfg.env_obs_dim)).astype(np.float32)
    a, m = policy.decide(obs, inbox)
    b, n = loaded.decide(obs, inbox)
    np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(m, n)
    assert m.shape == (2, 8, d)


def test_shipped_policies_written_before_the_flag_load_as_no_ablation():
    for name in ("cihrl_consmac_a", "cihrl_tarmac"):
        policy, _ = load_highlevel_policy(paths.POLICIES_DIR / f"{name}.pt")
        assert policy.ablation == "none" and policy.comm.cfg.ablation == "none" and policy.message_dim == 64


@pytest.mark.parametrize(
    "argv, needle",
    [
        (["--ablation", "wo-com", "--variant", "mappo"], "--ablation 'wo-com': ablates ConsMAC"),
        (["--ablation", "wt-rl", "--variant", "tarmac"], "--ablation 'wt-rl': ablates ConsMAC"),
        (["--ablation", "wo-everything"], "--ablation: invalid choice"),
    ],
)
def test_cli_refuses_a_meaningless_ablation_with_one_line(argv, needle, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as e:
        main(["highlevel", "--budget", "1", *argv])
    assert e.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert needle in err[-1] and (len(err) == 1 or "usage:" in err[0])
    assert not any(tmp_path.iterdir())
