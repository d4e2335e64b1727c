"""Typed, validated training configurations. Every run saves its resolved config as JSON
(`config.json` in the run folder) and in every checkpoint; a resumed run must match it.

>>> cfg = LowLevelConfig(formation=6, step=1, budget=Budget.parse("20it"))
>>> cfg.density, cfg.ppo.gamma
(0.0, 0.8)
"""

from __future__ import annotations

import dataclasses
import math
import re
from dataclasses import dataclass, field

from cefc_mj.errors import ConfigError
from cefc_mj.nn.registry import DISTILL_TEACHER, clm_name, lowlevel_name
from cefc_mj.task.config import (
    FORMATION_EPISODE_STEPS,
    MAX_ACCEL,
    STRAGGLER_MAX_DISTANCE,
    STRAGGLER_MIN_DISTANCE,
)
from cefc_mj.task.push_observer import MAX_PUSH_OBSERVER_S

FORMATIONS = (3, 4, 5, 6, 7, 8)
"""The paper's formation sizes c (Fig. 3)."""
STEP_DENSITY = {1: 0.0, 2: 0.03, 3: 0.03}
"""Training obstacle density (per m^2) of each AT-M step (paper Sec. V-A: 0 and 0.03)."""

# Upper bounds of user-facing values. They are far beyond anything useful and exist so that a typo
# ('1e99it', --envs 100000000, --tuples 10**12) ends in one clear line instead of an overflow, an
# out-of-memory kill or a run that never ends.
MAX_ITERATIONS = 10_000_000
"""Largest iteration budget (PPO iterations or distillation gradient steps)."""
MAX_SECONDS = 30 * 24 * 3600.0
"""Largest wall-clock budget: 30 days."""
MAX_SEED = 2**32 - 1
"""Seeds are in [0, 2^32 - 1] (numpy's SeedSequence takes no negative entropy)."""
MAX_ENVS = 1024
"""Most parallel envs of one PPO rollout (over 1 GB of rollout tensors at c = 8)."""
MAX_EPOCHS = 100
"""Most PPO epochs per iteration."""
MAX_THREADS = 256
"""Most torch threads."""
MAX_LR = 1.0
"""Largest Adam learning rate."""
MAX_TUPLES = 1_000_000
"""Most replay tuples per teacher (about 260 MB each, held in memory)."""
MAX_DENSITY = 0.2
"""Largest training obstacle density (per m^2)."""
MAX_CURRICULUM_PHASES = 20
"""Most phases (densities) of a CL-M curriculum."""
MAX_ANCHOR_PERIODS = 20
"""Most anchor periods of one training episode."""
CLM_CURRICULUM = (0.0, 0.01, 0.02, 0.03)
"""The default CL-M curriculum: from AT-M Step 1's free space to Step 2's density 0.03 in equal steps."""


def _fail(name: str, value: object, why: str) -> None:
    raise ConfigError(f"{name}={value!r}: {why}")


def _check_int(name: str, value: object, least: int, most: int | None = None) -> None:
    """An int (not a bool) in [least, most]."""
    if not isinstance(value, int) or isinstance(value, bool) or value < least:
        _fail(name, value, f"must be an integer >= {least}")
    if most is not None and value > most:
        _fail(name, value, f"must be at most {most}")


