"""The MuJoCo quadrotor world: MJCF drones flown by the PX4-like cascade (World protocol).

B envs, each its own MjModel copy + MjData: N UAVs (`uav<i>_`) and, unless disabled, one
adversary quadrotor (`adv_`) are attached from the airframe MJCF into `assets/mjcf/arena.xml` with
`mujoco.MjSpec` (rigid body, footprint, rotor sites and the four site-mounted thrust `<motor>`
actuators; visual geoms only if asked for). The cascade writes each rotor's thrust (after the motor
lag) to `data.ctrl`, drone by drone in the airframe's motor order, and MuJoCo applies it with the yaw
reaction torque through the actuators' gear; rotor drag and wind act through `xfrc_applied`
(`rotor_actuation = "external"`: no actuators, the whole rotor wrench through xfrc_applied, as before
the actuators were live; the default "auto" keeps the actuators up to AUTO_ACTUATORS_MAX_DRONES drones
per env and goes external above, where MuJoCo's site transmissions, O(actuators x dofs) per mj_step,
would make the cost quadratic in the swarm; `world.rotor_actuation_used` says which). K obstacles are cylinders
(radius 0.4 m by default, geom group 1), each in its own world-welded body, compiled once and moved
at reset by writing the env's `model.body_pos` (no recompile). Moving geoms inside one body instead
(`model.geom_pos`) would leave the bounding-volume trees MuJoCo compiled for the body stale: its
collision midphase and its rays would then miss the moved obstacles. One decision step (0.1 s)
hands the setpoints to the offboard interface (`offboard`: "velocity", "acceleration" or
"acceleration-assisted"; docs/px4_interface.md) and runs
`decision_dt / physics_dt` physics steps; each physics step runs the compiled cascade
(cefc_mj.control.cascade), then `mj_step`, all in one compiled call up to the next wind redraw
(`physics_loop = "compiled"`) or from Python (`"python"`, the same arithmetic).

- Positions/velocities: the drones' true x-y from qpos/qvel.
- LiDAR: what `mj_multiRay` reports from the given origins at flight altitude, obstacles (static
  geoms, so flg_static = 1) and, if lidar_sees_agents, the UAV footprints (group 2), excluding the
  casting drone's body; the adversary (group 4) is not seen, as in the particle world. An origin
  inside a circle reads 0 (the particle world's convention; a ray cast from inside a MuJoCo cylinder
  would report the far wall). Computed by one compiled call per env that runs MuJoCo's `mju_rayGeom`
  on the geoms within range only (cefc_mj.sim.raycast; bit for bit `mj_multiRay`'s readings).
- Collisions: MuJoCo contacts of a UAV footprint with an obstacle or another UAV footprint at any
  physics step of the last decision step, read from two MuJoCo contact sensors per UAV (all contacts
  of its footprint, those with the floor). The adversary does not collide (the particle world's
  adversary passes through obstacles too).
- Divergence: non-finite state, a drone tilted past `flip_tilt_deg`, or a MuJoCo bad-qacc/qpos/qvel
  warning raises `SimulationDiverged` naming env, drone and time; the env must be reset.

>>> world = MujocoWorld(MujocoWorldConfig(), n_envs=1, n_agents=2, n_obstacles=1, seed=0)
>>> import numpy as np
>>> world.reset(np.ones(1, bool), np.array([[[0.0, 0.0], [1.0, 0.0]]]), np.array([[0.0, 5.0]]),
...             np.array([[[3.0, 0.0]]]))
>>> world.step(np.zeros((1, 2, 2)), np.zeros((1, 2)))
>>> world.agent_pos.shape, world.lidar(world.agent_pos).shape
((1, 2, 2), (1, 2, 24))
"""

from __future__ import annotations

import copy
import ctypes
import dataclasses
import math
import warnings
from dataclasses import asdict, dataclass
from pathlib import Path

import mujoco
import numpy as np

from cefc_mj.control.airframe import Airframe, load_airframe
from cefc_mj.control.cascade import (
    HOLD_POSITION_GAIN,
    OFFBOARD_MODES,
    SP_VMAX,
    SP_Z,
    CascadeTiming,
    Px4Cascade,
    cascade_step,
    run_physics,
)
from cefc_mj.control.params import load_params, params_for_airframe, params_path
from cefc_mj.errors import ConfigError, SimulationDiverged
from cefc_mj.paths import MJCF_DIR
from cefc_mj.sim.raycast import MJU_RAY_GEOM, REACH_MARGIN, cast_lidar
from cefc_mj.sim.wind import WindConfig, WindField, wind_config_direction
from cefc_mj.task.config import TaskConfig

OBSTACLE_GROUP = 1
UAV_GROUP = 2
ADVERSARY_GROUP = 4
_PARKED = 1.0e3  # where obstacles wait before the first reset (far outside the arena)
_BAD_STATE_WARNINGS = (
    mujoco.mjtWarning.mjWARN_BADQACC,
    mujoco.mjtWarning.mjWARN_BADQPOS,
    mujoco.mjtWarning.mjWARN_BADQVEL,
)
_VISUAL_GROUP = 3  # the airframe file's visual-only geoms and rotor sites
_FOOTPRINT_HALF_HEIGHT = 0.05  # of the footprint cylinder the world adds to an airframe without one (m)
_HOVER_MISMATCH = 0.1  # largest |MPC_THR_HOVER - the airframe's hover thrust| accepted (normalised)
PHYSICS_LOOPS = ("compiled", "python")
ROTOR_ACTUATIONS = ("auto", "actuators", "external")
AUTO_ACTUATORS_MAX_DRONES = 16
"""rotor_actuation = "auto": live actuators up to this many drones per env (UAVs + adversary), the external
rotor wrench above. MuJoCo's site transmission builds a dense 3 x nv Jacobian per actuator, so the live
actuators cost O(drones^2) per mj_step (no transmission MuJoCo offers applies a body-frame force at a
rotor in O(1); jacobian="sparse" does not change it); the external path is the same physics (~1e-15)
and linear. 16 keeps every shipped scene (Table VIII: 5-8 drones, Tables V/VI: 9, Table VII: up to 16)
on the actuators, bit for bit as before "auto"; measured cross-over in docs/research/mujoco_world.md (Performance)."""


