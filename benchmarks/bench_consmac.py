"""Cost of one ConsMAC supervised step (eq. (11)), on one core: the attention as the shipped
policies were trained (`fast=False`: every key and value projected) against the reassociated
attention the trainer now uses (`fast=True`, `MaskedMultiHeadAttention`), measured in the same run.

One step = forward over a batch of replay tuples, the loss, backward, gradient clip and Adam, as
`HighLevelTrainer.train_consmac` does it (the replay draw, about 3 ms at batch 2048, is left out:
it is the same for both). The shipped ConsMAC shape (N = 8, ConsMAC-A, 64-number messages, 4
heads) and batch 2048 (the paper's); inputs are random with 0 to 7 received messages per row.
Rounds alternate old / new so that both see the same machine load; the best round of each counts.

    .venv/bin/python benchmarks/bench_consmac.py
    .venv/bin/python benchmarks/bench_consmac.py --batch 4096 --rounds 7
    .venv/bin/python benchmarks/bench_consmac.py --smoke   # batch 64, 1 round of 2 steps (tests/test_benchmarks.py)
"""

from __future__ import annotations

import argparse
import time

import torch

from cefc_mj.nn.consmac import ConsMAC, ConsMACConfig, consmac_loss
from cefc_mj.task.config import TaskConfig


def batch(cfg: ConsMACConfig, size: int, seed: int = 0) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    k, d = cfg.n_agents - 1, cfg.sent_dim
    received = torch.randint(0, k + 1, (size, 1), generator=g)
    mask = torch.arange(k) < received
    return {
        "obs": torch.randn(size, cfg.env_obs_dim, generator=g) * 4,
        "own": torch.randn(size, d, generator=g),
        "messages": torch.randn(size, k, d, generator=g) * mask.unsqueeze(-1),
        "mask": mask,
        "distance": torch.rand(size, k, generator=g) * 3 * mask,
        "label": torch.randn(size, cfg.global_dim, generator=g) * 8,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batch", type=int, default=2048)
    parser.add_argument("--steps", type=int, default=10, help="steps per round")
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--smoke", action="store_true", help="batch 64, 1 round of 2 steps")
    args = parser.parse_args()
    if args.smoke:
        args.batch, args.steps, args.rounds = 64, 2, 1
    torch.set_num_threads(1)
    cfg = ConsMACConfig.from_task(TaskConfig(n_agents=8, mode="cefc"))
    data = batch(cfg, args.batch)
    nets = {fast: ConsMAC(cfg, seed=0) for fast in (False, True)}
    opts = {fast: torch.optim.Adam(net.parameters(), lr=1e-4) for fast, net in nets.items()}

    def step(fast: bool) -> float:
        net, opt = nets[fast], opts[fast]
        out = net(data["obs"], data["own"], data["messages"], data["mask"], data["distance"], fast=fast)
        loss = consmac_loss(out.estimate, data["label"])
        opt.zero_grad()
        loss.backward()
        torch.nn.utils.clip_grad_norm_(net.parameters(), 0.5)
        opt.step()
        return loss.item()

    with torch.no_grad():
        ref = nets[False](data["obs"], data["own"], data["messages"], data["mask"], data["distance"])
        new = nets[True](data["obs"], data["own"], data["messages"], data["mask"], data["distance"], fast=True)
    diff = (ref.estimate - new.estimate).abs().max().item()
    for fast in (False, True):  # warm-up
        step(fast)
    best = {False: float("inf"), True: float("inf")}
    for _ in range(args.rounds):
        for fast in (False, True):
            start = time.perf_counter()
            for _ in range(args.steps):
                step(fast)
            best[fast] = min(best[fast], (time.perf_counter() - start) / args.steps * 1e3)
    print(f"ConsMAC supervised step, batch {args.batch}, 1 thread, best of {args.rounds} x {args.steps}")
    print(f"  old (fast=False, per-key projections): {best[False]:8.2f} ms/step")
    print(f"  new (fast=True, reassociated):         {best[True]:8.2f} ms/step")
    print(f"  max |g_hat new - g_hat old| at the same weights: {diff:.2e}")
    print(f"new / old: {best[True] / best[False]:.3f}")


if __name__ == "__main__":
    main()
