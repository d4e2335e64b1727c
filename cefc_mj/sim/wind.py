"""Wind with the semantics of PX4's Gazebo-Classic wind plugin (docs/design.md §7).

Every `update_period` (0.5 s) each env's wind speed is redrawn as |Normal(mean, sigma)| clipped to
`max_speed`, and its direction as Normal(mean direction, direction_sigma) (an angle in the
horizontal plane, ENU, the direction the air moves *towards*). The mean direction is `direction`,
or, when None, drawn uniformly once per episode (at reset) and then held. An optional gust adds
|Normal(gust_mean_speed, gust_speed_sigma)| along `gust_direction` while the update time lies in
[gust_start, gust_start + gust_duration). For training over many winds, `mean_speed_max` and
`gust_start_max` make the mean speed and the gust's start a per-episode uniform draw as well
(the evaluators leave both None: one fixed wind per condition, as the plugin has). The wind is only
a velocity field: it acts on the drones through rotor drag on the relative airspeed
(cefc_mj.control.cascade), never on their state.

>>> import numpy as np
>>> wind = WindField(WindConfig(mean_speed=5.0, direction=0.0), n_envs=2, rng=np.random.default_rng(0))
>>> wind.reset(0); wind.reset(1)
>>> wind.vector.shape, bool(np.all(wind.vector[:, 0] > 0))
((2, 3), True)
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from cefc_mj.errors import ConfigError

MAX_WIND_SPEED = 20.0
"""Default upper clip of a wind speed draw (m/s): a mean above it would be clipped, not flown."""


def wind_config_direction(degrees: float | None) -> float | None:
    """WindConfig.direction (rad in [0, 2 pi)) for a user's direction in degrees (None stays None: the
    seeded random draw); ConfigError for anything but a finite number or None."""
    if degrees is None:
        return None
    if isinstance(degrees, bool) or not isinstance(degrees, (int, float)) or not math.isfinite(degrees):
        raise ConfigError(f"wind_direction={degrees!r}: must be a finite angle in degrees or None (random per episode)")
    return math.radians(float(degrees) % 360.0)


@dataclass(frozen=True)
class WindConfig:
    """Wind field parameters (Gazebo wind-plugin names in brackets). Speeds in m/s, angles in rad."""

    mean_speed: float = 0.0
    """Mean wind speed [windVelocityMean]; Table VIII's Wind-3/5/8 are 3, 5, 8."""
    speed_sigma: float | None = None
    """Standard deviation of the speed draw [sqrt(windVelocityVariance)]; None = 0.2 x mean_speed."""
    max_speed: float = MAX_WIND_SPEED
    """Upper clip of a speed draw [windVelocityMax]."""
    direction: float | None = None
    """Mean direction the wind blows towards (rad, ENU, 0 = +x); None = uniform random per episode."""
    direction_sigma: float = 0.0
    """Standard deviation of the direction draw around the mean (rad) [windDirectionVariance]."""
    update_period: float = 0.5
    """Seconds between redraws [publish rate 2 Hz]; must be a multiple of the physics step."""
    gust_start: float = 0.0
    """Episode time at which the gust starts (s) [windGustStart]."""
    gust_duration: float = 0.0
    """Gust duration (s); 0 = no gust [windGustDuration]."""
    gust_mean_speed: float = 0.0
    """Mean gust speed added on top of the wind (m/s) [windGustVelocityMean]."""
    gust_speed_sigma: float | None = None
    """Standard deviation of the gust speed; None = 0.2 x gust_mean_speed."""
    gust_direction: float | None = None
    """Gust direction (rad); None = the episode's mean wind direction."""
    mean_speed_max: float | None = None
    """None: every episode has mean_speed. Set: each episode draws its mean speed uniformly from
    [mean_speed, mean_speed_max] at reset (training over a range of winds; the plugin has no such option)."""
    gust_start_max: float | None = None
    """None: the gust starts at gust_start. Set: each episode draws its gust's start uniformly from
    [gust_start, gust_start_max] at reset."""

    def __post_init__(self) -> None:
        for name in ("mean_speed", "max_speed", "direction_sigma", "gust_start", "gust_duration", "gust_mean_speed"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ConfigError(f"wind.{name} must be a finite number >= 0, got {value!r}")
        for name in ("speed_sigma", "gust_speed_sigma", "direction", "gust_direction"):
            value = getattr(self, name)
            if value is not None and not math.isfinite(value):
                raise ConfigError(f"wind.{name} must be finite or None, got {value!r}")
        for name in ("speed_sigma", "gust_speed_sigma"):
            value = getattr(self, name)
            if value is not None and value < 0:
                raise ConfigError(f"wind.{name} must be >= 0, got {value!r}")
        if not (math.isfinite(self.update_period) and self.update_period > 0):
            raise ConfigError(f"wind.update_period must be > 0, got {self.update_period!r}")
        for name, low in (("mean_speed_max", "mean_speed"), ("gust_start_max", "gust_start")):
            value = getattr(self, name)
            if value is not None and not (math.isfinite(value) and value >= getattr(self, low)):
                raise ConfigError(f"wind.{name} must be a finite number >= wind.{low}, got {value!r}")

    @property
    def calm(self) -> bool:
        """No episode of this config has any wind."""
        no_gust = self.gust_duration == 0 or self.gust_mean_speed == 0
        return self.mean_speed == 0 and not self.mean_speed_max and no_gust

    @property
    def sigma(self) -> float:
        """The speed standard deviation in use (of an episode at mean_speed)."""
        return self.sigma_at(self.mean_speed)

    def sigma_at(self, mean_speed: float) -> float:
        """The speed standard deviation of an episode whose mean speed is `mean_speed`."""
        return 0.2 * mean_speed if self.speed_sigma is None else self.speed_sigma

    @property
    def gust_sigma(self) -> float:
        """The gust speed standard deviation in use."""
        return 0.2 * self.gust_mean_speed if self.gust_speed_sigma is None else self.gust_speed_sigma

    def to_dict(self) -> dict:
        """Plain dict for run records."""
        return asdict(self)


class WindField:
    """Per-env wind vectors [B, 3] (m/s, world frame), redrawn on the plugin's schedule."""

    def __init__(self, config: WindConfig, n_envs: int, rng: np.random.Generator):
        self.config = config
        self.rng = rng
        self.vector = np.zeros((n_envs, 3))
        self.mean_direction = np.zeros(n_envs)
        self.mean_speed = np.full(n_envs, config.mean_speed)
        """Each env's mean wind speed this episode (m/s; drawn at reset when config.mean_speed_max is set)."""
        self.gust_start = np.full(n_envs, config.gust_start)
        """Each env's gust start this episode (s; drawn at reset when config.gust_start_max is set)."""

    def reset(self, env: int) -> None:
        """New episode for env: draw its mean direction (if random), its mean speed and gust start (if
        ranged) and its first wind vector."""
        cfg = self.config
        self.mean_direction[env] = self.rng.uniform(0.0, 2.0 * math.pi) if cfg.direction is None else cfg.direction
        if cfg.mean_speed_max is not None:
            self.mean_speed[env] = self.rng.uniform(cfg.mean_speed, cfg.mean_speed_max)
        if cfg.gust_start_max is not None:
            self.gust_start[env] = self.rng.uniform(cfg.gust_start, cfg.gust_start_max)
        self.update(env, 0.0)

    def update(self, env: int, time: float) -> None:
        """Redraw env's wind for episode time `time` (s)."""
        cfg = self.config
        mean_speed, gust_start = self.mean_speed[env], self.gust_start[env]
        speed = min(abs(self.rng.normal(mean_speed, cfg.sigma_at(mean_speed))), cfg.max_speed)
        angle = (
            self.rng.normal(self.mean_direction[env], cfg.direction_sigma)
            if cfg.direction_sigma > 0
            else self.mean_direction[env]
        )
        wx, wy = speed * math.cos(angle), speed * math.sin(angle)
        if cfg.gust_duration > 0 and gust_start <= time < gust_start + cfg.gust_duration:
            gust = abs(self.rng.normal(cfg.gust_mean_speed, cfg.gust_sigma))
            g_angle = self.mean_direction[env] if cfg.gust_direction is None else cfg.gust_direction
            wx += gust * math.cos(g_angle)
            wy += gust * math.sin(g_angle)
        self.vector[env] = (wx, wy, 0.0)
