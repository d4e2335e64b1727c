"""Local observations, batch-first (docs/architecture.md has the layouts as tables).

Everything an agent perceives is derived from *perceived* positions (true position plus its sensing
deviation): the anchor- and target-relative vectors, neighbours' broadcast positions (each with the
neighbour's own deviation) and the LiDAR (cast by the world from the perceived position).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cefc_mj.task.config import TaskConfig
from cefc_mj.task.kernels import low_level_observation_kernel, neighbours_kernel


@dataclass(frozen=True)
class ObservationLayout:
    """Named slices of the flat per-agent observation vector."""

    parts: tuple[tuple[str, int], ...]
    """(name, size) in order."""

    @property
    def size(self) -> int:
        return sum(n for _, n in self.parts)

    def __getitem__(self, name: str) -> slice:
        start = 0
        for part, n in self.parts:
            if part == name:
                return slice(start, start + n)
            start += n
        raise KeyError(f"no observation part {name!r}; parts are {[p for p, _ in self.parts]}")

    def names(self) -> list[str]:
        return [p for p, _ in self.parts]

    def to_dict(self) -> dict:
        return {name: size for name, size in self.parts}


def low_level_layout(cfg: TaskConfig) -> ObservationLayout:
    """[anchor 2, own_velocity 2, neighbours 4K, neighbour_mask K, lidar M] (63 for K=7, M=24)."""
    k = cfg.neighbour_slots
    return ObservationLayout(
        (("anchor", 2), ("own_velocity", 2), ("neighbours", 4 * k), ("neighbour_mask", k), ("lidar", cfg.n_lidar_rays))
    )


def cefc_layout(cfg: TaskConfig) -> ObservationLayout:
    """[targets 3J, adversary 4, neighbours 4K, neighbour_mask K, lidar M]; the first 3J + 4 + 4K
    numbers are the paper's o_i (38 for K = 7 = N - 1 at N = 8, J = 2). K = cfg.neighbour_slots."""
    k = cfg.neighbour_slots
    return ObservationLayout(
        (
            ("targets", 3 * cfg.n_targets),
            ("adversary", 4),
            ("neighbours", 4 * k),
            ("neighbour_mask", k),
            ("lidar", cfg.n_lidar_rays),
        )
    )


def layout_for(cfg: TaskConfig) -> ObservationLayout:
    return low_level_layout(cfg) if cfg.mode == "formation" else cefc_layout(cfg)


def neighbour_features(
    perceived_pos: np.ndarray, velocity: np.ndarray, slots: int, observation_distance: float
) -> tuple[np.ndarray, np.ndarray]:
    """Neighbours sorted by perceived distance, nearest first (ties by index), padded to `slots`.

    perceived_pos, velocity [B, N, 2] -> (features [B, N, slots, 4] = (p_j - p_i, v_j - v_i),
    mask [B, N, slots] float, 1 for a neighbour closer than observation_distance).
    """
    b, n, _ = perceived_pos.shape
    features = np.empty((b, n, slots, 4))
    mask = np.empty((b, n, slots))
    neighbours_kernel(
        np.ascontiguousarray(perceived_pos, dtype=np.float64),
        np.ascontiguousarray(velocity, dtype=np.float64),
        int(slots),
        float(observation_distance),
        features,
        mask,
    )
    return features, mask


def build_low_level_observation(
    cfg: TaskConfig, perceived_pos: np.ndarray, velocity: np.ndarray, anchor: np.ndarray, lidar: np.ndarray
) -> np.ndarray:
    """Low-level observation [B, N, D]. anchor [B, 2] (one anchor per env) or [B, N, 2] (per agent)."""
    b, n, _ = perceived_pos.shape
    if anchor.ndim == 2:
        anchor = anchor[:, None, :]
    slots = cfg.neighbour_slots
    out = np.empty((b, n, 4 + 5 * slots + lidar.shape[-1]), dtype=np.float32)
    f64 = lambda a: np.ascontiguousarray(a, dtype=np.float64)  # noqa: E731 - one array type per kernel argument
    low_level_observation_kernel(
        f64(perceived_pos),
        f64(velocity),
        f64(np.broadcast_to(anchor, (b, n, 2))),
        f64(lidar),
        int(slots),
        float(cfg.observation_distance),
        out,
    )
    return out


def build_cefc_observation(
    cfg: TaskConfig,
    perceived_pos: np.ndarray,
    velocity: np.ndarray,
    targets: np.ndarray,
    urgency: np.ndarray,
    adversary_pos: np.ndarray,
    adversary_vel: np.ndarray,
    lidar: np.ndarray,
) -> np.ndarray:
    """CEFC observation [B, N, D]: o_i (targets, adversary, neighbours), mask, LiDAR."""
    b, n, _ = perceived_pos.shape
    target_rel = targets[:, None, :, :] - perceived_pos[:, :, None, :]  # [B, N, J, 2]
    target_part = np.concatenate(
        [target_rel, np.broadcast_to(urgency[:, None, :, None], (b, n, urgency.shape[1], 1))], axis=-1
    ).reshape(b, n, -1)
    adversary_part = np.concatenate(
        [adversary_pos[:, None, :] - perceived_pos, adversary_vel[:, None, :] - velocity], axis=-1
    )
    feats, mask = neighbour_features(perceived_pos, velocity, cfg.neighbour_slots, cfg.observation_distance)
    return np.concatenate([target_part, adversary_part, feats.reshape(b, n, -1), mask, lidar], axis=-1).astype(
        np.float32
    )
