"""Compiled (numba) kernels of the per-step hot loop, one pass over envs x agents each.

The numpy formulations these replace are kept as slow, obvious references in
`tests/reference_impl.py`, and the tests check the kernels against them case by case.
"""

from __future__ import annotations

import numpy as np

from cefc_mj.jit import njit


@njit
def neighbours_kernel(pos, vel, slots, radius, feats, mask):
    """Neighbours of each agent sorted by distance (ties by index), padded: feats [B,N,slots,4]
    = (p_j - p_i, v_j - v_i), mask [B,N,slots] (1 for a neighbour closer than radius)."""
    n_envs, n, _ = pos.shape
    dist = np.empty(n)
    order = np.empty(n, dtype=np.int64)
    for b in range(n_envs):
        for i in range(n):
            count = 0
            for j in range(n):
                if j == i:
                    continue
                dx = pos[b, j, 0] - pos[b, i, 0]
                dy = pos[b, j, 1] - pos[b, i, 1]
                d = np.sqrt(dx * dx + dy * dy)
                if d >= radius:
                    continue
                # insertion sort: stable, so equal distances keep index order
                k = count
                while k > 0 and dist[k - 1] > d:
                    dist[k] = dist[k - 1]
                    order[k] = order[k - 1]
                    k -= 1
                dist[k] = d
                order[k] = j
                count += 1
            for s in range(slots):
                if s < count:
                    j = order[s]
                    feats[b, i, s, 0] = pos[b, j, 0] - pos[b, i, 0]
                    feats[b, i, s, 1] = pos[b, j, 1] - pos[b, i, 1]
                    feats[b, i, s, 2] = vel[b, j, 0] - vel[b, i, 0]
                    feats[b, i, s, 3] = vel[b, j, 1] - vel[b, i, 1]
                    mask[b, i, s] = 1.0
                else:
                    feats[b, i, s, :] = 0.0
                    mask[b, i, s] = 0.0


@njit(inline="always")
def _observation_row(out, ax, ay, vx, vy, feats, mask, lidar):
    """One low-level observation row (the layout's order: anchor - own position, own velocity, neighbour
    features, neighbour mask, LiDAR), every number rounded from float64 to float32."""
    out[0] = np.float32(ax)
    out[1] = np.float32(ay)
    out[2] = np.float32(vx)
    out[3] = np.float32(vy)
    slots = mask.shape[0]
    at = 4
    for s in range(slots):
        for c in range(4):
            out[at] = np.float32(feats[s, c])
            at += 1
    for s in range(slots):
        out[at] = np.float32(mask[s])
        at += 1
    for m in range(lidar.shape[0]):
        out[at + m] = np.float32(lidar[m])


@njit
def low_level_observation_kernel(pos, vel, anchor, lidar, slots, radius, out):
    """Low-level observations out [B, N, D] (float32) of build_low_level_observation, bit for bit:
    pos, vel [B, N, 2] (perceived positions, velocities), anchor [B, N, 2] (each agent's), lidar [B, N, M]."""
    n_envs, n, _ = pos.shape
    feats = np.empty((n_envs, n, slots, 4))
    mask = np.empty((n_envs, n, slots))
    neighbours_kernel(pos, vel, slots, radius, feats, mask)
    for b in range(n_envs):
        for i in range(n):
            _observation_row(
                out[b, i],
                anchor[b, i, 0] - pos[b, i, 0],
                anchor[b, i, 1] - pos[b, i, 1],
                vel[b, i, 0],
                vel[b, i, 1],
                feats[b, i],
                mask[b, i],
                lidar[b, i],
            )


@njit
def local_observation_kernel(own, anchor, lidar, rows, slots, radius):
    """One agent's low-level observation [D] (float32, the low-level layout) from what it senses (own = [px, py, vx,
    vy], anchor [2], lidar [M]) and hears (rows [k, 5] = [id, px, py, vx, vy], increasing id): row 0
    of build_low_level_observation for the swarm [self, rows...], bit for bit (the same kernel picks
    the neighbours, every number computed in float64 and then rounded to float32)."""
    k = rows.shape[0]
    pos = np.empty((1, k + 1, 2))
    vel = np.empty((1, k + 1, 2))
    pos[0, 0, 0], pos[0, 0, 1], vel[0, 0, 0], vel[0, 0, 1] = own[0], own[1], own[2], own[3]
    for s in range(k):
        pos[0, s + 1, 0], pos[0, s + 1, 1] = rows[s, 1], rows[s, 2]
        vel[0, s + 1, 0], vel[0, s + 1, 1] = rows[s, 3], rows[s, 4]
    feats = np.empty((1, k + 1, slots, 4))
    mask = np.empty((1, k + 1, slots))
    neighbours_kernel(pos, vel, slots, radius, feats, mask)
    out = np.empty(4 + 5 * slots + lidar.shape[0], dtype=np.float32)
    _observation_row(out, anchor[0] - own[0], anchor[1] - own[1], own[2], own[3], feats[0, 0], mask[0, 0], lidar)
    return out


