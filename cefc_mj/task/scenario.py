"""Seeded scenario sampling: starts, targets, anchors, obstacles (docs/design.md §4, docs/research/layouts.md).

Everything is drawn from one `numpy.random.Generator`, batched over envs; rejection sampling loops
over slots (agents, obstacles) and vectorizes over envs. A placement that keeps failing raises
`ConfigError` instead of hanging.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cefc_mj.errors import ConfigError
from cefc_mj.task.config import STRAGGLER_MAX_DISTANCE, STRAGGLER_MIN_DISTANCE, TaskConfig

MAX_TRIES = 2000
TARGET_CORNER_SIGNS = np.array([[-1.0, -1.0], [-1.0, 1.0], [1.0, -1.0], [1.0, 1.0]])


@dataclass
class Scenario:
    """One batch of episode layouts. Arrays are [B, ...]."""

    agent_pos: np.ndarray
    """[B, N, 2] start positions."""
    adversary_pos: np.ndarray
    """[B, 2] adversary start."""
    obstacles: np.ndarray
    """[B, K, 2] obstacle centres."""
    targets: np.ndarray
    """[B, J, 2] target centres (J = n_targets; J = 0 in formation mode)."""
    anchor: np.ndarray
    """[B, 2] anchor point of the low-level game."""


def _place(rng, count_envs, low, high, ok, what, arg, draw=None):
    """Draw one point per env in [low, high]^2 (or `draw(count)` points [count, 2]) until
    ok(points, active) holds for every env."""
    points = np.empty((count_envs, 2))
    pending = np.ones(count_envs, dtype=bool)
    for _ in range(MAX_TRIES):
        idx = np.flatnonzero(pending)
        if idx.size == 0:
            return points
        candidate = rng.uniform(low, high, size=(idx.size, 2)) if draw is None else draw(idx.size)
        good = ok(candidate, idx)
        points[idx[good]] = candidate[good]
        pending[idx[good]] = False
    raise ConfigError(f"{arg}: could not place {what} after {MAX_TRIES} tries; lower the density or enlarge the arena")


def sample_starts(cfg: TaskConfig, rng: np.random.Generator, n_envs: int) -> np.ndarray:
    """Start positions [B, N, 2] uniform in [-s, s]^2, pairwise at least start_min_spacing apart."""
    pos = np.empty((n_envs, cfg.n_agents, 2))
    s = cfg.start_half_size
    for i in range(cfg.n_agents):
        placed = pos[:, :i]

        def ok(candidate, idx, placed=placed):
            if placed.shape[1] == 0:
                return np.ones(len(idx), dtype=bool)
            d = np.linalg.norm(placed[idx] - candidate[:, None, :], axis=-1)
            return (d >= cfg.start_min_spacing).all(axis=-1)

        pos[:, i] = _place(rng, n_envs, -s, s, ok, f"start position of agent {i}", "n_agents")
    if cfg.straggler_fraction > 0:  # nothing drawn otherwise: the paper's starts keep their random stream
        move_straggler(cfg, rng, pos)
    return pos


def move_straggler(cfg: TaskConfig, rng: np.random.Generator, pos: np.ndarray) -> None:
    """In a straggler_fraction of the envs, move the last agent of the starts pos [B, N, 2] (in place)
    to a point STRAGGLER_MIN_DISTANCE..STRAGGLER_MAX_DISTANCE m from the centre, uniform in angle and
    radius, at least observation_distance from every other start: it sees no neighbour."""
    chosen = np.flatnonzero(rng.random(pos.shape[0]) < cfg.straggler_fraction)
    others = pos[chosen, :-1]

    def ok(candidate, idx):
        return (np.linalg.norm(others[idx] - candidate[:, None, :], axis=-1) >= cfg.observation_distance).all(-1)

    def draw(count):
        angle = rng.uniform(0.0, 2 * np.pi, count)
        radius = rng.uniform(STRAGGLER_MIN_DISTANCE, STRAGGLER_MAX_DISTANCE, count)
        return radius[:, None] * np.stack([np.cos(angle), np.sin(angle)], axis=-1)

    pos[chosen, -1] = _place(rng, chosen.size, 0.0, 0.0, ok, "a straggler", "straggler_fraction", draw)


START_DISC_MARGIN = 0.1
"""Extra room (m) between an obstacle surface and a UAV's start disc in the "paper" layout."""


def sample_obstacles(
    cfg: TaskConfig, rng: np.random.Generator, anchor: np.ndarray, targets: np.ndarray, starts: np.ndarray | None = None
) -> np.ndarray:
    """Obstacle centres [B, K, 2], each wholly inside the arena, clear of each other (obstacle_min_gap
    between surfaces), and at least anchor_clearance from the anchor and the targets' centres.

    cfg.obstacle_layout picks what else is kept free: "clear-start" the whole start square grown by
    the obstacle and UAV radii; "paper" only each UAV's start disc (`starts` [B, N, 2], required) plus
    START_DISC_MARGIN, so obstacles may stand between the swarm and its anchor (docs/research/layouts.md).
    """
    n_envs = anchor.shape[0]
    k = cfg.n_obstacles
    paper = cfg.obstacle_layout == "paper"
    if paper and starts is None:
        raise ConfigError("obstacle_layout='paper': sample_obstacles needs the start positions")
    obstacles = np.empty((n_envs, k, 2))
    keep_out = cfg.start_half_size + cfg.obstacle_radius + cfg.uav_radius
    start_clearance = cfg.uav_radius + cfg.obstacle_radius + START_DISC_MARGIN
    min_centre_dist = 2 * cfg.obstacle_radius + cfg.obstacle_min_gap
    edge = cfg.arena_half_size - cfg.obstacle_radius
    for j in range(k):
        placed = obstacles[:, :j]

        def ok(candidate, idx, placed=placed):
            if paper:
                good = (np.linalg.norm(candidate[:, None] - starts[idx], axis=-1) >= start_clearance).all(-1)
            else:
                good = np.abs(candidate).max(axis=-1) > keep_out
            good &= np.linalg.norm(candidate - anchor[idx], axis=-1) >= cfg.anchor_clearance
            if targets.shape[1]:
                good &= (np.linalg.norm(candidate[:, None] - targets[idx], axis=-1) >= cfg.anchor_clearance).all(-1)
            if j:
                good &= (np.linalg.norm(placed[idx] - candidate[:, None], axis=-1) >= min_centre_dist).all(-1)
            return good

        obstacles[:, j] = _place(rng, n_envs, -edge, edge, ok, f"obstacle {j + 1} of {k}", "obstacle_density")
    return obstacles