@dataclass(frozen=True)
class Budget:
    """How long a stage trains: a number of iterations, a wall-clock time, or both (whichever ends
    first). Wall-clock time counts across resumes."""

    iterations: int | None = None
    """Stop after this many PPO iterations (or distillation gradient steps)."""
    seconds: float | None = None
    """Stop once this much training wall-clock time (s) has been spent."""

    def __post_init__(self) -> None:
        if self.iterations is None and self.seconds is None:
            _fail("budget", self, "give iterations, seconds or both")
        if self.iterations is not None and (not isinstance(self.iterations, int) or self.iterations < 1):
            _fail("budget.iterations", self.iterations, "must be an integer >= 1")
        if self.seconds is not None and (not math.isfinite(self.seconds) or self.seconds <= 0):
            _fail("budget.seconds", self.seconds, "must be a positive number of seconds")

    @classmethod
    def parse(cls, text: str) -> "Budget":
        """'40' or '40it' -> 40 iterations; '90s', '15m', '1.5h' -> seconds."""
        text = str(text)
        shown = text if len(text) <= 40 else text[:37] + "..."
        m = re.fullmatch(r"\s*(\d+(?:\.\d+)?)\s*(it|s|m|h)?\s*", text)
        if not m:
            raise ConfigError(f"--budget {shown!r}: expected iterations ('40', '40it') or time ('90s', '15m', '1.5h')")
        value, unit = float(m.group(1)), m.group(2) or "it"
        if value <= 0:
            raise ConfigError(f"--budget {shown!r}: must be more than zero")
        if unit == "it":
            if not value <= MAX_ITERATIONS:
                raise ConfigError(f"--budget {shown!r}: at most {MAX_ITERATIONS} iterations")
            if value != int(value):
                raise ConfigError(f"--budget {shown!r}: iterations must be a whole number")
            return cls(iterations=int(value))
        seconds = value * {"s": 1, "m": 60, "h": 3600}[unit]
        if not seconds <= MAX_SECONDS:
            raise ConfigError(f"--budget {shown!r}: at most {MAX_SECONDS / 86400:.0f} days")
        return cls(seconds=seconds)

    def scaled(self, share: float) -> "Budget":
        """This budget times `share` (at least one iteration / one second)."""
        return Budget(
            iterations=None if self.iterations is None else max(1, round(self.iterations * share)),
            seconds=None if self.seconds is None else max(1.0, self.seconds * share),
        )

    def exhausted(self, iterations: int, seconds: float) -> bool:
        return (self.iterations is not None and iterations >= self.iterations) or (
            self.seconds is not None and seconds >= self.seconds
        )

    def __str__(self) -> str:
        parts = ([f"{self.iterations} it"] if self.iterations is not None else []) + (
            [f"{self.seconds:.0f} s"] if self.seconds is not None else []
        )
        return " or ".join(parts)


@dataclass(frozen=True)
class PPOConfig:
    """MAPPO hyperparameters. gamma, lambda, clip and the 20 envs are the paper's (Sec. V-A, Table
    II). Three defaults differ from it, chosen by measurement within a 2-hour budget on 2 CPU cores (the
    paper's 500 iterations x 15 epochs do not fit in it): 5 epochs instead of 15 (3x cheaper
    updates, more fresh data per second), Adam 3e-4 instead of 1e-4 (the KL per iteration stayed
    ~0.003 at 1e-4), no entropy bonus (with it the action std grew past 1.3 and formation learning
    stalled). `--epochs 15 --lr 1e-4` restores the paper's settings."""

    n_envs: int = 20
    """Parallel envs per rollout (the paper's 20 threads), stepped as one batch in this process."""
    episodes_per_iteration: int = 1
    """Whole episodes per env collected before each update (1: 20 episodes x 100 steps)."""
    epochs: int = 5
    """PPO epochs over each batch (paper: 15)."""
    minibatches: int = 4
    """Minibatches per epoch; the batch is split over env-steps, all agents of a step together."""
    lr: float = 3e-4
    """Adam learning rate of actor and critic (paper: 1e-4)."""
    gamma: float = 0.8
    """Discount factor (paper Table II: 0.8)."""
    gae_lambda: float = 0.95
    """GAE lambda (paper: 0.95)."""
    clip_eps: float = 0.2
    """PPO ratio clip epsilon (paper: 0.2)."""
    entropy_coef: float = 0.0
    """Entropy bonus alpha of eq. (7) (MAPPO's default is 0.01; see the class docstring)."""
    max_grad_norm: float = 10.0
    """Global gradient-norm clip, applied to actor and critic separately (MAPPO default 10)."""
    collision_credit: str = "agent"
    """"team": every agent learns from the team reward R_L (the paper). "agent": the collision term
    is credited to the agent it belongs to, r_i = 15 R_f + 4 R_n - 100 CR_i (cefc_mj.train.mappo)."""
    normalize_advantages: bool = True
    """Standardize the advantages of each batch (zero mean, unit std) before the epochs."""
    value_normalization: bool = True
    """Critic regresses running-normalized returns (ValueNorm)."""
    rollout_threads: int = 1
    """torch intra-op threads while collecting rollouts (tiny batches: 1 is fastest)."""
    update_threads: int = 2
    """torch intra-op threads during the PPO update."""

    def validate(self) -> None:
        for name, most in (
            ("n_envs", MAX_ENVS),
            ("episodes_per_iteration", 100),
            ("epochs", MAX_EPOCHS),
            ("minibatches", None),
            ("rollout_threads", MAX_THREADS),
            ("update_threads", MAX_THREADS),
        ):
            _check_int(name, getattr(self, name), 1, most)
        # A minibatch is a set of env-steps; more minibatches than env-steps would leave some empty.
        env_steps = self.n_envs * self.episodes_per_iteration * FORMATION_EPISODE_STEPS
        if self.minibatches > env_steps:
            _fail(
                "minibatches",
                self.minibatches,
                f"must be at most the {env_steps} env-steps of an iteration "
                f"(n_envs x episodes x {FORMATION_EPISODE_STEPS} steps)",
            )
        for name in ("lr", "clip_eps", "max_grad_norm"):
            v = getattr(self, name)
            if not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
                _fail(name, v, "must be a positive number")
        if self.lr > MAX_LR:
            _fail("lr", self.lr, f"must be at most {MAX_LR}")
        for name in ("gamma", "gae_lambda"):
            v = getattr(self, name)
            if not isinstance(v, (int, float)) or not 0 <= v <= 1:
                _fail(name, v, "must be in [0, 1]")
        if self.collision_credit not in ("team", "agent"):
            _fail("collision_credit", self.collision_credit, "must be 'team' or 'agent'")
        if not isinstance(self.entropy_coef, (int, float)) or self.entropy_coef < 0:
            _fail("entropy_coef", self.entropy_coef, "must be >= 0")