def _mj_step_address() -> int | None:
    """C address of mj_step in the MuJoCo library the bindings loaded (None if it cannot be found)."""
    for lib in sorted(Path(mujoco.__file__).parent.glob("libmujoco*")):
        try:
            return ctypes.cast(ctypes.CDLL(str(lib)).mj_step, ctypes.c_void_p).value
        except (OSError, AttributeError):
            continue
    return None


_MJ_STEP = _mj_step_address()


SETTLE_POSITION_GAIN = HOLD_POSITION_GAIN
"""Position gain (1/s) of the "acceleration-assisted" interface's own settle: PX4's MPC_XY_P default."""


@dataclass(frozen=True)
class MujocoWorldConfig:
    """Physics, controller and scene settings of the MuJoCo backend (validated at construction)."""

    airframe: str = "iris"
    """Airframe: a name in assets/mjcf/ (without .xml; "iris", "crazyflie") or the path of an MJCF
    quadrotor file with four site-mounted thrust motors (cefc_mj.control.airframe; docs/airframes.md)."""
    params: str | None = None
    """Controller gains: a name in controllers/ (without .params) or a path to a .params file; None:
    the airframe's own, `<stem>.params` beside an airframe given as a file, else controllers/<stem>.params."""
    rotor_actuation: str = "auto"
    """"actuators": the airframe's four `<motor>` actuators stay in the compiled scene and the cascade
    writes the rotor thrusts to `data.ctrl` (MuJoCo applies thrust and yaw reaction torque);
    "external": the actuators are left out and the same rotor wrench is summed into xfrc_applied (the
    earlier path; same forces to ~1e-15 relative, cheaper per mj_step: 1.4x at 8 drones, 30x at 256, as the
    actuators' cost grows with drones x dofs); "auto" (default): "actuators" up to
    AUTO_ACTUATORS_MAX_DRONES drones per env (UAVs + adversary), "external" above (`resolve_rotor_actuation`;
    the world's `rotor_actuation_used` says which). Rotor drag and wind go through xfrc_applied either way."""
    physics_dt: float = 0.002
    """Physics step (s); 0.002 = 500 Hz (docs/design.md §3: 500 Hz or finer)."""
    decision_dt: float = 0.1
    """Decision step (s); a multiple of physics_dt."""
    rate_loop_hz: float = 250.0
    """Attitude + body-rate loop rate (Hz, >= 250; a divisor of the physics rate)."""
    position_loop_hz: float = 100.0
    """Offboard interface + altitude/thrust loop rate (Hz; a divisor of the physics rate)."""
    flight_altitude: float = 2.0
    """Altitude the drones hold and the LiDAR casts at (m)."""
    offboard: str = "velocity"
    """What the offboard interface makes of the policy's acceleration setpoint (docs/px4_interface.md):
    "velocity" integrates it into a velocity setpoint as the particle world integrates velocity and
    flies that with PX4's velocity PID (acceleration feed-forward; the integral rejects wind);
    "acceleration" is PX4's own: the setpoint goes straight to tilt and collective thrust (PositionControl
    with NaN position and velocity setpoints: tilt limit MPC_TILTMAX_AIR, no feedback, no integral, no
    speed limit, no drag compensation); "acceleration-assisted" is not PX4's: the earlier acceleration
    interface (a speed limiter that cancels an estimate of the wind's push, a calm-air rotor-drag
    feed-forward, and its own settle), kept to reproduce results made with it."""
    speed_limit_tau: float = 0.35
    """offboard = "acceleration-assisted": time constant (s) with which the interface pulls a speed that would
    exceed the limit back onto it (a velocity loop of gain 1/tau, active only at the limit)."""
    disturbance_tau: float = 0.1
    """offboard = "acceleration-assisted": low-pass time constant (s) of the external-push (wind) estimate the
    speed limiter cancels."""
    flip_tilt_deg: float = 90.0
    """A drone tilted past this angle counts as flipped: SimulationDiverged."""
    wind_settle_s: float = 5.0
    """In wind, every drone first holds its start position for this long with PX4's position hold
    (velocity setpoint MPC_XY_P x position error, PX4's velocity PID with its integral, started where a
    long hold in the episode's first wind draw takes it; the wind is held at that draw meanwhile), for
    every interface, before the episode begins at its sampled position with the attitude, rotor
    speeds, velocity and integrals it settled into, as a PX4 vehicle holds in Position mode before
    offboard starts ("acceleration-assisted": its own earlier settle). 0 starts from a level hover
    with empty integrators in full wind. In calm air the level hover at rest is the hold's end state
    and nothing is flown."""
    obstacle_height: float = 4.0
    """Height of the cylinder obstacles (m), from the floor."""
    gravity: float = 9.81
    """Gravity (m/s^2)."""
    physics_loop: str = "compiled"
    """"compiled": cascade + mj_step run in one numba call per stretch of physics steps (mj_step called
    through its C address); "python": one Python round-trip per physics step. Same arithmetic, same
    trajectories bit for bit; "python" is the fallback (and is used if the library is not found)."""
    visual_geoms: bool = False
    """Keep the airframe's visual-only geoms and rotor sites (group 3) in the compiled scene, for a MuJoCo
    viewer. They cannot collide, but they cost about a quarter of mj_step (kinematics, collision)."""

    def params_file(self) -> Path:
        """The parameter file this config flies with (see `params`); ConfigError if there is none."""
        if self.params is None:
            return params_for_airframe(load_airframe(self.airframe).path)
        return params_path(self.params)

    def validate(self) -> None:
        """Raise ConfigError naming the first bad field."""
        if not isinstance(self.airframe, (str, Path)):
            raise ConfigError(f"mujoco.airframe must be a name or a path, got {self.airframe!r}")
        airframe = load_airframe(self.airframe)
        params_file = self.params_file()
        for name in (
            "physics_dt",
            "decision_dt",
            "rate_loop_hz",
            "position_loop_hz",
            "flight_altitude",
            "speed_limit_tau",
            "disturbance_tau",
            "obstacle_height",
            "gravity",
        ):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise ConfigError(f"mujoco.{name} must be a finite number > 0, got {value!r}")
        if self.physics_dt > 0.002 + 1e-12:
            raise ConfigError(f"mujoco.physics_dt must be <= 0.002 s (500 Hz or finer), got {self.physics_dt}")
        if _ratio(self.decision_dt, self.physics_dt) is None:
            raise ConfigError(
                f"mujoco.decision_dt = {self.decision_dt} must be a multiple of physics_dt = {self.physics_dt}"
            )
        if self.rate_loop_hz < 250:
            raise ConfigError(f"mujoco.rate_loop_hz must be >= 250 (PX4-like), got {self.rate_loop_hz}")
        for name in ("rate_loop_hz", "position_loop_hz"):
            if _ratio(1.0 / getattr(self, name), self.physics_dt) is None:
                raise ConfigError(
                    f"mujoco.{name} = {getattr(self, name)} must divide the physics rate {1 / self.physics_dt:g} Hz"
                )
        if not (
            isinstance(self.wind_settle_s, (int, float))
            and math.isfinite(self.wind_settle_s)
            and self.wind_settle_s >= 0
            and _ratio(self.wind_settle_s + self.decision_dt, self.decision_dt) is not None
        ):
            raise ConfigError(
                f"mujoco.wind_settle_s must be a whole number (>= 0) of decision steps "
                f"({self.decision_dt} s), got {self.wind_settle_s!r}"
            )
        if not 0 < self.flip_tilt_deg <= 180:
            raise ConfigError(f"mujoco.flip_tilt_deg must be in (0, 180], got {self.flip_tilt_deg}")
        if self.obstacle_height <= self.flight_altitude:
            raise ConfigError(
                f"mujoco.obstacle_height = {self.obstacle_height} must exceed flight_altitude = {self.flight_altitude}"
            )
        if self.offboard not in OFFBOARD_MODES:
            raise ConfigError(f"mujoco.offboard must be one of {', '.join(OFFBOARD_MODES)}, got {self.offboard!r}")
        if self.offboard == "velocity" and _ratio(self.decision_dt * self.position_loop_hz, 1.0) is None:
            raise ConfigError(
                f"mujoco.decision_dt = {self.decision_dt} must be a whole number of position-loop periods "
                f"(1 / {self.position_loop_hz:g} Hz) with offboard = 'velocity'"
            )
        if self.physics_loop not in PHYSICS_LOOPS:
            raise ConfigError(
                f"mujoco.physics_loop must be one of {', '.join(PHYSICS_LOOPS)}, got {self.physics_loop!r}"
            )
        if not isinstance(self.visual_geoms, bool):
            raise ConfigError(f"mujoco.visual_geoms must be a bool, got {self.visual_geoms!r}")
        if self.rotor_actuation not in ROTOR_ACTUATIONS:
            raise ConfigError(
                f"mujoco.rotor_actuation must be one of {', '.join(ROTOR_ACTUATIONS)}, got {self.rotor_actuation!r}"
            )
        hover, expected = load_params(params_file)["MPC_THR_HOVER"], airframe.hover_thrust(self.gravity)
        if abs(hover - expected) > _HOVER_MISMATCH:
            raise ConfigError(
                f"params: MPC_THR_HOVER = {hover:g} in {params_file.name} but airframe {airframe.name!r} "
                f"hovers at {expected:.3f} of full thrust: these gains are not this airframe's"
            )

    def to_dict(self) -> dict:
        """Plain dict for run records."""
        return asdict(self)


