"""Game-seed blocks: which games train, which choose, which report (docs/evaluate.md, "Seed blocks").

A game seed is the integer that seeds the layouts of an episode (Table VIII: one seed per episode) or
of a batch of episodes (Tables III and V-VII: one seed per batch of 50). The blocks are disjoint:

- TRAINING: every training episode; `train.mappo.iteration_seed` maps (run seed, iteration) into it.
- VALIDATION: every choice (budgets, learning rates, which checkpoint, any selection among
  candidates) is made on these games.
- TEST: the shipped comparison reports are flown once on these, after every choice is made. The test
  batches reports use are declared below (TEST_BATCHES), and every flight of a declared batch is
  recorded in the test ledger (`cefc_mj.eval.ledger`); other test seeds are not recorded.
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
"""The batch seed of the game tables' test games (50 episodes; TEST) of the shipped Tables V-VII.
Flown in several generations, and two adversary replacements were decided from its numbers
(eval/test_ledger.jsonl): it no longer decides anything, see GAME_PREREGISTERED_TEST_SEED."""
GAME_PREREGISTERED_TEST_SEED = 50_000
"""The batch seed of the pre-registered Table V (docs/research/preregistration.md): never flown before that
flight, and `cefc-eval` flies it only with --preregistered-flight. A batch seed seeds one generator
(`numpy.random.default_rng(seed)`) that draws every game of the batch at reset
(`env.BatchedCEFCEnv.reset`), so two batch seeds give unrelated games, not shifted copies
(tests/test_test_ledger.py compares the layouts of this batch with 10000's and 200's). Far from
10000 to keep clear of the one-game-per-seed protocols too, which fly seed, seed + 1, ... (the SITL-M
game study flew 20000..20099). The batches reserved before it, 30000 and 40000, were each flown once
by accident before any new run's result was in (eval/test_ledger.jsonl, docs/research/preregistration.md
"Deviations"), so they are spent (SPENT_PREREGISTERED_TEST_SEEDS)."""
GAME_PAPER_SCHEDULE_TEST_SEED = 80_000
"""The test batch of the second pre-registration, CI-HRL against MAPPO+AT-M at the paper's schedule
(docs/research/preregistration_paper_schedule.md): 50 games drawn from this one batch seed, flown
once after every planned run is in, with the first pre-registration's 75-update runs on the same games
in the same flight. Reserved: `cefc-eval` refuses to fly it until that flight's tool exists."""
SPENT_PREREGISTERED_TEST_SEEDS = (30_000, 40_000)
"""The pre-registration's earlier test batches, each flown once by accident (see GAME_PREREGISTERED_TEST_SEED)."""
TABLE8_TEST_SEEDS = TEST.seeds(20)
"""The Table VIII test block: episode seeds 10000..10019 of every c and condition."""
TABLE8_MUJOCO_TEST_SEEDS = TEST.seeds(20, offset=50_000)
"""The test batch of AT-M-MuJoCo's Table VIII (episode seeds 60000..60019 of every c and condition):
never flown before the fine-tuned policy was chosen; then flown once per grid, before (AT-M-Nav) and
after (AT-M-MuJoCo) with the acceleration interface and no guard, and the new policy on the default
path (docs/research/training_in_mujoco.md)."""

TABLE8_PX4_TEST_SEEDS = TEST.seeds(20, offset=60_000)
"""The test batch of Table VIII with the paper's agent on PX4's own acceleration interface (episode
seeds 70000..70019 of every c and condition): flown once per grid after every policy and setting is
chosen on validation seeds (examples/px4_exact_table8.py)."""


def block_of(seed: int) -> str:
    """The name of the block holding `seed` ("outside" for a seed no block holds)."""
    return next((block.name for block in BLOCKS if seed in block), "outside")