def sample_anchor(cfg: TaskConfig, rng: np.random.Generator, obstacles: np.ndarray | None, n_envs: int) -> np.ndarray:
    """Anchor points [B, 2] uniform in [-h, h]^2, at least anchor_clearance from every obstacle."""
    h = cfg.anchor_half_size

    def ok(candidate, idx):
        if obstacles is None or obstacles.shape[1] == 0:
            return np.ones(len(idx), dtype=bool)
        d = np.linalg.norm(obstacles[idx] - candidate[:, None], axis=-1)
        return (d >= cfg.anchor_clearance).all(-1)

    return _place(rng, n_envs, -h, h, ok, "an anchor clear of the obstacles", "obstacle_density")


def sample_scenario(cfg: TaskConfig, rng: np.random.Generator, n_envs: int) -> Scenario:
    """Sample B independent episode layouts from one generator."""
    agent_pos = sample_starts(cfg, rng, n_envs)
    if cfg.mode == "cefc":
        choice = np.argsort(rng.random((n_envs, 4)), axis=-1)[:, : cfg.n_targets]
        targets = TARGET_CORNER_SIGNS[choice] * cfg.target_corner
    else:
        targets = np.zeros((n_envs, 0, 2))
    # The anchor is drawn first (obstacles keep clear of it); later redraws avoid the obstacles.
    # Both layouts draw in this order, so "clear-start" keeps the random stream it always had.
    anchor = sample_anchor(cfg, rng, None, n_envs)
    obstacles = sample_obstacles(cfg, rng, anchor, targets, agent_pos)
    adversary_pos = np.broadcast_to(np.asarray(cfg.adversary_start, dtype=float), (n_envs, 2)).copy()
    adversary_pos[:, 0] += rng.uniform(-cfg.start_half_size, cfg.start_half_size, size=n_envs)
    return Scenario(
        agent_pos=agent_pos, adversary_pos=adversary_pos, obstacles=obstacles, targets=targets, anchor=anchor
    )


def check_scenario(cfg: TaskConfig, scenario: Scenario, n_envs: int) -> None:
    """Raise ConfigError naming the first array of a hand-built `scenario` whose shape does not fit
    `n_envs` layouts of `cfg`, or that is not finite."""
    shapes = {
        "agent_pos": (n_envs, cfg.n_agents, 2),
        "adversary_pos": (n_envs, 2),
        "obstacles": (n_envs, cfg.n_obstacles, 2),
        "anchor": (n_envs, 2),
        "targets": (n_envs, cfg.n_targets if cfg.mode == "cefc" else 0, 2),
    }
    for name, shape in shapes.items():
        value = np.asarray(getattr(scenario, name))
        if value.shape != shape:
            raise ConfigError(f"scenario.{name}: expected shape {shape}, got {value.shape}")
        if not np.isfinite(value).all():
            raise ConfigError(f"scenario.{name}: contains NaN or inf")


def obstacle_near_path(scenario: Scenario, obstacle_radius: float, margin: float = 1.0) -> np.ndarray:
    """[B] bool: some obstacle's surface lies within `margin` m of the straight segment from the
    start centre (mean start position) to the anchor, i.e. its centre is within
    obstacle_radius + margin of that segment."""
    start = scenario.agent_pos.mean(axis=1)  # [B, 2]
    seg = scenario.anchor - start  # [B, 2]
    rel = scenario.obstacles - start[:, None]  # [B, K, 2]
    length_sq = np.maximum((seg * seg).sum(-1), 1e-12)[:, None]
    along = np.clip((rel * seg[:, None]).sum(-1) / length_sq, 0.0, 1.0)  # [B, K] projection onto the segment
    dist = np.linalg.norm(rel - along[..., None] * seg[:, None], axis=-1)
    return (dist <= obstacle_radius + margin).any(axis=-1)


def near_path_fraction(cfg: TaskConfig, n_layouts: int = 1000, seed: int = 0, margin: float = 1.0) -> float:
    """Fraction of `n_layouts` layouts of `cfg` with an obstacle surface within `margin` m of the
    start-centre -> anchor segment (obstacle_near_path); how often the way to the anchor is obstructed.
    The layouts are drawn as one batch from default_rng(seed), as BatchedCEFCEnv.reset does."""
    if not isinstance(n_layouts, int) or n_layouts < 1:
        raise ConfigError(f"n_layouts={n_layouts!r}: must be an integer >= 1")
    scenario = sample_scenario(cfg, np.random.default_rng(seed), n_layouts)
    return float(obstacle_near_path(scenario, cfg.obstacle_radius, margin).mean())