def _ratio(a: float, b: float) -> int | None:
    """a / b if it is a positive integer (to 1e-9), else None."""
    r = a / b
    n = round(r)
    return n if n >= 1 and abs(r - n) < 1e-9 * max(1.0, r) else None


def resolve_rotor_actuation(rotor_actuation: str, n_drones: int) -> str:
    """The rotor path a scene of `n_drones` drones per env flies with: "actuators" or "external"; "auto"
    is "actuators" up to AUTO_ACTUATORS_MAX_DRONES drones, "external" above."""
    if rotor_actuation not in ROTOR_ACTUATIONS:
        raise ConfigError(
            f"mujoco.rotor_actuation must be one of {', '.join(ROTOR_ACTUATIONS)}, got {rotor_actuation!r}"
        )
    if rotor_actuation != "auto":
        return rotor_actuation
    return "actuators" if n_drones <= AUTO_ACTUATORS_MAX_DRONES else "external"


def build_scene(
    config: MujocoWorldConfig,
    n_agents: int,
    n_obstacles: int,
    with_adversary: bool,
    uav_radius: float,
    obstacle_radius: float = 0.4,
    airframe: Airframe | None = None,
) -> mujoco.MjModel:
    """Compose arena + N UAVs (+ adversary) + K parked obstacle cylinders (+ 2 contact sensors per UAV,
    sensordata[2i:2i+2] = contacts of UAV i's footprint: all, with the floor) into one MjModel.

    Each drone is the airframe's body with its footprint and, with live actuators (rotor_actuation
    "actuators", or "auto" at this drone count: `resolve_rotor_actuation`), its four rotor sites and
    thrust motors (ctrlrange set to exactly 0 .. k omega_max^2): actuators 4 d .. 4 d + 3 are drone d's,
    in the airframe's motor order. Everything else of the file (other geoms, sites, sensors, keyframes)
    is left out, visual geoms kept (without contacts) if config.visual_geoms.
    The body keeps the mass and inertia the airframe file gives it, whatever geoms are left out."""
    airframe = airframe or load_airframe(config.airframe)
    live = resolve_rotor_actuation(config.rotor_actuation, n_agents + int(with_adversary)) == "actuators"
    arena = mujoco.MjSpec.from_file(str(MJCF_DIR / "arena.xml"))
    arena.option.timestep = config.physics_dt
    arena.option.gravity = [0.0, 0.0, -config.gravity]
    names = [f"uav{i}_" for i in range(n_agents)] + (["adv_"] if with_adversary else [])
    for i, prefix in enumerate(names):
        child = mujoco.MjSpec.from_file(str(airframe.path))
        child.meshdir = str((airframe.path.parent / child.meshdir).resolve())  # assets resolve from the file's folder
        child.texturedir = str((airframe.path.parent / child.texturedir).resolve())
        body = child.worldbody.first_body()
        if not body.explicitinertial:  # mass from geoms: pin it before any geom is left out
            body.explicitinertial = True
            body.mass, body.ipos, body.iquat = airframe.mass, airframe.centre_of_mass, airframe.inertia_quat
            body.inertia = airframe.inertia
        for element in list(child.keys) + list(child.sensors):
            child.delete(element)
        for actuator in list(child.actuators):
            if live:  # the rotor's thrust (N) is ctrl; the exact range keeps MuJoCo's clamp a no-op
                actuator.ctrllimited = mujoco.mjtLimited.mjLIMITED_TRUE
                actuator.ctrlrange = [0.0, airframe.max_thrust]
            else:  # the cascade applies the rotor wrenches (xfrc_applied)
                child.delete(actuator)
        footprint = None
        for geom in list(child.geoms):
            if geom.name == "footprint":
                footprint = geom
            elif config.visual_geoms:
                geom.contype, geom.conaffinity, geom.group = 0, 0, _VISUAL_GROUP
            else:
                child.delete(geom)
        keep_sites = set(airframe.rotor_sites) if live else set()
        for site in list(child.sites):
            if site.name not in keep_sites and not config.visual_geoms:
                child.delete(site)
        if footprint is None:
            footprint = body.add_geom(
                name="footprint",
                type=mujoco.mjtGeom.mjGEOM_CYLINDER,
                pos=airframe.centre_of_mass,
                size=[uav_radius, _FOOTPRINT_HALF_HEIGHT, 0.0],
                rgba=[0.3, 0.3, 0.35, 0.25],
            )
        elif footprint.type != mujoco.mjtGeom.mjGEOM_CYLINDER:
            raise ConfigError(
                f"airframe: {airframe.path}: geom 'footprint' must be a cylinder (the collision disc), "
                "or leave it out and the world adds one"
            )
        footprint.contype, footprint.conaffinity, footprint.group = 1, 1, UAV_GROUP
        frame = arena.worldbody.add_frame(pos=[2.0 * i, 0.0, config.flight_altitude])
        frame.attach_body(body, prefix, "")
        footprint = arena.geom(f"{prefix}footprint")
        footprint.size = [uav_radius, footprint.size[1], 0.0]
        if prefix == "adv_":
            footprint.contype = 0
            footprint.conaffinity = 0
            footprint.group = ADVERSARY_GROUP
            footprint.rgba = [0.85, 0.15, 0.1, 0.5]
    half_h = config.obstacle_height / 2.0
    for k in range(n_obstacles):
        # one world-welded body per obstacle, moved through model.body_pos: the geom never moves in its
        # body's frame, so the bounding volumes MuJoCo compiles for collisions and rays stay valid
        arena.worldbody.add_body(name=f"obstacle{k}", pos=[_PARKED + 2.0 * k, _PARKED, half_h]).add_geom(
            name=f"obstacle{k}",
            type=mujoco.mjtGeom.mjGEOM_CYLINDER,
            size=[obstacle_radius, half_h, 0.0],
            group=OBSTACLE_GROUP,
            contype=1,
            conaffinity=1,
            rgba=[0.55, 0.45, 0.35, 1.0],
        )
    floor = next((g.name for g in arena.geoms if g.type == mujoco.mjtGeom.mjGEOM_PLANE), None)
    if floor is None:
        raise ConfigError("mujoco: assets/mjcf/arena.xml needs a plane geom (the floor)")
    found = [1 << int(mujoco.mjtConDataField.mjCONDATA_FOUND), 0, 1]  # data = "found" (count), no reduction, 1 slot
    for i in range(n_agents):
        geom = dict(
            type=mujoco.mjtSensor.mjSENS_CONTACT,
            objtype=mujoco.mjtObj.mjOBJ_GEOM,
            objname=f"uav{i}_footprint",
            intprm=found,
        )
        arena.add_sensor(name=f"uav{i}_contacts", **geom)
        arena.add_sensor(name=f"uav{i}_floor_contacts", reftype=mujoco.mjtObj.mjOBJ_GEOM, refname=floor, **geom)
    return arena.compile()


