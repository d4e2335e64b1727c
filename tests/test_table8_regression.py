"""Regression tests on the Table VIII metrics: a CI-sized subset of the grid (c = 5 and 8; calm,
Wind-8, Deviation-0.8; seed 0; 1000 steps) flown on MuJoCo quadrotors with the shipped AT-M policies,
checked against the bands in eval/table8_bands.json (how they were set is written there)."""

import pytest

from cefc_mj.eval.bands import BANDS_FILE, SUBSET_CONDITIONS, SUBSET_FORMATIONS, load_bands
from cefc_mj.eval.runner import CONDITIONS, EpisodeSpec, run_episode

pytestmark = pytest.mark.skipif(not BANDS_FILE.is_file(), reason="no regression bands shipped yet")


@pytest.fixture(scope="module")
def bands():
    return load_bands()


@pytest.fixture(scope="module")
def flown(bands):
    results = {}
    for c in SUBSET_FORMATIONS:
        for cond in SUBSET_CONDITIONS:
            wind, deviation = CONDITIONS[cond]
            spec = EpisodeSpec(formation=c, seed=bands["seed"], wind=wind, deviation=deviation, steps=bands["steps"],
                               policy=bands["policy"])
            results[(c, cond)] = run_episode(spec)
    return results


@pytest.mark.parametrize("c", SUBSET_FORMATIONS)
@pytest.mark.parametrize("cond", SUBSET_CONDITIONS)
def test_metrics_within_bands(c, cond, flown, bands):
    result = flown[(c, cond)]
    assert result.diverged is None, f"c={c} {cond}: simulation diverged: {result.diverged}"
    band = bands["cells"][str(c)][cond]
    for metric in "FNC":
        value, (low, high) = getattr(result, metric), band[metric]
        assert low <= value <= high, (
            f"c={c} {cond}: metric {metric} = {value:.2f} left its band [{low:.2f}, {high:.2f}] "
            f"(measured {band['measured'][metric]:.2f} when the band was set)"
        )


@pytest.mark.parametrize("c", SUBSET_FORMATIONS)
def test_perturbations_lower_formation_and_navigation(c, flown):
    calm = flown[(c, "SITL-S")]
    for cond in ("Wind-8", "Deviation-0.8"):
        r = flown[(c, cond)]
        assert r.F + r.N < calm.F + calm.N, f"c={c}: {cond} F+N {r.F + r.N:.0f} is not below calm {calm.F + calm.N:.0f}"