def flag_error(error: ConfigError, flag_of_field: dict[str, str]) -> ConfigError:
    """'n_envs=0: must be ...' from a config -> '--envs 0: must be ...', naming the flag the user typed."""
    field_name, sep, rest = str(error).partition("=")
    if sep and field_name in flag_of_field:
        value, _, why = rest.partition(": ")
        return ConfigError(f"{flag_of_field[field_name]} {value}: {why}")
    return error


def config_from_flags(
    make,
    args,
    budget: "Budget",
    fields: tuple[str, ...],
    ppo_fields: tuple[str, ...],
    base_ppo: "PPOConfig",
    flag_of_field: dict[str, str],
):
    """make(budget=, ppo=, **fields) from command-line arguments: the `fields` and `ppo_fields` given
    (not None) override the defaults and `base_ppo`; a bad value raises ConfigError naming its flag."""
    given = {name: getattr(args, name) for name in fields if getattr(args, name, None) is not None}
    ppo_given = {name: getattr(args, name) for name in ppo_fields if getattr(args, name, None) is not None}
    try:
        return make(budget=budget, ppo=dataclasses.replace(base_ppo, **ppo_given), **given)
    except ConfigError as e:
        raise flag_error(e, flag_of_field) from None


class BudgetPPODict:
    """to_dict / from_dict of a run config whose `budget` is a Budget and `ppo` a PPOConfig (the
    form saved in config.json and state.pt, read back by --resume)."""

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict):
        d = dict(d)
        d["budget"] = Budget(**d["budget"])
        d["ppo"] = PPOConfig(**d["ppo"])
        if d.get("mujoco") is not None:
            d["mujoco"] = MujocoTraining(**d["mujoco"])
        return cls(**d)


OFFBOARD_MODES = ("acceleration", "acceleration-assisted", "velocity")
"""What the MuJoCo world's offboard interface makes of a setpoint (MujocoWorldConfig.offboard)."""
MAX_TRAINING_WIND = 15.0
"""Largest mean wind (m/s) a MuJoCo fine-tune draws from."""
MAX_ROLLOUT_WORKERS = 64
"""Most rollout processes of one MuJoCo fine-tune."""


@dataclass(frozen=True)
class MujocoTraining:
    """Where a low-level fine-tune learns when it learns on quadrotors: the MuJoCo world with the
    PX4-like cascade, instead of the particle world. Each episode draws its own wind (mean speed,
    direction, a gust) and, with the stage's deviation_sampling "uniform", its own sensing deviation."""

    offboard: str = "acceleration"
    """The offboard interface the policy flies through (docs/px4_interface.md): "acceleration" (the
    paper's, with PX4's semantics: the setpoint straight to tilt and thrust, no velocity loop),
    "acceleration-assisted" (not PX4's: the earlier interface with a speed limiter and a drag
    feed-forward, with which the shipped atm_c<C>_mujoco were trained) or "velocity" (the evaluators'
    default)."""
    wind_max: float = 8.0
    """Each episode's mean wind speed is drawn uniformly from [0, wind_max] m/s, its direction
    uniformly; speeds are redrawn every 0.5 s around that mean (Gazebo wind-plugin semantics)."""
    gust_speed: float = 3.0
    """Mean speed (m/s) of a gust of `gust_duration` s along the episode's wind direction, starting at
    a uniformly drawn time of the episode; 0 = no gusts."""
    gust_duration: float = 2.0
    """Seconds each episode's gust lasts."""
    critic_warmup: int = 10
    """The first this many iterations train only the critic: the policy file holds only the actor, so
    the critic starts fresh, and its first advantages would otherwise push a trained actor around."""
    rollout_workers: int = 1
    """Processes collecting each iteration's episodes, each stepping n_envs / rollout_workers MuJoCo
    worlds (1: in the training process). Part of the run's identity: a run resumes with the same."""

    def validate(self, n_envs: int) -> None:
        if self.offboard not in OFFBOARD_MODES:
            _fail("mujoco.offboard", self.offboard, f"must be one of {', '.join(OFFBOARD_MODES)}")
        for name, most in (("wind_max", MAX_TRAINING_WIND), ("gust_speed", MAX_TRAINING_WIND), ("gust_duration", 60.0)):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 <= value <= most:
                _fail(f"mujoco.{name}", value, f"must be in [0, {most:g}]")
        _check_int("mujoco.rollout_workers", self.rollout_workers, 1, MAX_ROLLOUT_WORKERS)
        _check_int("mujoco.critic_warmup", self.critic_warmup, 0, MAX_ITERATIONS)
        if n_envs % self.rollout_workers:
            _fail(
                "mujoco.rollout_workers",
                self.rollout_workers,
                f"must divide the {n_envs} envs of an iteration (each process steps the same number)",
            )


