"""MAVLink offboard link: testbed drones that an offboard script written for PX4 SITL can fly unchanged.

    python -m cefc_mj.deploy.mavlink_link --drones 2 --real-time-factor 1

Each drone of a MuJoCo world (the same world, cascade and offboard interface SITL-M flies) is a
MAVLink 2 vehicle (common dialect) on its own UDP port and system id, as PX4 SITL presents itself to
an offboard companion: drone i binds `--port` + i (default 14580 + i) and sends to `--remote-port` + i
(default 14540 + i, PX4's offboard API port), system id `--sysid` + i. A script that listens with
`mavutil.mavlink_connection("udpin:127.0.0.1:14540")` (or sends to the vehicle's port with `udpout:`)
talks to it as to PX4.

- Sends HEARTBEAT (1 Hz: MAV_TYPE_QUADROTOR, MAV_AUTOPILOT_PX4, base_mode with SAFETY_ARMED when
  armed, custom_mode PX4's main/sub mode), LOCAL_POSITION_NED and ATTITUDE (`--telemetry-hz`, 50 Hz
  of simulated time), COMMAND_ACK and STATUSTEXT.
- Accepts SET_POSITION_TARGET_LOCAL_NED (`VehicleLink._setpoint`) in MAV_FRAME_LOCAL_NED,
  MAV_FRAME_LOCAL_OFFSET_NED, MAV_FRAME_BODY_NED and MAV_FRAME_BODY_OFFSET_NED. The type mask picks
  the horizontal setpoint, first of: a position (x, y in use; PX4's position mask 0b110111111000 =
  3576), flown by PX4's position loop, velocity = MPC_XY_P * (target - position) plus the velocity
  fields as feed-forward when they are in use too, limited to the speed limit; an acceleration (afx,
  afy: MAVROS' acceleration offboard); a velocity (vx, vy). z, vz, afz, yaw and yaw rate are not
  flown (the testbed holds its altitude and heading): a z more than ALTITUDE_TOLERANCE_M from the
  held altitude, or a vz, afz, yaw or yaw rate that asks for a change, draws a STATUSTEXT warning, as
  do horizontal fields in use beside the flown ones. A setpoint that cannot be flown (another frame,
  a force, x without y, no horizontal field, a non-finite value) is refused at once with a
  STATUSTEXT warning naming the cause; while only refused setpoints arrive, OFFBOARD (and arming in
  it) is answered MAV_RESULT_DENIED with that cause. Warnings are rate-limited per cause
  (STATUSTEXT_REPEAT_S).
- Accepts COMMAND_LONG MAV_CMD_COMPONENT_ARM_DISARM and MAV_CMD_DO_SET_MODE (and the SET_MODE
  message) for PX4's OFFBOARD (main mode 6) and AUTO.LOITER (hold, main 4 / sub 3). As in PX4,
  OFFBOARD is refused (TEMPORARILY_REJECTED) unless setpoints are streaming, and a vehicle in OFFBOARD
  that gets no setpoint for COM_OF_LOSS_T (`OFFBOARD_LOSS_TIMEOUT_S`, SITL-M's failsafe) switches to
  hold. Everything else is ignored and counted by reason (a bad frame, an unknown message id, an
  unsupported message, a setpoint for another system, ...); an unsupported command gets
  MAV_RESULT_UNSUPPORTED and a warning, and so do messages a script would fly with
  (`FLIGHT_MESSAGES`, e.g. SET_ATTITUDE_TARGET).

Frames: the testbed's world frame is ENU (x east, y north, z up; body FLU); MAVLink's local frame is
NED (x north, y east, z down; body FRD). Position (x, y, z)_NED = (y, x, -z)_ENU relative to a local
origin on the ground (z = 0) below the drone's spawn point (PX4's home; `--origin world` uses the
world's origin instead), velocity and acceleration alike, roll_NED = roll_ENU,
pitch_NED = -pitch_ENU, yaw_NED = pi/2 - yaw_ENU. Setpoint frames are converted to the local NED
frame at receipt: LOCAL_NED as is; LOCAL_OFFSET_NED positions relative to the vehicle's position then
(NED axes); BODY_NED and BODY_OFFSET_NED (the same here) positions relative to the vehicle and every
vector in axes turned by its yaw (x forward, y right), as PX4 turns BODY_NED velocities.

Flying: the vehicle's setpoint goes to the MuJoCo offboard interface exactly as an agent's action
does in SITL-M, at the 0.01 s control tick (`cefc_mj.deploy.tick_world`): an acceleration setpoint is
clipped per axis to the task's accel_max and integrated into the interface's velocity setpoint
(speed limit speed_max); a velocity setpoint (and the position loop's, evaluated at every tick) is
reached by the acceleration that drives the interface's velocity setpoint to it within the same
limit, and hold is that with zero velocity
(`TickedWorld.brake_accel`, SITL-M's failsafe). While disarmed or in hold the drone holds. The
testbed has no ground phase: the drones are spawned hovering at the flight altitude.

Simulated time advances at `--real-time-factor` times the wall clock (default 1: an external script
paces itself on the wall clock); telemetry rates and the offboard-loss timeout are in simulated time.
docs/sitl_m.md ("MAVLink offboard link") has the message table and an example script.
"""

from __future__ import annotations

import argparse
import collections
import functools
import math
import signal
import socket
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from cefc_mj.deploy.sim_server import OFFBOARD_LOSS_TIMEOUT_S, offboard_lost
from cefc_mj.errors import ConfigError, ExamplesHelpFormatter, OneLineParser, help_epilog

EXIT_USAGE = 2
EXIT_DIVERGED = 1
DEFAULT_VEHICLE_PORT = 14580
"""PX4 SITL's local port of its onboard (offboard API) MAVLink instance; drone i binds this + i."""
DEFAULT_OFFBOARD_PORT = 14540
"""PX4 SITL's offboard API port (the companion listens here); drone i sends to this + i."""
CONTROL_TICK_S = 0.01
"""The control tick at which setpoints take effect (SITL-M's tick on MuJoCo: one position-loop period)."""
HEARTBEAT_PERIOD_S = 1.0
MAX_DATAGRAMS_PER_TICK = 1000
"""A flood cannot stall the simulation: the rest waits in the socket for the next tick."""

# PX4's custom modes (px4_custom_mode.h): custom_mode = main << 16 | sub << 24
PX4_MAIN_MODE_AUTO = 4
PX4_SUB_MODE_AUTO_LOITER = 3
PX4_MAIN_MODE_OFFBOARD = 6
MODE_HOLD = (PX4_MAIN_MODE_AUTO, PX4_SUB_MODE_AUTO_LOITER)
MODE_OFFBOARD = (PX4_MAIN_MODE_OFFBOARD, 0)
MODE_NAMES = {MODE_HOLD: "AUTO.LOITER", MODE_OFFBOARD: "OFFBOARD"}
ORIGINS = ("spawn", "world")

