"""Typed configuration of the CEFC task, shared by both physics backends.

Every field has a docstring; `TaskConfig.validate()` runs at construction and raises
`ConfigError` naming the offending field. `TaskConfig.to_dict()` is what runs save next to their
results.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Literal, get_args

from cefc_mj.errors import ConfigError
from cefc_mj.task.estimator import POSITION_ESTIMATORS, PositionEstimator

Mode = Literal["formation", "cefc"]
AdversaryRule = Literal[
    "nearest_group",
    "r_nearest",
    "r_largest",
    "nearest_group_strike",
    "nearest_group_member",
    "nearest_group_intercept",
    "none",
    "learned",
]
ObstacleLayout = Literal["clear-start", "paper"]

MAX_ACCEL = 9.81
"""Largest action bound (TaskConfig.accel_max, m/s^2 per axis) the trainers and evaluators take: about
what PX4's 45 deg tilt limit (MPC_TILTMAX_AIR) lets a hovering quadrotor produce horizontally."""
FORMATION_EPISODE_STEPS = 100
"""Decision steps of a low-level ("formation") episode, the paper's."""
CEFC_EPISODE_STEPS = 400
"""Decision steps of a full-game ("cefc") episode, the paper's."""
DEFAULT_NEIGHBOUR_SLOTS = 7
"""K when TaskConfig.max_neighbours is None: N - 1 for the paper's 8 UAVs."""
STRAGGLER_MIN_DISTANCE, STRAGGLER_MAX_DISTANCE = 3.0, 7.0
"""A straggler (TaskConfig.straggler_fraction) starts this far (m) from the start square's centre."""
START_SPACING_MARGIN = 0.1
"""Room (m) beyond two UAV radii between any two start positions (TaskConfig.start_min_spacing = 0.5 +
0.1): a pair starting at rest closes by at most 2 sqrt(2) a_max dt^2 = 0.057 m in its first decision
step (both at a_max per axis towards each other), and a quadrotor's footprint disc tilted towards a
neighbour reaches sqrt(0.25^2 + 0.05^2) = 0.255 m from its centre; 0.6 m is also the centre distance
the separation guard holds (task/guard.py)."""
RULE_TEAMS = ("rule-urgent", "rule-split", "rule-evade")
"""The rule-driven UAV teams of the PPO adversary's training population (cefc_mj/rule_teams.py)."""
LEARNED_ADVERSARY = "learned"
"""TaskConfig.adversary of a trained adversary: the env asks its `adversary_policy` for the acceleration."""
ADVERSARIES = get_args(AdversaryRule)
"""Every TaskConfig.adversary: the rules (task/adversary.py), "none" and LEARNED_ADVERSARY."""
ADVERSARY_RULES = tuple(a for a in ADVERSARIES if a != LEARNED_ADVERSARY)
OBSTACLE_LAYOUTS = ("clear-start", "paper")


@dataclass(frozen=True)
class RewardConfig:
    """Reward parameters of the paper's Table II and Appendix A (Table IX)."""

    formation_weight: float = 15.0
    """omega_f: weight of the formation reward in R_L."""
    navigation_weight_low: float = 4.0
    """omega_n in R_L (low level, anchor navigation)."""
    collision_weight: float = 100.0
    """omega_c: weight of the collision-avoidance reward in R_L."""
    task_weight: float = 10.0
    """omega_t: weight of the task-accomplishment reward in R_H."""
    navigation_weight_high: float = 0.1
    """omega_n in R_H (high level, urgency-weighted target navigation)."""
    evasion_weight: float = 100.0
    """omega_e: weight of the evasion reward in R_H."""
    formation_lag: float = 0.3
    """omega_l: formation lag coefficient, R_f(t) = -sum_k HD_k - omega_l R_f(t-1)."""
    urgency_decay: float = 0.003
    """omega_d: urgency decay per covering agent per step."""
    evasion_alert_distance: float = 2.0
    """delta_a,e (m): agents closer than this to the adversary are penalised."""
    collision_alert_distance: float = 0.5
    """delta_a,c (m): LiDAR ranges below this are penalised."""
    safety_distance: float = 0.2
    """delta_s (m): minimum safety distance of the collision reward."""
    collision_constants: tuple[float, float, float, float] = (24.0, 8.0, 3.0, 1.0)
    """(omega_cr1, omega_cr2, C1, C2) of the collision reward."""


