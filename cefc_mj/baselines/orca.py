"""ORCA-F: formation keeping by ORCA, the paper's Table III baseline (docs/research/baselines.md).

Each decision step, every agent's preferred velocity points to its slot in the formation template
Delta_c placed a little ahead of the swarm centre, toward the anchor; ORCA (the RVO2 library through
the `pyrvo` binding) turns the preferred velocities into collision-free ones among the agents and
the cylinder obstacles (as polygons); a P-gain turns each ORCA velocity into the acceleration
setpoint the env takes, u = clip(5 (v_orca - v), +-accel_max), as AT-M's velocity head does.

>>> from cefc_mj.baselines.orca import evaluate_orca
>>> evaluate_orca(6, episodes=50, seed=0)            # doctest: +SKIP
{'R_L': ..., 'F': ..., 'N': ..., 'C': ...}
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment

from cefc_mj.env import BatchedCEFCEnv
from cefc_mj.errors import ConfigError
from cefc_mj.sim.particle import clip_speed
from cefc_mj.table3_protocol import TABLE3_DENSITY, TABLE3_EPISODES, TABLE3_STEPS, roll_out
from cefc_mj.task.config import TaskConfig
from cefc_mj.task.formation import formation_template

PYRVO_MISSING = "ORCA-F needs the RVO2 binding pyrvo, an optional extra: pip install -e '.[baselines]'"
"""The one line that says how to get the ORCA-F baseline's optional dependency."""


def pyrvo_available() -> bool:
    """Whether the optional RVO2 binding `pyrvo` imports (checked before any ORCA-F work starts)."""
    try:
        import pyrvo  # noqa: F401
    except ImportError:
        return False
    return True


def _pyrvo():
    """The pyrvo module (RVO2 bindings), or ImportError saying how to get it."""
    try:
        import pyrvo
    except ImportError as exc:  # pragma: no cover - depends on the install
        raise ImportError(PYRVO_MISSING) from exc
    return pyrvo


@dataclass(frozen=True)
class OrcaConfig:
    """ORCA-F settings. ORCA's own parameters follow RVO2's names (RVOSimulator::addAgent)."""

    neighbour_distance: float = 3.0
    """RVO2 neighborDist (m): other agents within this distance are avoided (delta_obs of the task)."""
    time_horizon: float = 2.0
    """RVO2 timeHorizon (s): velocities are kept collision-free with other agents for this long."""
    obstacle_time_horizon: float = 1.0
    """RVO2 timeHorizonObst (s): the same against obstacles."""
    radius_margin: float = 0.1
    """ORCA's agent radius is the UAV radius plus this (m): the env's agents follow the ORCA velocity
    with a lag (acceleration-limited), so ORCA plans with some room to spare."""
    obstacle_sides: int = 16
    """Each cylinder becomes a regular polygon with this many sides that contains it."""
    lookahead: float = 1.0
    """The template is placed this far (m) ahead of the swarm centre toward the anchor (less when
    the anchor is nearer)."""
    formation_gain: float = 1.0
    """Preferred velocity = this gain (1/s) x (slot - position), clipped to the speed limit."""
    velocity_gain: float = 5.0
    """u = clip(velocity_gain (v_orca - v), +-accel_max): the P-gain of AT-M's velocity head."""
    reassign_slots: bool = True
    """Assign agents to template slots by minimum total squared distance every step (True) or once
    per episode, at its first step (False)."""

    def validate(self) -> None:
        """Raise ConfigError naming the first invalid field."""
        for name in (
            "neighbour_distance",
            "time_horizon",
            "obstacle_time_horizon",
            "lookahead",
            "formation_gain",
            "velocity_gain",
        ):
            value = getattr(self, name)
            if not isinstance(value, (int, float)) or not np.isfinite(value) or value <= 0:
                raise ConfigError(f"{name}={value!r}: must be a finite number > 0")
        if (
            not isinstance(self.radius_margin, (int, float))
            or not np.isfinite(self.radius_margin)
            or self.radius_margin < 0
        ):
            raise ConfigError(f"radius_margin={self.radius_margin!r}: must be a finite number >= 0")
        if not isinstance(self.obstacle_sides, int) or self.obstacle_sides < 3:
            raise ConfigError(f"obstacle_sides={self.obstacle_sides!r}: must be an integer >= 3")

    def __post_init__(self) -> None:
        self.validate()


