"""Formation templates, groups and the Hausdorff formation error (docs/design.md §4).

Templates Delta_c are world-aligned and centred at the origin with nearest-neighbour spacing s:
c = 3..6 a regular c-gon of side s; c >= 7 a regular (c-1)-gon of side s plus its centre.
"""

from __future__ import annotations

import functools

import numpy as np

from cefc_mj.task.kernels import formation_error_kernel, groups_kernel


@functools.lru_cache(maxsize=64)
def _template(c: int, spacing: float) -> np.ndarray:
    if c < 3:
        raise ValueError(f"formation size c={c}: templates exist for c >= 3")
    ring = c if c <= 6 else c - 1
    circumradius = spacing / (2.0 * np.sin(np.pi / ring))
    angles = np.pi / 2 + 2.0 * np.pi * np.arange(ring) / ring
    points = circumradius * np.stack([np.cos(angles), np.sin(angles)], axis=-1)
    if c > 6:
        points = np.concatenate([points, np.zeros((1, 2))], axis=0)
    points = points - points.mean(axis=0)
    points.setflags(write=False)
    return points


def formation_template(c: int, spacing: float = 1.0) -> np.ndarray:
    """Template Delta_c as [c, 2] points centred at the origin (read-only array).

    >>> formation_template(4).round(3).tolist()
    [[0.0, 0.707], [-0.707, 0.0], [-0.0, -0.707], [0.707, -0.0]]
    """
    return _template(int(c), float(spacing))


def directed_hausdorff(template: np.ndarray, points: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """HD(template, points) = max over template points of the min distance to `points`.

    template [..., C, 2], points [..., P, 2], mask [..., P] (True = the point exists). Batched over
    the leading axes; returns [...]. Points are used as given (centre them first for the formation
    error). With no valid point the distance is +inf.
    """
    diff = template[..., :, None, :] - points[..., None, :, :]
    dist = np.sqrt((diff * diff).sum(axis=-1))  # [..., C, P]
    if mask is not None:
        dist = np.where(mask[..., None, :], dist, np.inf)
    return dist.min(axis=-1).max(axis=-1)


@functools.lru_cache(maxsize=64)
def template_table(max_size: int, spacing: float = 1.0) -> np.ndarray:
    """[max_size+1, max_size, 2] table for the compiled kernel: row c holds Delta_c in its first c rows."""
    table = np.zeros((max_size + 1, max_size, 2))
    for c in range(3, max_size + 1):
        table[c, :c] = formation_template(c, spacing)
    table.setflags(write=False)
    return table


def connected_groups(positions: np.ndarray, radius: float) -> np.ndarray:
    """Connected components of the graph "distance < radius" per env.

    positions [B, N, 2] -> labels [B, N] int, each component labelled by its smallest member index
    (so labels are stable and comparable across steps).
    """
    labels = np.empty(positions.shape[:2], dtype=np.int64)
    groups_kernel(np.ascontiguousarray(positions, dtype=np.float64), float(radius), labels)
    return labels


def group_formation_error(
    positions: np.ndarray, labels: np.ndarray, spacing: float = 1.0, min_size: int = 3
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-group Hausdorff formation error HD(Delta_{n_g}, P_g) of the centred members.

    positions [B, N, 2], labels [B, N] (from `connected_groups`, or all zeros for "one group").
    Returns (error [B, G], size [B, G], centre [B, G, 2]) with G = N, indexed by group label:
    error is NaN where a label is unused or its group has fewer than `min_size` members.
    """
    b, n, _ = positions.shape
    error = np.empty((b, n))
    size = np.empty((b, n), dtype=np.int64)
    centre = np.empty((b, n, 2))
    formation_error_kernel(
        np.ascontiguousarray(positions, dtype=np.float64),
        np.ascontiguousarray(labels, dtype=np.int64),
        template_table(n, float(spacing)),
        min_size,
        error,
        size,
        centre,
    )
    return error, size, centre


def agent_group_error(error: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """Gather each agent's group formation error: [B, G] errors, [B, N] labels -> [B, N]."""
    return np.take_along_axis(error, labels, axis=1)