MPC_XY_P = 0.95
"""Horizontal position gain (1/s), PX4's MPC_XY_P at its default (0.95): a position setpoint is flown
as the velocity setpoint MPC_XY_P * (position setpoint - position), plus the message's velocity
feed-forward, limited to the horizontal speed limit (PX4's MPC_XY_VEL_MAX; here the task's
speed_max). The controller parameter files (controllers/*.params) have no MPC_XY_P: the testbed's
cascade starts at the velocity loop, so the gain of the link's position loop lives here."""
ALTITUDE_TOLERANCE_M = 0.25
"""A position setpoint's z that differs from the held altitude by more than this draws a warning (it
is ignored either way): five times the altitude loop's error in flight (< 0.05 m), so a script that
sends back the z it reads in LOCAL_POSITION_NED never trips it, and half of the smallest altitude
change a script would mean (PX4's default take-off altitude is 2.5 m, the testbed flies at 2 m)."""
IGNORED_FIELD_TOLERANCES = {"vz": 0.1, "afz": 0.5, "yaw": 0.1, "yaw_rate": 0.05}
"""Vertical and heading fields in use are ignored (fixed altitude, held heading); beyond these
magnitudes (m/s, m/s^2, rad from the current heading, rad/s) a warning says so."""
STATUSTEXT_REPEAT_S = 10.0
"""A warning for the same cause (a refused frame, an ignored field, ...) is sent at most once per this
many simulated seconds, however often the cause recurs (each occurrence is counted)."""
FLIGHT_MESSAGES = (
    "SET_POSITION_TARGET_GLOBAL_INT",
    "SET_ATTITUDE_TARGET",
    "SET_ACTUATOR_CONTROL_TARGET",
    "MANUAL_CONTROL",
    "COMMAND_INT",
)
"""Messages a script may fly with that the link does not handle: ignored with a warning, not silently."""


def _mavlink():
    """The MAVLink 2 common dialect (pymavlink, the `mavlink` extra), imported on first use."""
    try:
        from pymavlink.dialects.v20 import common
    except ImportError:
        raise ConfigError("the MAVLink link needs pymavlink: pip install 'cefc-mj[mavlink]'") from None
    return common


# ====================================================================== configuration
@dataclass(frozen=True)
class MavlinkLinkConfig:
    """The vehicles, their UDP endpoints and the simulation they fly in (validated by `validate`)."""

    n_drones: int = 1
    """How many testbed drones (MAVLink vehicles) to serve."""
    system_id: int = 1
    """MAVLink system id of drone 0; drone i has system_id + i (PX4 multi-vehicle SITL's numbering)."""
    bind_host: str = "127.0.0.1"
    """Address the vehicles' UDP sockets bind (0.0.0.0 to accept scripts on other machines)."""
    ports: tuple[int, ...] = (DEFAULT_VEHICLE_PORT,)
    """The vehicles' local UDP ports: one value P gives drone i P + i (0: any free port each), or
    one value per drone."""
    remote_host: str = "127.0.0.1"
    """Where the offboard scripts listen."""
    remote_ports: tuple[int, ...] = (DEFAULT_OFFBOARD_PORT,)
    """The scripts' UDP ports, one base (drone i sends to P + i) or one per drone. A vehicle also
    answers whoever last sent it a valid MAVLink frame (a script connected with udpout:)."""
    real_time_factor: float = 1.0
    """Simulated seconds per wall second (1: real time, as an offboard script expects)."""
    offboard_loss_timeout_s: float = OFFBOARD_LOSS_TIMEOUT_S
    """PX4's COM_OF_LOSS_T: simulated seconds without a setpoint before a vehicle in OFFBOARD holds."""
    telemetry_hz: float = 50.0
    """LOCAL_POSITION_NED and ATTITUDE rate (per simulated second; must divide the 100 Hz control tick)."""
    duration_s: float | None = None
    """Stop after this many simulated seconds; None: run until SIGINT/SIGTERM."""
    spacing: float = 2.0
    """Drone i spawns at (i * spacing, 0) in the world frame (m, ENU), hovering at the flight altitude."""
    origin: str = "spawn"
    """Local NED origin: "spawn" (on the ground below each drone's spawn point, as PX4's home) or
    "world" (the world's origin, shared by all drones)."""
    airframe: str | None = None
    """A shipped airframe name ("iris", "crazyflie") or an MJCF path; None: the world's default."""
    wind: float = 0.0
    """Mean wind speed (m/s; 0: calm air)."""
    speed_max: float | None = None
    """Horizontal speed limit of the offboard interface (m/s); None: the task's (1 m/s)."""
    accel_max: float | None = None
    """Per-axis acceleration setpoint limit (m/s^2); None: the task's (2 m/s^2)."""
    seed: int = 0
    """Seeds the wind."""

    def validate(self) -> None:
        """ConfigError naming the first bad field (host names are resolved here)."""
        n = self.n_drones
        if not isinstance(n, int) or isinstance(n, bool) or not 1 <= n <= 64:
            raise ConfigError(f"n_drones={n!r}: must be an integer in 1..64")
        if not isinstance(self.system_id, int) or not 1 <= self.system_id <= 256 - n:
            raise ConfigError(
                f"system_id={self.system_id!r}: must be in 1..{256 - n} (drone i has system id + i <= 255)"
            )
        for name, low in (("ports", 0), ("remote_ports", 1)):
            ports = getattr(self, name)
            if not isinstance(ports, tuple) or len(ports) not in (1, n):
                raise ConfigError(f"{name}={ports!r}: give one base port or one port per drone ({n})")
            values = self._expand(ports)
            if any(not isinstance(p, int) or isinstance(p, bool) or not low <= p <= 65535 for p in values):
                raise ConfigError(f"{name}={ports!r}: every drone's port must be in {low}..65535")
            used = [p for p in values if p]
            if len(set(used)) != len(used):
                raise ConfigError(f"{name}={ports!r}: two drones would share a port")
        for name in ("real_time_factor", "offboard_loss_timeout_s", "telemetry_hz", "spacing"):
            value = getattr(self, name)
            if not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
                raise ConfigError(f"{name}={value!r}: must be a finite number > 0")
        ticks = 1.0 / (CONTROL_TICK_S * self.telemetry_hz)
        if self.telemetry_hz > 1.0 / CONTROL_TICK_S or abs(ticks - round(ticks)) > 1e-9:
            raise ConfigError(
                f"telemetry_hz={self.telemetry_hz!r}: must divide the control rate "
                f"{1.0 / CONTROL_TICK_S:g} Hz (e.g. 50, 25, 10)"
            )
        if self.duration_s is not None and not (
            isinstance(self.duration_s, (int, float)) and math.isfinite(self.duration_s) and self.duration_s > 0
        ):
            raise ConfigError(f"duration_s={self.duration_s!r}: must be a finite number > 0 (or None: no limit)")
        if self.origin not in ORIGINS:
            raise ConfigError(f"origin={self.origin!r}: must be one of {', '.join(ORIGINS)}")
        if not isinstance(self.wind, (int, float)) or not math.isfinite(self.wind) or self.wind < 0:
            raise ConfigError(f"wind={self.wind!r}: must be a finite number >= 0 (mean speed, m/s)")
        for name in ("bind_host", "remote_host"):
            resolve(getattr(self, name), name)
        self.task_config()  # speed_max, accel_max
        if self.airframe is not None:
            from cefc_mj.control.airframe import load_airframe

            load_airframe(self.airframe)

    def _expand(self, ports: tuple[int, ...]) -> list[int]:
        if len(ports) == self.n_drones:
            return list(ports)
        return [ports[0] + i if ports[0] else 0 for i in range(self.n_drones)]

    def vehicle_ports(self) -> list[int]:
        """Drone i's local UDP port (0: any free one)."""
        return self._expand(self.ports)

    def offboard_ports(self) -> list[int]:
        """The UDP port drone i sends to."""
        return self._expand(self.remote_ports)

    def task_config(self):
        """The TaskConfig of the world: n_drones UAVs, no obstacles, no adversary (validated)."""
        from cefc_mj.task.config import TaskConfig

        limits = {k: v for k, v in (("speed_max", self.speed_max), ("accel_max", self.accel_max)) if v is not None}
        try:
            task = TaskConfig(n_agents=self.n_drones, mode="formation", obstacle_density=0.0, **limits)
            task.validate()
        except (TypeError, ValueError) as e:
            raise ConfigError(str(e).splitlines()[0]) from None
        return task


