"""The agent's separation guard (`TaskConfig.separation_guard`, on in `cefc-eval` unless `--guard off`;
docs/research/decisions.md, "Separation guard").

A quadrotor follows a velocity command about 0.2-0.3 s late. The AT-M policies learned in a world
where the velocity follows at once: they brake hard only once a neighbour is 0.9 m away, and on
quadrotors the lag carries the pair into contact (the calm-air touches of Table VIII). The guard is
a rule on the agent's own observation, applied after the policy, that keeps the closing speed
towards anything nearby small enough to stop in time, the way PX4's Collision Prevention limits
velocity setpoints towards what its range sensors see:

    for every neighbour j in the observation within NEIGHBOUR_RANGE (unit vector u from me to it,
    distance d, both velocities from the observation):
        d' = d - max(0, closing speed now) x LAG                 (where the lag takes us first)
        closing speed after this command  s = (v_i + a dt - v_j) . u
        allowed                             = GAIN x (d' - NEIGHBOUR_DISTANCE)
        if s > allowed:  a -= (s - allowed) / dt x u
    and the same for every LiDAR beam shorter than OBSTACLE_RANGE, the hit a still point at the
    beam's range along its direction (surface distance; OBSTACLE_DISTANCE from it).

Then the per-axis action clip. It reads only the agent's observation (own velocity, the neighbours'
relative positions and velocities, the LiDAR), so it runs unchanged in a SITL-M agent process. An
agent whose action no constraint limits gets it back bit for bit. The constants were chosen on
MuJoCo calm-air episodes (seeds 0..4) of the Step 3 policies, and checked on seeds 5..9.
"""

from __future__ import annotations

import numpy as np

from cefc_mj.jit import njit
from cefc_mj.task.lidar import beam_directions

NEIGHBOUR_DISTANCE = 0.6
"""Centre distance (m) the guard holds to a neighbour (collision at 2 x uav_radius = 0.5 m)."""
NEIGHBOUR_RANGE = 1.6
"""Neighbours closer than this (m) are guarded against (formation spacing 1 m)."""
OBSTACLE_DISTANCE = 0.35
"""Distance (m) from a LiDAR hit (an obstacle's surface) that the guard holds (uav_radius 0.25 m)."""
OBSTACLE_RANGE = 1.2
"""LiDAR beams shorter than this (m) are guarded against."""
GAIN = 2.0
"""Allowed closing speed per metre of room beyond the held distance (1/s)."""
LAG = 0.3
"""Look-ahead (s) over which the present closing speed still shrinks the distance (the vehicle's lag)."""


@njit
def _guard_kernel(obs, actions, slots, directions, dt, accel_max, out):
    """out [B, N, 2] (float64) = guarded actions; obs [B, N, D] in the low-level layout."""
    n_envs, n, _ = obs.shape
    n_rays = directions.shape[0]
    mask_at = 4 + 4 * slots
    lidar_at = mask_at + slots
    for b in range(n_envs):
        for i in range(n):
            ax = np.float64(actions[b, i, 0])
            ay = np.float64(actions[b, i, 1])
            vx = np.float64(obs[b, i, 2])
            vy = np.float64(obs[b, i, 3])
            moved = False
            for s in range(slots):
                if obs[b, i, mask_at + s] < 0.5:
                    continue
                rx = np.float64(obs[b, i, 4 + 4 * s])
                ry = np.float64(obs[b, i, 5 + 4 * s])
                d = np.sqrt(rx * rx + ry * ry)
                if d >= NEIGHBOUR_RANGE or d < 1e-6:
                    continue
                ux, uy = rx / d, ry / d
                rvx = np.float64(obs[b, i, 6 + 4 * s])  # v_j - v_i
                rvy = np.float64(obs[b, i, 7 + 4 * s])
                closing = -(rvx * ux + rvy * uy)
                ahead = d - max(0.0, closing) * LAG
                after = closing + (ax * ux + ay * uy) * dt
                excess = after - GAIN * (ahead - NEIGHBOUR_DISTANCE)
                if excess > 0.0:
                    ax -= excess / dt * ux
                    ay -= excess / dt * uy
                    moved = True
            for k in range(n_rays):
                r = np.float64(obs[b, i, lidar_at + k])
                if r >= OBSTACLE_RANGE:
                    continue
                ux, uy = directions[k, 0], directions[k, 1]
                ahead = r - max(0.0, vx * ux + vy * uy) * LAG
                after = (vx + ax * dt) * ux + (vy + ay * dt) * uy
                excess = after - GAIN * (ahead - OBSTACLE_DISTANCE)
                if excess > 0.0:
                    ax -= excess / dt * ux
                    ay -= excess / dt * uy
                    moved = True
            if moved:
                out[b, i, 0] = min(max(ax, -accel_max), accel_max)
                out[b, i, 1] = min(max(ay, -accel_max), accel_max)
            else:
                out[b, i, 0] = actions[b, i, 0]
                out[b, i, 1] = actions[b, i, 1]


def guard_actions(
    obs: np.ndarray, actions: np.ndarray, slots: int, n_rays: int, dt: float, accel_max: float
) -> np.ndarray:
    """The guarded actions [B, N, 2] (dtype of `actions`) for low-level observations obs [B, N, D]
    with `slots` neighbour slots and `n_rays` LiDAR beams."""
    obs = np.asarray(obs)
    actions = np.asarray(actions)
    if obs.ndim != 3 or obs.shape[-1] < 4 + 5 * slots + n_rays or actions.shape != obs.shape[:2] + (2,):
        raise ValueError(f"guard_actions: obs {obs.shape} and actions {actions.shape} do not match the layout")
    out = np.empty(actions.shape, dtype=np.float64)
    _guard_kernel(
        obs, actions, int(slots), np.ascontiguousarray(beam_directions(n_rays)), float(dt), float(accel_max), out
    )
    return out.astype(actions.dtype, copy=False)


def guard_with(config, obs: np.ndarray, actions: np.ndarray) -> np.ndarray:
    """`guard_actions` with the neighbour slots, LiDAR beams, step and action bound of `config` (a TaskConfig)."""
    return guard_actions(obs, actions, config.neighbour_slots, config.n_lidar_rays, config.dt, config.accel_max)


def guarded(act, config):
    """`act` (obs [B, N, D] -> actions [B, N, 2]) with the separation guard after it when
    `config.separation_guard` is set (a TaskConfig); `act` itself otherwise."""
    if not config.separation_guard:
        return act

    def act_guarded(obs):
        return guard_with(config, obs, act(obs))

    return act_guarded