@dataclass(frozen=True)
class TaskConfig:
    """The CEFC game, physics-free. Defaults are the paper's (Table II, Sec. V-A)."""

    n_agents: int = 8
    """N: number of UAVs."""
    mode: Mode = "cefc"
    """"formation": the low-level game (one group of all agents flies in formation to an anchor;
    no targets, no adversary; reward R_L). "cefc": the full game (targets, adversary, groups as
    connected components; reward R_H)."""
    episode_steps: int | None = None
    """Decision steps per episode; None picks 100 (formation) or 400 (cefc)."""
    dt: float = 0.1
    """Decision step (s)."""
    arena_half_size: float = 10.0
    """The arena is [-a, a]^2 m (20 m x 20 m); obstacles are placed inside it."""
    start_half_size: float = 2.0
    """Agents start uniformly in [-s, s]^2 m."""
    start_min_spacing: float = 0.6
    """Minimum distance between two start positions (m): two UAV radii (0.5) plus START_SPACING_MARGIN, so no
    pair is in contact at the start or after its first decision step (docs/research/decisions.md, "Start spacing")."""
    straggler_fraction: float = 0.0
    """Fraction of episodes (drawn per env at reset) in which the last agent starts away from the
    others: 3-7 m from the start square's centre and at least observation_distance from every other
    start, so it sees no neighbour and must rejoin the group, often around obstacles. A training
    scenario (`cefc-train lowlevel --straggler-fraction`); 0 is the paper's starts, and draws nothing."""
    obstacle_density: float = 0.0
    """Obstacles per m^2 over the arena (paper: 0 and 0.03 for training, 0.05 for Table III)."""
    obstacle_radius: float = 0.4
    """Radius of the cylinder obstacles (m)."""
    obstacle_min_gap: float = 0.5
    """Minimum free gap between two obstacle surfaces (m): twice the UAV radius, so a UAV fits."""
    obstacle_layout: ObstacleLayout = "paper"
    """How obstacle centres are drawn (docs/research/layouts.md). "paper" (the paper's description):
    uniform over the arena, a centre rejected only when the obstacle would overlap another
    (obstacle_min_gap) or a UAV's start disc (with 0.1 m to spare), or lie within anchor_clearance
    of the anchor or a target centre. "clear-start" (the project's first, easier sampler): also
    outside the whole start square grown by the obstacle and UAV radii."""
    anchor_half_size: float = 5.0
    """Anchors are drawn uniformly in [-h, h]^2 m."""
    anchor_clearance: float = 2.0
    """Minimum distance from an anchor to an obstacle centre (m), so a formation fits around it."""
    anchor_redraw_steps: int | None = None
    """Redraw the anchor every this many steps (Table VIII: 250); None keeps it for the episode."""
    observation_distance: float = 3.0
    """delta_obs (m): neighbours and groups are defined by distance below this."""
    formation_spacing: float = 1.0
    """Nearest-neighbour spacing s of the formation templates (m)."""
    formation_tolerance: float = 1.0
    """delta_for (m): a group is in formation when its Hausdorff error is below this."""
    navigation_tolerance: float = 1.0
    """Metric N counts steps with the swarm centre within this distance of the anchor (m)."""
    target_radius: float = 3.0
    """delta_task (m): radius of a target area."""
    n_targets: int = 2
    """Targets drawn per episode from the 4 corners (+-c, +-c)."""
    target_corner: float = 8.0
    """The candidate targets are at (+-c, +-c) m."""
    speed_max: float = 1.0
    """UAV speed limit (m/s)."""
    adversary_speed_max: float = 0.75
    """Adversary speed limit (m/s)."""
    accel_max: float = 2.0
    """Per-axis clip of every drone's acceleration setpoint (m/s^2): the policy's action bound. Our
    choice: the paper states no action bound (it limits speed to 1 m/s and sends acceleration
    setpoints to PX4); within 2 m/s^2 no policy can hold Iris against Wind-8's rotor-drag push
    (docs/px4_interface.md)."""
    uav_radius: float = 0.25
    """UAV collision footprint radius (m), the same in both backends (Iris-class frame)."""
    n_lidar_rays: int = 24
    """M: LiDAR beams, evenly spaced over 360 degrees, beam k at angle 2 pi k / M."""
    lidar_range: float = 3.0
    """LiDAR range (m); ranges are clipped to it."""
    lidar_sees_agents: bool = True
    """LiDAR beams hit other UAVs' discs as well as obstacles."""
    max_neighbours: int | None = None
    """K: neighbour slots in the observations (low level and CEFC): each agent sees its K nearest
    neighbours within observation_distance, nearest first. None picks 7 (N - 1 for the paper's 8
    UAVs), so every policy reads the same observation shape for any N: the low level for c = 3..8,
    and the whole hierarchy for N = 8..15 (Table VII)."""
    adversary: AdversaryRule = "nearest_group"
    """Adversary strategy in cefc mode: the rules pursue the nearest group of >= 3 agents, the nearest
    agent (R-Nearest) or the largest group (R-Largest); "none" has no adversary; "learned" is flown by
    a trained policy handed to the env (`BatchedCEFCEnv(adversary_policy=...)`, e.g. the PPO adversary)."""
    adversary_start: tuple[float, float] = (0.0, 8.0)
    """Where the adversary starts (m); its x is jittered by the scenario sampler."""
    adversary_avoids_obstacles: bool = False
    """The rule adversary steers around the obstacles, keeping uav_radius + obstacle_radius from
    their centres (task/adversary.py); False: it flies straight through them, the game the shipped
    high levels were trained in."""
    deviation: float = 0.0
    """Sensing deviation d (m): each agent perceives from p + delta, |delta| ~ |Normal(d, d/4)|."""
    position_estimator: PositionEstimator = "raw"
    """How an agent turns its noisy position fixes into the position it acts on (task/estimator.py):
    "raw" uses each fix as it is (the paper's memoryless agent); "fused" is an onboard Kalman filter
    that fuses the fixes with the agent's own measured velocity, as a drone's EKF does."""
    push_observer_s: float = 0.0
    """Time constant tau (s) of the agent's push observer (task/push_observer.py): an onboard estimate
    of the acceleration the agent feels beyond its own setpoint (the wind's push), cancelled in the
    setpoint it sends, within accel_max. 0: none, the paper's memoryless agent. Part of the agent,
    applied in the env's step as the position estimate is."""
    separation_guard: bool = False
    """Each agent passes its policy's action through the separation guard (task/guard.py), a rule on
    its own observation that limits the closing speed towards neighbours and LiDAR hits so that a
    lagging vehicle still stops in time; False is the paper's agent (the policy's action as it is).
    Part of the agent: the env never reads it, the evaluators' agents do (`guarded`)."""
    deviation_sampling: str = "fixed"
    """"fixed": every episode uses `deviation`. "uniform": each env draws its episode's d uniformly
    from [0, deviation] at reset (training under a range of sensing quality)."""
    response_time: float = 0.0
    """Particle world only: time constant (s) of the first-order lag between the commanded velocity
    (the integrated action) and the velocity; 0 is the paper's MPE (no lag)."""
    velocity_noise: float = 0.0
    """Particle world only: std (m/s, per axis) of a Gaussian kick added to every UAV's velocity each
    step, standing in for the tracking error of a real vehicle; 0 is the paper's MPE."""
    rewards: RewardConfig = field(default_factory=RewardConfig)
    """Reward parameters."""

    def __post_init__(self) -> None:
        self.validate()

    # ---------------------------------------------------------------- derived values
    @property
    def steps(self) -> int:
        """Episode length in decision steps."""
        if self.episode_steps is not None:
            return self.episode_steps
        return FORMATION_EPISODE_STEPS if self.mode == "formation" else CEFC_EPISODE_STEPS

    @property
    def neighbour_slots(self) -> int:
        """K: neighbour slots of the observations (the K nearest within observation_distance)."""
        return self.max_neighbours if self.max_neighbours is not None else DEFAULT_NEIGHBOUR_SLOTS

    @property
    def n_obstacles(self) -> int:
        """Obstacle count: density x arena area, rounded."""
        return int(round(self.obstacle_density * (2 * self.arena_half_size) ** 2))

    # ---------------------------------------------------------------- validation
    def validate(self) -> None:
        """Raise ConfigError naming the first invalid field."""

        def fail(name: str, value: object, why: str) -> None:
            raise ConfigError(f"{name}={value!r}: {why}")

        def finite(name: str, value: float) -> None:
            if not isinstance(value, (int, float)) or not math.isfinite(value):
                fail(name, value, "must be a finite number")

        if not isinstance(self.n_agents, int) or self.n_agents < 1:
            fail("n_agents", self.n_agents, "must be an integer >= 1")
        if self.mode not in ("formation", "cefc"):
            fail("mode", self.mode, "must be 'formation' or 'cefc'")
        if self.episode_steps is not None and (not isinstance(self.episode_steps, int) or self.episode_steps < 1):
            fail("episode_steps", self.episode_steps, "must be an integer >= 1")
        for name in (
            "dt",
            "arena_half_size",
            "start_half_size",
            "obstacle_radius",
            "anchor_half_size",
            "observation_distance",
            "formation_spacing",
            "formation_tolerance",
            "navigation_tolerance",
            "target_radius",
            "target_corner",
            "speed_max",
            "adversary_speed_max",
            "accel_max",
            "uav_radius",
            "lidar_range",
        ):
            value = getattr(self, name)
            finite(name, value)
            if value <= 0:
                fail(name, value, "must be > 0")
        for name in (
            "obstacle_density",
            "start_min_spacing",
            "obstacle_min_gap",
            "anchor_clearance",
            "deviation",
            "response_time",
            "velocity_noise",
            "push_observer_s",
        ):
            value = getattr(self, name)
            finite(name, value)
            if value < 0:
                fail(name, value, "must be >= 0")
        if self.anchor_redraw_steps is not None and (
            not isinstance(self.anchor_redraw_steps, int) or self.anchor_redraw_steps < 1
        ):
            fail("anchor_redraw_steps", self.anchor_redraw_steps, "must be an integer >= 1 or None")
        if not isinstance(self.n_lidar_rays, int) or self.n_lidar_rays < 1:
            fail("n_lidar_rays", self.n_lidar_rays, "must be an integer >= 1")
        if self.max_neighbours is not None and (not isinstance(self.max_neighbours, int) or self.max_neighbours < 1):
            fail("max_neighbours", self.max_neighbours, "must be an integer >= 1 or None")
        if not isinstance(self.n_targets, int) or not 0 <= self.n_targets <= 4:
            fail("n_targets", self.n_targets, "must be an integer in 0..4")
        if self.position_estimator not in POSITION_ESTIMATORS:
            fail("position_estimator", self.position_estimator, f"must be one of {', '.join(POSITION_ESTIMATORS)}")
        if not isinstance(self.separation_guard, bool):
            fail("separation_guard", self.separation_guard, "must be True or False")
        if self.separation_guard and self.mode != "formation":
            fail(
                "separation_guard",
                self.separation_guard,
                "the guard reads the low-level observation: mode='formation' only",
            )
        if self.deviation_sampling not in ("fixed", "uniform"):
            fail("deviation_sampling", self.deviation_sampling, "must be 'fixed' or 'uniform'")
        finite("straggler_fraction", self.straggler_fraction)
        if not 0 <= self.straggler_fraction <= 1:
            fail("straggler_fraction", self.straggler_fraction, "must be in [0, 1]")
        if self.straggler_fraction > 0 and (
            self.n_agents < 2
            or self.observation_distance >= STRAGGLER_MAX_DISTANCE - self.start_half_size * math.sqrt(2)
        ):
            fail(
                "straggler_fraction",
                self.straggler_fraction,
                f"needs at least 2 agents and observation_distance + the start square's half-diagonal below "
                f"{STRAGGLER_MAX_DISTANCE} m",
            )
        if self.obstacle_layout not in OBSTACLE_LAYOUTS:
            fail("obstacle_layout", self.obstacle_layout, f"must be one of {', '.join(OBSTACLE_LAYOUTS)}")
        if self.adversary not in ADVERSARIES:
            fail("adversary", self.adversary, f"must be one of {', '.join(ADVERSARIES)}")
        if not isinstance(self.adversary_avoids_obstacles, bool):
            fail("adversary_avoids_obstacles", self.adversary_avoids_obstacles, "must be True or False")
        if self.start_half_size >= self.arena_half_size:
            fail("start_half_size", self.start_half_size, "must be smaller than arena_half_size")
        if self.anchor_half_size > self.arena_half_size:
            fail("anchor_half_size", self.anchor_half_size, "must be at most arena_half_size")
        if self.start_min_spacing < 2 * self.uav_radius:
            fail(
                "start_min_spacing",
                self.start_min_spacing,
                f"must be at least 2 x uav_radius = {2 * self.uav_radius:g} m, or two UAVs start in contact",
            )
        # Start positions: the square must hold N points at min spacing (hexagonal packing bound).
        side = 2 * self.start_half_size
        if self.start_min_spacing > 0:
            capacity = (side / self.start_min_spacing + 1) ** 2
            if self.n_agents > capacity:
                fail(
                    "n_agents",
                    self.n_agents,
                    f"cannot place {self.n_agents} starts {self.start_min_spacing} m apart "
                    f"in [-{self.start_half_size}, "
                    f"{self.start_half_size}]^2",
                )
        # Obstacles: each needs a disc of radius r + gap/2 that no other may overlap; hard-disc random
        # packing jams near 55 % coverage, and the start square is kept free.
        if self.n_obstacles > 0:
            r_eff = self.obstacle_radius + self.obstacle_min_gap / 2
            keep_out = 2 * (self.start_half_size + self.obstacle_radius + self.uav_radius)
            free_area = (2 * self.arena_half_size) ** 2 - keep_out**2
            coverage = self.n_obstacles * math.pi * r_eff**2 / max(free_area, 1e-9)
            if coverage > 0.4:
                fail(
                    "obstacle_density",
                    self.obstacle_density,
                    f"too high: {self.n_obstacles} obstacles of radius {self.obstacle_radius} m cannot be placed "
                    f"{self.obstacle_min_gap} m apart in the free part of the arena (coverage {coverage:.0%} > 40%)",
                )

    def to_dict(self) -> dict:
        """A JSON-ready dict of every field (nested dataclasses included)."""
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict) -> "TaskConfig":
        """Inverse of to_dict; unknown keys raise ConfigError (a typo must fail loudly)."""
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = set(data) - known
        if unknown:
            raise ConfigError(f"unknown TaskConfig field(s): {', '.join(sorted(unknown))}")
        data = dict(data)
        # configs saved before the field existed were drawn with the first sampler
        data.setdefault("obstacle_layout", "clear-start")
        if isinstance(data.get("rewards"), dict):
            rewards = dict(data["rewards"])
            if "collision_constants" in rewards:
                rewards["collision_constants"] = tuple(rewards["collision_constants"])
            data["rewards"] = RewardConfig(**rewards)
        if "adversary_start" in data:
            data["adversary_start"] = tuple(data["adversary_start"])
        return cls(**data)