def resolve(host: str, name: str = "host") -> str:
    """The IPv4 address of `host` (ConfigError if it has none)."""
    if not isinstance(host, str) or not host:
        raise ConfigError(f"{name}={host!r}: not a host name or IPv4 address")
    try:
        return socket.getaddrinfo(host, None, socket.AF_INET, socket.SOCK_DGRAM)[0][4][0]
    except (socket.gaierror, UnicodeError) as e:
        raise ConfigError(f"{name}={host!r}: cannot resolve it ({e})") from None


def bind_udp(host: str, port: int) -> socket.socket:
    """A non-blocking UDP socket bound to (host, port); ConfigError if the address cannot be bound."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        sock.bind((resolve(host), port))
    except OSError as e:
        sock.close()
        raise ConfigError(f"cannot bind UDP {host}:{port}: {e.strerror or e}") from None
    sock.setblocking(False)
    return sock


# ====================================================================== frames
def enu_to_ned(v: np.ndarray) -> np.ndarray:
    """[..., 3] ENU (x east, y north, z up) -> NED (x north, y east, z down); positions, velocities."""
    return np.stack([v[..., 1], v[..., 0], -v[..., 2]], axis=-1)


def ned_to_enu_xy(north: float, east: float) -> np.ndarray:
    """A horizontal NED vector (north, east) in the world's ENU x-y (east, north)."""
    return np.array([east, north], dtype=np.float64)


def rotate_yaw(yaw: float, x: float, y: float) -> np.ndarray:
    """A horizontal vector given in axes turned by `yaw` (NED heading, rad, from north toward east:
    x forward, y right, as PX4's MAV_FRAME_BODY_NED) in the local (north, east) axes."""
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([c * x - s * y, s * x + c * y])


def constrain_xy(v0: np.ndarray, v1: np.ndarray, v_max: float) -> np.ndarray:
    """v0 + v1 limited to norm v_max, v0 first (PX4's ControlMath::constrainXY): v0 is the position
    loop's demand, v1 the velocity feed-forward, which only fills what the limit leaves."""
    total = v0 + v1
    if np.hypot(*total) <= v_max:
        return total
    n0 = float(np.hypot(*v0))
    if n0 >= v_max:
        return v0 * (v_max / n0)
    n1 = float(np.hypot(*v1))
    if n0 < 1e-6:
        return v1 * (v_max / n1)
    u1 = v1 / n1  # v0 + s u1 on the circle |v| = v_max, s >= 0
    m = float(u1 @ v0)
    return v0 + u1 * (-m + math.sqrt(m * m - (n0 * n0 - v_max * v_max)))


_ENU_TO_NED = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
_FLU_TO_FRD = np.diag([1.0, -1.0, -1.0])


def attitude_ned(quat_wxyz: np.ndarray) -> tuple[float, float, float]:
    """(roll, pitch, yaw) of the FRD body in NED (rad, ZYX Euler angles, as PX4's ATTITUDE) from the
    MuJoCo quaternion [w, x, y, z] of the FLU body in ENU."""
    w, x, y, z = (float(c) for c in quat_wxyz)
    r_enu_flu = np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )
    r = _ENU_TO_NED @ r_enu_flu @ _FLU_TO_FRD
    roll = math.atan2(r[2, 1], r[2, 2])
    pitch = -math.asin(max(-1.0, min(1.0, r[2, 0])))
    yaw = math.atan2(r[1, 0], r[0, 0])
    return roll, pitch, yaw


# ====================================================================== one vehicle
SETPOINT_FRAMES = {1: "LOCAL_NED", 7: "LOCAL_OFFSET_NED", 8: "BODY_NED", 9: "BODY_OFFSET_NED"}
"""The MAV_FRAME values a SET_POSITION_TARGET_LOCAL_NED may use (module docstring, "Frames")."""
TYPE_MASK_BITS = {
    "x": 1,
    "y": 2,
    "z": 4,
    "vx": 8,
    "vy": 16,
    "vz": 32,
    "afx": 64,
    "afy": 128,
    "afz": 256,
    "yaw": 1024,
    "yaw_rate": 2048,
}
"""POSITION_TARGET_TYPEMASK: a set bit means the field is ignored. Bit 512 (FORCE_SET) is not a field:
it says afx, afy, afz are a force."""
TYPE_MASK_FORCE_SET = 512


class _UdpWriter:
    """The file pymavlink writes a vehicle's frames to: every destination of the vehicle."""

    def __init__(self, link: VehicleLink):
        self.link = link

    def write(self, data: bytes) -> None:
        for peer in self.link.destinations():
            try:
                self.link.sock.sendto(data, peer)
            except OSError:  # no route, buffer full: telemetry is best effort, as over real UDP
                self.link.send_errors += 1


