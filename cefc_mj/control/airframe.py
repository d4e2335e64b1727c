"""Airframe properties read from its MJCF file, and PX4's mixer.

The MJCF file is the single source of truth, and its rotor actuators are the ones MuJoCo simulates
(cefc_mj.sim.mujoco_world keeps them in the scene; the cascade writes each rotor's thrust to their
`data.ctrl`). What a quadrotor file must hold, as MuJoCo Menagerie's per-rotor quadrotors (Skydio X2)
do, plus the motor model:

- one body with a free joint (mass and inertia from its `<inertial>` or its geoms);
- exactly four `<motor>` actuators, each on its own site on that body, the site's z axis along the
  body's z axis, `gear="0 0 1 0 0 +-km"` (ctrl = the rotor's thrust in newtons along the rotor axis;
  the sixth entry makes the yaw reaction torque km x thrust, negative for a counter-clockwise rotor)
  and `ctrlrange="0 T_max"`; two rotors spinning each way;
- the motor model (Gazebo's gazebo_motor_model constants) as `<custom><numeric>` entries:
  motor_constant, max_rot_velocity, time_constant_up, time_constant_down, rotor_drag_coefficient,
  rolling_moment_coefficient (and optionally moment_constant, which must then equal km);
- optionally a cylinder geom named "footprint" (the collision disc; the world adds one otherwise).

Motor order is the order of the actuators in the file; the mixer is computed from the geometry, so
any order (and any asymmetric layout with full control authority) works. An airframe is named by a
file stem in `assets/mjcf/` ("iris", "crazyflie") or given as a path to an MJCF file:

>>> af = load_airframe("iris")
>>> round(af.mass, 3), round(af.max_thrust, 4), af.spin.tolist()
(1.5, 7.0664, [1.0, 1.0, -1.0, -1.0])
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np

from cefc_mj.errors import ConfigError
from cefc_mj.paths import MJCF_DIR

MOTOR_NUMERICS = (
    "motor_constant",
    "moment_constant",
    "max_rot_velocity",
    "time_constant_up",
    "time_constant_down",
    "rotor_drag_coefficient",
    "rolling_moment_coefficient",
)
OPTIONAL_NUMERICS = ("moment_constant",)  # the actuators' gear gives it
NOT_AIRFRAMES = ("arena",)  # MJCF files in assets/mjcf/ that are not airframes


@dataclass(frozen=True)
class Airframe:
    """A quadrotor: rigid body, rotor geometry (FLU body frame) and Gazebo motor model."""

    name: str
    """Airframe name (the MJCF file stem)."""
    path: Path
    """The MJCF file."""
    body_name: str
    """Name of the drone's body in the file (the world attaches it with a per-drone prefix)."""
    mass: float
    """Total mass (kg)."""
    inertia: np.ndarray
    """Principal inertia [3] (kg m^2)."""
    inertia_quat: np.ndarray
    """[4] orientation of the principal axes in the body frame [w, x, y, z]."""
    centre_of_mass: np.ndarray
    """[3] centre of mass in the body frame (m)."""
    rotor_pos: np.ndarray
    """Rotor positions [4, 3] relative to the centre of mass, body frame (m), in motor order."""
    spin: np.ndarray
    """[4] +1 for a counter-clockwise rotor (seen from above), -1 for clockwise (Gazebo's turning direction)."""
    rotor_sites: tuple[str, ...]
    """The four rotor sites' names, in motor order."""
    motor_constant: float
    """k: thrust = k omega^2 (N s^2 / rad^2)."""
    moment_constant: float
    """Yaw reaction torque per newton of thrust (m)."""
    max_rot_velocity: float
    """Rotor speed limit (rad/s)."""
    time_constant_up: float
    """Motor lag time constant while spinning up (s)."""
    time_constant_down: float
    """Motor lag time constant while spinning down (s)."""
    rotor_drag_coefficient: float
    """c_rd: rotor drag = -|omega| c_rd v_perp (N per rad/s per m/s)."""
    rolling_moment_coefficient: float
    """c_rm: rolling moment = -|omega| spin c_rm v_perp (N m per rad/s per m/s)."""

    @property
    def max_thrust(self) -> float:
        """Per-rotor thrust at max_rot_velocity (N)."""
        return self.motor_constant * self.max_rot_velocity**2

    def hover_thrust(self, gravity: float = 9.81) -> float:
        """Normalised hover thrust m g / (4 T_max) (what MPC_THR_HOVER should be)."""
        return self.mass * gravity / (4.0 * self.max_thrust)

    def hover_rot_velocity(self, gravity: float = 9.81) -> float:
        """Rotor speed (rad/s) at which four rotors carry the weight."""
        return float(np.sqrt(self.mass * gravity / (4.0 * self.motor_constant)))

    def effectiveness(self) -> np.ndarray:
        """[4, 4]: rows (roll torque, pitch torque, yaw torque in N m, thrust in N) per unit normalised motor
        command."""
        t = self.max_thrust
        x, y = self.rotor_pos[:, 0], self.rotor_pos[:, 1]
        # thrust t u along body +z at (x, y, z): torque r x F = (y F, -x F, 0); yaw reaction -spin km F
        return np.stack([y * t, -x * t, -self.spin * self.moment_constant * t, np.full(4, t)])


