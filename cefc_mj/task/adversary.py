"""Rule-based adversaries (docs/design.md §4): pick a point to chase, fly at it at top speed.

- "nearest_group": the centre of the nearest group with at least 3 members (the paper's default
  behaviour of its PPO adversary); the nearest agent when there is no such group.
- "r_nearest": the nearest agent (R-Nearest).
- "r_largest": the centre of the largest group, nearest first among equals (R-Largest).
"""

from __future__ import annotations

import numpy as np


def adversary_goal(
    rule: str, adversary_pos: np.ndarray, agent_pos: np.ndarray, group_size: np.ndarray, group_centre: np.ndarray
) -> np.ndarray:
    """The point [B, 2] the adversary chases. group_size [B, G] and group_centre [B, G, 2] describe
    the agents' groups (as returned by `group_formation_error`)."""
    b = agent_pos.shape[0]
    offset = agent_pos - adversary_pos[:, None, :]
    nearest_agent = agent_pos[np.arange(b), (offset * offset).sum(-1).argmin(axis=-1)]
    if rule == "r_nearest":
        return nearest_agent
    size, centre = group_size, group_centre
    centre_offset = centre - adversary_pos[:, None, :]
    centre_dist = np.sqrt((centre_offset * centre_offset).sum(-1))
    if rule == "r_largest":
        # Largest group first, ties broken by distance (a distance below 1e6 m never outweighs size).
        score = np.where(size > 0, size * 1e6 - centre_dist, -np.inf)
        return centre[np.arange(b), score.argmax(axis=-1)]
    if rule == "nearest_group":
        eligible = size >= 3
        best = np.where(eligible, centre_dist, np.inf).argmin(axis=-1)
        return np.where(eligible.any(-1)[:, None], centre[np.arange(b), best], nearest_agent)
    raise ValueError(f"unknown adversary rule {rule!r}")


def pursuit_acceleration(
    goal: np.ndarray, position: np.ndarray, velocity: np.ndarray, speed_max: float, accel_max: float, dt: float
) -> np.ndarray:
    """Acceleration [B, 2] that turns the velocity towards speed_max along goal - position,
    per-axis clipped to accel_max."""
    offset = goal - position
    dist = np.linalg.norm(offset, axis=-1, keepdims=True)
    desired = speed_max * offset / np.maximum(dist, 1e-9)
    return np.clip((desired - velocity) / dt, -accel_max, accel_max)