@dataclass(frozen=True)
class LowLevelConfig(BudgetPPODict):
    """One low-level training stage: formation size c, AT-M step, Safe or not; with a `curriculum`,
    the CL-M baseline instead (one MAPPO stage from random weights over rising obstacle densities)."""

    formation: int
    """c: agents in the group (one of 3..8)."""
    step: int
    """AT-M step: 1 (no obstacles, random init), 2 (obstacles, random init), 3 (obstacles, init
    from Step 1's formation & output modules and Step 2's obstacle module and critic). CL-M (a
    `curriculum`) is step 1: random init, the curriculum's densities instead of 0."""
    budget: Budget
    """How long this stage trains."""
    safe: bool = False
    """AT-M-Safe: train (from the Step 3 result) with the LiDAR reported 0.2 m shorter where it
    sees something. Only with step 3."""
    seed: int = 0
    """Seeds network init, action sampling and every iteration's episodes."""
    obstacle_density: float | None = None
    """Training obstacle density (per m^2); None: the step's default (0 / 0.03 / 0.03)."""
    deviation: float = 0.0
    """Sensing deviation d (m) during training. With step 3 and d > 0 this is AT-M-Robust: the Step 3
    policy fine-tuned while every agent perceives from a noisy position (docs/design.md §7), so that it
    keeps its distance from neighbours it sees up to ~1 m off (this project's addition)."""
    deviation_sampling: str = "fixed"
    """"fixed": every training episode uses `deviation`; "uniform": each env draws its episode's d
    from [0, deviation], so one policy learns calm and noisy sensing alike."""
    response_time: float = 0.0
    """Velocity lag (s) of the particle world during training (TaskConfig.response_time); 0 is the
    paper's MPE, about 0.1 matches the MuJoCo quadrotor's velocity loop."""
    velocity_noise: float = 0.0
    """Std (m/s) of the particle world's per-step velocity kicks during training
    (TaskConfig.velocity_noise); 0 is the paper's MPE."""
    accel_max: float = 2.0
    """The action bound (m/s^2 per axis) the stage trains at (TaskConfig.accel_max): our choice, the
    paper states none. A policy file records it; `--init-from` may start from one trained at another
    bound (the bound clips the network's output, the weights keep their meaning)."""
    push_observer_s: float = 0.0
    """Time constant (s) of the agent's push observer during training (TaskConfig.push_observer_s,
    task/push_observer.py); 0: none, the paper's memoryless agent. A policy file records it and every
    evaluator flies the policy with it."""
    collision_margin: float = 0.0
    """Added (m) to both distances of the collision reward (delta_s and delta_a,c, RewardConfig) during
    training, so the policy keeps that much more clearance than the paper's reward asks; 0 is the paper's.
    A quadrotor's tracking lag turns the particle world's near misses into touches (docs/research/decisions.md)."""
    navigation_weight: float | None = None
    """omega_n of R_L during training (RewardConfig.navigation_weight_low); None keeps the paper's 4.
    Only for Step 3 fine-tunes (not Safe). On an otherwise plain Step 3 fine-tune this is AT-M-Nav
    (this project's), named atm_c{c}_nav: the Step 3 policy fine-tuned to weigh reaching the anchor
    more, as a quadrotor keeps less of the particle world's N (docs/research/decisions.md)."""
    anchor_periods: int = 1
    """Anchor periods per training episode: the episode lasts this many times the paper's 100 steps and
    the anchor is redrawn at the start of each period, as Table VIII's protocol redraws it every 250
    steps, so the policy also learns to leave a reached anchor for a far one, obstacles in between and
    the group spread out. 1 is the paper's (one anchor per episode). Only for Step 3 fine-tunes."""
    straggler_fraction: float = 0.0
    """Fraction of training episodes in which one agent starts 3-7 m away from the others, out of their
    sight (TaskConfig.straggler_fraction), so the policy learns to rejoin the group around obstacles
    when it sees no neighbour; a lone UAV behind an obstacle otherwise tends to stop. 0 is the paper's
    starts. Only for Step 3 fine-tunes."""
    lidar_sees_uavs: bool = True
    """Whether the LiDAR beams hit the other UAVs as well as the obstacles (TaskConfig.lidar_sees_agents).
    False names the stage <name>_obstacle_lidar (e.g. atm_c6_step1_obstacle_lidar): AT-M Step 1 trained
    so is the paper's Step 1 of Table III, which collides once obstacles appear because its LiDAR never
    read anything while training (docs/research/layouts.md). The choice is saved in the policy file, and the
    evaluators fly every policy with the LiDAR it was trained with."""
    hidden: int = 128
    """Hidden width of the AT-M modules."""
    critic_hidden: int = 128
    """Hidden width of the centralized critic."""
    log_std_init: float = -0.7
    """Initial log-std of the Gaussian head for randomly initialised actors (std 0.5 m/s^2: with
    std 1 the 2 m/s^2 action range is mostly noise and formation learning stalls)."""
    ppo: PPOConfig = field(default_factory=PPOConfig)
    """MAPPO hyperparameters."""
    checkpoint_every: int = 10
    """Write the resumable state every this many iterations (and always at the end)."""
    mujoco: MujocoTraining | None = None
    """None: train in the particle world (the paper's). Set: this is AT-M-MuJoCo, a Step 3 fine-tune
    (of AT-M-Nav by default) in the MuJoCo quadrotor world under wind, named atm_c{c}_mujoco."""
    curriculum: tuple[float, ...] | None = None
    """CL-M: obstacle densities (per m^2, non-decreasing, 2 to 20 of them) trained in turn, each for
    an equal share of the budget: phase k of K runs while the budget's progress (iterations done /
    budget iterations, or training seconds / budget seconds, whichever is further) is in [k/K,
    (k+1)/K). Only with step 1 (random init) and no obstacle_density; the stage is then CL-M,
    named clm_c{c}. None: one density for the whole stage (AT-M)."""

    def __post_init__(self) -> None:
        if isinstance(self.curriculum, (list, tuple)):  # JSON gives lists; keep configs comparable
            object.__setattr__(
                self,
                "curriculum",
                tuple(float(d) if isinstance(d, int) and not isinstance(d, bool) else d for d in self.curriculum),
            )
        self.validate()

    @property
    def density(self) -> float:
        """Training obstacle density (per m^2); with a curriculum, that of its first phase."""
        if self.curriculum is not None:
            return self.curriculum[0]
        return STEP_DENSITY[self.step] if self.obstacle_density is None else float(self.obstacle_density)

    def curriculum_phase(self, iteration: int, seconds: float) -> int:
        """The curriculum phase that training is in after `iteration` iterations and `seconds` s:
        k while the budget's progress is in [k/K, (k+1)/K); the last phase once the budget is spent."""
        k = len(self.curriculum)
        phase = 0
        if self.budget.iterations is not None:
            phase = max(phase, iteration * k // self.budget.iterations)
        if self.budget.seconds is not None:
            phase = max(phase, int(seconds / self.budget.seconds * k))
        return min(phase, k - 1)

    @property
    def name(self) -> str:
        """Stage name, also the policy file stem: atm_c6_step3, atm_c6_safe, atm_c6_robust, atm_c6_quad,
        atm_c6_nav, clm_c6 (CL-M); with an obstacles-only LiDAR e.g. atm_c6_step1_obstacle_lidar."""
        if self.curriculum is not None:
            return clm_name(self.formation) + self.name_suffix
        kind = (
            "mujoco"
            if self.mujoco is not None
            else "safe"
            if self.safe
            else "robust"
            if self.robust
            else "nav"
            if self.nav
            else "quad"
            if self.quad
            else f"step{self.step}"
        )
        return lowlevel_name(self.formation, kind) + self.name_suffix

    @property
    def name_suffix(self) -> str:
        """ "_obstacle_lidar" for a stage whose LiDAR does not see the UAVs, else "" (its earlier stages
        carry the same suffix)."""
        return "" if self.lidar_sees_uavs else "_obstacle_lidar"

    @property
    def source_stages(self) -> tuple[str, ...]:
        """The stages whose runs a Step 3 stage starts from (without `init_from`): Step 3 for a fine-tune
        (Safe, Robust, Quad), else Steps 1 and 2; each with this stage's LiDAR suffix."""
        return tuple(
            lowlevel_name(self.formation, f"step{k}") + self.name_suffix for k in ((3,) if self.fine_tune else (1, 2))
        )

    @property
    def robust(self) -> bool:
        """AT-M-Robust: a Step 3 fine-tune under sensing deviation."""
        return self.step == 3 and self.deviation > 0

    @property
    def quad(self) -> bool:
        """AT-M-Quad: a Step 3 fine-tune with quadrotor-like lag and/or tracking noise, exact sensing."""
        return self.step == 3 and self.deviation == 0 and (self.response_time > 0 or self.velocity_noise > 0)

    @property
    def in_mujoco(self) -> bool:
        """AT-M-MuJoCo: a Step 3 fine-tune on quadrotors (the `mujoco` field)."""
        return self.mujoco is not None

    @property
    def nav(self) -> bool:
        """AT-M-Nav: a Step 3 fine-tune with another navigation weight, exact sensing, particle dynamics.
        (A navigation weight on a Robust or Quad fine-tune keeps that stage's name; its card records it.)"""
        return self.step == 3 and self.navigation_weight is not None and not (self.safe or self.robust or self.quad)

    @property
    def fine_tune(self) -> bool:
        """Starts from the Step 3 result (Safe, Robust, Quad, Nav) rather than from Steps 1 and 2."""
        return self.safe or self.robust or self.quad or self.nav or self.in_mujoco

    def paper_differences(self) -> list[str]:
        """What this stage's training changes from the paper's recipe (Algorithm 1, Table IX), one line
        each: this project's training perturbations and reward changes. Empty for the paper's own stages
        (Steps 1-3, Safe, CL-M)."""
        out = []
        if self.mujoco is not None:
            m = self.mujoco
            out.append(
                f"trained on MuJoCo quadrotors through the {m.offboard} interface, each episode's mean wind "
                f"drawn from [0, {m.wind_max:g}] m/s"
                + (f" with a {m.gust_speed:g} m/s gust of {m.gust_duration:g} s" if m.gust_speed else "")
                + " (paper: particle world only)"
            )
        if self.deviation:
            out.append(f"sensing deviation up to {self.deviation:g} m ({self.deviation_sampling})")
        if self.response_time:
            out.append(f"velocity lag {self.response_time:g} s in the particle world")
        if self.velocity_noise:
            out.append(f"velocity kicks of std {self.velocity_noise:g} m/s in the particle world")
        if self.collision_margin:
            out.append(f"collision reward distances widened by {self.collision_margin:g} m")
        if self.navigation_weight is not None:
            out.append(f"navigation weight omega_n = {self.navigation_weight:g} (paper 4)")
        if self.anchor_periods > 1:
            out.append(
                f"episodes of {self.anchor_periods} anchor periods of {FORMATION_EPISODE_STEPS} steps, the anchor "
                "redrawn at each (paper: one anchor per episode)"
            )
        if self.accel_max != 2.0:
            out.append(f"action bound {self.accel_max:g} m/s^2 per axis (ours; the paper states none)")
        if self.push_observer_s:
            out.append(
                f"the agent's push observer, time constant {self.push_observer_s:g} s (the paper's agent is memoryless)"
            )
        if self.straggler_fraction:
            out.append(
                f"in {self.straggler_fraction:.0%} of the episodes one agent starts {STRAGGLER_MIN_DISTANCE:g}-"
                f"{STRAGGLER_MAX_DISTANCE:g} m from the others (paper: every agent in the start square)"
            )
        return out

    @property
    def method(self) -> str:
        """The method name as the paper's Table III writes it (Robust, Quad and Nav are this project's)."""
        if self.curriculum is not None:
            return "CL-M"
        if self.mujoco is not None:
            return "AT-M-MuJoCo"
        if self.safe:
            return "AT-M-Safe"
        if self.robust:
            return "AT-M-Robust"
        if self.nav:
            return "AT-M-Nav"
        return "AT-M-Quad" if self.quad else f"AT-M-Step{self.step}"

    def validate(self) -> None:
        if self.formation not in FORMATIONS:
            _fail("formation", self.formation, f"must be one of {FORMATIONS}")
        if self.step not in (1, 2, 3):
            _fail("step", self.step, "must be 1, 2 or 3")
        if self.safe and self.step != 3:
            _fail("safe", self.safe, "AT-M-Safe fine-tunes the Step 3 policy: use it with step 3")
        if not isinstance(self.budget, Budget):
            _fail("budget", self.budget, "must be a Budget")
        _check_int("seed", self.seed, 0, MAX_SEED)
        if not isinstance(self.deviation, (int, float)) or not 0 <= self.deviation <= 2.0:
            _fail("deviation", self.deviation, "must be in [0, 2] m")
        if self.deviation > 0 and (self.step != 3 or self.safe):
            _fail(
                "deviation",
                self.deviation,
                "training under sensing deviation fine-tunes the Step 3 policy: use it with step 3 and without --safe",
            )
        if self.deviation_sampling not in ("fixed", "uniform"):
            _fail("deviation_sampling", self.deviation_sampling, "must be 'fixed' or 'uniform'")
        if not isinstance(self.response_time, (int, float)) or not 0 <= self.response_time <= 1.0:
            _fail("response_time", self.response_time, "must be in [0, 1] s")
        if not isinstance(self.velocity_noise, (int, float)) or not 0 <= self.velocity_noise <= 1.0:
            _fail("velocity_noise", self.velocity_noise, "must be in [0, 1] m/s")
        if not isinstance(self.collision_margin, (int, float)) or not 0 <= self.collision_margin <= 0.5:
            _fail("collision_margin", self.collision_margin, "must be in [0, 0.5] m")
        if self.navigation_weight is not None:
            w = self.navigation_weight
            if isinstance(w, bool) or not isinstance(w, (int, float)) or not 0 < w <= 50:
                _fail("navigation_weight", w, "must be in (0, 50]")
            if self.step != 3 or self.safe:
                _fail(
                    "navigation_weight",
                    w,
                    "another navigation weight fine-tunes the Step 3 policy: use it with step 3 and without --safe",
                )
        _check_int("anchor_periods", self.anchor_periods, 1, MAX_ANCHOR_PERIODS)
        if self.anchor_periods > 1 and not self.fine_tune:
            _fail(
                "anchor_periods",
                self.anchor_periods,
                "longer episodes with anchor redraws fine-tune the Step 3 "
                "policy: use them with step 3 and a fine-tune such as a navigation weight",
            )
        if (
            isinstance(self.straggler_fraction, bool)
            or not isinstance(self.straggler_fraction, (int, float))
            or not 0 <= self.straggler_fraction <= 1
        ):
            _fail("straggler_fraction", self.straggler_fraction, "must be in [0, 1]")
        if self.straggler_fraction > 0 and not self.fine_tune:
            _fail(
                "straggler_fraction",
                self.straggler_fraction,
                "starts away from the group fine-tune the Step 3 "
                "policy: use them with step 3 and a fine-tune such as a navigation weight",
            )
        if self.lidar_sees_uavs not in (True, False):
            _fail("lidar_sees_uavs", self.lidar_sees_uavs, "must be true or false")
        if (self.response_time > 0 or self.velocity_noise > 0) and (self.step != 3 or self.safe):
            _fail(
                "response_time/velocity_noise",
                (self.response_time, self.velocity_noise),
                "quadrotor-like dynamics fine-tune the Step 3 policy: use them with step 3 and without --safe",
            )
        if (
            isinstance(self.accel_max, bool)
            or not isinstance(self.accel_max, (int, float))
            or not 0 < self.accel_max <= MAX_ACCEL
        ):
            _fail("accel_max", self.accel_max, f"must be in (0, {MAX_ACCEL:g}] m/s^2")
        if (
            isinstance(self.push_observer_s, bool)
            or not isinstance(self.push_observer_s, (int, float))
            or not 0 <= self.push_observer_s <= MAX_PUSH_OBSERVER_S
        ):
            _fail("push_observer_s", self.push_observer_s, f"must be in [0, {MAX_PUSH_OBSERVER_S:g}] s")
        if self.push_observer_s > 0 and self.step != 3:
            _fail("push_observer_s", self.push_observer_s, "the push observer fine-tunes a Step 3 policy: use step 3")
        if self.obstacle_density is not None and (
            not isinstance(self.obstacle_density, (int, float)) or not 0 <= self.obstacle_density <= MAX_DENSITY
        ):
            _fail("obstacle_density", self.obstacle_density, f"must be in [0, {MAX_DENSITY}] per m^2")
        if self.curriculum is not None:
            self._validate_curriculum()
        if self.mujoco is not None:
            self._validate_mujoco()
        for name in ("hidden", "critic_hidden", "checkpoint_every"):
            v = getattr(self, name)
            if not isinstance(v, int) or v < 1:
                _fail(name, v, "must be an integer >= 1")
        self.ppo.validate()

    def _validate_mujoco(self) -> None:
        if not isinstance(self.mujoco, MujocoTraining):
            _fail("mujoco", self.mujoco, "must be a MujocoTraining or None")
        self.mujoco.validate(self.ppo.n_envs)
        if self.step != 3 or self.safe or self.curriculum is not None:
            _fail("mujoco", "set", "training in MuJoCo fine-tunes a Step 3 policy: use it with step 3, without --safe")
        if self.response_time or self.velocity_noise:
            _fail(
                "response_time/velocity_noise",
                (self.response_time, self.velocity_noise),
                "particle-world stand-ins for a quadrotor; the MuJoCo world has its own lag and tracking error",
            )

    def _validate_curriculum(self) -> None:
        densities = self.curriculum

        def fail(why: str) -> None:  # names the densities as --curriculum takes them: 0,0.01,0.02
            shown = (
                ",".join(f"{d:g}" if isinstance(d, float) else repr(d) for d in densities)
                if isinstance(densities, tuple)
                else repr(densities)
            )
            raise ConfigError(f"curriculum={shown}: {why}")

        if not isinstance(densities, tuple) or not 2 <= len(densities) <= MAX_CURRICULUM_PHASES:
            fail(f"must be 2 to {MAX_CURRICULUM_PHASES} obstacle densities")
        for d in densities:
            if not isinstance(d, float) or not 0 <= d <= MAX_DENSITY:
                fail(f"density {d!r} is not in [0, {MAX_DENSITY}] per m^2")
        if any(later < earlier for earlier, later in zip(densities, densities[1:])):
            fail("densities must not decrease (a curriculum gets harder)")
        if self.step != 1:
            fail("CL-M trains from random weights: use it with step 1")
        if self.obstacle_density is not None:
            fail("sets the densities itself: leave obstacle_density unset")
        if self.budget.iterations is not None and self.budget.iterations < len(densities):
            fail(
                f"{len(densities)} phases need a budget of at least {len(densities)} iterations, "
                f"got {self.budget.iterations}"
            )


DISTILL_TEACHERS = ("step3", "nav")  # registry.LOWLEVEL_KINDS a student can imitate
"""The low levels a student can be distilled from (DistillConfig.teacher)."""


@dataclass(frozen=True)
class DistillConfig:
    """Policy distillation (paper Sec. IV-B3): one student imitates every teacher's actions."""

    budget: Budget
    """Gradient steps (iterations) and/or wall-clock time of the student's training."""
    formations: tuple[int, ...] = FORMATIONS
    """The teachers' formation sizes c."""
    teacher: str = DISTILL_TEACHER
    """Which low level of each c teaches: "step3" (atm_c<c>_step3, the paper's AT-M) or "nav"
    (atm_c<c>_nav, AT-M-Nav, the evaluators' default low level)."""
    tuples_per_formation: int = 60_000
    """Replay capacity Lambda per teacher: (observation, action) tuples, one per agent-step."""
    collect_density: float = 0.03
    """Obstacle density of the envs in which the teachers fly to fill the replay."""
    batch_size: int = 600
    """Tuples per gradient step (paper: 600), drawn uniformly from the union of all teachers' replay."""
    lr: float = 1e-4
    """Adam learning rate (paper: 1e-4)."""
    hidden: int = 256
    """Student hidden width (paper: 256)."""
    held_out: float = 0.05
    """Share of each teacher's replay kept out of training, to report the student's error."""
    seed: int = 0
    """Seeds collection, student init and sampling."""
    checkpoint_every: int = 2000
    """Write the resumable state every this many gradient steps (and at the end)."""
    threads: int = 1
    """torch intra-op threads (batches of 600 gain nothing from more; more oversubscribes a busy CPU)."""

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        if not self.formations or any(c not in FORMATIONS for c in self.formations):
            _fail("formations", self.formations, f"must be a non-empty subset of {FORMATIONS}")
        if self.teacher not in DISTILL_TEACHERS:
            _fail("teacher", self.teacher, f"must be one of {', '.join(DISTILL_TEACHERS)}")
        if not isinstance(self.budget, Budget):
            _fail("budget", self.budget, "must be a Budget")
        _check_int("seed", self.seed, 0, MAX_SEED)
        _check_int("tuples_per_formation", self.tuples_per_formation, 1, MAX_TUPLES)
        for name in ("batch_size", "hidden", "checkpoint_every"):
            _check_int(name, getattr(self, name), 1)
        _check_int("threads", self.threads, 1, MAX_THREADS)
        if not 0 < self.held_out < 0.5:
            _fail("held_out", self.held_out, "must be in (0, 0.5)")
        if not 0 <= self.collect_density <= 0.2:
            _fail("collect_density", self.collect_density, "must be in [0, 0.2] per m^2")
        if not math.isfinite(self.lr) or self.lr <= 0:
            _fail("lr", self.lr, "must be a positive number")

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "DistillConfig":
        d = dict(d)
        d["budget"] = Budget(**d["budget"])
        d["formations"] = tuple(d["formations"])
        return cls(**d)
