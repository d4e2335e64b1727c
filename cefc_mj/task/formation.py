"""Formation templates, groups and the Hausdorff formation error (DESIGN §4).

Templates Delta_c are world-aligned and centred at the origin with nearest-neighbour spacing s:
c = 3..6 a regular c-gon of side s; c >= 7 a regular (c-1)-gon of side s plus its centre.
"""

from __future__ import annotations

import functools

import numpy as np


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


def connected_groups(positions: np.ndarray, radius: float) -> np.ndarray:
    """Connected components of the graph "distance < radius" per env.

    positions [B, N, 2] -> labels [B, N] int, each component labelled by its smallest member index
    (so labels are stable and comparable across steps).
    """
    b, n, _ = positions.shape
    diff = positions[:, :, None, :] - positions[:, None, :, :]
    adjacency = np.einsum("bijk,bijk->bij", diff, diff) < radius * radius
    labels = np.broadcast_to(np.arange(n), (b, n)).copy()
    # Min-label propagation over the adjacency: converges in at most n - 1 rounds.
    for _ in range(max(n - 1, 0)):
        candidate = np.where(adjacency, labels[:, None, :], n).min(axis=-1)
        if np.array_equal(candidate, labels):
            break
        labels = candidate
    return labels


def group_formation_error(
    positions: np.ndarray, labels: np.ndarray, spacing: float = 1.0, min_size: int = 3
) -> tuple[np.ndarray, np.ndarray]:
    """Per-group Hausdorff formation error.

    positions [B, N, 2], labels [B, N] (from `connected_groups`, or all zeros for "one group").
    Returns (error [B, N], group_size [B, N]): error[b, g] is HD(Delta_{n_g}, P_g) for the group
    labelled g (indexed by its label), NaN where label g is unused or the group has fewer than
    `min_size` members; group_size[b, g] is that group's size (0 where unused).
    """
    b, n, _ = positions.shape
    one_hot = labels[:, None, :] == np.arange(n)[None, :, None]  # [B, G=N, N]
    size = one_hot.sum(axis=-1)
    centre = np.einsum("bgn,bnk->bgk", one_hot, positions) / np.maximum(size, 1)[..., None]
    centred = positions[:, None, :, :] - centre[:, :, None, :]  # [B, G, N, 2]
    error = np.full((b, n), np.nan)
    for c in np.unique(size):
        if c < min_size:
            continue
        sel = size == c
        error[sel] = directed_hausdorff(formation_template(int(c), spacing)[None], centred[sel], one_hot[sel])
    return error, size


def agent_group_error(error: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """Gather each agent's group formation error: [B, G] errors, [B, N] labels -> [B, N]."""
    return np.take_along_axis(error, labels, axis=1)
