"""Top-down PNG of an episode (for readers without a Rerun viewer).

Obstacles as circles, each anchor point with its 1 m zone, one trajectory per UAV (start o, end ^),
collision onsets as red crosses, targets, the adversary's path; the title names the backend,
condition, formation, seed and the episode's F / N / C. Headless: draws on an Agg canvas without
pyplot, so it never needs a display nor touches matplotlib's global backend.

>>> from cefc_mj.eval.record import synthetic_record
>>> plot_episode(synthetic_record(n_steps=30, n_agents=5), "/tmp/doctest_episode.png").name
'doctest_episode.png'
"""

from __future__ import annotations

import os
from pathlib import Path

import matplotlib
import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.patches import Circle

from cefc_mj.eval.record import EpisodeRecord
from cefc_mj.fileio import atomic_write

_ZONE_RADIUS = 1.0  # N counts steps with the swarm centre within 1 m of the anchor (docs/design.md §5)


def episode_title(record: EpisodeRecord) -> str:
    """'<backend> · <condition> · c=<c> · seed <s>' and, on a second line, F / N / C where known."""
    head = f"{record.backend} · {record.condition} · c={record.formation} · seed {record.seed}"
    parts = []
    for key, label, fmt in (("F_so_far", "F", "{:.0f}"), ("N_so_far", "N", "{:.0f}"), ("C_so_far", "C", "{:.2f} %")):
        series = record.scalars.get(key)
        if series is not None and len(series):
            parts.append(f"{label} = {fmt.format(series[-1])}")
    steps = f"{record.n_steps} steps"
    return f"{head}\n{', '.join([*parts, steps])}"


def plot_episode(record: EpisodeRecord, path: str | os.PathLike, dpi: int = 120) -> Path:
    """Draw the episode top-down and write it to `path` (PNG) atomically; returns the path."""
    path = Path(path)
    fig = Figure(figsize=(7.5, 7.5), dpi=dpi)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.grid(True, linewidth=0.3, alpha=0.5)

    for cx, cy in record.obstacles:
        ax.add_patch(Circle((cx, cy), record.obstacle_radius, facecolor="0.55", edgecolor="0.3", linewidth=0.6))

    changes = np.flatnonzero(np.any(np.diff(record.anchor, axis=0) != 0, axis=1)) + 1
    for k, (x, y) in enumerate(record.anchor[np.concatenate([[0], changes])]):
        ax.add_patch(Circle((x, y), _ZONE_RADIUS, fill=False, edgecolor="tab:green", linestyle="--"))
        ax.plot(
            x,
            y,
            marker="*",
            markersize=14,
            color="tab:green",
            markeredgecolor="k",
            label="anchor (1 m zone)" if k == 0 else None,
        )
        ax.annotate(str(k + 1), (x, y), textcoords="offset points", xytext=(6, 6), color="tab:green")

    cmap = matplotlib.colormaps["tab10"]
    xy = record.agent_pos[..., :2]
    for i in range(record.n_agents):
        color = cmap(i % 10)
        ax.plot(xy[:, i, 0], xy[:, i, 1], color=color, linewidth=1.0, label=f"uav {i}")
        ax.plot(*xy[0, i], marker="o", color=color, markeredgecolor="k", markersize=5)
        ax.plot(*xy[-1, i], marker="^", color=color, markeredgecolor="k", markersize=7)

    ax.plot([], [], marker="o", linestyle="", color="0.6", markeredgecolor="k", label="start")
    ax.plot([], [], marker="^", linestyle="", color="0.6", markeredgecolor="k", label="end")

    onset = record.collision & ~np.concatenate([np.zeros((1, record.n_agents), bool), record.collision[:-1]])
    if onset.any():
        hits = xy[onset]
        ax.scatter(
            hits[:, 0],
            hits[:, 1],
            marker="x",
            s=60,
            color="red",
            linewidths=2,
            zorder=5,
            label=f"collision ({len(hits)})",
        )
    if len(record.targets):
        ax.scatter(
            record.targets[:, 0],
            record.targets[:, 1],
            marker="s",
            s=80,
            color="gold",
            edgecolor="k",
            zorder=4,
            label="target",
        )
    if record.adversary_pos is not None:
        ax.plot(record.adversary_pos[:, 0], record.adversary_pos[:, 1], color="k", linestyle=":", label="adversary")

    ax.set_title(episode_title(record), fontsize=10)
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8, frameon=False)
    fig.tight_layout()
    atomic_write(path, lambda fh: fig.savefig(fh, format="png"))
    return path