class VehicleLink:
    """One drone's MAVLink endpoint: its UDP socket, PX4's arming and mode logic, the setpoint it flies.

    `poll(t)` reads and handles every datagram waiting in the socket; `command(t)` then says what the
    drone flies at simulated time t: ("accel", a) or ("velocity", v) with a horizontal ENU vector (a
    position setpoint becomes the velocity of the position loop, `MPC_XY_P`), or None (hold).
    `send_heartbeat` and `send_telemetry` write to the configured script address and to whoever last
    sent a valid frame. Nothing a peer sends can raise: what is not acted on is counted in `ignored`
    by reason, and a setpoint that cannot be flown is refused with a STATUSTEXT warning at once.

    `state`, set by the simulation, returns the drone's position in the local NED frame and its NED
    yaw (the vehicle's estimate, which position setpoints and the offset and body frames need; None:
    no estimate, such setpoints are refused); `speed_max` is the horizontal speed limit.
    """

    def __init__(
        self,
        uav: int,
        system_id: int,
        sock: socket.socket,
        remote: tuple[str, int],
        offboard_loss_timeout_s: float = OFFBOARD_LOSS_TIMEOUT_S,
        log: Callable[[str], None] | None = None,
        verbose: bool = False,
        state: Callable[[], tuple[np.ndarray, float]] | None = None,
        speed_max: float = math.inf,
    ):
        self.mavlink = _mavlink()
        self.uav, self.system_id, self.sock = uav, system_id, sock
        self.remote = (resolve(remote[0]), int(remote[1]))
        self.last_peer: tuple[str, int] | None = None
        self.offboard_loss_timeout_s = offboard_loss_timeout_s
        self.log = log or (lambda text: None)
        self.verbose = verbose
        self.mav = self.mavlink.MAVLink(
            _UdpWriter(self), srcSystem=system_id, srcComponent=self.mavlink.MAV_COMP_ID_AUTOPILOT1
        )
        self.parser = self._new_parser()
        self.armed = False
        self.mode = MODE_HOLD
        self.state = state
        self.speed_max = speed_max
        self.setpoint_kind: str | None = None
        """"accel", "velocity" or "position" once a setpoint has arrived."""
        self.setpoint = np.zeros(2)
        """The newest setpoint, horizontal ENU (m/s^2 or m/s; "position": the velocity feed-forward)."""
        self.position_target = np.zeros(2)
        """"position": the target (north, east) in the local NED frame (m)."""
        self.last_setpoint_t = -math.inf
        self.last_refusal: tuple[float, str] = (-math.inf, "")
        """(simulated time, cause) of the newest setpoint refused."""
        self.warned: dict[str, float] = {}
        """Warning cause -> simulated time of its last STATUSTEXT (`STATUSTEXT_REPEAT_S`)."""
        self.warnings: collections.Counter = collections.Counter()
        """Setpoint fields in use but not flown, by cause, counted every time (announced by `_warn`)."""
        self.t = 0.0
        self.handled: collections.Counter = collections.Counter()
        """Messages acted on, by type."""
        self.ignored: collections.Counter = collections.Counter()
        """Datagrams or messages not acted on, by reason."""
        self.events: list[dict] = []
        self.send_errors = 0

    def _new_parser(self):
        parser = self.mavlink.MAVLink(None)
        parser.robust_parsing = True  # bad bytes come back as MAVLink_bad_data instead of raising
        return parser

    def destinations(self) -> list[tuple[str, int]]:
        if self.last_peer is None or self.last_peer == self.remote:
            return [self.remote]
        return [self.remote, self.last_peer]

    def event(self, name: str, detail: str) -> None:
        self.events.append({"t": round(self.t, 6), "sysid": self.system_id, "event": name, "detail": detail})
        self.log(f"t={self.t:.2f} s uav {self.uav} (sysid {self.system_id}): {name}: {detail}")

    def _ignore(self, reason: str) -> None:
        self.ignored[reason] += 1
        if self.verbose:
            self.log(f"t={self.t:.2f} s uav {self.uav}: ignored ({reason})")

    def _warn(self, cause: str, text: str) -> None:
        """STATUSTEXT `text` (severity WARNING) and a logged event, at most once per STATUSTEXT_REPEAT_S
        of simulated time for the same `cause`."""
        last = self.warned.get(cause)
        if last is not None and self.t - last < STATUSTEXT_REPEAT_S:
            return
        self.warned[cause] = self.t
        self.status_text(text, self.mavlink.MAV_SEVERITY_WARNING)
        self.event("warning", text)

    def _field_ignored(self, cause: str, text: str) -> None:
        """A setpoint is flown but a field of it in use is not: counted in `warnings`, announced (`_warn`)."""
        self.warnings[cause] += 1
        self._warn(f"ignored: {cause}", text)

    def _refuse(self, cause: str) -> bool:
        """Refuse the setpoint being handled for `cause`: counted, remembered (an OFFBOARD request that
        fails for want of a stream names it) and announced (`_warn`). Returns False (not acted on)."""
        self._ignore(f"setpoint refused: {cause}")
        self.last_refusal = (self.t, cause)
        self._warn(f"refused: {cause}", f"Setpoint refused: {cause}")
        return False

    def _recent_refusal(self) -> str | None:
        """Why the newest setpoints were refused, if one was within the offboard-loss timeout."""
        t, text = self.last_refusal
        return text if not offboard_lost(self.t, t, self.offboard_loss_timeout_s) else None

    # ------------------------------------------------------------------ state
    @property
    def streaming(self) -> bool:
        """Setpoints are arriving: one within the offboard-loss timeout (PX4's offboard signal)."""
        return not offboard_lost(self.t, self.last_setpoint_t, self.offboard_loss_timeout_s)

    @property
    def custom_mode(self) -> int:
        return self.mode[0] << 16 | self.mode[1] << 24

    @property
    def base_mode(self) -> int:
        m = self.mavlink
        flags = (
            m.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
            | m.MAV_MODE_FLAG_AUTO_ENABLED
            | m.MAV_MODE_FLAG_GUIDED_ENABLED
            | m.MAV_MODE_FLAG_STABILIZE_ENABLED
        )  # PX4's flags for its AUTO and OFFBOARD modes
        return flags | (m.MAV_MODE_FLAG_SAFETY_ARMED if self.armed else 0)

    def command(self, t: float) -> tuple[str, np.ndarray] | None:
        """What the drone flies at simulated time t (see the class docstring); switches an OFFBOARD
        vehicle whose setpoints stopped to hold first (PX4's offboard-loss failsafe)."""
        self.t = t
        if self.mode == MODE_OFFBOARD and not self.streaming:
            self.mode = MODE_HOLD
            self.event("offboard_loss_hold", f"no setpoint for {self.offboard_loss_timeout_s:g} s: AUTO.LOITER (hold)")
            self.status_text("Failsafe: offboard signal lost, holding", self.mavlink.MAV_SEVERITY_WARNING)
        if not (self.armed and self.mode == MODE_OFFBOARD and self.setpoint_kind is not None):
            return None
        if self.setpoint_kind == "position":
            if self.state is None:  # cannot happen: position setpoints are refused without an estimate
                return None
            position, _ = self.state()
            demand = ned_to_enu_xy(*(MPC_XY_P * (self.position_target - np.asarray(position)[:2])))
            return "velocity", constrain_xy(demand, self.setpoint, self.speed_max)
        return self.setpoint_kind, self.setpoint

    # ------------------------------------------------------------------ receiving
    def poll(self, t: float) -> int:
        """Handle every datagram waiting (at most MAX_DATAGRAMS_PER_TICK); returns how many were read."""
        self.t = t
        count = 0
        while count < MAX_DATAGRAMS_PER_TICK:
            try:
                data, peer = self.sock.recvfrom(65535)
            except (BlockingIOError, InterruptedError):
                break
            except OSError:  # e.g. an ICMP error reported on the socket: try again next tick
                self._ignore("socket error")
                break
            count += 1
            self.handle_datagram(data, peer)
        return count

    def handle_datagram(self, data: bytes, peer: tuple[str, int]) -> None:
        """Parse one datagram (each is parsed on its own: a broken one cannot spoil the next) and
        handle every message in it."""
        m = self.mavlink
        try:
            messages = self.parser.parse_buffer(data) or []
        except Exception:  # noqa: BLE001 (pymavlink raises on some malformed input even when parsing robustly)
            messages, self.parser = [None], self._new_parser()
        if self.parser.buf_len() > 0:  # a truncated frame at the end of the datagram
            self._ignore("truncated frame")
            self.parser = self._new_parser()
        if any(msg is None or isinstance(msg, m.MAVLink_bad_data) for msg in messages):
            self._ignore("bad data (framing or CRC)")  # once per datagram, however many pieces
        for message in messages:
            if message is not None and not isinstance(message, m.MAVLink_bad_data):
                self._handle(message, peer)

    def _handle(self, message, peer: tuple[str, int]) -> None:
        m = self.mavlink
        if isinstance(message, m.MAVLink_unknown) or message.get_type().startswith("UNKNOWN"):
            self._ignore("unknown message id")
            return
        self.last_peer = peer  # like PX4, answer whoever talks to us
        kind = message.get_type()
        handler = {
            "HEARTBEAT": None,
            "SET_POSITION_TARGET_LOCAL_NED": self._setpoint,
            "COMMAND_LONG": self._command_long,
            "SET_MODE": self._set_mode_message,
        }.get(kind, False)
        if handler is False:
            self._ignore(f"unsupported message {kind}")
            if kind in FLIGHT_MESSAGES and getattr(message, "target_system", 0) in (0, self.system_id):
                self._warn(f"message {kind}", f"{kind} unsupported")
            return
        if handler is not None and getattr(message, "target_system", 0) not in (0, self.system_id):
            self._ignore("addressed to another system")
            return
        if handler is not None and getattr(message, "target_component", 0) not in (0, self.mav.srcComponent):
            self._ignore("addressed to another component")
            return
        if handler is not None and not handler(message):
            return
        self.handled[kind] += 1

    def _setpoint(self, msg) -> bool:
        """SET_POSITION_TARGET_LOCAL_NED: the horizontal position, acceleration or velocity setpoint it
        carries (in that order of precedence) becomes the vehicle's setpoint, converted from its frame
        to the local NED frame at receipt as PX4 does; what cannot be flown is refused, fields in use
        that the testbed ignores (altitude, heading, ...) draw a warning. See the module docstring."""
        m = self.mavlink
        frame = msg.coordinate_frame
        if frame not in SETPOINT_FRAMES:
            entry = m.enums["MAV_FRAME"].get(frame)
            name = entry.name.removeprefix("MAV_FRAME_") if entry is not None else "unknown"
            return self._refuse(f"frame {frame} unsupported ({name})")
        mask = msg.type_mask
        used = {field: not mask & bit for field, bit in TYPE_MASK_BITS.items()}
        if mask & TYPE_MASK_FORCE_SET and (used["afx"] or used["afy"] or used["afz"]):  # as PX4
            return self._refuse("force setpoints unsupported")
        pairs = {"position": ("x", "y"), "accel": ("afx", "afy"), "velocity": ("vx", "vy")}
        kind = next((k for k in ("position", "accel", "velocity") if used[pairs[k][0]] and used[pairs[k][1]]), None)
        if kind is None:
            half = next(((a, b) if used[a] else (b, a) for a, b in pairs.values() if used[a] or used[b]), None)
            return self._refuse(f"{half[0]} without {half[1]}" if half else "no x/y, vx/vy or afx/afy in use")
        if not (math.isfinite(getattr(msg, pairs[kind][0])) and math.isfinite(getattr(msg, pairs[kind][1]))):
            return self._refuse("non-finite value")
        body = frame in (m.MAV_FRAME_BODY_NED, m.MAV_FRAME_BODY_OFFSET_NED)
        if self.state is None and (kind == "position" or frame != m.MAV_FRAME_LOCAL_NED):
            return self._refuse("no position estimate")
        position, yaw = self.state() if self.state is not None else (None, None)

        def horizontal(a: str, b: str) -> np.ndarray:  # (north, east) of a field pair, at receipt
            xy = (getattr(msg, a), getattr(msg, b))
            return rotate_yaw(yaw, *xy) if body else np.array(xy, dtype=np.float64)

        flown = {kind}
        if kind == "position":
            target = horizontal("x", "y")
            if frame != m.MAV_FRAME_LOCAL_NED:  # offset and body frames: relative to the vehicle, now
                target = target + np.asarray(position)[:2]
            feed_forward = np.zeros(2)
            if used["vx"] and used["vy"] and math.isfinite(msg.vx) and math.isfinite(msg.vy):
                feed_forward, flown = horizontal("vx", "vy"), {"position", "velocity"}  # PX4's feed-forward
            self.setpoint_kind, self.position_target, self.setpoint = kind, target, ned_to_enu_xy(*feed_forward)
        else:
            self.setpoint_kind, self.setpoint = kind, ned_to_enu_xy(*horizontal(*pairs[kind]))
        for other, fields in pairs.items():  # horizontal fields in use that are not flown
            names = "/".join(f for f in fields if used[f])
            if other not in flown and names:
                self._field_ignored(f"{other} with {kind}", f"{names} ignored: {kind} setpoint flown")
        self._check_ignored_fields(msg, used, frame, position, yaw)
        self.last_setpoint_t = self.t
        return True

    def _check_ignored_fields(self, msg, used: dict, frame: int, position, yaw) -> None:
        """Warn about vertical and heading fields in use that the testbed cannot follow (it holds its
        altitude and heading): z beyond ALTITUDE_TOLERANCE_M of the held altitude, vz, afz, yaw and yaw
        rate beyond IGNORED_FIELD_TOLERANCES. Needs the vehicle's estimate (`state`) for z and yaw."""
        tol = IGNORED_FIELD_TOLERANCES
        if used["z"] and position is not None:
            held = float(position[2])
            z = msg.z + (held if frame != self.mavlink.MAV_FRAME_LOCAL_NED else 0.0)
            if abs(z - held) > ALTITUDE_TOLERANCE_M:
                self._field_ignored("z", f"z={z:.2f} ignored: altitude held at z={held:.2f}")
        if used["vz"] and abs(msg.vz) > tol["vz"]:
            self._field_ignored("vz", "vz ignored: the altitude is held")
        if used["afz"] and abs(msg.afz) > tol["afz"]:
            self._field_ignored("afz", "afz ignored: the altitude is held")
        if used["yaw"] and yaw is not None and abs(math.remainder(msg.yaw - yaw, math.tau)) > tol["yaw"]:
            self._field_ignored("yaw", f"yaw ignored: heading held at {math.degrees(yaw):.0f} deg")
        if used["yaw_rate"] and abs(msg.yaw_rate) > tol["yaw_rate"]:
            self._field_ignored("yaw_rate", "yaw rate ignored: the heading is held")

    def _command_long(self, msg) -> bool:
        m = self.mavlink
        if msg.command == m.MAV_CMD_COMPONENT_ARM_DISARM:
            result = self._arm(msg.param1)
        elif msg.command == m.MAV_CMD_DO_SET_MODE:
            result = self._set_mode(msg.param1, msg.param2, msg.param3)
        else:
            self._ignore(f"unsupported command {msg.command}")
            entry = m.enums["MAV_CMD"].get(msg.command)
            name = entry.name.removeprefix("MAV_CMD_") if entry is not None else "unknown"
            self._warn(f"command {msg.command}", f"Command {msg.command} unsupported ({name})")
            self._ack(msg, m.MAV_RESULT_UNSUPPORTED)
            return False
        self._ack(msg, result)
        return True

    def _set_mode_message(self, msg) -> bool:
        """SET_MODE (MAVROS' set_mode): answered with a COMMAND_ACK for MAV_CMD_DO_SET_MODE, as PX4 does."""
        main, sub = (msg.custom_mode >> 16) & 0xFF, (msg.custom_mode >> 24) & 0xFF
        result = self._set_mode(msg.base_mode, main, sub)
        self.mav.command_ack_send(
            self.mavlink.MAV_CMD_DO_SET_MODE, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent()
        )
        return True

    def _ack(self, msg, result: int) -> None:
        self.mav.command_ack_send(msg.command, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent())

    def _arm(self, param1: float) -> int:
        m = self.mavlink
        action = round(param1) if math.isfinite(param1) else -1
        if action not in (0, 1) or abs(param1 - action) > 1e-3:
            self.status_text(f"Unsupported ARM_DISARM param: {param1:.3f}", m.MAV_SEVERITY_CRITICAL)
            return m.MAV_RESULT_DENIED
        if action == 1 and self.mode == MODE_OFFBOARD and not self.streaming:
            refusal = self._recent_refusal()
            if refusal is not None:  # setpoints arrive but cannot be flown: retrying will not help
                self.status_text(f"Arming denied: {refusal}", m.MAV_SEVERITY_WARNING)
                return m.MAV_RESULT_DENIED
            self.status_text("Arming denied: no offboard setpoints", m.MAV_SEVERITY_CRITICAL)
            return m.MAV_RESULT_TEMPORARILY_REJECTED
        if bool(action) != self.armed:
            self.armed = bool(action)
            self.event("armed" if self.armed else "disarmed", "by command")
        return m.MAV_RESULT_ACCEPTED

    def _set_mode(self, base_mode: float, main: float, sub: float) -> int:
        m = self.mavlink
        if not math.isfinite(base_mode) or not int(base_mode) & m.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
            return m.MAV_RESULT_UNSUPPORTED  # only PX4's custom modes are flown
        main, sub = int(main) if math.isfinite(main) else -1, int(sub) if math.isfinite(sub) else -1
        if main == PX4_MAIN_MODE_OFFBOARD:
            wanted = MODE_OFFBOARD
        elif (main, sub) == MODE_HOLD:
            wanted = MODE_HOLD
        else:
            self.status_text(
                f"Unsupported mode {main}/{sub}: the testbed flies OFFBOARD and AUTO.LOITER", m.MAV_SEVERITY_WARNING
            )
            return m.MAV_RESULT_UNSUPPORTED
        if wanted == MODE_OFFBOARD and not self.streaming:  # PX4: stream setpoints before switching
            refusal = self._recent_refusal()
            if refusal is not None:  # setpoints arrive but cannot be flown: retrying will not help
                self.status_text(f"OFFBOARD denied: {refusal}", m.MAV_SEVERITY_WARNING)
                return m.MAV_RESULT_DENIED
            self.status_text("Switching to OFFBOARD denied: no setpoint stream", m.MAV_SEVERITY_CRITICAL)
            return m.MAV_RESULT_TEMPORARILY_REJECTED
        if wanted != self.mode:
            self.mode = wanted
            self.event("mode", MODE_NAMES[wanted])
        return m.MAV_RESULT_ACCEPTED

    # ------------------------------------------------------------------ sending
    def status_text(self, text: str, severity: int) -> None:
        """One STATUSTEXT (50 characters): a name in parentheses at the end that would not fit is dropped
        (e.g. a long frame or command name: its number stays), the rest cut at 50."""
        if len(text) > 50 and text.endswith(")") and " (" in text:
            text = text[: text.rindex(" (")]
        self.mav.statustext_send(severity, text[:50].encode())

    def send_heartbeat(self) -> None:
        m = self.mavlink
        self.mav.heartbeat_send(
            m.MAV_TYPE_QUADROTOR,
            m.MAV_AUTOPILOT_PX4,
            self.base_mode,
            self.custom_mode,
            m.MAV_STATE_ACTIVE if self.armed else m.MAV_STATE_STANDBY,
        )

    def send_telemetry(
        self,
        t: float,
        position_ned: np.ndarray,
        velocity_ned: np.ndarray,
        attitude: tuple[float, float, float],
        rates_frd: np.ndarray,
    ) -> None:
        """LOCAL_POSITION_NED and ATTITUDE at simulated time t (time_boot_ms = simulated ms)."""
        boot_ms = round(t * 1e3) & 0xFFFFFFFF
        x, y, z = (float(c) for c in position_ned)
        vx, vy, vz = (float(c) for c in velocity_ned)
        self.mav.local_position_ned_send(boot_ms, x, y, z, vx, vy, vz)
        self.mav.attitude_send(boot_ms, *attitude, *(float(c) for c in rates_frd))

    def close(self) -> None:
        self.sock.close()


