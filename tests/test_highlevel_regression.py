"""Regression test of the shipped CI-HRL high level (cefc_mj/eval/highlevel.py, Table V's game: the
shipped student, the PPO adversary).

Closed-loop figures are chaotic: the same seed repeats bit for bit on one machine, not across CPUs
or library builds. So the test asserts means over 30 episodes against bands set from the measured
spread, not exact values. Measured (particle world, seconds scale):

    30 episodes, seed 100 / 200    R_t             E (s)
    cihrl_consmac_a                146.8 / 112.6    7.7 /  8.5
    cihrl_consmac_a_seed1          118.8 / 133.0    8.3 /  9.5
    cihrl_consmac_a_seed2          119.0 / 131.8    7.2 /  6.4
    cihrl_consmac_a_wo_ft           79.1 /  84.9   11.1 / 11.5   (pre-training only)
    untrained networks              56.7 /  60.7   24.7 / 26.0

The standard error of a 30-episode mean is about 18 for R_t and 0.8 s for E; the bands sit about
2.5 of them from the shipped policy's mean: R_t >= 95 and E <= 10.5 s. A policy without the
fine-tuning (wo-FT) or an untrained one fails both.
"""

import pytest

from cefc_mj import paths
from cefc_mj.eval.highlevel import DT, GAME_ADVERSARY, evaluate_highlevel, game_task, resolve_adversary
from cefc_mj.hierarchy import load_low_level
from cefc_mj.nn.highlevel_policy import load_highlevel_policy

pytestmark = pytest.mark.usefixtures("one_torch_thread")

EPISODES, SEED = 30, 100
R_T_FLOOR = 95.0
E_CEILING_S = 10.5


def figures(name: str) -> tuple[float, float]:
    kind, adversary, _ = resolve_adversary(GAME_ADVERSARY)
    task = game_task(kind)
    policy, _ = load_highlevel_policy(paths.POLICIES_DIR / f"{name}.pt")
    result = evaluate_highlevel(policy, task, load_low_level("atm_student", task), EPISODES, seed=SEED,
                                adversary_policy=adversary)
    return result["R_t"] * DT, result["E"] * DT


def test_shipped_ci_hrl_covers_targets_and_keeps_away_from_the_adversary():
    r_t, e = figures("cihrl_consmac_a")
    assert r_t >= R_T_FLOOR, f"R_t {r_t:.1f} below the band {R_T_FLOOR}"
    assert e <= E_CEILING_S, f"E {e:.2f} s above the band {E_CEILING_S}"


def test_the_bands_fail_a_degraded_high_level():
    """The same test on the pre-training weights (no fine-tuning on the formation low level)."""
    r_t, e = figures("cihrl_consmac_a_wo_ft")
    assert r_t < R_T_FLOOR and e > E_CEILING_S
