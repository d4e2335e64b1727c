"""The game-seed blocks (cefc_mj/seeds.py) are disjoint, training games come from the training block
only, and the shipped protocols' default seeds lie in the blocks the docs name."""

from __future__ import annotations

import itertools

import numpy as np

from cefc_mj import seeds
from cefc_mj.train.mappo import iteration_seed


def test_blocks_are_disjoint_and_ordered():
    for a, b in itertools.pairwise(seeds.BLOCKS):
        assert a.start < a.stop <= b.start < b.stop
    for a, b in itertools.combinations(seeds.BLOCKS, 2):
        assert not set(range(a.start, min(a.stop, a.start + 1000))) & set(range(b.start, min(b.stop, b.start + 1000)))
        assert a.stop <= b.start or b.stop <= a.start


def test_training_games_never_leave_the_training_block():
    drawn = [iteration_seed(run_seed, it) for run_seed in range(20) for it in range(500)]
    assert all(s in seeds.TRAINING for s in drawn)
    assert not any(s in block for s in drawn for block in (seeds.PROTOCOL, seeds.VALIDATION, seeds.TEST))
    assert len(set(drawn)) == len(drawn)  # independent streams per (run seed, iteration)
    np.random.default_rng(max(drawn))  # a valid numpy seed


def test_named_seeds_lie_in_their_blocks():
    assert seeds.GAME_VALIDATION_SEED in seeds.VALIDATION
    assert seeds.GAME_TEST_SEED in seeds.TEST
    assert all(s in seeds.TEST for s in seeds.TABLE8_TEST_SEEDS)
    assert seeds.block_of(0) == "protocol" and seeds.block_of(200) == "validation"
    assert seeds.block_of(seeds.GAME_TEST_SEED) == "test" and seeds.block_of(2**32) == "outside"