# ====================================================================== the simulation
@dataclass
class LinkReport:
    """What a run of the link did: simulated and wall time, and each vehicle's counters and events."""

    sim_s: float
    wall_s: float
    vehicles: list[dict]
    overruns: int
    """How often the simulation fell more than OVERRUN_S behind the wall clock (and stopped catching up)."""

    def summary(self) -> str:
        rate = self.sim_s / max(self.wall_s, 1e-9)
        lines = [f"{self.sim_s:.1f} s simulated in {self.wall_s:.1f} s wall ({rate:.2f}x), {self.overruns} overruns"]
        for v in self.vehicles:
            ignored = ", ".join(f"{k}: {n}" for k, n in sorted(v["ignored"].items())) or "none"
            warned = ", ".join(f"{k}: {n}" for k, n in sorted(v.get("warnings", {}).items()))
            lines.append(
                f"uav {v['uav']} (sysid {v['system_id']}): handled {sum(v['handled'].values())}, "
                f"ignored {sum(v['ignored'].values())} ({ignored})" + (f"; warnings ({warned})" if warned else "")
            )
        return "\n".join(lines)


OVERRUN_S = 0.25
"""Wall seconds the simulation may lag its real-time schedule before it re-anchors the schedule
instead of racing to catch up (a burst of simulated time would look like a time jump to a script)."""


