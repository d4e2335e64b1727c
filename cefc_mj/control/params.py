"""PX4 parameter files (`controllers/<name>.params`): parse, check against PX4's documented ranges.

A parameter file holds one ``NAME VALUE`` per line (``#`` starts a comment). Every parameter of
`PX4_PARAMS` must appear exactly once; an unknown name, a missing one, a non-number or a value
outside PX4's documented range raises `ConfigError` with one line naming the parameter.

>>> params = load_params("iris")
>>> params["MC_ROLL_P"], params["MPC_TILTMAX_AIR"]
(6.5, 45.0)
"""

from __future__ import annotations

import math
from pathlib import Path

from cefc_mj.errors import ConfigError
from cefc_mj.paths import CONTROLLERS_DIR

INF = math.inf

# name -> (min, max) as documented in PX4-Autopilot's parameter definitions
# (mc_pos_control/multicopter_position_control_*_params.c, mc_att_control_params.c,
# mc_rate_control_params.c, sensors/vehicle_angular_velocity/imu_gyro_parameters.c).
PX4_PARAMS: dict[str, tuple[float, float]] = {
    "MPC_Z_P": (0.0, 1.5),
    "MPC_Z_VEL_P_ACC": (2.0, 15.0),
    "MPC_Z_VEL_I_ACC": (0.2, 3.0),
    "MPC_Z_VEL_D_ACC": (0.0, 2.0),
    "MPC_Z_VEL_MAX_UP": (0.5, 8.0),
    "MPC_Z_VEL_MAX_DN": (0.5, 4.0),
    "MPC_XY_VEL_P_ACC": (1.2, 5.0),
    "MPC_XY_VEL_I_ACC": (0.0, 60.0),
    "MPC_XY_VEL_D_ACC": (0.1, 2.0),
    "MPC_VELD_LP": (0.0, 10.0),
    "MPC_TILTMAX_AIR": (20.0, 89.0),
    "MPC_THR_HOVER": (0.1, 0.8),
    "MPC_THR_MIN": (0.05, 0.5),
    "MPC_THR_MAX": (0.0, 1.0),
    "MPC_THR_XY_MARG": (0.0, 0.5),
    "MC_ROLL_P": (0.0, 12.0),
    "MC_PITCH_P": (0.0, 12.0),
    "MC_YAW_P": (0.0, 5.0),
    "MC_YAW_WEIGHT": (0.0, 1.0),
    "MC_ROLLRATE_MAX": (0.0, 1800.0),
    "MC_PITCHRATE_MAX": (0.0, 1800.0),
    "MC_YAWRATE_MAX": (0.0, 1800.0),
    "MC_ROLLRATE_P": (0.01, 0.5),
    "MC_ROLLRATE_I": (0.0, INF),
    "MC_ROLLRATE_D": (0.0, 0.01),
    "MC_ROLLRATE_FF": (0.0, INF),
    "MC_ROLLRATE_K": (0.01, 5.0),
    "MC_RR_INT_LIM": (0.0, INF),
    "MC_PITCHRATE_P": (0.01, 0.6),
    "MC_PITCHRATE_I": (0.0, INF),
    "MC_PITCHRATE_D": (0.0, INF),
    "MC_PITCHRATE_FF": (0.0, INF),
    "MC_PITCHRATE_K": (0.01, 5.0),
    "MC_PR_INT_LIM": (0.0, INF),
    "MC_YAWRATE_P": (0.0, 0.6),
    "MC_YAWRATE_I": (0.0, INF),
    "MC_YAWRATE_D": (0.0, INF),
    "MC_YAWRATE_FF": (0.0, INF),
    "MC_YAWRATE_K": (0.01, 5.0),
    "MC_YR_INT_LIM": (0.0, INF),
    "MC_YAW_TQ_CUTOFF": (0.0, 10.0),
    "IMU_DGYRO_CUTOFF": (0.0, 1000.0),
}

PARAM_NAMES: tuple[str, ...] = tuple(PX4_PARAMS)
"""The order of `params_array`; the compiled cascade indexes it by these positions."""


def params_path(name_or_path: str | Path) -> Path:
    """`controllers/<name>.params` for a bare name, else the given path (which must exist)."""
    text = str(name_or_path)
    path = Path(text) if ("/" in text or text.endswith(".params")) else CONTROLLERS_DIR / f"{text}.params"
    if not path.is_file():
        known = sorted(p.stem for p in CONTROLLERS_DIR.glob("*.params"))
        raise ConfigError(f"params: unknown parameter file {text!r} (no {path}; known: {', '.join(known) or 'none'})")
    return path


def params_for_airframe(mjcf_path: Path) -> Path:
    """The gains that go with an airframe MJCF file: `<stem>.params` beside it, else
    `controllers/<stem>.params`; ConfigError naming both when neither exists."""
    candidates = [mjcf_path.with_suffix(".params"), CONTROLLERS_DIR / f"{mjcf_path.stem}.params"]
    for path in candidates:
        if path.is_file():
            return path
    raise ConfigError(
        f"params: no parameter file for airframe {mjcf_path.stem!r} (looked for {candidates[0]} and "
        f"{candidates[1]}); write one (docs/airframes.md, Adding an airframe) or name it with params="
    )


def parse_params(text: str, source: str = "<params>") -> dict[str, float]:
    """Parse and validate the text of a parameter file; `source` names it in errors."""
    values: dict[str, float] = {}
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        fields = line.split()
        if len(fields) != 2:
            raise ConfigError(f"{source}:{lineno}: expected 'NAME VALUE', got {line!r}")
        name, value_text = fields
        if name not in PX4_PARAMS:
            raise ConfigError(
                f"{source}:{lineno}: unknown parameter {name} (the cascade uses: {', '.join(PARAM_NAMES)})"
            )
        if name in values:
            raise ConfigError(f"{source}:{lineno}: parameter {name} is set twice")
        try:
            value = float(value_text)
        except ValueError:
            raise ConfigError(f"{source}:{lineno}: parameter {name} = {value_text!r} is not a number") from None
        lo, hi = PX4_PARAMS[name]
        if not (lo <= value <= hi):  # also rejects nan
            raise ConfigError(
                f"{source}:{lineno}: parameter {name} = {value:g} is outside PX4's range [{lo:g}, {hi:g}]"
            )
        values[name] = value
    missing = [n for n in PARAM_NAMES if n not in values]
    if missing:
        raise ConfigError(
            f"{source}: missing parameter {missing[0]}"
            + (f" (and {len(missing) - 1} more)" if len(missing) > 1 else "")
        )
    if values["MPC_THR_MIN"] >= values["MPC_THR_MAX"]:
        raise ConfigError(
            f"{source}: parameter MPC_THR_MIN = {values['MPC_THR_MIN']:g} "
            f"must be below MPC_THR_MAX = {values['MPC_THR_MAX']:g}"
        )
    if not values["MPC_THR_MIN"] < values["MPC_THR_HOVER"] < values["MPC_THR_MAX"]:
        raise ConfigError(
            f"{source}: parameter MPC_THR_HOVER = {values['MPC_THR_HOVER']:g} "
            "must lie between MPC_THR_MIN and MPC_THR_MAX"
        )
    return values


def load_params(name_or_path: str | Path) -> dict[str, float]:
    """Load `controllers/<name>.params` (or a path) into a validated {name: value} dict."""
    path = params_path(name_or_path)
    return parse_params(path.read_text(), source=str(path))
