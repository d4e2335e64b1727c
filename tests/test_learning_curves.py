"""Training curves over seeds (`cefc_mj.eval.learning_curves`, the paper's Figs. 6 and 7): grouping by
run name, the mean and band against scipy, truncation to what every seed reached, the files written
(the PNG read back), and bad input as one line with exit code 2 before anything is written."""

from __future__ import annotations

import csv
import subprocess
import sys

import numpy as np
import pytest
from PIL import Image
from scipy import stats

from cefc_mj.eval import learning_curves as lc


def _run(folder, iterations, rng, phase_at=None, offset=0.0):
    folder.mkdir(parents=True)
    (folder / "config.json").write_text("{}")
    with (folder / "progress.csv").open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["iteration", "episodes_total", "phase", *lc.METRICS, "approx_kl"])
        for i in range(1, iterations + 1):
            phase = int(phase_at is not None and i > phase_at)
            w.writerow([i, 20 * i, phase, -1000 + 10 * i + offset + rng.normal(), 300 - i + rng.normal(), i, 0.01])
    return folder


@pytest.fixture
def runs(tmp_path):
    rng = np.random.default_rng(0)
    root = tmp_path / "runs"
    _run(root / "cihrl_consmac_a", 12, rng, phase_at=8)
    _run(root / "cihrl_consmac_a_seed1", 12, rng, phase_at=8, offset=5)
    _run(root / "cihrl_consmac_a_seed2", 10, rng, phase_at=8, offset=-5)  # interrupted
    _run(root / "cihrl_consmac_a_wo_com", 12, rng, phase_at=8, offset=-100)
    return root


def test_groups_mean_band_and_truncation(runs):
    curves = lc.group_curves([lc.read_run(f) for f, _ in lc.find_runs([runs])], smooth=3)
    assert list(curves) == ["cihrl_consmac_a", "cihrl_consmac_a_wo_com"]
    a = curves["cihrl_consmac_a"]
    assert a["seeds"] == [0, 1, 2] and a["episodes"].size == 10  # the shortest seed's length
    assert a["phase_switch"] == 180.0
    seeds = [lc.read_run(runs / n).columns["episode_return"][:10] for n in a["runs"]]
    smoothed = np.stack([np.convolve(s, np.ones(3) / 3, mode="full")[:10] for s in seeds])
    smoothed[:, 0], smoothed[:, 1] = [s[0] for s in seeds], [s[:2].mean() for s in seeds]
    np.testing.assert_allclose(a["episode_return"]["mean"], smoothed.mean(axis=0))
    low, high = stats.t.interval(0.95, 2, loc=smoothed[:, -1].mean(), scale=stats.sem(smoothed[:, -1]))
    band = a["episode_return"]
    assert band["low"][-1] == pytest.approx(low) and band["high"][-1] == pytest.approx(high)
    # one seed: a mean, no band; and the ablation's curve sits where its data is, not at the reference's
    w = curves["cihrl_consmac_a_wo_com"]
    assert np.isnan(w["episode_return"]["low"]).all()
    assert (w["episode_return"]["mean"][3:10] < a["episode_return"]["mean"][3:] - 80).all()


def test_command_writes_the_figure_and_refuses_bad_input(runs, tmp_path):
    out = tmp_path / "fig7"
    cmd = [sys.executable, "-m", "cefc_mj.eval.learning_curves", str(runs), "--figure", "fig7", "--out", str(out)]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert Image.open(out / "curves.png").size[0] > 500
    rows = list(csv.DictReader((out / "curves.csv").open()))
    assert {r["group"] for r in rows} == {"cihrl_consmac_a", "cihrl_consmac_a_wo_com"}
    readme = (out / "README.md").read_text()
    assert "| ConsMAC-A | 3 (" in readme and "| ConsMAC-wo-Com | 1 (" in readme
    for bad, says in (
        ([str(tmp_path / "nowhere"), "--out", str(tmp_path / "x")], "not a folder"),
        ([str(runs), "--out", str(tmp_path / "x"), "--smooth", "0"], "--smooth"),
        ([str(runs), "--out", str(tmp_path / "no" / "such" / "x")], "cannot write"),
        ([str(runs / "cihrl_consmac_a_wo_com"), "--figure", "fig6", "--out", str(tmp_path / "x")], "none of its runs"),
        ([str(runs)], "--out"),
    ):
        done = subprocess.run(cmd[:3] + bad, capture_output=True, text=True, timeout=120)
        assert done.returncode == 2 and says in done.stderr and len(done.stderr.strip().splitlines()) == 1, done.stderr
    assert not (tmp_path / "x").exists()
    shown = subprocess.run(cmd[:3] + ["--help"], capture_output=True, text=True, timeout=120).stdout
    assert "95 % band" in shown and "%%" not in shown  # the description is printed as written


def _benchmarl_run(folder):
    """A run of `cefc-train highlevel-benchmarl` (its progress.csv has other columns)."""
    folder.mkdir(parents=True)
    (folder / "progress.csv").write_text("iteration,frames,episodes,episode_return\n1,800,20,-77809.5\n")
    return folder


def test_other_trainers_runs_beside_them_are_skipped_and_named_ones_refused(runs, tmp_path):
    """The training commands put BenchMARL's runs in the same folder: drawing that folder skips them
    (and says so); naming one is refused in one line."""
    bench = _benchmarl_run(runs / "benchmarl_masac")
    out = tmp_path / "all"
    cmd = [sys.executable, "-m", "cefc_mj.eval.learning_curves"]
    done = subprocess.run([*cmd, str(runs), "--out", str(out)], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert "skipped: benchmarl_masac" in done.stdout
    assert "Skipped (not `cefc-train highlevel` logs): benchmarl_masac." in (out / "README.md").read_text()
    assert {r["group"] for r in csv.DictReader((out / "curves.csv").open())} == {
        "cihrl_consmac_a",
        "cihrl_consmac_a_wo_com",
    }
    done = subprocess.run([*cmd, str(bench), "--out", str(tmp_path / "x")], capture_output=True, text=True, timeout=120)
    assert done.returncode == 2 and "not a high-level training log" in done.stderr, done.stderr
    assert len(done.stderr.strip().splitlines()) == 1 and not (tmp_path / "x").exists()
    # a folder holding only other trainers' runs draws nothing: one line, exit 2
    only = _benchmarl_run(tmp_path / "only" / "benchmarl_mappo").parent
    done = subprocess.run([*cmd, str(only), "--out", str(tmp_path / "x")], capture_output=True, text=True, timeout=120)
    assert done.returncode == 2 and "no high-level training run (skipped benchmarl_mappo)" in done.stderr, done.stderr
    assert len(done.stderr.strip().splitlines()) == 1 and not (tmp_path / "x").exists()