class MavlinkLink:
    """The MuJoCo world and one `VehicleLink` per drone (module docstring). `run()` flies until
    `duration_s` or until `stop()` says so; the sockets are bound in the constructor (ConfigError if
    a port is taken), so a caller learns of a bad address before the world is built."""

    def __init__(self, config: MavlinkLinkConfig, log: Callable[[str], None] | None = None, verbose: bool = False):
        config.validate()
        self.config = config
        self.log = log or (lambda text: None)
        self.vehicles: list[VehicleLink] = []
        try:
            remote_ports = config.offboard_ports()
            for i, port in enumerate(config.vehicle_ports()):
                sock = bind_udp(config.bind_host, port)
                self.vehicles.append(
                    VehicleLink(
                        i,
                        config.system_id + i,
                        sock,
                        (config.remote_host, remote_ports[i]),
                        config.offboard_loss_timeout_s,
                        self.log,
                        verbose,
                    )
                )
        except BaseException:
            self.close()
            raise
        self.world = None

    def endpoints(self) -> list[str]:
        """One line per drone: its system id, its bound address and where it sends."""
        return [
            f"uav {v.uav}: sysid {v.system_id}, udp {v.sock.getsockname()[0]}:{v.sock.getsockname()[1]} "
            f"-> {v.remote[0]}:{v.remote[1]}"
            for v in self.vehicles
        ]

    def build_world(self) -> None:
        """The ticked MuJoCo world with the drones hovering at their spawn points."""
        from cefc_mj.deploy.tick_world import make_ticked_world

        config = self.config
        task = config.task_config()
        self.world = make_ticked_world(
            "mujoco", task, CONTROL_TICK_S, wind=config.wind, seed=config.seed, airframe=config.airframe
        )
        n = config.n_drones
        self.spawn = np.stack([np.arange(n) * config.spacing, np.zeros(n)], axis=1)
        reset = (np.ones(1, dtype=bool), self.spawn[None], np.zeros((1, 2)), np.zeros((1, 0, 2)))
        self.world.reset(*reset)
        self.world.step(np.zeros((1, n, 2)), np.zeros((1, 2)))  # warm-up (compiled kernels load), then start afresh
        self.world.reset(*reset)
        origin_enu = np.zeros((n, 3))
        if config.origin == "spawn":
            origin_enu[:, :2] = self.spawn
        self.origin_ned = enu_to_ned(origin_enu)
        self.accel_max = task.accel_max
        for i, v in enumerate(self.vehicles):  # the estimate position setpoints and body frames use
            v.state = functools.partial(self._vehicle_state, i)
            v.speed_max = task.speed_max

    def _vehicle_state(self, i: int) -> tuple[np.ndarray, float]:
        """Drone i's position in its local NED frame (m) and its NED yaw (rad), now."""
        world = self.world
        position = enu_to_ned(world.drone_positions[0, i]) - self.origin_ned[i]
        return position, attitude_ned(world.drone_quaternions[0, i])[2]

    def _setpoints(self, t: float) -> np.ndarray:
        """[1, N, 2] the acceleration setpoints every drone flies in the control tick at time t."""
        world = self.world
        # -v_sp / tick: the unclipped acceleration that zeroes each interface's velocity setpoint in one tick
        to_zero = world.brake_accel(math.inf)[0]
        accel = np.empty((len(self.vehicles), 2))
        for i, v in enumerate(self.vehicles):
            command = v.command(t)
            if command is None:  # hold: SITL-M's failsafe brake
                accel[i] = np.clip(to_zero[i], -self.accel_max, self.accel_max)
            elif command[0] == "accel":
                accel[i] = command[1]  # the world clips it per axis
            else:
                accel[i] = np.clip(to_zero[i] + command[1] / world.tick_s, -self.accel_max, self.accel_max)
        return accel[None]

    def _telemetry(self, t: float) -> None:
        world = self.world
        n = len(self.vehicles)
        position = enu_to_ned(world.drone_positions[0, :n]) - self.origin_ned
        velocity = enu_to_ned(world.drone_velocities[0, :n])
        quats = world.drone_quaternions[0, :n]
        omega = world.inner.datas[0].qvel.reshape(-1, 6)[:n, 3:6]  # free joint: body-frame (FLU) rates
        for i, v in enumerate(self.vehicles):
            v.send_telemetry(t, position[i], velocity[i], attitude_ned(quats[i]), omega[i] * (1.0, -1.0, -1.0))

    def run(self, stop: Callable[[], bool] = lambda: False) -> LinkReport:
        """Fly until `duration_s` of simulated time or until `stop()` is true (checked every 0.1 s
        of simulated time). Raises SimulationDiverged if a drone flips."""
        if self.world is None:
            self.build_world()
        config, world = self.config, self.world
        n_ticks, tick_s = world.n_ticks, world.tick_s
        telemetry_every = round(1.0 / (config.telemetry_hz * tick_s))
        heartbeat_every = round(HEARTBEAT_PERIOD_S / tick_s)
        clock = {"wall0": time.perf_counter(), "overruns": 0, "step": 0}
        rtf = config.real_time_factor

        def controller(j: int) -> np.ndarray:
            index = clock["step"] * n_ticks + j
            t = index * tick_s
            lag = clock["wall0"] + t / rtf - time.perf_counter()
            if lag > 0:
                time.sleep(lag)
            elif lag < -OVERRUN_S:  # behind schedule: carry on from here rather than race
                clock["wall0"] -= lag
                clock["overruns"] += 1
            for v in self.vehicles:
                v.poll(t)
            if index % heartbeat_every == 0:
                for v in self.vehicles:
                    v.send_heartbeat()
            if index % telemetry_every == 0:
                self._telemetry(t)
            return self._setpoints(t)

        world.controller = controller
        start = time.perf_counter()
        zeros, no_adversary = np.zeros((1, config.n_drones, 2)), np.zeros((1, 2))
        try:
            while not stop():
                if config.duration_s is not None and clock["step"] * world.dt >= config.duration_s - 1e-9:
                    break
                world.step(zeros, no_adversary)  # n_ticks control ticks, each through controller()
                clock["step"] += 1
        finally:
            world.controller = None
        return LinkReport(
            sim_s=clock["step"] * world.dt,
            wall_s=time.perf_counter() - start,
            overruns=clock["overruns"],
            vehicles=[
                {
                    "uav": v.uav,
                    "system_id": v.system_id,
                    "handled": dict(v.handled),
                    "ignored": dict(v.ignored),
                    "warnings": dict(v.warnings),
                    "events": list(v.events),
                }
                for v in self.vehicles
            ],
        )

    def close(self) -> None:
        for v in self.vehicles:
            v.close()


