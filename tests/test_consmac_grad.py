"""ConsMAC's supervised step with the hand-written backward pass (cefc_mj/nn/consmac_grad.py) learns
as the autograd step it replaced (tests/reference_impl.py keeps a frozen copy of that step).

Same arithmetic in another order, so the bar is float rounding, not bit equality: gradients within
1e-5 of each tensor's largest entry (float32 sums of 2,048 rows reordered differ by about 1e-6), and
a short training run whose ConsMAC losses, PPO losses and returns agree to 1e-4 relative
(docs/research/highlevel_speed.md, "Equivalence").
"""

import pytest
import torch
from reference_impl import consmac_supervised_loss_reference
from test_highlevel import make_trainer, tiny_config

from cefc_mj.nn import consmac_grad
from cefc_mj.nn.consmac import ABLATIONS, ConsMAC, ConsMACConfig
from cefc_mj.task.config import TaskConfig
from cefc_mj.train import highlevel_trainer
from cefc_mj.train.config import Budget

pytestmark = pytest.mark.usefixtures("one_torch_thread")
GRAD_TOL = 1e-5
"""Largest |new - old| gradient entry, relative to the tensor's largest old entry."""
RUN_RTOL = 1e-4
"""Relative tolerance on a short run's logged losses and returns."""


def replay_batch(cfg: ConsMACConfig, rows: int, seed: int = 0) -> dict[str, torch.Tensor]:
    """Random replay rows with 0..K received messages; empty slots hold garbage (NaN messages, huge
    distances), which neither step may read."""
    g = torch.Generator().manual_seed(seed)
    k, d = cfg.n_agents - 1, cfg.sent_dim
    mask = torch.arange(k) < torch.randint(0, k + 1, (rows, 1), generator=g)
    messages = torch.randn(rows, k, d, generator=g)
    return {
        "obs": torch.randn(rows, cfg.env_obs_dim, generator=g) * 4,
        "own": torch.randn(rows, d, generator=g),
        "messages": torch.where(mask.unsqueeze(-1), messages, torch.nan),
        "mask": mask,
        "distance": torch.where(mask, torch.rand(rows, k, generator=g) * 3, 1e6),
        "label": torch.randn(rows, cfg.global_dim, generator=g) * 8,
    }


def reference_grads(net: ConsMAC, batch: dict) -> torch.Tensor:
    """The old step's loss and gradients (autograd through the frozen forward)."""
    net.zero_grad(set_to_none=True)
    loss = consmac_supervised_loss_reference(net, batch)
    loss.backward()
    return loss.detach()


@pytest.mark.parametrize("variant", ["A", "O"])
@pytest.mark.parametrize("ablation", [a for a in ABLATIONS if a != "wt-rl"])  # wt-rl: the same network as none
def test_gradients_match_autograd_of_the_old_step(variant, ablation):
    cfg = ConsMACConfig.from_task(TaskConfig(n_agents=8, mode="cefc"), variant=variant, ablation=ablation)
    net = ConsMAC(cfg, seed=3)
    assert consmac_grad.fused_supported(net)
    batch = replay_batch(cfg, 256)
    old_loss = reference_grads(net, batch)
    old = {name: None if p.grad is None else p.grad.clone() for name, p in net.named_parameters()}
    new_loss = consmac_grad.supervised_grads(net, batch)
    assert torch.isfinite(new_loss) and abs(float(new_loss) - float(old_loss)) <= 1e-6 * float(old_loss)
    for name, p in net.named_parameters():
        if old[name] is None:  # wo-de: the frequencies are not in the graph
            assert p.grad is None, name
            continue
        if name == "attention.key.bias":  # shifts every score of a row alike: softmax cancels it
            scale = net.attention.key.weight.grad.abs().max()
            assert old[name].abs().max() <= 1e-6 * scale and p.grad.abs().max() <= 1e-6 * scale
            continue
        error = (p.grad - old[name]).abs().max() / old[name].abs().max().clamp_min(1e-30)
        assert error <= GRAD_TOL, (name, float(error))


def test_a_module_it_does_not_cover_keeps_autograd():
    cfg = ConsMACConfig.from_task(TaskConfig(n_agents=8, mode="cefc"), residual=False)
    assert not consmac_grad.fused_supported(ConsMAC(cfg, seed=0))


def test_a_short_run_learns_as_with_the_old_step(monkeypatch):
    """Three iterations (ConsMAC rounds after each) with the new step and with the old one."""

    def run() -> list[dict]:
        trainer = make_trainer(tiny_config("consmac-a", budget=Budget(iterations=3), consmac_steps=20))
        return [trainer.iterate() for _ in range(3)]

    new_rows = run()
    monkeypatch.setattr(highlevel_trainer, "supervised_grads", reference_grads)
    old_rows = run()
    keys = ("episode_return", "consmac_loss", "consmac_loss_last", "policy_loss", "value_loss", "entropy")
    for new, old in zip(new_rows, old_rows):
        for key in keys:
            assert new[key] == pytest.approx(old[key], rel=RUN_RTOL, abs=1e-7), (new["iteration"], key)