class MujocoWorld:
    """B envs of N quadrotors (+ adversary; Iris-class unless config.airframe says otherwise) and K
    cylinders, implementing `World`.

    Args:
        config: physics/controller/scene settings.
        n_envs, n_agents, n_obstacles: B, N, K (K is fixed for the world's life).
        n_lidar_rays, lidar_range, lidar_sees_agents: LiDAR as in TaskConfig.
        uav_radius: the footprint cylinder's radius (the same disc as the particle world).
        obstacle_radius: radius of the cylinder obstacles (m).
        speed_max, adversary_speed_max: horizontal speed limits kept by the offboard interface.
        accel_max: per-axis clip of the acceleration setpoints (m/s^2).
        wind: WindConfig or None for calm air.
        with_adversary: False builds no adversary drone (Table VIII); step() then ignores
            adversary_accel and adversary_pos/vel read zeros.
        seed: seeds the world's numpy Generator (wind draws).
    """

    def __init__(
        self,
        config: MujocoWorldConfig,
        n_envs: int,
        n_agents: int,
        n_obstacles: int,
        *,
        n_lidar_rays: int = 24,
        lidar_range: float = 3.0,
        lidar_sees_agents: bool = True,
        uav_radius: float = 0.25,
        obstacle_radius: float = 0.4,
        speed_max: float = 1.0,
        adversary_speed_max: float = 0.75,
        accel_max: float = 2.0,
        wind: WindConfig | None = None,
        with_adversary: bool = True,
        seed: int = 0,
    ):
        config.validate()
        for name, value in (("n_envs", n_envs), ("n_agents", n_agents), ("n_lidar_rays", n_lidar_rays)):
            if not isinstance(value, (int, np.integer)) or value < 1:
                raise ConfigError(f"{name} must be an integer >= 1, got {value!r}")
        if not isinstance(n_obstacles, (int, np.integer)) or n_obstacles < 0:
            raise ConfigError(f"n_obstacles must be an integer >= 0, got {n_obstacles!r}")
        for name, value in (
            ("lidar_range", lidar_range),
            ("uav_radius", uav_radius),
            ("obstacle_radius", obstacle_radius),
            ("speed_max", speed_max),
            ("adversary_speed_max", adversary_speed_max),
            ("accel_max", accel_max),
        ):
            if not (math.isfinite(value) and value > 0):
                raise ConfigError(f"{name} must be a finite number > 0, got {value!r}")
        if wind is not None and not isinstance(wind, WindConfig):
            raise ConfigError(f"wind must be a WindConfig or None, got {type(wind).__name__}")
        self.config = config
        self.n_envs, self.n_agents, self.n_obstacles = int(n_envs), int(n_agents), int(n_obstacles)
        self.with_adversary = bool(with_adversary)
        self.n_drones = self.n_agents + int(self.with_adversary)
        self.n_lidar_rays, self.lidar_range, self.lidar_sees_agents = (
            int(n_lidar_rays),
            float(lidar_range),
            bool(lidar_sees_agents),
        )
        self.uav_radius, self.obstacle_radius = float(uav_radius), float(obstacle_radius)
        self.accel_max = float(accel_max)
        self.dt = float(config.decision_dt)
        self.n_substeps = _ratio(config.decision_dt, config.physics_dt)
        self.rng = np.random.default_rng(seed)
        self.wind_config = wind if wind is not None else WindConfig()
        self.wind = WindField(self.wind_config, self.n_envs, self.rng)
        self._wind_period = _ratio(self.wind_config.update_period, config.physics_dt)
        if self._wind_period is None:
            raise ConfigError(
                f"wind.update_period = {self.wind_config.update_period} "
                f"must be a multiple of physics_dt = {config.physics_dt}"
            )

        self.airframe = load_airframe(config.airframe)
        timing = CascadeTiming(
            config.physics_dt,
            _ratio(1.0 / config.rate_loop_hz, config.physics_dt),
            _ratio(1.0 / config.position_loop_hz, config.physics_dt),
        )
        self.params_file = config.params_file()
        self.cascade = Px4Cascade(
            self.airframe,
            load_params(self.params_file),
            timing,
            self.n_envs,
            self.n_drones,
            speed_limit_tau=config.speed_limit_tau,
            disturbance_tau=config.disturbance_tau,
            flip_tilt_deg=config.flip_tilt_deg,
            gravity=config.gravity,
            offboard=config.offboard,
        )
        self.cascade.setpoint[:, :, SP_Z] = config.flight_altitude
        self.cascade.setpoint[:, : self.n_agents, SP_VMAX] = speed_max
        self.cascade.setpoint[:, self.n_agents :, SP_VMAX] = adversary_speed_max

        base = build_scene(
            config,
            self.n_agents,
            self.n_obstacles,
            self.with_adversary,
            self.uav_radius,
            self.obstacle_radius,
            airframe=self.airframe,
        )
        self.models = [base] + [copy.deepcopy(base) for _ in range(self.n_envs - 1)]
        self.datas = [mujoco.MjData(m) for m in self.models]
        prefixes = [f"uav{i}_" for i in range(self.n_agents)] + (["adv_"] if self.with_adversary else [])
        self.drone_body_ids = np.array([base.body(f"{p}{self.airframe.body_name}").id for p in prefixes])
        if not np.array_equal(self.drone_body_ids, np.arange(1, self.n_drones + 1)) or base.nq != 7 * self.n_drones:
            raise ConfigError("mujoco: the scene must hold the drones as bodies 1..D with one free joint each")
        if not (
            np.allclose(base.body_mass[1 : self.n_drones + 1], self.airframe.mass, rtol=1e-12)
            and np.allclose(base.body_ipos[1 : self.n_drones + 1], self.airframe.centre_of_mass, atol=1e-12)
        ):
            raise ConfigError(
                f"mujoco: the drones in the scene lost the mass or centre of mass of {self.airframe.path}"
            )
        # "actuators" or "external": the rotor path this world flies (config.rotor_actuation, "auto" resolved)
        self.rotor_actuation_used = resolve_rotor_actuation(config.rotor_actuation, self.n_drones)
        self.rotor_actuators = self.rotor_actuation_used == "actuators"
        if self.rotor_actuators:
            # actuator 4 d + i: drone d's rotor i, on its rotor site (data.ctrl viewed as [D, 4])
            sites = [base.site(f"{p}{s}").id for p in prefixes for s in self.airframe.rotor_sites]
            if base.nu != 4 * self.n_drones or base.actuator_trnid[:, 0].tolist() != sites:
                raise ConfigError("mujoco: the scene must hold four rotor actuators per drone, in motor order")
        elif base.nu:
            raise ConfigError(
                f"mujoco: with rotor_actuation = 'external' (configured {config.rotor_actuation!r}) "
                "the scene must have no actuators"
            )
        if base.nsensordata != 2 * self.n_agents:
            raise ConfigError("mujoco: the scene must have exactly the UAVs' contact sensors")
        self.obstacle_geom_ids = np.array([base.geom(f"obstacle{k}").id for k in range(self.n_obstacles)], dtype=int)
        self.obstacle_body_ids = np.array([base.body(f"obstacle{k}").id for k in range(self.n_obstacles)], dtype=int)
        d, n = self.n_drones, self.n_agents
        # per env: qpos [D, 7], qvel [D, 6], xfrc_applied [D, 6], ctrl [D, 4] (rotor thrusts; [0, 4] without
        # actuators), contact counts [N, 2] (views into MjData)
        no_ctrl = np.empty((0, 4))
        self._views = [
            (
                dat.qpos.reshape(d, 7),
                dat.qvel.reshape(d, 6),
                dat.xfrc_applied[1 : d + 1],
                dat.ctrl.reshape(d, 4) if self.rotor_actuators else no_ctrl,
                dat.sensordata.reshape(n, 2),
            )
            for dat in self.datas
        ]
        self._compiled = config.physics_loop == "compiled" and _MJ_STEP is not None
        if config.physics_loop == "compiled" and not self._compiled:
            warnings.warn(
                "mujoco: mj_step's C address not found next to the bindings; physics_loop falls back to 'python'",
                RuntimeWarning,
                stacklevel=2,
            )
        self._tick = np.zeros(self.n_envs, dtype=np.int64)
        self._collided = np.zeros((self.n_envs, self.n_agents), dtype=bool)
        self.start_offset = np.zeros((self.n_envs, self.n_drones))
        """[B, D] how far (m) the hold before the last episode left each drone from its start position,
        before the episode began there (0 without a hold)."""
        self._accel = np.zeros((self.n_envs, self.n_drones, 2))
        self.obstacles = np.full((self.n_envs, self.n_obstacles, 2), _PARKED)
        angles = 2.0 * np.pi * np.arange(self.n_lidar_rays) / self.n_lidar_rays
        self._ray_vec = np.stack([np.cos(angles), np.sin(angles), np.zeros_like(angles)], axis=1).ravel()
        self._ray_group = np.array([0, 1, 1 if self.lidar_sees_agents else 0, 0, 0, 0], dtype=np.uint8)
        self._ray_geomid = np.zeros(self.n_lidar_rays, dtype=np.int32)
        self._drone_body_list = [int(i) for i in self.drone_body_ids]
        self._ray_pnt = np.zeros(3)
        # the compiled LiDAR (cefc_mj.sim.raycast): the geoms mj_multiRay would test (visible, in an enabled
        # group), with their horizontal reach: the radius for the vertical obstacle cylinders, else the bounding sphere
        self._lidar_compiled = MJU_RAY_GEOM is not None
        alpha = base.geom_rgba[:, 3].copy()
        if base.nmat:
            with_material = base.geom_matid >= 0
            alpha[with_material] = base.mat_rgba[base.geom_matid[with_material], 3]
        seen = (alpha != 0) & (self._ray_group[np.clip(base.geom_group, 0, 5)] != 0)
        self._ray_candidates = np.flatnonzero(seen).astype(np.int64)
        reach = base.geom_rbound[self._ray_candidates].copy()
        is_obstacle = np.isin(self._ray_candidates, self.obstacle_geom_ids)
        reach[is_obstacle] = base.geom_size[self._ray_candidates[is_obstacle], 0]
        self._ray_candidate_reach = reach + REACH_MARGIN
        self._ray_candidate_body = base.geom_bodyid[self._ray_candidates].astype(np.int64)
        self._ray_caster_body = self.drone_body_ids[: self.n_agents].astype(np.int64)
        self._ray_directions = self._ray_vec.reshape(-1, 3).copy()
        self._ray_arrays = [
            (dat.geom_xpos, dat.geom_xmat, mdl.geom_size, mdl.geom_type) for mdl, dat in zip(self.models, self.datas)
        ]

    # ------------------------------------------------------------------ World protocol
    def reset(
        self, env_mask: np.ndarray, agent_pos: np.ndarray, adversary_pos: np.ndarray, obstacles: np.ndarray
    ) -> None:
        """Place the masked envs' drones (level hover at flight altitude, zero velocity) and obstacles."""
        b, n, k = self.n_envs, self.n_agents, self.n_obstacles
        mask = _check(np.asarray(env_mask, dtype=bool), (b,), "env_mask")
        agent_pos = _check(agent_pos, (b, n, 2), "agent_pos")
        adversary_pos = _check(adversary_pos, (b, 2), "adversary_pos")
        obstacles = _check(obstacles, (b, k, 2), "obstacles")
        alt = self.config.flight_altitude
        for e in np.flatnonzero(mask):
            model, data = self.models[e], self.datas[e]
            mujoco.mj_resetData(model, data)
            model.body_pos[self.obstacle_body_ids, :2] = obstacles[e]
            self.obstacles[e] = obstacles[e]
            qpos = self._views[e][0]
            xy = np.concatenate([agent_pos[e], adversary_pos[e][None]]) if self.with_adversary else agent_pos[e]
            qpos[:, :2] = xy
            qpos[:, 2] = alt
            qpos[:, 3:] = (1.0, 0.0, 0.0, 0.0)
            self.cascade.reset(e)
            self._tick[e] = 0
            self._collided[e] = False
            self.wind.reset(e)
            self.start_offset[e] = 0.0
            mujoco.mj_forward(model, data)
            if self.wind.mean_speed[e] > 0 and self.config.wind_settle_s > 0:
                self._settle(e)

    def _settle(self, e: int) -> None:
        """Env e's drones hold their start positions in the wind for `wind_settle_s` with PX4's
        position hold (Px4Cascade.holding: velocity PID with its integral), whatever the interface;
        then the episode's clock starts at 0 with them back at the start positions (`start_offset`
        says how far each was moved), in the state they settled into (attitude, rotor speeds,
        integrators, velocity, the wind's own state). "acceleration-assisted" keeps its own earlier
        settle (`_settle_assisted`), to reproduce results made with it."""
        if self.cascade.offboard == "acceleration-assisted":
            self._settle_assisted(e)
            return
        qpos = self._views[e][0]
        start = qpos[:, :2].copy()
        with self.cascade.holding(e, start, self.wind.vector[e]):
            steps = self.n_substeps * (_ratio(self.config.wind_settle_s + self.dt, self.dt) - 1)
            self._advance(e, steps, redraw_wind=False)
        self._restart_at(e, start)

    def _restart_at(self, e: int, start: np.ndarray) -> None:
        """Env e's episode clock to 0 with its drones moved back onto `start` [D, 2]."""
        qpos = self._views[e][0]
        self.start_offset[e] = np.linalg.norm(qpos[:, :2] - start, axis=-1)
        qpos[:, :2] = start
        self._tick[e] = 0
        self._collided[e] = False
        mujoco.mj_forward(self.models[e], self.datas[e])

    def _settle_assisted(self, e: int) -> None:
        """The settle before an "acceleration-assisted" episode, as it was before the PX4 hold: each
        decision step a setpoint towards MPC_XY_P x the position error, clipped to the action bound,
        through the interface itself (no integral)."""
        qpos, qvel = self._views[e][0], self._views[e][1]
        start = qpos[:, :2].copy()
        for _ in range(_ratio(self.config.wind_settle_s + self.dt, self.dt) - 1):
            target = SETTLE_POSITION_GAIN * (start - qpos[:, :2])
            accel = np.clip((target - qvel[:, :2]) / self.dt, -self.accel_max, self.accel_max)
            self.cascade.command(accel[None], self.dt, envs=slice(e, e + 1))
            self._advance(e, self.n_substeps)
        self._restart_at(e, start)

    def step(self, agent_accel: np.ndarray, adversary_accel: np.ndarray) -> None:
        """One decision step: hand the (per-axis clipped) setpoints to the offboard interface and run
        decision_dt of physics."""
        b, n = self.n_envs, self.n_agents
        a = self.accel_max
        accel = self._accel
        accel[:, :n] = np.clip(_check(agent_accel, (b, n, 2), "agent_accel"), -a, a)
        if self.with_adversary:
            accel[:, n] = np.clip(_check(adversary_accel, (b, 2), "adversary_accel"), -a, a)
        self.cascade.command(accel, self.dt)
        self._collided[:] = False
        for e in range(b):
            self._advance(e, self.n_substeps)
            data = self.datas[e]
            for w in _BAD_STATE_WARNINGS:
                if data.warning[w].number:
                    raise SimulationDiverged(
                        f"env {e}: MuJoCo {mujoco.mjtWarning(w).name} (unstable physics) "
                        f"before t = {self.sim_time[e]:.3f} s"
                    )

    def _advance(self, e: int, n_steps: int, redraw_wind: bool = True) -> None:
        """n_steps physics steps of env e, redrawing its wind on the plugin's schedule (or, with
        redraw_wind False, holding it)."""
        c = self.cascade
        model, data = self.models[e], self.datas[e]
        qpos, qvel, xfrc, ctrl, contacts = self._views[e]
        s_e, sp_e, wind_e, collided = c.state[e], c.setpoint[e], self.wind.vector[e], self._collided[e]
        period = self._wind_period if redraw_wind else n_steps + int(self._tick[e]) + 1
        tick = int(self._tick[e])
        end = tick + n_steps
        while tick < end:
            if tick and tick % period == 0:
                self.wind.update(e, tick * self.config.physics_dt)
            stop = min(end, (tick // period + 1) * period)  # the next wind redraw
            if self._compiled:
                done, bad = run_physics(
                    tick,
                    stop - tick,
                    _MJ_STEP,
                    model._address,
                    data._address,
                    qpos,
                    qvel,
                    xfrc,
                    ctrl,
                    contacts,
                    collided,
                    s_e,
                    sp_e,
                    wind_e,
                    c.prm,
                    c.k,
                    c.mix,
                    c.eff,
                    c.rotors,
                )
            else:
                done, bad = stop - tick, -1
                for j in range(stop - tick):
                    bad = cascade_step(
                        tick + j, qpos, qvel, xfrc, s_e, sp_e, wind_e, c.prm, c.k, c.mix, c.eff, c.rotors, ctrl
                    )
                    if bad >= 0:
                        done = j
                        break
                    mujoco.mj_step(model, data)
                    collided |= contacts[:, 0] > contacts[:, 1]
            tick += done
            if bad >= 0:
                self._tick[e] = tick
                self._diverged(e, bad)
        self._tick[e] = tick

    @property
    def agent_pos(self) -> np.ndarray:
        """[B, N, 2] true positions (m)."""
        if self.n_envs == 1:
            return self._views[0][0][None, : self.n_agents, :2].copy()
        return np.stack([v[0][: self.n_agents, :2] for v in self._views])

    @property
    def agent_vel(self) -> np.ndarray:
        """[B, N, 2] true velocities (m/s)."""
        if self.n_envs == 1:
            return self._views[0][1][None, : self.n_agents, :2].copy()
        return np.stack([v[1][: self.n_agents, :2] for v in self._views])

    @property
    def adversary_pos(self) -> np.ndarray:
        """[B, 2] (zeros without an adversary)."""
        if not self.with_adversary:
            return np.zeros((self.n_envs, 2))
        return np.stack([v[0][self.n_agents, :2] for v in self._views])

    @property
    def adversary_vel(self) -> np.ndarray:
        """[B, 2] (zeros without an adversary)."""
        if not self.with_adversary:
            return np.zeros((self.n_envs, 2))
        return np.stack([v[1][self.n_agents, :2] for v in self._views])

    def lidar(self, origins: np.ndarray) -> np.ndarray:
        """Ranges [B, N, M] cast from origins [B, N, 2] at flight altitude (see the module docstring)."""
        b, n, m = self.n_envs, self.n_agents, self.n_lidar_rays
        origins = _check(origins, (b, n, 2), "origins")
        out = np.empty((b, n, m))
        if self._lidar_compiled:
            no_discs = np.empty((0, 2))
            for e in range(b):
                discs = np.ascontiguousarray(self._views[e][0][:n, :2]) if self.lidar_sees_agents else no_discs
                cast_lidar(
                    MJU_RAY_GEOM,
                    origins[e],
                    self.config.flight_altitude,
                    self._ray_directions,
                    self.lidar_range,
                    *self._ray_arrays[e],
                    self._ray_candidates,
                    self._ray_candidate_body,
                    self._ray_candidate_reach,
                    self._ray_caster_body,
                    self.obstacles[e],
                    self.obstacle_radius,
                    discs,
                    self.uav_radius,
                    out[e],
                )
            return out
        self._multiray(origins, out)
        out[out < 0] = self.lidar_range  # no hit within the cutoff
        np.minimum(out, self.lidar_range, out=out)
        inside = _inside_any(origins, self.obstacles, self.obstacle_radius)
        if self.lidar_sees_agents:
            pos = self.agent_pos
            gap = origins[:, :, None, :] - pos[:, None, :, :]
            within = (gap * gap).sum(-1) <= self.uav_radius**2
            within[:, np.arange(n), np.arange(n)] = False
            inside |= within.any(-1)
        out[inside] = 0.0
        return out

    def _multiray(self, origins: np.ndarray, out: np.ndarray) -> None:
        """The beams' nearest hits (-1: none) from `mj_multiRay`, drone by drone: the reference the compiled
        LiDAR equals bit for bit, and its fallback when mju_rayGeom's address is not found."""
        pnt, geomid, vec, group, cutoff = (
            self._ray_pnt,
            self._ray_geomid,
            self._ray_vec,
            self._ray_group,
            self.lidar_range,
        )
        pnt[2] = self.config.flight_altitude
        for e in range(self.n_envs):
            model, data = self.models[e], self.datas[e]
            for i in range(self.n_agents):
                pnt[0] = origins[e, i, 0]
                pnt[1] = origins[e, i, 1]
                mujoco.mj_multiRay(
                    model,
                    data,
                    pnt,
                    vec,
                    group,
                    1,
                    self._drone_body_list[i],
                    geomid,
                    out[e, i],
                    None,
                    self.n_lidar_rays,
                    cutoff,
                )

    def collisions(self) -> np.ndarray:
        """[B, N] bool: UAV touched an obstacle or another UAV during the last decision step."""
        return self._collided.copy()

    # ------------------------------------------------------------------ read-only extras (visualisation, tests)
    @property
    def drone_positions(self) -> np.ndarray:
        """[B, D, 3] positions of all drones (UAVs first, then the adversary)."""
        return np.stack([v[0][:, :3] for v in self._views])

    @property
    def drone_quaternions(self) -> np.ndarray:
        """[B, D, 4] attitudes [w, x, y, z] (body -> world)."""
        return np.stack([v[0][:, 3:7] for v in self._views])

    @property
    def drone_velocities(self) -> np.ndarray:
        """[B, D, 3] linear velocities (m/s)."""
        return np.stack([v[1][:, :3] for v in self._views])

    @property
    def motor_thrusts(self) -> np.ndarray:
        """[B, D, 4] rotor thrusts (N) applied at the last physics step, PX4 motor order."""
        return np.stack([self.cascade.motor_thrusts(e).copy() for e in range(self.n_envs)])

    @property
    def velocity_setpoints(self) -> np.ndarray:
        """[B, D, 2] the offboard interface's horizontal velocity setpoints (m/s; offboard = "velocity")."""
        return np.stack([self.cascade.velocity_setpoints(e).copy() for e in range(self.n_envs)])

    @property
    def motor_speeds(self) -> np.ndarray:
        """[B, D, 4] rotor speeds (rad/s)."""
        return np.stack([self.cascade.motor_speeds(e).copy() for e in range(self.n_envs)])

    @property
    def drag_forces(self) -> np.ndarray:
        """[B, D, 6] rotor-drag force (N) and torque (N m) about the centre of mass, world frame, last physics step."""
        return np.stack([self.cascade.drag_wrenches(e).copy() for e in range(self.n_envs)])

    @property
    def wind_vector(self) -> np.ndarray:
        """[B, 3] current wind velocity (m/s)."""
        return self.wind.vector.copy()

    @property
    def sim_time(self) -> np.ndarray:
        """[B] simulated seconds since each env's reset."""
        return self._tick * self.config.physics_dt

    def tilt_deg(self) -> np.ndarray:
        """[B, D] tilt of each drone's body z axis from vertical (deg)."""
        q = self.drone_quaternions
        upright = 1.0 - 2.0 * (q[..., 1] ** 2 + q[..., 2] ** 2)
        return np.degrees(np.arccos(np.clip(upright, -1.0, 1.0)))

    def reseed(self, seed) -> None:
        """Seed the world's own draws (wind) afresh, e.g. per training iteration, so that a resumed
        run replays them; `seed` is anything numpy's default_rng takes."""
        self.rng = np.random.default_rng(seed)
        self.wind.rng = self.rng

    # ------------------------------------------------------------------ internals
    def _diverged(self, env: int, drone: int) -> None:
        qpos, qvel = self._views[env][0][drone], self._views[env][1][drone]
        who = f"uav {drone}" if drone < self.n_agents else "adversary"
        t = self._tick[env] * self.config.physics_dt
        if not (np.isfinite(qpos).all() and np.isfinite(qvel).all()):
            raise SimulationDiverged(f"env {env}: {who} state became NaN/inf at t = {t:.3f} s")
        tilt = self.tilt_deg()[env, drone]
        raise SimulationDiverged(
            f"env {env}: {who} flipped (tilt {tilt:.0f} deg > {self.config.flip_tilt_deg:g}) at t = {t:.3f} s"
        )


def _check(array, shape: tuple[int, ...], name: str) -> np.ndarray:
    """As float64 (bool for masks) with the exact shape and finite values, else ConfigError."""
    arr = np.asarray(array)
    if arr.shape != shape:
        raise ConfigError(f"{name} must have shape {list(shape)}, got {list(arr.shape)}")
    if arr.dtype != bool:
        arr = arr.astype(np.float64, copy=False)
        if not np.isfinite(arr).all():
            raise ConfigError(f"{name} contains NaN or inf")
    return arr


def _inside_any(origins: np.ndarray, centres: np.ndarray, radius: float) -> np.ndarray:
    """[B, N] origin lies inside (or on) one of the circles centres [B, K, 2]."""
    if centres.shape[1] == 0:
        return np.zeros(origins.shape[:2], dtype=bool)
    gap = origins[:, :, None, :] - centres[:, None, :, :]
    return ((gap * gap).sum(-1) <= radius * radius).any(-1)


def make_mujoco_world(
    task: TaskConfig,
    n_envs: int = 1,
    wind: float | WindConfig = 0.0,
    seed: int | None = None,
    config: MujocoWorldConfig | None = None,
    airframe: str | Path | None = None,
    wind_direction: float | None = None,
) -> MujocoWorld:
    """The MuJoCo world for a task: its counts, radii, speed limits and LiDAR, plus a wind of mean
    speed `wind` (m/s, Gazebo wind-plugin semantics; 0 for calm air) blowing towards
    `wind_direction` (degrees, ENU: 0 = +x, 90 = +y; None = drawn uniformly per episode from the seed),
    or a whole WindConfig (then without wind_direction).
    `airframe` (a shipped name or an MJCF path) replaces config.airframe; its gains are found as for
    MujocoWorldConfig.params = None.
    The footprint disc is the task's uav_radius whatever the airframe (docs/airframes.md)."""
    for name in ("response_time", "velocity_noise"):  # the quadrotor has its own lag and tracking error
        if getattr(task, name):
            raise ConfigError(
                f"{name}={getattr(task, name)}: a particle-world setting; the MuJoCo world must keep it 0"
            )
    if wind_direction is not None and not wind:
        raise ConfigError(f"wind_direction={wind_direction!r}: there is no wind to point (wind = 0)")
    if isinstance(wind, WindConfig):
        if wind_direction is not None:
            raise ConfigError("wind_direction: give the direction inside the WindConfig")
        wind_config = None if wind.calm else wind
    else:
        direction = wind_config_direction(wind_direction)
        wind_config = WindConfig(mean_speed=float(wind), direction=direction) if wind else None
    config = config or MujocoWorldConfig()
    if airframe is not None:
        config = dataclasses.replace(config, airframe=str(airframe))
    return MujocoWorld(
        config,
        n_envs=n_envs,
        n_agents=task.n_agents,
        n_obstacles=task.n_obstacles,
        n_lidar_rays=task.n_lidar_rays,
        lidar_range=task.lidar_range,
        lidar_sees_agents=task.lidar_sees_agents,
        uav_radius=task.uav_radius,
        obstacle_radius=task.obstacle_radius,
        speed_max=task.speed_max,
        adversary_speed_max=task.adversary_speed_max,
        accel_max=task.accel_max,
        wind=wind_config,
        with_adversary=task.mode == "cefc" and task.adversary != "none",
        seed=0 if seed is None else seed,
    )
