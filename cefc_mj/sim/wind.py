"""Wind with the semantics of PX4's Gazebo-Classic wind plugin (docs/design.md §7).

Every `update_period` (0.5 s) each env's wind speed is redrawn as |Normal(mean, sigma)| clipped to
`max_speed`, and its direction as Normal(mean direction, direction_sigma) (an angle in the
horizontal plane, ENU, the direction the air moves *towards*). The mean direction is `direction`,
or, when None, drawn uniformly once per episode (at reset) and then held. An optional gust adds
|Normal(gust_mean_speed, gust_speed_sigma)| along `gust_direction` while the update time lies in
[gust_start, gust_start + gust_duration). The wind is only a velocity field: it acts on the drones
through rotor drag on the relative airspeed (cefc_mj.control.cascade), never on their state.

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

    @property
    def sigma(self) -> float:
        """The speed standard deviation in use."""
        return 0.2 * self.mean_speed if self.speed_sigma is None else self.speed_sigma

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

    def reset(self, env: int) -> None:
        """New episode for env: draw its mean direction (if random) and its first wind vector."""
        cfg = self.config
        self.mean_direction[env] = self.rng.uniform(0.0, 2.0 * math.pi) if cfg.direction is None else cfg.direction
        self.update(env, 0.0)

    def update(self, env: int, time: float) -> None:
        """Redraw env's wind for episode time `time` (s)."""
        cfg = self.config
        speed = min(abs(self.rng.normal(cfg.mean_speed, cfg.sigma)), cfg.max_speed)
        angle = (
            self.rng.normal(self.mean_direction[env], cfg.direction_sigma)
            if cfg.direction_sigma > 0
            else self.mean_direction[env]
        )
        wx, wy = speed * math.cos(angle), speed * math.sin(angle)
        if cfg.gust_duration > 0 and cfg.gust_start <= time < cfg.gust_start + cfg.gust_duration:
            gust = abs(self.rng.normal(cfg.gust_mean_speed, cfg.gust_sigma))
            g_angle = self.mean_direction[env] if cfg.gust_direction is None else cfg.gust_direction
            wx += gust * math.cos(g_angle)
            wy += gust * math.sin(g_angle)
        self.vector[env] = (wx, wy, 0.0)
