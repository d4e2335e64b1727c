"""Airframe properties read from its MJCF file (`assets/mjcf/<name>.xml`), and PX4's mixer.

The MJCF file is the single source of truth: mass and inertia from the drone body, rotor positions
from the sites `rotor1..4`, spin directions and the moment constant from the actuators' gear, the
motor model (Gazebo's gazebo_motor_model constants) from `<custom><numeric>` entries.

A new airframe is a new MJCF file with the same names (one free body, four `rotor<i>` sites, four
`<motor>` actuators on them, the seven numerics) plus a `controllers/<name>.params` gain file:

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


@dataclass(frozen=True)
class Airframe:
    """A quad-X airframe: rigid body, rotor geometry (FLU body frame) and Gazebo motor model."""

    name: str
    """Airframe name (the MJCF file stem)."""
    path: Path
    """The MJCF file."""
    mass: float
    """Total mass (kg)."""
    inertia: np.ndarray
    """Principal inertia [3] (kg m^2)."""
    rotor_pos: np.ndarray
    """Rotor positions [4, 3] in the body frame (m), PX4 motor order."""
    spin: np.ndarray
    """[4] +1 for a counter-clockwise rotor (seen from above), -1 for clockwise (Gazebo's turning direction)."""
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
        """[4, 4]: rows (roll torque, pitch torque, yaw torque in N m, thrust in N) per unit normalised motor command."""
        t = self.max_thrust
        x, y = self.rotor_pos[:, 0], self.rotor_pos[:, 1]
        # thrust t u along body +z at (x, y, z): torque r x F = (y F, -x F, 0); yaw reaction -spin km F
        return np.stack([y * t, -x * t, -self.spin * self.moment_constant * t, np.full(4, t)])


def airframe_path(name: str) -> Path:
    """`assets/mjcf/<name>.xml`, or ConfigError naming the known airframes."""
    path = MJCF_DIR / f"{name}.xml"
    if not name or "/" in name or not path.is_file() or name == "arena":
        known = sorted(p.stem for p in MJCF_DIR.glob("*.xml") if p.stem != "arena")
        raise ConfigError(f"airframe: unknown airframe {name!r} (known: {', '.join(known)})")
    return path


def load_airframe(name: str) -> Airframe:
    """Read an airframe's MJCF file (see the module docstring for what it must contain)."""
    path = airframe_path(name)
    try:
        model = mujoco.MjModel.from_xml_path(str(path))
    except ValueError as exc:
        raise ConfigError(f"airframe: {path} does not compile: {str(exc).splitlines()[0]}") from None
    if model.nbody != 2 or model.nu != 4 or model.njnt != 1 or model.jnt_type[0] != mujoco.mjtJoint.mjJNT_FREE:
        raise ConfigError(f"airframe: {path} must hold one free body with 4 rotor actuators")
    numerics = {model.numeric(i).name: float(model.numeric_data[model.numeric_adr[i]]) for i in range(model.nnumeric)}
    missing = [n for n in MOTOR_NUMERICS if n not in numerics]
    if missing:
        raise ConfigError(f"airframe: {path} lacks <numeric name={missing[0]!r}>")
    rotor_pos = np.empty((4, 3))
    spin = np.empty(4)
    for i in range(4):
        site = model.site(f"rotor{i + 1}")
        rotor_pos[i] = model.site_pos[site.id]
        actuator = model.actuator(f"thrust{i + 1}")
        if actuator.trnid[0] != site.id:
            raise ConfigError(f"airframe: {path}: actuator thrust{i + 1} must act on site rotor{i + 1}")
        gear = model.actuator_gear[actuator.id]
        if not np.allclose(gear[:5], [0, 0, 1, 0, 0]) or not np.isclose(abs(gear[5]), numerics["moment_constant"]):
            raise ConfigError(f"airframe: {path}: actuator thrust{i + 1} gear must be '0 0 1 0 0 +-moment_constant'")
        spin[i] = -np.sign(gear[5])  # a CCW rotor's reaction torque is clockwise (-z)
    max_thrust = numerics["motor_constant"] * numerics["max_rot_velocity"] ** 2
    if not np.allclose(model.actuator_ctrlrange, [[0.0, max_thrust]] * 4, rtol=1e-4):
        raise ConfigError(f"airframe: {path}: actuator ctrlrange must be 0 .. k * max_rot_velocity^2 = {max_thrust:.4f}")
    return Airframe(
        name=name,
        path=path,
        mass=float(model.body_mass[1]),
        inertia=model.body_inertia[1].copy(),
        rotor_pos=rotor_pos,
        spin=spin,
        **{n: numerics[n] for n in MOTOR_NUMERICS},
    )


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