# ====================================================================== command line
_Parser = OneLineParser


def build_parser() -> argparse.ArgumentParser:
    d = MavlinkLinkConfig()
    p = _Parser(
        prog="cefc-mavlink",
        description="Serve testbed drones as MAVLink 2 vehicles (PX4 SITL's offboard interface over UDP): "
        "HEARTBEAT, LOCAL_POSITION_NED and ATTITUDE out; position, velocity or "
        "acceleration SET_POSITION_TARGET_LOCAL_NED, ARM_DISARM and DO_SET_MODE "
        "(OFFBOARD) in. A script written for PX4's offboard API (pymavlink, MAVSDK) listens on UDP port "
        "14540 (udpin:127.0.0.1:14540), as it would for PX4 SITL. Needs the mavlink extra: "
        "pip install -e '.[mavlink]'.",
        formatter_class=ExamplesHelpFormatter,
        epilog=help_epilog(
            [
                "cefc-mavlink                     # one drone: UDP 127.0.0.1:14580 -> 127.0.0.1:14540, until Ctrl-C",
                "cefc-mavlink --drones 3 --real-time-factor 2 --duration 120   # 3 drones, 2x real time, 120 sim. s",
                "cefc-mavlink --bind 0.0.0.0 --remote-host 192.168.1.20 --wind 5   # a script on another machine",
            ],
            "docs/sitl_m.md (SITL-M and MAVLink, with a short pymavlink script)",
        ),
    )
    p.add_argument("--drones", type=int, default=d.n_drones, metavar="N", help="how many drones (default 1)")
    p.add_argument(
        "--sysid",
        type=int,
        default=d.system_id,
        metavar="ID",
        help="MAVLink system id of drone 0; drone i has ID + i (default 1)",
    )
    p.add_argument(
        "--bind",
        default=d.bind_host,
        metavar="HOST",
        help="address the vehicles' UDP sockets bind (default 127.0.0.1; 0.0.0.0 for other machines)",
    )
    p.add_argument(
        "--port",
        type=int,
        nargs="+",
        default=list(d.ports),
        metavar="PORT",
        help=f"the vehicles' local UDP ports: one base (drone i binds PORT + i; 0: any free port) "
        f"or one per drone (default {DEFAULT_VEHICLE_PORT})",
    )
    p.add_argument(
        "--remote-host",
        default=d.remote_host,
        metavar="HOST",
        help="where the offboard scripts listen (default 127.0.0.1)",
    )
    p.add_argument(
        "--remote-port",
        type=int,
        nargs="+",
        default=list(d.remote_ports),
        metavar="PORT",
        help=f"the scripts' UDP ports: one base (drone i sends to PORT + i) or one per drone "
        f"(default {DEFAULT_OFFBOARD_PORT}, PX4's offboard API port)",
    )
    p.add_argument(
        "--real-time-factor",
        type=float,
        default=d.real_time_factor,
        metavar="X",
        help="simulated seconds per wall second (default 1: real time)",
    )
    p.add_argument(
        "--offboard-loss-timeout",
        type=float,
        default=d.offboard_loss_timeout_s,
        metavar="S",
        help=f"COM_OF_LOSS_T: simulated seconds without a setpoint before an OFFBOARD vehicle holds "
        f"(default {d.offboard_loss_timeout_s:g})",
    )
    p.add_argument(
        "--telemetry-hz",
        type=float,
        default=d.telemetry_hz,
        metavar="HZ",
        help="LOCAL_POSITION_NED and ATTITUDE rate, per simulated second (default 50; divides 100)",
    )
    p.add_argument(
        "--duration",
        type=float,
        metavar="S",
        help="stop after S simulated seconds (default: run until Ctrl-C or SIGTERM)",
    )
    p.add_argument(
        "--spacing",
        type=float,
        default=d.spacing,
        metavar="M",
        help="drone i spawns at (i * M, 0) m in the world frame (ENU), hovering (default 2)",
    )
    p.add_argument(
        "--origin",
        choices=ORIGINS,
        default=d.origin,
        help="local NED origin: below each drone's spawn point (PX4's home; default) or the world's origin",
    )
    p.add_argument("--airframe", metavar="NAME|PATH", help="airframe: iris (default), crazyflie or an MJCF path")
    p.add_argument("--wind", type=float, default=d.wind, metavar="M/S", help="mean wind speed (default 0)")
    p.add_argument("--speed-max", type=float, metavar="M/S", help="horizontal speed limit (default: the task's, 1)")
    p.add_argument(
        "--accel-max", type=float, metavar="M/S2", help="per-axis acceleration limit (default: the task's, 2)"
    )
    p.add_argument("--seed", type=int, default=d.seed, help="seeds the wind (default 0)")
    p.add_argument("--verbose", action="store_true", help="log every ignored message to stderr")
    return p