@njit
def groups_kernel(pos, radius, labels):
    """Connected components of "distance < radius"; each labelled by its smallest member."""
    n_envs, n, _ = pos.shape
    r2 = radius * radius
    for b in range(n_envs):
        for i in range(n):
            labels[b, i] = i
        changed = True
        while changed:
            changed = False
            for i in range(n):
                for j in range(i + 1, n):
                    dx = pos[b, i, 0] - pos[b, j, 0]
                    dy = pos[b, i, 1] - pos[b, j, 1]
                    if dx * dx + dy * dy < r2 and labels[b, i] != labels[b, j]:
                        low = min(labels[b, i], labels[b, j])
                        labels[b, i] = low
                        labels[b, j] = low
                        changed = True


@njit
def formation_error_kernel(pos, labels, templates, min_size, error, size, centre):
    """Per-group directed Hausdorff error HD(Delta_c, centred members), indexed by group label.

    templates [Cmax+1, Cmax, 2]: templates[c, :c] is Delta_c. error [B,G] (NaN for unused labels
    and groups below min_size), size [B,G], centre [B,G,2].
    """
    n_envs, n, _ = pos.shape
    for b in range(n_envs):
        for g in range(n):
            size[b, g] = 0
            centre[b, g, 0] = 0.0
            centre[b, g, 1] = 0.0
            error[b, g] = np.nan
        for i in range(n):
            g = labels[b, i]
            size[b, g] += 1
            centre[b, g, 0] += pos[b, i, 0]
            centre[b, g, 1] += pos[b, i, 1]
        for g in range(n):
            c = size[b, g]
            if c == 0:
                continue
            centre[b, g, 0] /= c
            centre[b, g, 1] /= c
            if c < min_size:
                continue
            worst = 0.0
            for t in range(c):
                best = np.inf
                for i in range(n):
                    if labels[b, i] != g:
                        continue
                    dx = templates[c, t, 0] - (pos[b, i, 0] - centre[b, g, 0])
                    dy = templates[c, t, 1] - (pos[b, i, 1] - centre[b, g, 1])
                    d = np.sqrt(dx * dx + dy * dy)
                    if d < best:
                        best = d
                if best > worst:
                    worst = best
            error[b, g] = worst


@njit
def particle_step_kernel(
    pos, vel, vel_cmd, accel, kick, obstacles, dt, speed_max, response, contact_dist, uav_diameter, collided
):
    """Semi-implicit Euler with a speed clip, UAV-UAV overlap flags, and inelastic obstacle
    contacts (pushed back onto the surface, inward velocity removed). The action integrates into the
    commanded velocity vel_cmd; the velocity follows it by the first-order factor `response` in (0, 1]
    per step (1: no lag, the paper's MPE), then gets the disturbance `kick` [B, N, 2] (m/s) added
    before the position update. Updates in place."""
    n_envs, n, _ = pos.shape
    k_obs = obstacles.shape[1]
    for b in range(n_envs):
        for i in range(n):
            vx = vel_cmd[b, i, 0] + accel[b, i, 0] * dt
            vy = vel_cmd[b, i, 1] + accel[b, i, 1] * dt
            speed = np.sqrt(vx * vx + vy * vy)
            if speed > speed_max:
                vx *= speed_max / speed
                vy *= speed_max / speed
            vel_cmd[b, i, 0] = vx
            vel_cmd[b, i, 1] = vy
            if response < 1.0:
                vx = vel[b, i, 0] + response * (vx - vel[b, i, 0])
                vy = vel[b, i, 1] + response * (vy - vel[b, i, 1])
            vx += kick[b, i, 0]
            vy += kick[b, i, 1]
            vel[b, i, 0] = vx
            vel[b, i, 1] = vy
            pos[b, i, 0] += vx * dt
            pos[b, i, 1] += vy * dt
        for i in range(n):
            collided[b, i] = False
            for j in range(n):
                if j != i:
                    dx = pos[b, i, 0] - pos[b, j, 0]
                    dy = pos[b, i, 1] - pos[b, j, 1]
                    if dx * dx + dy * dy < uav_diameter * uav_diameter:
                        collided[b, i] = True
        for i in range(n):
            nearest = -1
            best = np.inf
            for k in range(k_obs):
                dx = pos[b, i, 0] - obstacles[b, k, 0]
                dy = pos[b, i, 1] - obstacles[b, k, 1]
                d = np.sqrt(dx * dx + dy * dy)
                if d < best:
                    best = d
                    nearest = k
            if nearest < 0 or best >= contact_dist:
                continue
            collided[b, i] = True
            nx = (pos[b, i, 0] - obstacles[b, nearest, 0]) / max(best, 1e-9)
            ny = (pos[b, i, 1] - obstacles[b, nearest, 1]) / max(best, 1e-9)
            pos[b, i, 0] = obstacles[b, nearest, 0] + nx * contact_dist
            pos[b, i, 1] = obstacles[b, nearest, 1] + ny * contact_dist
            vn = vel[b, i, 0] * nx + vel[b, i, 1] * ny
            if vn < 0.0:
                vel[b, i, 0] -= vn * nx
                vel[b, i, 1] -= vn * ny
            vn = vel_cmd[b, i, 0] * nx + vel_cmd[b, i, 1] * ny
            if vn < 0.0:
                vel_cmd[b, i, 0] -= vn * nx
                vel_cmd[b, i, 1] -= vn * ny
