"""Rule-based adversaries (docs/design.md §4): pick a point to chase, fly at it at top speed.

- "nearest_group": the centre of the nearest group with at least 3 members (the paper's default
  behaviour of its PPO adversary); the nearest agent when there is no such group.
- "r_nearest": the nearest agent (R-Nearest).
- "r_largest": the centre of the largest group, nearest first among equals (R-Largest).

The adversary flies at top speed toward that point (`pursuit_acceleration`). With
`TaskConfig.adversary_avoids_obstacles` it steers around the obstacle cylinders on the way
(`avoiding_velocity`); otherwise it flies straight through them, as neither world stops it.
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


def avoiding_velocity(desired: np.ndarray, position: np.ndarray, obstacles: np.ndarray, keep_out: float,
                      margin: float) -> np.ndarray:
    """Bend the desired velocity [B, 2] around obstacle discs (centres [B, K, 2]) so that the
    adversary stays outside `keep_out` (m, obstacle plus body radius) of every centre.

    Within `margin` (m) of a keep-out circle an obstacle acts with weight w rising from 0 at the
    margin to 1 at the circle: the part of the velocity heading into it is removed in proportion
    to w and replaced by motion along the circle (on the side the velocity already leans to, so a
    goal behind the obstacle is reached around it) plus a push outwards of w x speed. The result
    keeps the desired speed. Far from every obstacle it is `desired` unchanged."""
    speed = np.linalg.norm(desired, axis=-1, keepdims=True)  # [B, 1]
    offset = position[:, None, :] - obstacles  # [B, K, 2], obstacle -> adversary
    dist = np.maximum(np.linalg.norm(offset, axis=-1, keepdims=True), 1e-9)
    away = offset / dist
    weight = np.clip((keep_out + margin - dist) / margin, 0.0, 1.0)  # [B, K, 1]
    tangent = np.stack([-away[..., 1], away[..., 0]], axis=-1)
    side = np.sign((desired[:, None, :] * tangent).sum(-1, keepdims=True))
    tangent *= np.where(side == 0, 1.0, side)  # head-on: go round counter-clockwise
    inward = np.maximum(-(desired[:, None, :] * away).sum(-1, keepdims=True), 0.0)  # speed into the obstacle
    steer = (weight * (inward * (away + tangent) + speed[:, None, :] * away)).sum(axis=1)
    velocity = desired + steer
    norm = np.linalg.norm(velocity, axis=-1, keepdims=True)
    return np.where(norm > 1e-9, velocity * speed / np.maximum(norm, 1e-9), desired)


def pursuit_acceleration(
    goal: np.ndarray, position: np.ndarray, velocity: np.ndarray, speed_max: float, accel_max: float, dt: float,
    obstacles: np.ndarray | None = None, keep_out: float = 0.0, margin: float = 1.0,
) -> np.ndarray:
    """Acceleration [B, 2] that turns the velocity towards speed_max along goal - position (bent
    around `obstacles` [B, K, 2] by `avoiding_velocity` when given), per-axis clipped to accel_max."""
    offset = goal - position
    dist = np.linalg.norm(offset, axis=-1, keepdims=True)
    desired = speed_max * offset / np.maximum(dist, 1e-9)
    if obstacles is not None and obstacles.shape[1]:
        desired = avoiding_velocity(desired, position, obstacles, keep_out, margin)
    return np.clip((desired - velocity) / dt, -accel_max, accel_max)
