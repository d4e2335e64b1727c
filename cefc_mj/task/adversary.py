"""Rule-based adversaries (docs/design.md §4): pick a point to chase, fly at it at top speed.

- "nearest_group": the centre of the nearest group with at least 3 members (the paper's default
  behaviour of its PPO adversary); the nearest agent when there is no such group.
- "r_nearest": the nearest agent (R-Nearest).
- "r_largest": the centre of the largest group, nearest first among equals (R-Largest).
- "nearest_group_strike": "nearest_group", but the nearest agent once one is within STRIKE_DISTANCE
  (not in the paper: the teacher the PPO adversary imitated before PPO, docs/research/high_level.md).
- "nearest_group_member": "nearest_group", but the nearest member of that group once one is within
  STRIKE_DISTANCE (not in the paper): unlike "nearest_group_strike" a lone UAV cannot lure it away
  from the group it chases (docs/research/high_level.md).
- "nearest_group_intercept": "nearest_group_member", but aiming ahead (not in the paper): at the
  group's centre plus the group's mean velocity times the time it needs to get there (at most
  INTERCEPT_HORIZON), and at a member within STRIKE_DISTANCE plus STRIKE_LEAD of its velocity. The
  UAVs fly faster than the adversary, so a pure pursuit falls behind what it chases; like the member
  rule it ignores a lone UAV, which teams learn to use as a lure (the game adversary's teacher,
  chosen on validation games: docs/research/high_level.md). `InterceptRule` holds its settings; other
  settings of the same family are the variants it was chosen among.

The adversary flies at top speed toward that point (`pursuit_acceleration`). With
`TaskConfig.adversary_avoids_obstacles` it steers around the obstacle cylinders on the way
(`avoiding_velocity`); otherwise it flies straight through them, as neither world stops it.

The learned adversary (TaskConfig.adversary = "learned", the paper's PPO predator) reads
`adversary_observation` and is trained on `adversary_reward`; both are task code, the same for
particles and quadrotors. Its observation does not grow with N: the nearest `ADVERSARY_SLOTS`
agents and the nearest `ADVERSARY_OBSTACLE_SLOTS` obstacles, each slot with a presence flag.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal, get_args

import numpy as np

STRIKE_DISTANCE = 3.0
"""Within this distance (m) of a UAV, "nearest_group_strike" chases that UAV (the UAVs' observation range)."""
INTERCEPT_HORIZON = 2.0
"""The longest time (s) "nearest_group_intercept" looks ahead of the group it flies to."""
STRIKE_LEAD = 1.5
"""How far ahead (s of its velocity) "nearest_group_intercept" aims at a member within STRIKE_DISTANCE."""

StrikeTarget = Literal["member", "grouped", "any"]
STRIKE_TARGETS = get_args(StrikeTarget)


@dataclass(frozen=True)
class InterceptRule:
    """A chase rule of the "nearest_group_intercept" family; the defaults are that rule. Rules with
    other settings are flown by `benchmarks/adversary_strength.py`, which compares them on validation games."""

    horizon: float = INTERCEPT_HORIZON
    """The longest time (s) it looks ahead of the group it flies to (0: the group's centre as it is)."""
    strike_distance: float | None = STRIKE_DISTANCE
    """Within this distance (m) of a UAV it may strike, i.e. chase that UAV (None: never)."""
    strike_lead: float = STRIKE_LEAD
    """How far ahead (s of its velocity) it aims at the UAV it strikes at (0: where it is)."""
    strike_at: StrikeTarget = "member"
    """Which UAVs it strikes at: members of the group it chases, any UAV of a group of >= 3, any UAV.
    A UAV outside the chased group can lure the two latter away from it."""

    def __post_init__(self) -> None:
        if not (math.isfinite(self.horizon) and self.horizon >= 0):
            raise ValueError(f"horizon={self.horizon!r}: must be a finite number >= 0 (s)")
        if self.strike_distance is not None and not (math.isfinite(self.strike_distance) and self.strike_distance > 0):
            raise ValueError(f"strike_distance={self.strike_distance!r}: must be a finite number > 0 (m), or None")
        if not (math.isfinite(self.strike_lead) and self.strike_lead >= 0):
            raise ValueError(f"strike_lead={self.strike_lead!r}: must be a finite number >= 0 (s)")
        if self.strike_at not in STRIKE_TARGETS:
            raise ValueError(f"strike_at={self.strike_at!r}: must be member, grouped or any")


def adversary_goal(
    rule: str | InterceptRule,
    adversary_pos: np.ndarray,
    agent_pos: np.ndarray,
    group_size: np.ndarray,
    group_centre: np.ndarray,
    labels: np.ndarray | None = None,
    agent_vel: np.ndarray | None = None,
    speed_max: float | None = None,
) -> np.ndarray:
    """The point [B, 2] the adversary chases under `rule` (a rule's name, or an `InterceptRule`).
    group_size [B, G] and group_centre [B, G, 2] describe the agents' groups (as returned by
    `group_formation_error`), indexed by the agents' group labels [B, N] (`connected_groups`), which
    only "nearest_group_member" and the intercept rules need; the latter also need the agents'
    velocities [B, N, 2] and the adversary's top speed (m/s)."""
    b = agent_pos.shape[0]
    offset = agent_pos - adversary_pos[:, None, :]
    square = (offset * offset).sum(-1)
    nearest_agent = agent_pos[np.arange(b), square.argmin(axis=-1)]
    if rule == "r_nearest":
        return nearest_agent
    if rule == "nearest_group_strike":
        group = adversary_goal("nearest_group", adversary_pos, agent_pos, group_size, group_centre)
        return np.where((square.min(axis=-1) < STRIKE_DISTANCE**2)[:, None], nearest_agent, group)
    size, centre = group_size, group_centre
    centre_offset = centre - adversary_pos[:, None, :]
    centre_dist = np.sqrt((centre_offset * centre_offset).sum(-1))
    eligible = size >= 3
    chased = np.where(eligible, centre_dist, np.inf).argmin(axis=-1)  # the nearest group of >= 3
    if rule == "nearest_group_member":
        if labels is None:
            raise ValueError("the nearest_group_member rule needs the agents' group labels")
        near_member = (labels == chased[:, None]) & eligible.any(-1)[:, None] & (square < STRIKE_DISTANCE**2)
        member = agent_pos[np.arange(b), np.where(near_member, square, np.inf).argmin(axis=-1)]
        group = adversary_goal("nearest_group", adversary_pos, agent_pos, group_size, group_centre)
        return np.where(near_member.any(-1)[:, None], member, group)
    if rule == "nearest_group_intercept":
        rule = InterceptRule()
    if isinstance(rule, InterceptRule):
        if labels is None or agent_vel is None or speed_max is None:
            raise ValueError("the nearest_group_intercept rule needs the group labels, velocities and top speed")
        # the chased group's members, or the nearest agent alone when no group has 3
        nearest = np.arange(agent_pos.shape[1])[None] == square.argmin(axis=-1)[:, None]
        member = np.where(eligible.any(-1)[:, None], labels == chased[:, None], nearest)
        count = member.sum(-1, keepdims=True)
        centre_now = (agent_pos * member[..., None]).sum(1) / count
        velocity = (agent_vel * member[..., None]).sum(1) / count
        reach = np.linalg.norm(centre_now - adversary_pos, axis=-1, keepdims=True) / speed_max
        goal = centre_now + velocity * np.minimum(reach, rule.horizon)
        if rule.strike_distance is None:
            return goal
        if rule.strike_at == "member":
            target = member
        elif rule.strike_at == "grouped":
            target = np.take_along_axis(size, labels, axis=1) >= 3
        else:
            target = np.ones_like(member)
        near_target = target & (square < rule.strike_distance**2)
        struck = np.where(near_target, square, np.inf).argmin(axis=-1)
        strike = agent_pos[np.arange(b), struck] + rule.strike_lead * agent_vel[np.arange(b), struck]
        return np.where(near_target.any(-1)[:, None], strike, goal)
    if rule == "r_largest":
        # Largest group first, ties broken by distance (a distance below 1e6 m never outweighs size).
        score = np.where(size > 0, size * 1e6 - centre_dist, -np.inf)
        return centre[np.arange(b), score.argmax(axis=-1)]
    if rule == "nearest_group":
        return np.where(eligible.any(-1)[:, None], centre[np.arange(b), chased], nearest_agent)
    raise ValueError(f"unknown adversary rule {rule!r}")


def avoiding_velocity(
    desired: np.ndarray, position: np.ndarray, obstacles: np.ndarray, keep_out: float, margin: float
) -> np.ndarray:
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


def pursuit_velocity(
    goal: np.ndarray,
    position: np.ndarray,
    speed_max: float,
    obstacles: np.ndarray | None = None,
    keep_out: float = 0.0,
    margin: float = 1.0,
) -> np.ndarray:
    """The velocity [B, 2] a pursuer wants: speed_max along goal - position, bent around `obstacles`
    [B, K, 2] by `avoiding_velocity` when given."""
    offset = goal - position
    dist = np.linalg.norm(offset, axis=-1, keepdims=True)
    desired = speed_max * offset / np.maximum(dist, 1e-9)
    if obstacles is not None and obstacles.shape[1]:
        desired = avoiding_velocity(desired, position, obstacles, keep_out, margin)
    return desired


def clip_speed(velocity: np.ndarray, speed_max: float) -> np.ndarray:
    """Scale velocities [..., 2] whose norm exceeds speed_max back onto it."""
    speed = np.sqrt((velocity * velocity).sum(-1, keepdims=True))
    return velocity * np.minimum(1.0, speed_max / np.maximum(speed, 1e-12))


def velocity_tracking_acceleration(
    desired: np.ndarray, velocity: np.ndarray, accel_max: float, dt: float
) -> np.ndarray:
    """The acceleration [B, 2] that turns `velocity` into `desired` within one step, per-axis clipped."""
    return np.clip((desired - velocity) / dt, -accel_max, accel_max)


def pursuit_acceleration(
    goal: np.ndarray,
    position: np.ndarray,
    velocity: np.ndarray,
    speed_max: float,
    accel_max: float,
    dt: float,
    obstacles: np.ndarray | None = None,
    keep_out: float = 0.0,
    margin: float = 1.0,
) -> np.ndarray:
    """Acceleration [B, 2] that turns the velocity towards speed_max along goal - position (bent
    around `obstacles` [B, K, 2] by `avoiding_velocity` when given), per-axis clipped to accel_max."""
    desired = pursuit_velocity(goal, position, speed_max, obstacles, keep_out, margin)
    return velocity_tracking_acceleration(desired, velocity, accel_max, dt)


# ---------------------------------------------------------------------------- learned adversary
ADVERSARY_SLOTS = 8
"""Agents the learned adversary observes (the nearest first); fewer agents leave slots empty."""
ADVERSARY_OBSTACLE_SLOTS = 4
"""Obstacles the learned adversary observes (the nearest first)."""
ADVERSARY_GROUP_SLOTS = 8
"""Groups of UAVs the learned adversary observes (the nearest centres first): 8, every group of 8 UAVs
(with 3 slots the nearest group of >= 3 was out of sight in 13 % of the steps against CI-HRL)."""
ADVERSARY_OBS_DIM = 6 + 6 * ADVERSARY_SLOTS + 4 * ADVERSARY_OBSTACLE_SLOTS + 4 * ADVERSARY_GROUP_SLOTS
"""[own position / a, own velocity / v_max, the goal relative to it / a (the centre of the nearest
group of >= 3, `adversary_goal("nearest_group")`, what it is set to chase)] + per agent slot
[relative position / a, relative velocity / v_max, group size / N, present] + per obstacle slot
[unit direction to it, clearance / range (the gap to its keep-out disc, clipped to [0, 1]),
present] + per group slot [its centre relative to it / a, its size / N, present]; a is the arena's
half size. The clearance is what avoidance needs at full resolution: a 0.65 m keep-out disc is a
few hundredths of the arena-scaled positions. The groups are what it sees of the swarm (connected
UAVs within 3 m of each other), not a choice among them: which one to trace is the policy's."""
OWN_VELOCITY_COLUMNS = slice(2, 4)
"""The adversary's own velocity / speed_max in its observation."""
ADVERSARY_GOAL_COLUMNS = slice(4, 6)
"""The goal's columns in the observation: a policy that plays by the paper's observation (its
`observes_goal` False) never reads them; it must find the nearest group from the agent slots."""
ADVERSARY_OBSTACLE_RANGE = 3.0
"""Clearance (m) at which an obstacle slot reads 1 (the UAVs' LiDAR range)."""


def _nearest(offset: np.ndarray, slots: int) -> tuple[np.ndarray, np.ndarray]:
    """Indices [B, slots] of the nearest rows of offset [B, K, 2] (padded with 0) and their presence."""
    b, k = offset.shape[:2]
    order = np.argsort((offset * offset).sum(-1), axis=-1, kind="stable")[:, :slots]
    present = np.ones((b, min(slots, k)), dtype=bool)
    if k < slots:
        order = np.concatenate([order, np.zeros((b, slots - k), dtype=order.dtype)], axis=1)
        present = np.concatenate([present, np.zeros((b, slots - k), dtype=bool)], axis=1)
    return order, present


def adversary_observation(
    adversary_pos: np.ndarray,
    adversary_vel: np.ndarray,
    goal: np.ndarray,
    agent_pos: np.ndarray,
    agent_vel: np.ndarray,
    agent_group_size: np.ndarray,
    obstacles: np.ndarray,
    arena_half_size: float,
    speed_max: float,
    keep_out: float,
    group_centre: np.ndarray | None = None,
    group_size: np.ndarray | None = None,
) -> np.ndarray:
    """The learned adversary's observation [B, ADVERSARY_OBS_DIM] float32 (layout: ADVERSARY_OBS_DIM)
    from true states: it is the simulator's agent, not a sensing UAV. goal [B, 2] is the point it is
    set to chase; agent_group_size [B, N] is the size of each agent's group; keep_out (m) is the
    obstacle radius plus its body radius. group_centre [B, G, 2] and group_size [B, G] (0 for an
    unused slot) describe the groups; None leaves the group slots empty."""
    b, n = agent_pos.shape[:2]
    rows = np.arange(b)[:, None]
    offset = agent_pos - adversary_pos[:, None, :]
    order, present = _nearest(offset, ADVERSARY_SLOTS)
    agents = np.concatenate(
        [
            offset[rows, order] / arena_half_size,
            (agent_vel - adversary_vel[:, None, :])[rows, order] / speed_max,
            agent_group_size[rows, order][..., None] / n,
            present[..., None],
        ],
        axis=-1,
    )
    agents *= present[..., None]
    obstacle_offset = obstacles - adversary_pos[:, None, :]
    order, present = _nearest(obstacle_offset, ADVERSARY_OBSTACLE_SLOTS)
    if obstacle_offset.shape[1] == 0:
        obstacle_offset = np.zeros((b, 1, 2))
    offset = obstacle_offset[rows, order]
    dist = np.maximum(np.linalg.norm(offset, axis=-1, keepdims=True), 1e-9)
    clearance = np.clip((dist - keep_out) / ADVERSARY_OBSTACLE_RANGE, 0.0, 1.0)
    near = np.concatenate([offset / dist, clearance, present[..., None]], axis=-1)
    near *= present[..., None]
    own = np.concatenate(
        [adversary_pos / arena_half_size, adversary_vel / speed_max, (goal - adversary_pos) / arena_half_size], axis=-1
    )
    groups = np.zeros((b, ADVERSARY_GROUP_SLOTS, 4))
    if group_centre is not None and group_centre.shape[1]:
        rel = group_centre - adversary_pos[:, None, :]
        dist = np.where(group_size > 0, (rel * rel).sum(-1), np.inf)
        order = np.argsort(dist, axis=-1, kind="stable")[:, :ADVERSARY_GROUP_SLOTS]
        k = order.shape[1]
        present = np.isfinite(np.take_along_axis(dist, order, axis=1))
        groups[:, :k] = np.concatenate(
            [rel[rows, order] / arena_half_size, group_size[rows, order][..., None] / n, present[..., None]], axis=-1
        )
        groups[:, :k] *= present[..., None]
    return np.concatenate([own, agents.reshape(b, -1), near.reshape(b, -1), groups.reshape(b, -1)], axis=-1).astype(
        np.float32
    )


def adversary_reward(
    adversary_pos: np.ndarray,
    goal: np.ndarray,
    agent_pos: np.ndarray,
    obstacles: np.ndarray,
    alert_distance: float,
    keep_out: float,
    distance_weight: float = 0.1,
    alert_weight: float = 1.0,
    collision_weight: float = 10.0,
    previous_distance: np.ndarray | None = None,
    progress_weight: float = 0.0,
    gamma: float = 1.0,
) -> dict[str, np.ndarray]:
    """The learned adversary's reward terms [B] after a step, and their weighted sum "reward":
    "distance" = -|goal - p| (m; goal: the nearest group of >= 3, `adversary_goal("nearest_group")`),
    "alert" = share of agents within `alert_distance` of it, "collision" = -1 inside an obstacle's
    keep-out disc (obstacle plus body radius), else 0, and "progress" = d_before - gamma d_after
    (potential-based shaping with the potential -d, which leaves the optimal policy unchanged and
    credits each step with the approach it made; 0 without previous_distance, the step's d_before)."""
    distance = -np.linalg.norm(goal - adversary_pos, axis=-1)
    progress = np.zeros_like(distance) if previous_distance is None else previous_distance + gamma * distance
    alert = (np.linalg.norm(agent_pos - adversary_pos[:, None, :], axis=-1) < alert_distance).mean(axis=-1)
    if obstacles.shape[1]:
        inside = (np.linalg.norm(obstacles - adversary_pos[:, None, :], axis=-1) < keep_out).any(axis=-1)
    else:
        inside = np.zeros(len(adversary_pos), dtype=bool)
    collision = -inside.astype(float)
    reward = (
        distance_weight * distance + alert_weight * alert + collision_weight * collision + progress_weight * progress
    )
    return {"distance": distance, "alert": alert, "collision": collision, "progress": progress, "reward": reward}