def known_airframes() -> list[str]:
    """The airframe names shipped in assets/mjcf/."""
    return sorted(p.stem for p in MJCF_DIR.glob("*.xml") if p.stem not in NOT_AIRFRAMES)


def is_airframe_path(name_or_path: str | Path) -> bool:
    """True when the argument names a file (has a folder part or ends in .xml), not a shipped airframe."""
    text = str(name_or_path)
    return isinstance(name_or_path, Path) or "/" in text or "\\" in text or text.endswith(".xml")


def airframe_path(name_or_path: str | Path) -> Path:
    """`assets/mjcf/<name>.xml` for a bare name, else the given MJCF path; ConfigError if there is none."""
    text = str(name_or_path)
    if is_airframe_path(name_or_path):
        path = Path(text).expanduser()
        if path.is_dir():
            raise ConfigError(f"airframe: {text!r} is a folder, not an MJCF file")
        if not path.is_file():
            raise ConfigError(f"airframe: no MJCF file {text!r}")
        return path
    path = MJCF_DIR / f"{text}.xml"
    if not text or not path.is_file() or text in NOT_AIRFRAMES:
        raise ConfigError(
            f"airframe: unknown airframe {text!r} (known: {', '.join(known_airframes())}; "
            "or give the path of an MJCF file)"
        )
    return path


def _fail(path: Path, what: str) -> None:
    raise ConfigError(f"airframe: {path}: {what}")


