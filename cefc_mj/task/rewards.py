"""The five CEFC rewards of the paper's Appendix A, batch-first, plus the urgency update.

All functions return per-env team rewards [B] (the paper's global reward shared by all agents)
unless stated otherwise. Distances are metres.
"""

from __future__ import annotations

import numpy as np

from cefc_mj.task.config import RewardConfig


def formation_reward(hd_sum: np.ndarray, previous: np.ndarray, lag: float) -> np.ndarray:
    """R_f(t) = -sum_k HD(Delta_{n_k}, P_k) - omega_l R_f(t-1), with R_f(0) = 0 (eq. 10)."""
    return -hd_sum - lag * previous


def anchor_navigation_reward(positions: np.ndarray, anchor: np.ndarray) -> np.ndarray:
    """Low-level R_n = -||mean position - p_a||. positions [B, N, 2], anchor [B, 2]."""
    return -np.linalg.norm(positions.mean(axis=1) - anchor, axis=-1)


def target_navigation_reward(positions: np.ndarray, targets: np.ndarray, urgency: np.ndarray) -> np.ndarray:
    """R_n = -sum_i sum_T kappa_T ||p_T - p_i|| (eq. 11). targets [B, J, 2], urgency [B, J]."""
    dist = np.linalg.norm(targets[:, None, :, :] - positions[:, :, None, :], axis=-1)  # [B, N, J]
    return -(dist * urgency[:, None, :]).sum(axis=(1, 2))


def target_coverage(
    group_error: np.ndarray,
    group_size: np.ndarray,
    group_centre: np.ndarray,
    targets: np.ndarray,
    formation_tolerance: float,
    target_radius: float,
) -> np.ndarray:
    """sum_{k*} TR_{k* -> T}: for each target, the summed size of the groups in formation
    (HD < delta_for) whose centre lies within delta_task of it. Returns [B, J].

    group_error, group_size [B, G]; group_centre [B, G, 2]; targets [B, J, 2].
    """
    in_formation = group_error < formation_tolerance  # [B, G]; NaN (not a formation group) compares False
    inside = np.linalg.norm(group_centre[:, :, None, :] - targets[:, None, :, :], axis=-1) < target_radius
    return (inside * (in_formation * group_size)[:, :, None]).sum(axis=1).astype(float)


def task_reward(coverage: np.ndarray, urgency: np.ndarray) -> np.ndarray:
    """R_t = sum_T kappa_T sum_{k*} TR_{k* -> T} (eq. 12), with coverage [B, J] from target_coverage."""
    return (urgency * coverage).sum(axis=-1)


def update_urgency(urgency: np.ndarray, coverage: np.ndarray, decay: float) -> np.ndarray:
    """kappa(t+1) = max(kappa(t) - omega_d sum_{k*} TR, 0) (eq. 14)."""
    return np.maximum(urgency - decay * coverage, 0.0)


def evasion_reward(positions: np.ndarray, adversary_pos: np.ndarray, alert_distance: float) -> np.ndarray:
    """R_e = -sum_i max(delta_a,e - ||p_A - p_i||, 0) (eq. 15). adversary_pos [B, 2]."""
    dist = np.linalg.norm(positions - adversary_pos[:, None, :], axis=-1)
    return -np.maximum(alert_distance - dist, 0.0).sum(axis=-1)


def collision_penalty(min_range: np.ndarray, params: RewardConfig) -> np.ndarray:
    """Per-agent CR (eq. 17) from the minimum LiDAR range d_{i,m}, [B, N] -> [B, N] (>= 0).

    d < delta_s: omega_cr1 (delta_s - d) + C1; delta_s <= d < delta_a,c: omega_cr2 (delta_a,c - d)
    + C2; otherwise 0. (The paper leaves d = delta_s open; it takes the second case here.)
    """
    w1, w2, c1, c2 = params.collision_constants
    near = w1 * (params.safety_distance - min_range) + c1
    alert = w2 * (params.collision_alert_distance - min_range) + c2
    return np.where(
        min_range < params.safety_distance, near, np.where(min_range < params.collision_alert_distance, alert, 0.0)
    )