GAME_FAMILY, FORMATION_FAMILY = "game", "formation"
PROTOCOL_FAMILY = {
    "table5": GAME_FAMILY,
    "table6": GAME_FAMILY,
    "table7": GAME_FAMILY,
    "table5-sitl-m": GAME_FAMILY,
    "table8": FORMATION_FAMILY,
    "single": FORMATION_FAMILY,
}
"""Which games a protocol's seeds draw: the high level's game (Tables V-VII, the SITL-M game) or the
low level's formation episodes (Table VIII, cefc-eval single). The same seed in one family is treated
as the same games (a batch seed and a one-game seed share their first draws), in two families as
unrelated games."""
BATCH_SEEDED = frozenset({"table5", "table6", "table7"})
"""Protocols whose --seed seeds one batch of games; the others fly one game per seed, seed + k."""


@dataclass(frozen=True)
class TestBatch:
    """A batch of test-block games that shipped or planned reports are flown on."""

    name: str
    """What the batch is for."""
    family: str
    """The games its seeds draw (PROTOCOL_FAMILY's values)."""
    first: int
    """Its first seed."""
    count: int
    """Seeds first..first + count - 1 (a game-table batch: its one batch seed)."""
    status: str
    """Where it stands: flown, tainted (a flight informed a change), or reserved."""

    __test__ = False  # not a pytest test class, whatever its name

    @property
    def seeds(self) -> range:
        return range(self.first, self.first + self.count)


TEST_BATCHES = (
    TestBatch(
        "Tables V-VII (shipped)",
        GAME_FAMILY,
        GAME_TEST_SEED,
        1,
        "flown in four generations; two flights informed adversary replacements (eval/test_ledger.jsonl)",
    ),
    TestBatch(
        "Table V (pre-registered)",
        GAME_FAMILY,
        GAME_PREREGISTERED_TEST_SEED,
        1,
        "reserved: never flown; flown once by the pre-registered comparison (docs/research/preregistration.md)",
    ),
    *(
        TestBatch(
            f"Table V (pre-registered, batch {seed}, spent)",
            GAME_FAMILY,
            seed,
            1,
            "spent: flown once by accident before the planned runs were in "
            "(docs/research/preregistration.md, Deviations)",
        )
        for seed in SPENT_PREREGISTERED_TEST_SEEDS
    ),
    TestBatch(
        "Table V at the paper's schedule (pre-registered)",
        GAME_FAMILY,
        GAME_PAPER_SCHEDULE_TEST_SEED,
        1,
        "reserved: never flown; flown once by the second pre-registration "
        "(docs/research/preregistration_paper_schedule.md)",
    ),
    TestBatch(
        "SITL-M game fidelity",
        GAME_FAMILY,
        20_000,
        100,
        "flown in three generations; 20-game studies on its first 20 seeds decided the study's size",
    ),
    TestBatch("Table VIII", FORMATION_FAMILY, TABLE8_TEST_SEEDS[0], len(TABLE8_TEST_SEEDS), "flown once"),
    TestBatch(
        "Table VIII of AT-M-MuJoCo",
        FORMATION_FAMILY,
        TABLE8_MUJOCO_TEST_SEEDS[0],
        len(TABLE8_MUJOCO_TEST_SEEDS),
        "reserved: flown once per grid after the fine-tuned policy is chosen (docs/research/training_in_mujoco.md)",
    ),
    TestBatch(
        "Table VIII on PX4's acceleration interface",
        FORMATION_FAMILY,
        TABLE8_PX4_TEST_SEEDS[0],
        len(TABLE8_PX4_TEST_SEEDS),
        "reserved: never flown; flown once per grid by examples/px4_exact_table8.py --fly",
    ),
)
"""Every test batch a shipped or planned report uses, in one place."""

FORMATION_VALIDATION_SEED = 300
"""The batch seed of the formation task's validation episodes (50 episodes of Table III's protocol,
VALIDATION): what BenchMARL formation runs report in their model cards and what their budgets are
chosen on (docs/formation_benchmarl.md). Table III itself flies the PROTOCOL batch seed 0."""
