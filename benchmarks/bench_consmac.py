"""Cost of one ConsMAC supervised step (eq. (11)) on one core: the step as it was (a frozen copy in
tests/reference_impl.py: the replay draw by advanced indexing, the reassociated attention of
`MaskedMultiHeadAttention(fast=True)`, autograd, clip, Adam) against the step the trainer now takes
(`ConsMACReplay.sample`, `cefc_mj.nn.consmac_grad.supervised_grads`, clip, Adam), measured in the
same run.

The shipped ConsMAC shape (N = 8, ConsMAC-A, 64-number messages, 4 heads) and batch 2048 (the
paper's), drawn from a replay of random rows with 0 to 7 received messages. Rounds alternate old /
new so that both see the same machine load; the median round of each counts (the machine may be
shared: read the ratio, which moves less than the times).

    .venv/bin/python benchmarks/bench_consmac.py
    .venv/bin/python benchmarks/bench_consmac.py --batch 4096 --rounds 9
    .venv/bin/python benchmarks/bench_consmac.py --smoke   # batch 64, 1 round of 2 steps (tests/test_benchmarks.py)

benchmarks/bench_highlevel_training.py puts the step into whole iterations and runs.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from reference_impl import consmac_train_step_reference  # noqa: E402

from cefc_mj.nn.consmac import ConsMAC, ConsMACConfig  # noqa: E402
from cefc_mj.nn.consmac_grad import supervised_grads  # noqa: E402
from cefc_mj.task.config import TaskConfig  # noqa: E402
from cefc_mj.train.consmac_replay import ConsMACReplay  # noqa: E402

MAX_GRAD_NORM = 0.5


def random_replay(cfg: ConsMACConfig, rows: int, seed: int = 0) -> ConsMACReplay:
    """A full replay of random rows (0..K received messages each, empty slots zero as the channel's)."""
    g = torch.Generator().manual_seed(seed)
    k, d = cfg.n_agents - 1, cfg.sent_dim
    mask = torch.arange(k) < torch.randint(0, k + 1, (rows, 1), generator=g)
    replay = ConsMACReplay(rows, cfg)
    replay.add(
        {
            "obs": torch.randn(rows, cfg.env_obs_dim, generator=g) * 4,
            "own": torch.randn(rows, d, generator=g),
            "messages": torch.randn(rows, k, d, generator=g) * mask.unsqueeze(-1),
            "mask": mask,
            "distance": torch.rand(rows, k, generator=g) * 3 * mask,
            "label": torch.randn(rows, cfg.global_dim, generator=g) * 8,
        }
    )
    return replay


class StepPair:
    """The old and the new ConsMAC step, each on its own copy of the same network, optimizer and RNG."""

    def __init__(self, net: ConsMAC, replay: ConsMACReplay, batch: int, lr: float = 1e-4, seed: int = 0):
        self.replay, self.batch = replay, batch
        self.nets = {name: ConsMAC(net.cfg) for name in ("old", "new")}
        for copy in self.nets.values():
            copy.load_state_dict(net.state_dict())
        self.opts = {
            "old": torch.optim.Adam(self.nets["old"].parameters(), lr=lr),
            "new": torch.optim.Adam(self.nets["new"].parameters(), lr=lr, foreach=True),
        }
        self.generators = {name: torch.Generator().manual_seed(seed) for name in self.nets}

    def step(self, which: str) -> float:
        net, opt, g = self.nets[which], self.opts[which], self.generators[which]
        if which == "old":
            return consmac_train_step_reference(
                net, opt, self.replay.data, self.replay.size, self.batch, g, MAX_GRAD_NORM
            )
        loss = supervised_grads(net, self.replay.sample(self.batch, g))
        torch.nn.utils.clip_grad_norm_(list(net.parameters()), MAX_GRAD_NORM)
        opt.step()
        return loss.item()

    def time(self, steps: int, rounds: int) -> dict[str, list[float]]:
        """ms per step of each, one entry per round, old and new alternating."""
        for which in self.nets:  # warm-up (and the kernels' compile or cache load)
            self.step(which)
        times: dict[str, list[float]] = {which: [] for which in self.nets}
        for _ in range(rounds):
            for which in self.nets:
                start = time.perf_counter()
                for _ in range(steps):
                    self.step(which)
                times[which].append((time.perf_counter() - start) / steps * 1e3)
        return times


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batch", type=int, default=2048)
    parser.add_argument("--steps", type=int, default=10, help="steps per round")
    parser.add_argument("--rounds", type=int, default=7)
    parser.add_argument("--smoke", action="store_true", help="batch 64, 1 round of 2 steps")
    args = parser.parse_args()
    if args.smoke:
        args.batch, args.steps, args.rounds = 64, 2, 1
    torch.set_num_threads(1)
    cfg = ConsMACConfig.from_task(TaskConfig(n_agents=8, mode="cefc"))
    pair = StepPair(ConsMAC(cfg, seed=0), random_replay(cfg, max(4 * args.batch, 1024)), args.batch)
    losses = [(pair.step("old"), pair.step("new")) for _ in range(3)]  # the same draws, the same learning
    drift = max(abs(a - b) / abs(a) for a, b in losses)
    times = pair.time(args.steps, args.rounds)
    old, new = statistics.median(times["old"]), statistics.median(times["new"])
    print(f"ConsMAC supervised step, batch {args.batch}, 1 thread, median of {args.rounds} x {args.steps}")
    print(f"  old (autograd, tests/reference_impl.py): {old:8.2f} ms/step  (rounds: {_list(times['old'])})")
    print(f"  new (consmac_grad.supervised_grads):     {new:8.2f} ms/step  (rounds: {_list(times['new'])})")
    print(f"  largest relative loss difference over 3 shared steps: {drift:.1e}")
    print(f"new / old: {new / old:.3f}  (speed-up {old / new:.2f}x)")


def _list(values: list[float]) -> str:
    return " ".join(f"{v:.1f}" for v in values)


if __name__ == "__main__":
    main()