def cylinder_polygon(centre: np.ndarray, radius: float, sides: int) -> np.ndarray:
    """[sides, 2] vertices, counterclockwise (as RVO2 wants), of the regular polygon circumscribed
    about the circle: its edges touch the circle, so the polygon contains the whole cylinder."""
    circumradius = radius / np.cos(np.pi / sides)
    angles = 2.0 * np.pi * np.arange(sides) / sides
    return np.asarray(centre, dtype=float) + circumradius * np.stack([np.cos(angles), np.sin(angles)], axis=-1)


class OrcaFormationPolicy:
    """ORCA-F for the low-level game on a `BatchedCEFCEnv` (mode="formation", one group).

    `act(env)` reads the true agent positions and velocities, the anchors and the obstacles of the
    env and returns acceleration setpoints [B, N, 2]. It keeps one RVO2 simulator per env and rebuilds
    it whenever that env's obstacles change (a new episode).
    """

    def __init__(self, config: TaskConfig, orca: OrcaConfig | None = None):
        if config.mode != "formation":
            raise ConfigError(f"mode={config.mode!r}: ORCA-F flies the low-level game (mode='formation')")
        if config.n_agents < 3:
            raise ConfigError(f"n_agents={config.n_agents}: a formation needs at least 3 agents")
        self.config = config
        self.orca = orca if orca is not None else OrcaConfig()
        self.template = np.asarray(formation_template(config.n_agents, config.formation_spacing))  # [N, 2]
        self._sims: list = []
        self._obstacles: np.ndarray | None = None  # [B, K, 2] the simulators were built for
        self._slots: np.ndarray | None = None  # [B, N] template slot of each agent (fixed assignment)

    # ------------------------------------------------------------------ simulators
    def _build(self, obstacles: np.ndarray):
        """An RVO2 simulator with N agents and the env's cylinders as polygons."""
        cfg, orca = self.config, self.orca
        sim = _pyrvo().RVOSimulator()
        sim.set_time_step(cfg.dt)
        sim.set_agent_defaults(
            orca.neighbour_distance,
            cfg.n_agents,
            orca.time_horizon,
            orca.obstacle_time_horizon,
            cfg.uav_radius + orca.radius_margin,
            cfg.speed_max,
        )
        for _ in range(cfg.n_agents):
            sim.add_agent((0.0, 0.0))
        for centre in obstacles:
            sim.add_obstacle(cylinder_polygon(centre, cfg.obstacle_radius, orca.obstacle_sides).tolist())
        sim.process_obstacles()
        return sim

    def reset(self, env: BatchedCEFCEnv) -> None:
        """Rebuild every simulator for the env's current episodes (act() also does this by itself)."""
        self._sims = [self._build(env.obstacles[b]) for b in range(env.n_envs)]
        self._obstacles = env.obstacles.copy()
        self._slots = None

    # ------------------------------------------------------------------ the policy
    def preferred_velocity(self, pos: np.ndarray, anchor: np.ndarray, new_episode: np.ndarray) -> np.ndarray:
        """[B, N, 2] preferred velocities: toward each agent's slot in the template placed at the
        swarm centre moved up to `lookahead` toward the anchor, clipped to the speed limit."""
        orca = self.orca
        centre = pos.mean(axis=1)  # [B, 2]
        goal = centre + clip_speed(anchor - centre, orca.lookahead)  # template centre [B, 2]
        rel = pos - centre[:, None]  # [B, N, 2]
        if self._slots is None or self._slots.shape != pos.shape[:2]:
            self._slots = np.zeros(pos.shape[:2], dtype=int)
            new_episode = np.ones(pos.shape[0], dtype=bool)
        for b in range(pos.shape[0]) if orca.reassign_slots else np.flatnonzero(new_episode):
            cost = ((rel[b][:, None] - self.template[None]) ** 2).sum(-1)  # [agent, slot]
            agents, slots = linear_sum_assignment(cost)
            self._slots[b, agents] = slots
        target = goal[:, None] + self.template[self._slots]  # [B, N, 2]
        return clip_speed(orca.formation_gain * (target - pos), self.config.speed_max)

    def act(self, env: BatchedCEFCEnv) -> np.ndarray:
        """Acceleration setpoints [B, N, 2] (m/s^2) for the env's current state."""
        cfg, orca = self.config, self.orca
        if env.config.mode != "formation" or env.n_agents != cfg.n_agents:
            raise ConfigError("env: ORCA-F was made for another task (mode or number of agents differ)")
        new_episode = env.t == 0
        if self._obstacles is None or self._obstacles.shape != env.obstacles.shape:
            self.reset(env)
            new_episode[:] = True
        else:
            changed = (self._obstacles != env.obstacles).any(axis=(1, 2))
            for b in np.flatnonzero(changed):
                self._sims[b] = self._build(env.obstacles[b])
            self._obstacles = env.obstacles.copy()
        pos, vel = env.world.agent_pos, env.world.agent_vel
        pref = self.preferred_velocity(pos, env.anchor, new_episode)
        v_orca = np.empty_like(vel)
        for b, sim in enumerate(self._sims):
            for i in range(cfg.n_agents):
                sim.set_agent_position(i, pos[b, i].tolist())
                sim.set_agent_velocity(i, vel[b, i].tolist())
                sim.set_agent_pref_velocity(i, pref[b, i].tolist())
            sim.do_step()
            for i in range(cfg.n_agents):
                v = sim.get_agent_velocity(i)
                v_orca[b, i] = (v.x, v.y)
        return np.clip(orca.velocity_gain * (v_orca - vel), -cfg.accel_max, cfg.accel_max)