FLAGS = {
    "n_drones": "--drones",
    "system_id": "--sysid",
    "bind_host": "--bind",
    "ports": "--port",
    "remote_host": "--remote-host",
    "remote_ports": "--remote-port",
    "real_time_factor": "--real-time-factor",
    "offboard_loss_timeout_s": "--offboard-loss-timeout",
    "telemetry_hz": "--telemetry-hz",
    "duration_s": "--duration",
    "spacing": "--spacing",
    "origin": "--origin",
    "wind": "--wind",
    "speed_max": "--speed-max",
    "accel_max": "--accel-max",
}
"""Config field -> the flag that sets it (error messages name the flag)."""


def _flag_message(error: ConfigError) -> str:
    text = str(error)
    field = text.split("=", 1)[0]
    return FLAGS[field] + text[len(field) :] if field in FLAGS else text


def config_from_args(args) -> MavlinkLinkConfig:
    return MavlinkLinkConfig(
        n_drones=args.drones,
        system_id=args.sysid,
        bind_host=args.bind,
        ports=tuple(args.port),
        remote_host=args.remote_host,
        remote_ports=tuple(args.remote_port),
        real_time_factor=args.real_time_factor,
        offboard_loss_timeout_s=args.offboard_loss_timeout,
        telemetry_hz=args.telemetry_hz,
        duration_s=args.duration,
        spacing=args.spacing,
        origin=args.origin,
        airframe=args.airframe,
        wind=args.wind,
        speed_max=args.speed_max,
        accel_max=args.accel_max,
        seed=args.seed,
    )


def main(argv: list[str] | None = None) -> int:
    """`cefc-mavlink` / `python -m cefc_mj.deploy.mavlink_link`: returns the exit code."""
    from cefc_mj.errors import SimulationDiverged

    parser = build_parser()
    args = parser.parse_args(argv)

    def log(text: str) -> None:
        print(f"{parser.prog}: {text}", file=sys.stderr, flush=True)

    try:
        link = MavlinkLink(config_from_args(args), log=log, verbose=args.verbose)
    except ConfigError as e:
        print(f"{parser.prog}: error: {_flag_message(e)}", file=sys.stderr)
        return EXIT_USAGE
    stopping = []

    def request_stop(signum, frame) -> None:
        stopping.append(signum)

    previous = {sig: signal.signal(sig, request_stop) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        try:
            link.build_world()
        except ConfigError as e:  # e.g. an airframe whose gains do not fit it
            print(f"{parser.prog}: error: {e}", file=sys.stderr)
            return EXIT_USAGE
        for line in link.endpoints():
            log(line)
        log(
            f"flying at {args.real_time_factor:g}x real time"
            + (f" for {args.duration:g} s" if args.duration else "; Ctrl-C or SIGTERM stops")
        )
        try:
            report = link.run(stop=lambda: bool(stopping))
        except SimulationDiverged as e:
            log(f"the simulation diverged: {e}")
            return EXIT_DIVERGED
        log(report.summary().replace("\n", f"\n{parser.prog}: "))
        return 0
    finally:
        link.close()
        for sig, handler in previous.items():
            signal.signal(sig, handler)


if __name__ == "__main__":
    sys.exit(main())
