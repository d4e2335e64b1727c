"""Slow, obvious numpy references of the compiled hot-loop kernels (cefc_mj/task/kernels.py)."""

import numpy as np

from cefc_mj.task.formation import directed_hausdorff, formation_template


def connected_groups_reference(positions: np.ndarray, radius: float) -> np.ndarray:
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


def group_formation_error_reference(
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


def neighbour_features_reference(
    perceived_pos: np.ndarray, velocity: np.ndarray, slots: int, observation_distance: float
) -> tuple[np.ndarray, np.ndarray]:
    """Neighbours sorted by perceived distance, nearest first, padded to `slots`.

    perceived_pos, velocity [B, N, 2] -> (features [B, N, slots, 4] = (p_j - p_i, v_j - v_i),
    mask [B, N, slots] float, 1 for a neighbour closer than observation_distance).
    """
    b, n, _ = perceived_pos.shape
    rel_pos = perceived_pos[:, None, :, :] - perceived_pos[:, :, None, :]  # [B, i, j, 2]
    rel_vel = velocity[:, None, :, :] - velocity[:, :, None, :]
    dist = np.sqrt((rel_pos * rel_pos).sum(-1))
    dist[:, np.arange(n), np.arange(n)] = np.inf
    take = min(slots, n - 1)
    order = np.argsort(dist, axis=-1, kind="stable")[:, :, :take]  # [B, N, take]
    near = np.take_along_axis(dist, order, axis=-1) < observation_distance
    feats = (
        np.concatenate(
            [
                np.take_along_axis(rel_pos, order[..., None], axis=2),
                np.take_along_axis(rel_vel, order[..., None], axis=2),
            ],
            axis=-1,
        )
        * near[..., None]
    )
    features = np.zeros((b, n, slots, 4))
    mask = np.zeros((b, n, slots))
    features[:, :, :take] = feats
    mask[:, :, :take] = near
    return features, mask


def low_level_observation_reference(
    perceived_pos: np.ndarray,
    velocity: np.ndarray,
    anchor: np.ndarray,
    lidar: np.ndarray,
    slots: int,
    observation_distance: float,
) -> np.ndarray:
    """The low-level observation [B, N, D] float32 as the concatenation of its parts (anchor [B, 2] or [B, N, 2])."""
    from cefc_mj.task.observation import neighbour_features

    b, n, _ = perceived_pos.shape
    if anchor.ndim == 2:
        anchor = anchor[:, None, :]
    feats, mask = neighbour_features(perceived_pos, velocity, slots, observation_distance)
    return np.concatenate([anchor - perceived_pos, velocity, feats.reshape(b, n, -1), mask, lidar], axis=-1).astype(
        np.float32
    )