def load_airframe(name_or_path: str | Path) -> Airframe:
    """Read and check an airframe's MJCF file (see the module docstring for what it must contain)."""
    path = airframe_path(name_or_path)
    try:
        model = mujoco.MjModel.from_xml_path(str(path))
    except Exception as exc:  # noqa: BLE001 (MuJoCo's parser and compiler: a bad file, in one line)
        reason = "; ".join(line.strip() for line in str(exc).strip().splitlines() if line.strip())[:240]
        raise ConfigError(f"airframe: {path} does not compile: {reason or type(exc).__name__}") from None
    if model.nbody != 2 or model.njnt != 1 or model.jnt_type[0] != mujoco.mjtJoint.mjJNT_FREE:
        _fail(
            path,
            f"a quadrotor airframe is one body with a free joint (found {model.nbody - 1} bodies, {model.njnt} joints)",
        )
    if model.nu != 4:
        _fail(
            path,
            f"has {model.nu} actuators; a quadrotor airframe needs exactly four <motor> actuators, "
            "one on each rotor site",
        )
    numerics = {model.numeric(i).name: float(model.numeric_data[model.numeric_adr[i]]) for i in range(model.nnumeric)}
    missing = [n for n in MOTOR_NUMERICS if n not in numerics and n not in OPTIONAL_NUMERICS]
    if missing:
        _fail(
            path,
            f"lacks <custom><numeric name={missing[0]!r}> (the motor model needs "
            f"{', '.join(n for n in MOTOR_NUMERICS if n not in OPTIONAL_NUMERICS)})",
        )
    for name, value in numerics.items():
        if name in MOTOR_NUMERICS and not (np.isfinite(value) and (value >= 0 if "coefficient" in name else value > 0)):
            _fail(
                path, f"numeric {name} = {value:g} must be a finite number {'>= 0' if 'coefficient' in name else '> 0'}"
            )

    sites: list[int] = []
    for i in range(4):
        label = f"actuator {model.actuator(i).name or i}"
        if (
            model.actuator_dyntype[i] != mujoco.mjtDyn.mjDYN_NONE
            or model.actuator_gaintype[i] != mujoco.mjtGain.mjGAIN_FIXED
            or model.actuator_biastype[i] != mujoco.mjtBias.mjBIAS_NONE
            or model.actuator_gainprm[i, 0] != 1.0
        ):
            _fail(path, f"{label} must be a <motor> (force = ctrl: no dynamics, gain 1, no bias)")
        if model.actuator_trntype[i] != mujoco.mjtTrn.mjTRN_SITE or model.actuator_trnid[i, 1] != -1:
            kind = mujoco.mjtTrn(model.actuator_trntype[i]).name.removeprefix("mjTRN_").lower()
            _fail(path, f"{label} must act on a rotor site (site=..., no refsite), not through a {kind} transmission")
        site = int(model.actuator_trnid[i, 0])
        if site in sites:
            _fail(
                path,
                f"{label} acts on site {model.site(site).name!r} like another actuator; a quadrotor airframe "
                "needs four rotor sites, one thrust motor on each",
            )
        sites.append(site)
    gears = np.empty(4)
    for i, site in enumerate(sites):
        gear = model.actuator_gear[i]
        if not np.allclose(gear[:5], [0, 0, 1, 0, 0], atol=1e-12) or gear[5] == 0:
            _fail(
                path,
                f"actuator {model.actuator(i).name or i} gear must be '0 0 1 0 0 +-km' (thrust along the rotor "
                f"axis, yaw reaction torque), got '{' '.join(f'{g:g}' for g in gear)}'",
            )
        gears[i] = gear[5]
        axes = np.empty(9)
        mujoco.mju_quat2Mat(axes, model.site_quat[site])
        if not np.allclose(axes.reshape(3, 3)[:, 2], [0, 0, 1], atol=1e-9):
            _fail(
                path,
                f"rotor site {model.site(site).name!r} must not tilt: "
                "its z axis (the thrust) must be the body's z axis",
            )
    km = float(abs(gears[0]))
    if not np.allclose(np.abs(gears), km, rtol=1e-9):
        _fail(path, f"the four actuators' yaw gears must share one moment constant, got {np.abs(gears).tolist()}")
    if "moment_constant" in numerics and not np.isclose(km, numerics["moment_constant"], rtol=1e-9):
        _fail(
            path, f"numeric moment_constant = {numerics['moment_constant']:g} differs from the actuators' gear {km:g}"
        )
    numerics["moment_constant"] = km
    spin = -np.sign(gears)  # a CCW rotor's reaction torque is clockwise (-z)
    if int((spin > 0).sum()) != 2:
        _fail(
            path,
            f"a quadrotor needs two counter-clockwise and two clockwise rotors (gear[5] < 0 and > 0), "
            f"got {int((spin > 0).sum())} and {int((spin < 0).sum())}",
        )
    max_thrust = numerics["motor_constant"] * numerics["max_rot_velocity"] ** 2
    if not model.actuator_ctrllimited.all() or not np.allclose(
        model.actuator_ctrlrange, [[0.0, max_thrust]] * 4, rtol=1e-4
    ):
        _fail(path, f"actuator ctrlrange must be 0 .. motor_constant * max_rot_velocity^2 = {max_thrust:.6g} N")
    centre = model.body_ipos[1].copy()
    airframe = Airframe(
        name=path.stem,
        path=path,
        body_name=model.body(1).name,
        mass=float(model.body_mass[1]),
        inertia=model.body_inertia[1].copy(),
        inertia_quat=model.body_iquat[1].copy(),
        centre_of_mass=centre,
        rotor_pos=model.site_pos[sites] - centre,
        spin=spin,
        rotor_sites=tuple(model.site(s).name for s in sites),
        **{n: numerics[n] for n in MOTOR_NUMERICS},
    )
    if not airframe.body_name:
        _fail(path, "the drone body needs a name")
    if not airframe.mass > 0:
        _fail(path, f"the drone body has mass {airframe.mass:g}; give it an <inertial> or geoms with mass")
    effectiveness = airframe.effectiveness()
    row_scale = np.maximum(np.abs(effectiveness).max(axis=1, keepdims=True), 1e-300)
    if np.linalg.matrix_rank(effectiveness / row_scale, tol=1e-6) < 4:
        _fail(
            path,
            "the four rotors cannot make independent roll, pitch and yaw torques and thrust "
            "(a quadrotor needs its rotors around the centre of mass, not in a line)",
        )
    return airframe


def px4_mixer(airframe: Airframe) -> tuple[np.ndarray, np.ndarray]:
    """PX4's normalised allocation: (mix [4 motors, 4 axes], effectiveness [4 axes, 4 motors]).

    As ControlAllocationPseudoInverse: mix = pinv(effectiveness); roll and pitch columns are divided
    by one common scale sqrt(|col|^2 / (nonzero / 2)), yaw by its largest entry, thrust by the mean
    absolute entry. Axes are (roll, pitch, yaw, collective thrust) in normalised units; the returned
    effectiveness is the inverse of the normalised mix, so `eff @ u` is the control a command u achieves.
    """
    mix = np.linalg.pinv(airframe.effectiveness())
    nz = lambda col: np.count_nonzero(np.abs(col) > 1e-3 * np.abs(col).max())  # noqa: E731
    roll_scale = np.sqrt((mix[:, 0] ** 2).sum() / (nz(mix[:, 0]) / 2.0))
    pitch_scale = np.sqrt((mix[:, 1] ** 2).sum() / (nz(mix[:, 1]) / 2.0))
    rp_scale = max(roll_scale, pitch_scale)
    mix = mix / np.array([rp_scale, rp_scale, mix[:, 2].max(), np.abs(mix[:, 3]).mean()])
    return mix, np.linalg.inv(mix)
