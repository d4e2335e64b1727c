"""Regression test of the shipped CI-HRL high level (cefc_mj/eval/highlevel.py, Table V's game: the
shipped student, the PPO adversary).

Closed-loop figures are chaotic: the same seed repeats bit for bit on one machine, not across CPUs
or library builds. And one training seed is not the method: the shipped CI-HRL seeds differ (one
seed's E moves by seconds between seeds). So the test pools three seeds, 20 episodes each, and
asserts the pooled means against bands set from the measured spread. Measured (particle world,
seconds scale, pooled over the seeds; game seeds of the training/validation blocks, never the test
block), against the game's PPO adversary (the one these high levels were trained against):

    20 episodes per seed, seed 100 / 200 / 300   R_t                     E (s)
    CI-HRL (seeds 0, 1, 2)                        106.6 /  78.9 /  73.0   15.03 / 15.44 / 14.68
    CI-HRL-wo-FT (seed 0, pre-training)           103.0 /  77.4 /  72.1   16.20 / 17.11 / 15.43
    untrained networks (build seeds 0-2)           23.6 /  32.9 /  24.3   32.47 / 31.53 / 33.03

The standard error of a pooled 60-episode mean is about 11 for R_t and 0.5 s for E (per-episode
std 81-85 and 3.3-4.6 s). The bands sit about 2.5-3 standard errors beyond the worst of the three
draws, R_t >= 45 and E <= 17.2 s; untrained networks fail both (their R_t about 3 standard errors
below the floor on the test's seed, their E twice the ceiling). The pre-trained weights without
fine-tuning sit inside the bands; they are not asserted.
"""

import numpy as np
import pytest

from cefc_mj import paths
from cefc_mj.game_protocol import DT, evaluate_highlevel, game_task
from cefc_mj.hierarchy import load_low_level
from cefc_mj.nn.adversary_policy import resolve_adversary
from cefc_mj.nn.highlevel_policy import HighLevelPolicy, load_highlevel_policy
from cefc_mj.nn.registry import GAME_ADVERSARY, HIERARCHY_LOWLEVEL

pytestmark = pytest.mark.usefixtures("one_torch_thread")

EPISODES, SEED = 20, 100
R_T_FLOOR = 45.0
E_CEILING_S = 17.2
CI_HRL_SEEDS = ("cihrl_consmac_a", "cihrl_consmac_a_seed1", "cihrl_consmac_a_seed2")


def pooled_figures(policies) -> tuple[float, float]:
    """Mean R_t and E (s) over the policies, EPISODES each, in Table V's game."""
    kind, adversary, _ = resolve_adversary(GAME_ADVERSARY)
    task = game_task(kind)
    low_level = load_low_level(HIERARCHY_LOWLEVEL, task)
    results = [
        evaluate_highlevel(policy(task), task, low_level, EPISODES, seed=SEED, adversary_policy=adversary)
        for policy in policies
    ]
    return float(np.mean([r["R_t"] for r in results])) * DT, float(np.mean([r["E"] for r in results])) * DT


def shipped(name: str):
    return lambda task: load_highlevel_policy(paths.POLICIES_DIR / f"{name}.pt")[0]


def test_shipped_ci_hrl_covers_targets_and_keeps_away_from_the_adversary():
    r_t, e = pooled_figures([shipped(name) for name in CI_HRL_SEEDS])
    assert r_t >= R_T_FLOOR, f"R_t {r_t:.1f} below the band {R_T_FLOOR}"
    assert e <= E_CEILING_S, f"E {e:.2f} s above the band {E_CEILING_S}"


def test_the_bands_fail_a_degraded_high_level():
    """The same test on untrained networks of the same shape."""
    r_t, e = pooled_figures([lambda task, s=s: HighLevelPolicy.build("consmac-a", task, seed=s) for s in range(3)])
    assert r_t < R_T_FLOOR and e > E_CEILING_S