def evaluate_orca_episodes(
    formation: int,
    episodes: int = TABLE3_EPISODES,
    seed: int = 0,
    steps: int = TABLE3_STEPS,
    density: float = TABLE3_DENSITY,
    orca: OrcaConfig | None = None,
    obstacle_layout: str = "paper",
) -> dict[str, np.ndarray]:
    """Per-episode R_L (per step), F, N, C [episodes] of ORCA-F for one group of `formation` agents,
    on the episodes cefc_mj.eval.table3.evaluate_lowlevel_episodes flies (same config, batch, seed)."""
    if not isinstance(formation, int) or formation < 3:
        raise ConfigError(f"formation={formation!r}: must be an integer >= 3")
    if not isinstance(episodes, int) or episodes < 1:
        raise ConfigError(f"episodes={episodes!r}: must be an integer >= 1")
    if not isinstance(steps, int) or steps < 1:
        raise ConfigError(f"steps={steps!r}: must be an integer >= 1")
    task = TaskConfig(
        n_agents=formation,
        mode="formation",
        obstacle_density=density,
        episode_steps=steps,
        obstacle_layout=obstacle_layout,
    )
    env = BatchedCEFCEnv(task, n_envs=episodes, seed=seed)
    policy = OrcaFormationPolicy(task, orca)
    obs = env.reset(seed=seed)
    policy.reset(env)
    return roll_out(env, obs, lambda _obs: policy.act(env), steps)  # ORCA reads the env's true state


def evaluate_orca(
    formation: int,
    episodes: int = TABLE3_EPISODES,
    seed: int = 0,
    steps: int = TABLE3_STEPS,
    density: float = TABLE3_DENSITY,
    orca: OrcaConfig | None = None,
    obstacle_layout: str = "paper",
) -> dict[str, float]:
    """R_L (per step), F, N (steps), C (% of agent-steps) of ORCA-F averaged over `episodes` episodes:
    the keys and protocol of cefc_mj.eval.table3.evaluate_lowlevel."""
    per_episode = evaluate_orca_episodes(formation, episodes, seed, steps, density, orca, obstacle_layout)
    return {m: float(v.mean()) for m, v in per_episode.items()}
