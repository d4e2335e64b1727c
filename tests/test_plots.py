"""Top-down PNG: written atomically, a real image, title with condition and F/N/C."""

from __future__ import annotations

import numpy as np
import pytest
from matplotlib.image import imread

from cefc_mj.errors import ConfigError
from cefc_mj.eval.record import synthetic_record
from cefc_mj.viz.plots import episode_title, plot_episode


def test_png_written_and_not_blank(tmp_path):
    record = synthetic_record(n_steps=120, n_agents=6)
    path = plot_episode(record, tmp_path / "episode.png")
    assert [p.name for p in tmp_path.iterdir()] == ["episode.png"]
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    image = imread(path)
    assert image.shape[0] > 500 and image.shape[1] > 500
    rgb = image[..., :3].reshape(-1, 3)
    assert len(np.unique((rgb * 255).astype(np.uint8), axis=0)) > 20  # many colours: lines, obstacles, legend
    # The obstacle grey lands where the first obstacle is: the drawing is not just the frame.
    assert (np.abs(rgb - 0.55).max(axis=1) < 0.02).sum() > 100


def test_title_names_condition_and_metrics():
    record = synthetic_record(n_steps=50, n_agents=5)
    title = episode_title(record)
    f, n, c = (record.scalars[k][-1] for k in ("F_so_far", "N_so_far", "C_so_far"))
    assert "Synthetic" in title and "c=5" in title and "seed 0" in title
    assert f"F = {f:.0f}" in title and f"N = {n:.0f}" in title and f"C = {c:.2f} %" in title


def test_title_without_metrics_still_names_the_episode():
    record = synthetic_record(n_steps=5, n_agents=3)
    record.scalars = {}
    assert episode_title(record).splitlines()[1] == "5 steps"


def test_unwritable_folder_is_a_config_error(tmp_path):
    with pytest.raises(ConfigError, match="does not exist"):
        plot_episode(synthetic_record(n_steps=5, n_agents=3), tmp_path / "missing" / "x.png")
