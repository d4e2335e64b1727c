"""Where episodes are flown: the physics backend, the wind and the sensing deviation (`Conditions`),
defaulted and range-checked here for every protocol that takes them (cefc-eval's single run and the
game tables V-VII); a bad value is one ConfigError line naming the flag that sets it."""

from __future__ import annotations

import math
from dataclasses import dataclass

from cefc_mj.errors import ConfigError
from cefc_mj.sim.backends import BACKENDS, make_world
from cefc_mj.sim.wind import MAX_WIND_SPEED, wind_config_direction
from cefc_mj.task.config import TaskConfig

MAX_DEVIATION = 10.0
"""Sensing deviation at most (m): beyond it every perceived position is noise (observation range is 3 m)."""


def number_text(value: object) -> str:
    """A number as a message shows it ("8", "1e+09", "nan"); anything else as its repr."""
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        return format(value, "g")
    return repr(value)


def is_number_in(value: object, low: float, high: float) -> bool:
    """Whether `value` is a finite int or float (not a bool) in [low, high]."""
    return (
        isinstance(value, (int, float))
        and not isinstance(value, bool)
        and math.isfinite(value)
        and low <= value <= high
    )


def check_wind_direction(degrees: object) -> None:
    """ConfigError naming --wind-direction unless `degrees` is None (drawn per episode) or a finite angle."""
    try:
        wind_config_direction(degrees)
    except ConfigError:
        raise ConfigError(f"--wind-direction {number_text(degrees)}: must be a finite angle in degrees") from None


@dataclass(frozen=True)
class Conditions:
    """Where episodes are flown: the backend, the mean wind speed, the direction it blows towards and
    the sensing deviation (cefc-eval's single run; the game tables V-VII)."""

    backend: str = "mujoco"
    """--backend: "mujoco" (quadrotors with the PX4-like controller) or "particle" (the paper's MPE)."""
    wind: float = 0.0
    """--wind: mean wind speed in m/s, 0..MAX_WIND_SPEED (the wind model's largest); MuJoCo only."""
    deviation: float = 0.0
    """--deviation: sensing deviation d in m, 0..MAX_DEVIATION; both backends."""
    wind_direction: float | None = None
    """--wind-direction: degrees the wind blows towards (ENU: 0 = +x, 90 = +y); None draws it per
    episode from the seed. Needs wind."""

    def __post_init__(self) -> None:
        if self.backend not in BACKENDS:
            raise ConfigError(f"--backend {self.backend}: must be one of {', '.join(BACKENDS)}")
        if not is_number_in(self.wind, 0.0, MAX_WIND_SPEED):
            raise ConfigError(
                f"--wind {number_text(self.wind)}: must be a number in 0..{MAX_WIND_SPEED:g} m/s "
                "(the wind model's maximum speed)"
            )
        if not is_number_in(self.deviation, 0.0, MAX_DEVIATION):
            raise ConfigError(f"--deviation {number_text(self.deviation)}: must be a number in 0..{MAX_DEVIATION:g} m")
        if self.backend == "particle" and self.wind:
            raise ConfigError("--wind: the particle backend has no wind model; use --backend mujoco")
        if self.wind_direction is not None:
            if self.backend != "mujoco":
                raise ConfigError("--wind-direction: the particle backend has no wind model; use --backend mujoco")
            if not self.wind:
                raise ConfigError("--wind-direction: there is no wind to point; add --wind MPS")
            check_wind_direction(self.wind_direction)
        object.__setattr__(self, "wind", float(self.wind))
        object.__setattr__(self, "deviation", float(self.deviation))

    @property
    def paper_like(self) -> bool:
        """The paper's Tables V and VI: the particle world, calm, exact sensing."""
        return self.backend == "particle" and not self.wind and not self.deviation

    def world(self, task: TaskConfig, episodes: int, seed: int):
        """None (the env's own particle world) or the MuJoCo world of `episodes` envs."""
        if self.backend == "particle":
            return None
        return make_world("mujoco", task, episodes, wind=self.wind, seed=seed, wind_direction=self.wind_direction)

    def to_dict(self) -> dict:
        out = {"backend": self.backend, "wind": self.wind, "deviation": self.deviation}
        if self.wind_direction is not None:  # absent: drawn per episode (and reports flown before it existed)
            out["wind_direction"] = self.wind_direction
        return out
