"""Exact 2-D LiDAR: ray-circle intersections, vectorized over envs x agents x beams x circles.

Beam k of every agent points at world angle 2 pi k / M (yaw is held at 0). A beam from origin o
with unit direction u hits a circle (centre c, radius r) at the smallest t >= 0 with
|o + t u - c| = r; an origin inside a circle reads 0. Ranges are clipped to the LiDAR range.

The compiled kernel (numba) is the fast path used by the particle world; `lidar_ranges_reference`
is the slow, obvious numpy version the tests compare it with.
"""

from __future__ import annotations

import functools

import numpy as np

from cefc_mj.jit import njit


@functools.lru_cache(maxsize=16)
def beam_directions(n_rays: int) -> np.ndarray:
    """Unit beam directions [M, 2] (read-only); beam k at angle 2 pi k / M."""
    angles = 2.0 * np.pi * np.arange(n_rays) / n_rays
    directions = np.stack([np.cos(angles), np.sin(angles)], axis=-1)
    directions.setflags(write=False)
    return directions


@njit(fastmath=False)
def _lidar_kernel(origins, directions, obstacles, obstacle_radius, agents, agent_radius, use_agents, max_range, out):
    n_envs, n_agents, _ = origins.shape
    n_rays = directions.shape[0]
    n_obstacles = obstacles.shape[1]
    n_bodies = agents.shape[1]
    beam_step = 2.0 * np.pi / n_rays
    for b in range(n_envs):
        for i in range(n_agents):
            ox = origins[b, i, 0]
            oy = origins[b, i, 1]
            for k in range(n_rays):
                out[b, i, k] = max_range
            # Each circle updates the beams it can reach; circles beyond range + radius are skipped.
            for j in range(n_obstacles + (n_bodies if use_agents else 0)):
                if j < n_obstacles:
                    cx = obstacles[b, j, 0] - ox
                    cy = obstacles[b, j, 1] - oy
                    r = obstacle_radius
                else:
                    if j - n_obstacles == i:
                        continue
                    cx = agents[b, j - n_obstacles, 0] - ox
                    cy = agents[b, j - n_obstacles, 1] - oy
                    r = agent_radius
                cc = cx * cx + cy * cy
                if cc > (max_range + r) * (max_range + r):
                    continue
                c_term = cc - r * r
                if c_term <= 0.0:  # the origin is inside this circle: every beam reads 0
                    for k in range(n_rays):
                        out[b, i, k] = 0.0
                    continue
                # Only beams within the circle's angular half-width asin(r / |c|) can hit it; one
                # extra beam each side guards the rounding at tangency (the exact test decides).
                centre_angle = np.arctan2(cy, cx)
                half_width = np.arcsin(r / np.sqrt(cc))
                first = int(np.floor((centre_angle - half_width) / beam_step))
                last = int(np.ceil((centre_angle + half_width) / beam_step))
                for kk in range(first, last + 1):
                    k = kk % n_rays
                    proj = directions[k, 0] * cx + directions[k, 1] * cy
                    if proj <= 0.0:
                        continue
                    disc = proj * proj - c_term
                    if disc < 0.0:
                        continue
                    t = proj - np.sqrt(disc)
                    if t < out[b, i, k]:
                        out[b, i, k] = t


def lidar_ranges(
    origins: np.ndarray,
    obstacles: np.ndarray,
    obstacle_radius: float,
    agents: np.ndarray,
    agent_radius: float,
    n_rays: int,
    max_range: float,
    see_agents: bool = True,
) -> np.ndarray:
    """LiDAR ranges [B, N, M] from `origins` [B, N, 2].

    obstacles [B, K, 2] circle centres of radius `obstacle_radius`; agents [B, N, 2] the UAVs' true
    positions (discs of `agent_radius`), agent i's own disc is never hit by its own beams.
    """
    out = np.empty((origins.shape[0], origins.shape[1], n_rays))
    _lidar_kernel(
        np.ascontiguousarray(origins, dtype=np.float64),
        beam_directions(n_rays),
        np.ascontiguousarray(obstacles, dtype=np.float64).reshape(origins.shape[0], -1, 2),
        float(obstacle_radius),
        np.ascontiguousarray(agents, dtype=np.float64),
        float(agent_radius),
        bool(see_agents),
        float(max_range),
        out,
    )
    return out


def lidar_ranges_reference(
    origins, obstacles, obstacle_radius, agents, agent_radius, n_rays, max_range, see_agents=True
):
    """Slow, obvious numpy reference of `lidar_ranges` (one ray-circle solve at a time)."""
    directions = beam_directions(n_rays)
    b, n, _ = origins.shape
    out = np.full((b, n, n_rays), float(max_range))
    for e in range(b):
        for i in range(n):
            circles = [(c, obstacle_radius) for c in obstacles[e]]
            if see_agents:
                circles += [(agents[e, j], agent_radius) for j in range(n) if j != i]
            for k in range(n_rays):
                for centre, radius in circles:
                    # |o + t u - c|^2 = r^2  ->  t^2 - 2 t (u.(c-o)) + |c-o|^2 - r^2 = 0
                    oc = centre - origins[e, i]
                    proj = directions[k] @ oc
                    c_term = oc @ oc - radius**2
                    if c_term <= 0:
                        out[e, i, k] = 0.0
                        continue
                    disc = proj**2 - c_term
                    if proj > 0 and disc >= 0:
                        out[e, i, k] = min(out[e, i, k], proj - np.sqrt(disc))
    return out
