"""Game-seed blocks: which games train, which choose, which report (docs/evaluation.md, "Seed blocks").

A game seed is the integer that seeds the layouts of an episode (Table VIII: one seed per episode) or
of a batch of episodes (Tables III and V-VII: one seed per batch of 50). The blocks are disjoint:

- TRAINING: every training episode; `train.mappo.iteration_seed` maps (run seed, iteration) into it.
- VALIDATION: every choice (budgets, learning rates, which checkpoint, any selection among
  candidates) is made on these games.
- TEST: the shipped comparison reports are flown once on these, after every choice is made.
- PROTOCOL: the paper's protocols as this project first flew them and the regression tests (Table VIII
  seeds 0..5, the batch seed 0 of Tables III and V-VII). Earlier choices looked at them, so they are
  kept for reproduction and regression, not for deciding.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class SeedBlock:
    """The game seeds start <= s < stop."""

    name: str
    start: int
    stop: int

    def __contains__(self, seed: object) -> bool:
        return isinstance(seed, int) and not isinstance(seed, bool) and self.start <= seed < self.stop

    @property
    def size(self) -> int:
        return self.stop - self.start

    def seeds(self, count: int, offset: int = 0) -> list[int]:
        """`count` consecutive seeds from start + offset (ValueError if they leave the block)."""
        first = self.start + offset
        if offset < 0 or count < 0 or first + count > self.stop:
            raise ValueError(f"{count} seeds from {first} leave the {self.name} block [{self.start}, {self.stop})")
        return list(range(first, first + count))


PROTOCOL = SeedBlock("protocol", 0, 100)
VALIDATION = SeedBlock("validation", 100, 10_000)
TEST = SeedBlock("test", 10_000, 1_000_000)
TRAINING = SeedBlock("training", 2**31, 2**32)
BLOCKS = (PROTOCOL, VALIDATION, TEST, TRAINING)
"""Every block, in the order of their seeds."""

GAME_VALIDATION_SEED = 200
"""The batch seed of the game tables' validation games (50 episodes; VALIDATION)."""
GAME_TEST_SEED = TEST.start
"""The batch seed of the game tables' test games (50 episodes; TEST), the reports' default."""
TABLE8_TEST_SEEDS = TEST.seeds(20)
"""The Table VIII test block: episode seeds 10000..10019 of every c and condition."""


def block_of(seed: int) -> str:
    """The name of the block holding `seed` ("outside" for a seed no block holds)."""
    return next((block.name for block in BLOCKS if seed in block), "outside")
