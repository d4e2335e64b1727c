"""MAVLink offboard link (cefc_mj.deploy.mavlink_link; docs/sitl_m.md "MAVLink offboard link").

The flight tests start the vehicle endpoint as a real process serving two drones on free localhost
ports and fly them with plain pymavlink "offboard scripts" written as for PX4 SITL: wait for the
heartbeat, stream setpoints (acceleration from a P-controller on LOCAL_POSITION_NED, velocity, or
position in the local, offset and body frames), switch to OFFBOARD, arm. Each flight test starts
from wherever the previous one left its drone, so any subset runs in any order. The process is
always terminated and no process outlives the module (psutil).
"""

import math
import os
import signal
import socket
import subprocess
import sys
import time

import numpy as np
import psutil
import pytest
from pymavlink import mavutil
from pymavlink.dialects.v20 import common as mavlink

from cefc_mj.deploy.mavlink_link import (
    MODE_HOLD,
    MODE_OFFBOARD,
    MPC_XY_P,
    OFFBOARD_LOSS_TIMEOUT_S,
    STATUSTEXT_REPEAT_S,
    TYPE_MASK_BITS,
    TYPE_MASK_FORCE_SET,
    MavlinkLink,
    MavlinkLinkConfig,
    VehicleLink,
    attitude_ned,
    bind_udp,
    constrain_xy,
    enu_to_ned,
    rotate_yaw,
)
from cefc_mj.errors import ConfigError

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
REAL_TIME_FACTOR = 3.0
"""Simulated seconds per wall second in the flight tests (the scripts pace themselves on the telemetry)."""
FLIGHT_ALTITUDE = 2.0  # the world's fixed altitude: z = -2 in the local NED frame
# MAVROS' acceleration offboard: position, velocity and yaw ignored; afx, afy, afz in use
ACCEL_MASK = (
    mavlink.POSITION_TARGET_TYPEMASK_X_IGNORE
    | mavlink.POSITION_TARGET_TYPEMASK_Y_IGNORE
    | mavlink.POSITION_TARGET_TYPEMASK_Z_IGNORE
    | mavlink.POSITION_TARGET_TYPEMASK_VX_IGNORE
    | mavlink.POSITION_TARGET_TYPEMASK_VY_IGNORE
    | mavlink.POSITION_TARGET_TYPEMASK_VZ_IGNORE
    | mavlink.POSITION_TARGET_TYPEMASK_YAW_IGNORE
    | mavlink.POSITION_TARGET_TYPEMASK_YAW_RATE_IGNORE
)
VELOCITY_MASK = 0b110111000111  # PX4 docs' velocity mask: vx, vy, vz in use
POSITION_MASK = 0b110111111000  # PX4's position mask (3576): x, y, z in use, velocity, acceleration, yaw ignored
SETPOINT_HZ = 5.0  # position setpoints stream at 5 Hz of simulated time (PX4 needs more than 2 Hz)


def _gone(pid: int) -> bool:
    try:
        return psutil.Process(pid).status() == psutil.STATUS_ZOMBIE
    except psutil.NoSuchProcess:
        return True


# ====================================================================== an offboard script, as for PX4
class OffboardScript:
    """A PX4 user's offboard loop over one pymavlink connection: every LOCAL_POSITION_NED updates the
    state and, while `controller` is set, answers with an acceleration setpoint (so the stream runs at
    the telemetry rate); acks, status texts and heartbeats are kept."""

    def __init__(self, conn):
        while conn.recv_match(blocking=False) is not None:  # the script starts now: drop what queued before
            pass
        self.conn = conn
        self.controller = None
        self.velocity = None  # or a fixed (north, east) velocity setpoint, streamed likewise
        self.stream = None  # or (pos, vel, yaw) -> (frame, type_mask, x, y, z, vx, vy, vz, afx, afy, afz, yaw, rate)
        self.stream_every = 1  # `stream` answers every n-th LOCAL_POSITION_NED
        self.n_positions = 0
        self.statustexts: list = []  # the STATUSTEXT messages themselves (severity, text)
        self.t = None  # time_boot_ms / 1000 of the newest LOCAL_POSITION_NED (simulated s)
        self.pos = self.vel = None
        self.track: list[tuple[float, float, float, float]] = []  # (t, x, y, z)
        self.acks: list = []
        self.texts: list[tuple[float, str]] = []
        self.attitude = None
        self.last_setpoint_t = None

    def pump(self, until, wall_timeout: float = 30.0) -> None:
        """Handle messages until `until()` is true; fails after `wall_timeout` wall seconds."""
        assert self.pump_until(until, wall_timeout), "timed out waiting on the vehicle"

    def pump_until(self, until, wall_timeout: float) -> bool:
        """Handle messages until `until()` is true (True) or `wall_timeout` wall seconds pass (False)."""
        deadline = time.monotonic() + wall_timeout
        while not until():
            if time.monotonic() >= deadline:
                return False
            msg = self.conn.recv_match(blocking=True, timeout=0.5)
            if msg is None:
                continue
            kind = msg.get_type()
            if kind == "LOCAL_POSITION_NED":
                self.t = msg.time_boot_ms / 1e3
                self.pos, self.vel = np.array([msg.x, msg.y, msg.z]), np.array([msg.vx, msg.vy, msg.vz])
                self.track.append((self.t, msg.x, msg.y, msg.z))
                self.n_positions += 1
                if self.stream is not None:
                    if self.n_positions % self.stream_every == 0:
                        yaw = self.attitude.yaw if self.attitude is not None else math.nan
                        self.conn.mav.set_position_target_local_ned_send(
                            msg.time_boot_ms,
                            self.conn.target_system,
                            self.conn.target_component,
                            *self.stream(self.pos, self.vel, yaw),
                        )
                        self.last_setpoint_t = self.t
                elif self.controller is not None:
                    accel = self.controller(self.pos, self.vel)
                    self.conn.mav.set_position_target_local_ned_send(
                        msg.time_boot_ms,
                        self.conn.target_system,
                        self.conn.target_component,
                        mavlink.MAV_FRAME_LOCAL_NED,
                        ACCEL_MASK,
                        0,
                        0,
                        0,
                        0,
                        0,
                        0,
                        accel[0],
                        accel[1],
                        0,
                        0,
                        0,
                    )
                    self.last_setpoint_t = self.t
                elif self.velocity is not None:
                    self.conn.mav.set_position_target_local_ned_send(
                        msg.time_boot_ms,
                        self.conn.target_system,
                        self.conn.target_component,
                        mavlink.MAV_FRAME_LOCAL_NED,
                        VELOCITY_MASK,
                        0,
                        0,
                        0,
                        *self.velocity,
                        0,
                        0,
                        0,
                        0,
                        0,
                        0,
                    )
                    self.last_setpoint_t = self.t
            elif kind == "COMMAND_ACK":
                self.acks.append(msg)
            elif kind == "STATUSTEXT":
                self.texts.append((self.t, msg.text))
                self.statustexts.append(msg)
            elif kind == "ATTITUDE":
                self.attitude = msg
        return True

    def run_for(self, seconds: float) -> None:
        """Pump for `seconds` of simulated time."""
        self.pump(lambda: self.t is not None)
        start = self.t
        self.pump(lambda: self.t >= start + seconds)

    def command(self, command: int, *params: float) -> int:
        """COMMAND_LONG to the vehicle; returns the result of its COMMAND_ACK (pumping meanwhile). As
        MAVLink's command protocol does, the command is sent again, with the confirmation field
        counting up, while no ACK came back: a UDP datagram (the command or its ACK) can be dropped
        when a loaded machine lets the socket buffer overflow with the vehicle's telemetry."""
        params = list(params) + [0.0] * (7 - len(params))
        self.acks = [a for a in self.acks if a.command != command]  # late ACKs of an earlier, resent call

        def acked():
            return any(a.command == command for a in self.acks)

        for confirmation in range(15):
            self.conn.mav.command_long_send(
                self.conn.target_system, self.conn.target_component, command, confirmation, *params
            )
            if self.pump_until(acked, wall_timeout=2.0):
                break
        assert acked(), "timed out waiting on the vehicle's COMMAND_ACK"
        ack = next(a for a in self.acks if a.command == command)
        self.acks.remove(ack)
        return ack.result

    def set_offboard(self) -> int:
        return self.command(mavlink.MAV_CMD_DO_SET_MODE, mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 6)  # PX4 OFFBOARD

    def arm(self) -> int:
        return self.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1)

    def wait_heartbeat_state(self, mode: str, armed: bool) -> None:
        """Pump until a heartbeat reports `mode` (pymavlink's PX4 mode name) and the armed state."""

        def state_ok():
            hb = self.conn.messages.get("HEARTBEAT")
            return hb is not None and self.conn.flightmode == mode and bool(self.conn.motors_armed()) == armed

        self.pump(state_ok)


def p_controller(goal_ne, kp: float = 1.0, kd: float = 1.8, limit: float = 2.0):
    """Acceleration (north, east) toward `goal_ne` from LOCAL_POSITION_NED: a PD law, clipped."""
    goal = np.asarray(goal_ne, dtype=float)

    def control(pos, vel):
        return np.clip(kp * (goal - pos[:2]) - kd * vel[:2], -limit, limit)

    return control


# ====================================================================== the vehicle process
@pytest.fixture(scope="module")
def vehicle(tmp_path_factory):
    """The endpoint serving two drones (sysid 1 and 2, spawned 2 m apart along world x = east) to two
    scripts listening on free ports (`udpin:`, as scripts listen for PX4 SITL on 14540), positions
    reported from the world's origin (so both frames' axes are checked); terminated afterwards."""
    conns = [mavutil.mavlink_connection("udpin:127.0.0.1:0") for _ in range(2)]
    ports = [str(c.port.getsockname()[1]) for c in conns]
    log = tmp_path_factory.mktemp("mavlink") / "vehicle.log"
    argv = [
        sys.executable,
        "-m",
        "cefc_mj.deploy.mavlink_link",
        "--drones",
        "2",
        "--port",
        "0",
        "--origin",
        "world",
        "--remote-port",
        *ports,
        "--real-time-factor",
        str(REAL_TIME_FACTOR),
        "--duration",
        "600",
    ]
    with open(log, "wb") as out:
        proc = subprocess.Popen(argv, cwd=REPO, stdin=subprocess.DEVNULL, stdout=out, stderr=out)
    try:
        yield {"proc": proc, "conns": conns, "log": log}
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
        try:
            code = proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            code = proc.wait()
        for c in conns:
            c.close()
        text = log.read_text(errors="replace")
        assert code == 0, text[-2000:]
        assert "simulated in" in text  # the summary it prints when stopped by SIGTERM
        assert _gone(proc.pid)
        assert [p.pid for p in psutil.Process().children(recursive=True)] == []


def test_offboard_script_flies_to_a_point_at_fixed_altitude(vehicle):
    script = OffboardScript(vehicle["conns"][0])
    hb = script.conn.wait_heartbeat(timeout=60)
    assert (hb.get_srcSystem(), hb.type, hb.autopilot) == (1, mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4)
    assert script.conn.flightmode == "LOITER" and not script.conn.motors_armed()
    script.run_for(0.2)
    start = script.pos.copy()
    assert np.allclose(start, [0.0, 0.0, -FLIGHT_ALTITUDE], atol=0.05)  # spawned at the world's origin, 2 m up
    assert abs(script.attitude.yaw - math.pi / 2) < 0.05  # spawned facing world +x (ENU east): NED yaw 90 deg

    # like PX4: OFFBOARD is refused until setpoints stream
    assert script.set_offboard() == mavlink.MAV_RESULT_TEMPORARILY_REJECTED
    goal = start[:2] + np.array([3.0, -2.0])  # 3 m north, 2 m west
    script.controller = p_controller(goal)
    script.run_for(0.3)
    assert script.set_offboard() == mavlink.MAV_RESULT_ACCEPTED
    assert script.arm() == mavlink.MAV_RESULT_ACCEPTED
    script.wait_heartbeat_state("OFFBOARD", armed=True)

    t_armed = script.t
    script.pump(
        lambda: (
            (np.linalg.norm(script.pos[:2] - goal) < 0.1 and np.linalg.norm(script.vel[:2]) < 0.05)
            or script.t > t_armed + 25.0
        )
    )
    track = np.array([row for row in script.track if row[0] >= t_armed])
    assert np.linalg.norm(script.pos[:2] - goal) < 0.1, f"ended at {script.pos} after {script.t - t_armed:.1f} s"
    assert script.t - t_armed < 15.0  # 3.6 m at the 1 m/s speed limit, then settling
    assert np.abs(track[:, 3] + FLIGHT_ALTITUDE).max() < 0.05  # the fixed altitude held all the way
    assert abs(script.attitude.roll) < 0.05 and abs(script.attitude.pitch) < 0.05  # level once arrived
    script.controller = None


def test_setpoint_loss_holds_position_after_the_timeout(vehicle):
    script = OffboardScript(vehicle["conns"][1])
    hb = script.conn.wait_heartbeat(timeout=60)
    assert hb.get_srcSystem() == 2  # the second drone: its own port and system id
    script.run_for(0.1)
    assert np.allclose(script.pos, [0.0, 2.0, -FLIGHT_ALTITUDE], atol=0.05)  # spawned 2 m along world x = east
    script.controller = p_controller(script.pos[:2] + np.array([0.0, 30.0]))  # far east: full speed
    script.run_for(0.3)
    assert script.set_offboard() == mavlink.MAV_RESULT_ACCEPTED
    assert script.arm() == mavlink.MAV_RESULT_ACCEPTED
    script.pump(lambda: script.vel[1] > 0.9)

    script.controller = None  # the script stops streaming
    t_stop, p_stop = script.last_setpoint_t, script.pos.copy()
    script.pump(lambda: script.texts)  # the vehicle announces the failsafe
    t_switch, text = script.texts[0]
    assert "offboard" in text.lower()
    assert OFFBOARD_LOSS_TIMEOUT_S - 0.05 <= t_switch - t_stop <= OFFBOARD_LOSS_TIMEOUT_S + 0.1
    p_switch = script.pos.copy()
    assert p_switch[1] - p_stop[1] > 0.7  # until the timeout it flew its last setpoint, as PX4 does
    script.wait_heartbeat_state("LOITER", armed=True)

    script.pump(lambda: script.t >= t_switch + 2.5)
    p_held = script.pos.copy()
    script.run_for(1.5)
    assert np.linalg.norm(script.pos - p_held) < 0.03, (p_held, script.pos)  # holding still
    assert np.linalg.norm(script.vel) < 0.05
    assert np.linalg.norm(script.pos[:2] - p_switch[:2]) < 1.0  # braked within the acceleration limit
    assert abs(script.pos[2] + FLIGHT_ALTITUDE) < 0.05

    # back to OFFBOARD only once setpoints stream again
    assert script.set_offboard() == mavlink.MAV_RESULT_TEMPORARILY_REJECTED
    script.controller = None
    script.velocity = (0.5, 0.0)  # velocity setpoints fly too: 0.5 m/s north
    script.run_for(0.2)
    assert script.set_offboard() == mavlink.MAV_RESULT_ACCEPTED
    script.run_for(2.0)
    assert np.allclose(script.vel, [0.5, 0.0, 0.0], atol=0.03)
    script.velocity = None


def _position_stream(frame: int, target):
    """A script's stream of position setpoints: `target(pos, yaw)` -> (x, y) in `frame`; z at the flight
    altitude (its offset 0 in the offset and body frames), velocity, acceleration and yaw ignored."""
    z = -FLIGHT_ALTITUDE if frame == mavlink.MAV_FRAME_LOCAL_NED else 0.0

    def stream(pos, vel, yaw):
        x, y = target(pos, yaw)
        return frame, POSITION_MASK, x, y, z, 0, 0, 0, 0, 0, 0, 0, 0

    return stream


def _fly_to(script, goal, frame: int, target, limit_s: float = 20.0) -> float:
    """Stream position setpoints (`_position_stream`) at SETPOINT_HZ, switch to OFFBOARD and arm (both
    must be accepted), fly until within 0.1 m of `goal` (north, east) and nearly at rest; returns the
    simulated seconds from the switch until first within 0.3 m. Asserts it got there in `limit_s`."""
    script.stream_every = round(50 / SETPOINT_HZ)  # 50 Hz of LOCAL_POSITION_NED
    script.stream = _position_stream(frame, target)
    script.run_for(0.5)  # two setpoints at least: the stream runs
    assert script.set_offboard() == mavlink.MAV_RESULT_ACCEPTED
    assert script.arm() == mavlink.MAV_RESULT_ACCEPTED
    script.wait_heartbeat_state("OFFBOARD", armed=True)
    t0, near = script.t, None

    def arrived():
        nonlocal near
        error = np.linalg.norm(script.pos[:2] - goal)
        if near is None and error < 0.3:
            near = script.t
        return (error < 0.1 and np.linalg.norm(script.vel[:2]) < 0.05) or script.t > t0 + limit_s

    script.pump(arrived)
    assert near is not None and np.linalg.norm(script.pos[:2] - goal) < 0.1, (
        f"at {script.pos} (goal {goal}) after {script.t - t0:.1f} s"
    )
    track = np.array([row for row in script.track if row[0] >= t0])
    assert np.abs(track[:, 3] + FLIGHT_ALTITUDE).max() < 0.05  # the altitude held all the way
    return near - t0


def test_position_setpoints_fly_to_the_target(vehicle):
    """PX4's most common offboard pattern: position setpoints (type mask 3576) in MAV_FRAME_LOCAL_NED at
    5 Hz; OFFBOARD is accepted and the drone flies to the target, at the speed limit, then settles."""
    script = OffboardScript(vehicle["conns"][0])
    script.conn.wait_heartbeat(timeout=60)
    script.run_for(0.2)
    start = script.pos.copy()
    goal = start[:2] + np.array([-3.0, 2.5])  # 3 m south, 2.5 m east: 3.9 m away
    near_s = _fly_to(script, goal, mavlink.MAV_FRAME_LOCAL_NED, lambda pos, yaw: goal)
    # 3.6 m to within 0.3 m at no more than the 1 m/s speed limit; PX4's P loop (0.95 /s) slows the last metre
    assert 3.6 < near_s < 7.0, near_s
    track = np.array(script.track)
    steps = np.diff(track, axis=0)
    speeds = np.linalg.norm(steps[:, 1:3], axis=1) / np.maximum(steps[:, 0], 1e-3)  # from time_boot_ms
    assert 0.9 < speeds.max() < 1.1  # at the speed limit, not beyond, for position setpoints too
    assert not script.statustexts, [m.text for m in script.statustexts]  # z = -2: the held altitude, no warning
    script.stream = None


def test_offset_and_body_frame_position_setpoints_are_relative_to_the_vehicle(vehicle):
    """MAV_FRAME_LOCAL_OFFSET_NED (offset from the vehicle, NED axes) then MAV_FRAME_BODY_NED (offset from
    the vehicle in axes turned by its yaw): the script sends each target relative to where the vehicle
    is; read in the wrong frame the drone would stop halfway (offset read as absolute) or circle (axes
    not turned: the drone faces east)."""
    script = OffboardScript(vehicle["conns"][1])
    script.conn.wait_heartbeat(timeout=60)
    script.run_for(0.2)
    start = script.pos.copy()
    assert abs(script.attitude.yaw - math.pi / 2) < 0.05  # facing east: body forward = east, right = south
    goal = start[:2] + np.array([2.0, 2.0])  # 2 m north, 2 m east
    _fly_to(script, goal, mavlink.MAV_FRAME_LOCAL_OFFSET_NED, lambda pos, yaw: goal - pos[:2])

    goal = goal + np.array([-2.5, 0.0])  # then 2.5 m south: to the right of a drone facing east

    def body_offset(pos, yaw):  # the NED offset in axes turned by the yaw (forward, right)
        north, east = goal - pos[:2]
        return math.cos(yaw) * north + math.sin(yaw) * east, -math.sin(yaw) * north + math.cos(yaw) * east

    assert np.allclose(body_offset(script.pos, script.attitude.yaw), [0.0, 2.5], atol=0.15)  # straight right
    _fly_to(script, goal, mavlink.MAV_FRAME_BODY_NED, body_offset)
    assert not script.statustexts, [m.text for m in script.statustexts]
    script.stream = None


def test_unsupported_frame_is_refused_at_once_with_a_statustext(vehicle):
    """A setpoint in a frame the link does not fly (MAV_FRAME_BODY_FRD) draws a STATUSTEXT warning naming
    it at once (one per cause, not one per setpoint); OFFBOARD is then DENIED, with the cause, and the
    drone does not move."""
    script = OffboardScript(vehicle["conns"][0])
    script.conn.wait_heartbeat(timeout=60)
    script.run_for(OFFBOARD_LOSS_TIMEOUT_S + 0.2)  # whatever the drone did before: no stream now
    p0 = script.pos.copy()
    script.stream_every = 10
    script.stream = lambda pos, vel, yaw: (mavlink.MAV_FRAME_BODY_FRD, POSITION_MASK, 2, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0)
    script.pump(lambda: script.last_setpoint_t is not None)
    t_sent = script.last_setpoint_t
    script.pump(lambda: script.statustexts or script.t > t_sent + 1.0)
    assert script.statustexts, "no STATUSTEXT for the refused setpoint"
    warning = script.statustexts[0]
    assert warning.severity == mavlink.MAV_SEVERITY_WARNING
    assert "frame 12" in warning.text and "BODY_FRD" in warning.text, warning.text
    assert script.texts[0][0] - t_sent <= 0.1  # at once: within the telemetry period and the transport
    script.run_for(1.0)  # five more refused setpoints: no new warning
    assert len(script.statustexts) == 1, [m.text for m in script.statustexts]
    assert script.set_offboard() == mavlink.MAV_RESULT_DENIED  # not "try later": the stream cannot be flown
    script.pump(lambda: len(script.statustexts) > 1)
    assert script.statustexts[1].text.startswith("OFFBOARD denied") and "frame 12" in script.statustexts[1].text
    assert np.linalg.norm(script.pos - p0) < 0.05 and script.conn.flightmode == "LOITER"
    script.stream = None


# ====================================================================== in-process: one VehicleLink
@pytest.fixture
def link_pair():
    """A VehicleLink on a free localhost port and the test's own UDP socket as its offboard script."""
    script = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    script.bind(("127.0.0.1", 0))
    script.settimeout(2.0)
    link = VehicleLink(0, 1, bind_udp("127.0.0.1", 0), script.getsockname(), offboard_loss_timeout_s=1.0)
    yield link, script
    link.close()
    script.close()


def _frames(sender, *messages) -> bytes:
    return b"".join(m.pack(sender) for m in messages)


def _deliver(link, script, data: bytes, t: float) -> None:
    script.sendto(data, link.sock.getsockname())
    deadline = time.monotonic() + 2.0
    while not link.poll(t):
        assert time.monotonic() < deadline, "datagram not received"
        time.sleep(0.001)


def _received(script, kind: str) -> list:
    """The messages of type `kind` among all the link sent the script since last asked (the rest dropped)."""
    parser = mavlink.MAVLink(None)
    out = []
    script.settimeout(0.2)
    try:
        while True:
            out += [m for m in parser.parse_buffer(script.recv(65535)) or [] if m.get_type() == kind]
    except TimeoutError:
        return out


def _acks(script) -> list:
    return _received(script, "COMMAND_ACK")


def test_malformed_unknown_and_unsupported_messages_are_ignored_and_counted(link_pair):
    link, script = link_pair
    gcs = mavlink.MAVLink(None, srcSystem=255, srcComponent=190)
    accel = mavlink.MAVLink_set_position_target_local_ned_message(
        0, 1, 1, mavlink.MAV_FRAME_LOCAL_NED, ACCEL_MASK, 0, 0, 0, 0, 0, 0, 1.0, 0.5, 0, 0, 0
    )
    good = accel.pack(gcs)
    bad_crc = bytearray(good)
    bad_crc[-1] ^= 0xFF
    unknown = bytearray(mavlink.MAVLink_heartbeat_message(6, 8, 0, 0, 0, 3).pack(gcs))
    unknown[7:10] = (42001).to_bytes(3, "little")  # a message id no dialect knows; the CRC cannot match it either
    cases = [
        (b"\x00garbage\xff" * 3, "bad data (framing or CRC)"),
        (bytes(bad_crc), "bad data (framing or CRC)"),
        (good[:-5], "truncated frame"),
        (_frames(gcs, mavlink.MAVLink_param_request_list_message(1, 1)), "unsupported message PARAM_REQUEST_LIST"),
        (
            _frames(
                gcs,
                mavlink.MAVLink_set_position_target_local_ned_message(
                    0, 1, 1, mavlink.MAV_FRAME_BODY_FRD, ACCEL_MASK, 0, 0, 0, 0, 0, 0, 1, 0, 0, 0, 0
                ),
            ),
            "setpoint refused: frame 12 unsupported (BODY_FRD)",
        ),
        (
            _frames(
                gcs,
                mavlink.MAVLink_set_position_target_local_ned_message(
                    0, 1, 1, mavlink.MAV_FRAME_LOCAL_NED, POSITION_MASK | 0b11, 5, 5, -2, 0, 0, 0, 0, 0, 0, 0, 0
                ),
            ),
            "setpoint refused: no x/y, vx/vy or afx/afy in use",
        ),  # altitude only
        (
            _frames(
                gcs,
                mavlink.MAVLink_set_position_target_local_ned_message(
                    0, 1, 1, mavlink.MAV_FRAME_LOCAL_NED, POSITION_MASK | 0b10, 5, 5, -2, 0, 0, 0, 0, 0, 0, 0, 0
                ),
            ),
            "setpoint refused: x without y",
        ),
        (
            _frames(
                gcs,
                mavlink.MAVLink_set_position_target_local_ned_message(
                    0,
                    1,
                    1,
                    mavlink.MAV_FRAME_LOCAL_NED,
                    ACCEL_MASK | TYPE_MASK_FORCE_SET,
                    0,
                    0,
                    0,
                    0,
                    0,
                    0,
                    1,
                    0,
                    0,
                    0,
                    0,
                ),
            ),
            "setpoint refused: force setpoints unsupported",
        ),
        (
            _frames(
                gcs,
                mavlink.MAVLink_set_position_target_local_ned_message(
                    0, 1, 1, mavlink.MAV_FRAME_LOCAL_NED, ACCEL_MASK, 0, 0, 0, 0, 0, 0, math.nan, 0, 0, 0, 0
                ),
            ),
            "setpoint refused: non-finite value",
        ),
        (
            _frames(
                gcs,
                mavlink.MAVLink_set_position_target_local_ned_message(
                    0, 1, 1, mavlink.MAV_FRAME_LOCAL_NED, POSITION_MASK, 5, 5, -2, 0, 0, 0, 0, 0, 0, 0, 0
                ),
            ),
            "setpoint refused: no position estimate",
        ),  # this VehicleLink flies no drone
        (
            _frames(
                gcs,
                mavlink.MAVLink_set_position_target_local_ned_message(
                    0, 7, 1, mavlink.MAV_FRAME_LOCAL_NED, ACCEL_MASK, 0, 0, 0, 0, 0, 0, 1, 0, 0, 0, 0
                ),
            ),
            "addressed to another system",
        ),
    ]
    for data, reason in cases:
        before = link.ignored[reason]
        _deliver(link, script, data, t=0.0)
        assert link.ignored[reason] == before + 1, (reason, dict(link.ignored))
    before = sum(link.ignored.values())
    _deliver(link, script, bytes(unknown), t=0.0)
    assert sum(link.ignored.values()) == before + 1  # an unknown id: dropped and counted (bad CRC or unknown)
    assert link.setpoint_kind is None and link.handled == {}  # nothing above was acted on

    # a bad datagram cannot spoil the next one: a frame's start without its end, then a valid setpoint
    _deliver(link, script, b"\xfd\x09\x00", t=0.5)
    _deliver(link, script, good, t=0.5)
    assert link.setpoint_kind == "accel" and np.allclose(link.setpoint, [0.5, 1.0])  # NED (1, 0.5) -> ENU (0.5, 1)
    assert link.handled["SET_POSITION_TARGET_LOCAL_NED"] == 1

    # an unknown command is answered UNSUPPORTED
    _acks(script)
    _deliver(
        link,
        script,
        _frames(gcs, mavlink.MAVLink_command_long_message(1, 1, mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 0, 2)),
        t=0.5,
    )
    assert [(a.command, a.result) for a in _acks(script)] == [
        (mavlink.MAV_CMD_NAV_TAKEOFF, mavlink.MAV_RESULT_UNSUPPORTED)
    ]


def test_mode_logic_follows_px4(link_pair):
    """OFFBOARD needs a setpoint stream; arming in OFFBOARD flies the setpoint; a velocity setpoint
    works too; after COM_OF_LOSS_T without setpoints the vehicle holds (AUTO.LOITER)."""
    link, script = link_pair
    gcs = mavlink.MAVLink(None, srcSystem=255, srcComponent=190)

    def command(cmd, *params, t):
        params = list(params) + [0.0] * (7 - len(params))
        _deliver(link, script, _frames(gcs, mavlink.MAVLink_command_long_message(1, 1, cmd, 0, *params)), t=t)
        (ack,) = _acks(script)
        return ack.result

    set_offboard = (mavlink.MAV_CMD_DO_SET_MODE, 29, 6, 0)  # pymavlink's set_mode("OFFBOARD") for PX4
    assert link.mode == MODE_HOLD and link.command(0.0) is None
    assert command(*set_offboard, t=0.0) == mavlink.MAV_RESULT_TEMPORARILY_REJECTED
    velocity = mavlink.MAVLink_set_position_target_local_ned_message(
        0, 1, 1, mavlink.MAV_FRAME_LOCAL_NED, VELOCITY_MASK, 0, 0, 0, 0.4, -0.3, 0, 0, 0, 0, 0, 0
    )
    _deliver(link, script, _frames(gcs, velocity), t=1.0)
    assert command(*set_offboard, t=1.0) == mavlink.MAV_RESULT_ACCEPTED and link.mode == MODE_OFFBOARD
    assert link.command(1.0) is None  # still disarmed: hold
    assert command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1, t=1.0) == mavlink.MAV_RESULT_ACCEPTED
    kind, value = link.command(1.5)
    assert kind == "velocity" and np.allclose(value, [-0.3, 0.4])  # NED (0.4 north, -0.3 east) -> ENU
    assert link.command(2.0) is not None  # exactly COM_OF_LOSS_T after the setpoint: still flying it
    assert link.command(2.01) is None and link.mode == MODE_HOLD and link.armed
    assert [e["event"] for e in link.events] == ["mode", "armed", "offboard_loss_hold"]
    assert command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 3, t=2.0) == mavlink.MAV_RESULT_DENIED
    assert command(mavlink.MAV_CMD_DO_SET_MODE, 29, 3, 0, t=2.0) == mavlink.MAV_RESULT_UNSUPPORTED  # POSCTL


def test_position_loop_frames_and_warnings_in_process(link_pair):
    """One VehicleLink given a fixed estimate: PX4's position loop (MPC_XY_P, the speed limit, velocity
    feed-forward second), each frame converted at receipt, ignored fields warned about once per cause,
    refused setpoints named at once and in the DENIED answer to OFFBOARD."""
    link, script = link_pair
    gcs = mavlink.MAVLink(None, srcSystem=255, srcComponent=190)
    est = {"pos": np.array([1.0, 2.0, -FLIGHT_ALTITUDE]), "yaw": math.pi / 2}  # facing east
    link.state = lambda: (est["pos"].copy(), est["yaw"])
    link.speed_max = 1.0
    link.armed, link.mode = True, MODE_OFFBOARD

    def send(frame, mask, *fields, t):  # fields: x, y, z, vx, vy, vz, afx, afy, afz, yaw, yaw_rate
        fields = list(fields) + [0.0] * (11 - len(fields))
        _deliver(
            link,
            script,
            _frames(gcs, mavlink.MAVLink_set_position_target_local_ned_message(0, 1, 1, frame, mask, *fields)),
            t=t,
        )

    def command(cmd, *params, t):
        params = list(params) + [0.0] * (7 - len(params))
        _deliver(link, script, _frames(gcs, mavlink.MAVLink_command_long_message(1, 1, cmd, 0, *params)), t=t)

    local, offset = mavlink.MAV_FRAME_LOCAL_NED, mavlink.MAV_FRAME_LOCAL_OFFSET_NED
    # MAV_FRAME_LOCAL_NED: velocity = MPC_XY_P * error, within the speed limit; ENU out (north -> y)
    send(local, POSITION_MASK, 1.5, 2.0, -FLIGHT_ALTITUDE, t=0.0)
    kind, v = link.command(0.0)
    assert link.setpoint_kind == "position" and kind == "velocity" and np.allclose(v, [0.0, MPC_XY_P * 0.5])
    est["pos"][:2] = (-3.0, 2.0)  # 4.5 m short: the speed limit
    assert np.allclose(link.command(0.0)[1], [0.0, 1.0])
    est["pos"][:2] = (1.0, 2.0)
    # velocity fields in use too: feed-forward, second to the position demand within the speed limit (PX4)
    with_ff = POSITION_MASK & ~(TYPE_MASK_BITS["vx"] | TYPE_MASK_BITS["vy"])
    send(local, with_ff, 1.5, 2.0, -FLIGHT_ALTITUDE, 0.0, 0.2, t=0.0)
    assert np.allclose(link.command(0.0)[1], [0.2, MPC_XY_P * 0.5])  # 0.2 east fits
    send(local, with_ff, 1.5, 2.0, -FLIGHT_ALTITUDE, 0.0, 2.0, t=0.0)
    demand = MPC_XY_P * 0.5
    assert np.allclose(link.command(0.0)[1], [math.sqrt(1.0 - demand**2), demand])
    # MAV_FRAME_LOCAL_OFFSET_NED: from the position at receipt, NED axes; the target stays put
    send(offset, POSITION_MASK, 1.0, -1.0, 0.0, t=0.1)
    assert np.allclose(link.position_target, [2.0, 1.0])
    est["pos"][:2] = (2.0, 1.0)
    assert np.allclose(link.command(0.1)[1], [0.0, 0.0])
    # MAV_FRAME_BODY_NED and BODY_OFFSET_NED: axes turned by the yaw; facing east, right is south
    for frame in (mavlink.MAV_FRAME_BODY_NED, mavlink.MAV_FRAME_BODY_OFFSET_NED):
        send(frame, POSITION_MASK, 2.0, 1.0, 0.0, t=0.2)
        assert np.allclose(link.position_target, [1.0, 3.0])  # 2 m forward = east, 1 m right = south
        send(frame, VELOCITY_MASK, 0, 0, 0, 0.5, -0.2, t=0.2)  # 0.5 m/s forward, 0.2 m/s left
        assert link.setpoint_kind == "velocity" and np.allclose(link.setpoint, [0.5, 0.2])  # ENU: east, north
        send(frame, ACCEL_MASK, 0, 0, 0, 0, 0, 0, 1.0, 0.0, t=0.2)
        assert link.setpoint_kind == "accel" and np.allclose(link.setpoint, [1.0, 0.0])
    assert np.allclose(rotate_yaw(0.3, *rotate_yaw(-0.3, 1.0, 2.0)), [1.0, 2.0])
    assert np.allclose(constrain_xy(np.array([3.0, 4.0]), np.array([1.0, 0.0]), 1.0), [0.6, 0.8])
    assert _received(script, "STATUSTEXT") == []  # all of the above flown as sent

    # fields that are not flown: one STATUSTEXT warning per cause (counted every time), again after a while
    send(local, POSITION_MASK, 1.5, 2.0, -5.0, t=0.3)
    send(local, POSITION_MASK, 1.5, 2.0, -5.0, t=0.4)
    send(local, POSITION_MASK, 1.5, 2.0, -FLIGHT_ALTITUDE - 0.2, t=0.5)  # within ALTITUDE_TOLERANCE_M: fine
    (text,) = _received(script, "STATUSTEXT")
    assert text.severity == mavlink.MAV_SEVERITY_WARNING and text.text == "z=-5.00 ignored: altitude held at z=-2.00"
    assert link.warnings["z"] == 2 and link.setpoint_kind == "position"  # flown all the same
    send(local, POSITION_MASK & ~TYPE_MASK_BITS["yaw"], 1.5, 2.0, -FLIGHT_ALTITUDE, 0, 0, 0, 0, 0, 0, 0.0, t=0.6)
    send(local, ACCEL_MASK & ~TYPE_MASK_BITS["vx"], 0, 0, 0, 0.3, 0, 0, 1.0, 0, 0, t=0.7)
    assert [m.text for m in _received(script, "STATUSTEXT")] == [
        "yaw ignored: heading held at 90 deg",
        "vx ignored: accel setpoint flown",
    ]
    send(local, POSITION_MASK, 1.5, 2.0, -5.0, t=0.3 + STATUSTEXT_REPEAT_S)
    assert [m.text for m in _received(script, "STATUSTEXT")] == ["z=-5.00 ignored: altitude held at z=-2.00"]
    # PX4 refuses force only with the acceleration in use: the common mask 0b111111000111 flies velocity
    send(local, 0b111111000111, 0, 0, 0, 0.3, 0.4, t=11.0)
    assert link.setpoint_kind == "velocity" and np.allclose(link.setpoint, [0.4, 0.3])

    # refused: at once, by name; while only refused setpoints arrive, OFFBOARD is DENIED with the cause
    link.mode = MODE_HOLD
    send(mavlink.MAV_FRAME_LOCAL_FRD, POSITION_MASK, 1, 0, 0, t=20.0)
    (text,) = _received(script, "STATUSTEXT")
    assert text.severity == mavlink.MAV_SEVERITY_WARNING
    assert text.text == "Setpoint refused: frame 20 unsupported (LOCAL_FRD)"
    command(mavlink.MAV_CMD_DO_SET_MODE, 29, 6, 0, t=20.1)
    assert [(a.command, a.result) for a in _acks(script)] == [(mavlink.MAV_CMD_DO_SET_MODE, mavlink.MAV_RESULT_DENIED)]
    send(mavlink.MAV_FRAME_LOCAL_FRD, POSITION_MASK, 1, 0, 0, t=20.2)
    command(mavlink.MAV_CMD_DO_SET_MODE, 29, 6, 0, t=20.3)
    assert [m.text for m in _received(script, "STATUSTEXT")] == ["OFFBOARD denied: frame 20 unsupported (LOCAL_FRD)"]
    assert link.mode == MODE_HOLD and link.ignored["setpoint refused: frame 20 unsupported (LOCAL_FRD)"] == 2
    command(mavlink.MAV_CMD_DO_SET_MODE, 29, 6, 0, t=22.0)  # nothing for a while: PX4's "no stream" again
    assert [(a.result) for a in _acks(script)] == [mavlink.MAV_RESULT_TEMPORARILY_REJECTED]
    # a message a script flies with that the link does not handle: a warning too
    _deliver(
        link,
        script,
        _frames(gcs, mavlink.MAVLink_set_attitude_target_message(0, 1, 1, 0, [1, 0, 0, 0], 0, 0, 0, 0.5)),
        t=22.0,
    )
    assert [m.text for m in _received(script, "STATUSTEXT")] == ["SET_ATTITUDE_TARGET unsupported"]


def test_local_origin_defaults_to_each_drones_spawn_point():
    """PX4's home: every drone's LOCAL_POSITION_NED starts at (0, 0, -altitude) (in-process, real sockets)."""
    script = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    script.bind(("127.0.0.1", 0))
    port = script.getsockname()[1]
    script.close()  # the ports of two drones: P and P + 1 (the second may be taken: then skip)
    sockets = []
    try:
        for p in (port, port + 1):
            sockets.append(socket.socket(socket.AF_INET, socket.SOCK_DGRAM))
            sockets[-1].bind(("127.0.0.1", p))
    except OSError:
        pytest.skip("no two adjacent free UDP ports")
    link = MavlinkLink(
        MavlinkLinkConfig(n_drones=2, ports=(0,), remote_ports=(port,), real_time_factor=100.0, duration_s=0.1)
    )
    try:
        link.run()
        parser = mavlink.MAVLink(None)
        for sock in sockets:
            sock.settimeout(2.0)
            positions = []
            while not positions:
                positions = [
                    m for m in parser.parse_buffer(sock.recv(65535)) or [] if m.get_type() == "LOCAL_POSITION_NED"
                ]
            assert np.allclose([positions[0].x, positions[0].y, positions[0].z], [0, 0, -FLIGHT_ALTITUDE], atol=1e-3)
    finally:
        link.close()
        for sock in sockets:
            sock.close()


def test_frame_conversions():
    assert np.allclose(enu_to_ned(np.array([1.0, 2.0, 3.0])), [2.0, 1.0, -3.0])
    half = math.sqrt(0.5)
    assert np.allclose(attitude_ned(np.array([1.0, 0, 0, 0])), [0, 0, math.pi / 2])  # facing east
    assert np.allclose(attitude_ned(np.array([half, 0, 0, half])), [0, 0, 0])  # ENU yaw 90 deg: facing north
    roll, pitch, _ = attitude_ned(np.array([math.cos(0.05), 0, math.sin(0.05), 0]))  # nose down 0.1 rad about ENU y
    assert abs(roll) < 1e-9 and abs(pitch + 0.1) < 1e-9  # FRD pitch is nose up: -0.1


# ====================================================================== command line
def _run_cli(*args, timeout=60):
    return subprocess.run(
        [sys.executable, "-m", "cefc_mj.deploy.mavlink_link", *args],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=timeout,
        check=False,
    )


def test_cli_help_and_bad_input_exit_2_with_one_line():
    assert _run_cli("--help").returncode == 0
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as taken:
        taken.bind(("127.0.0.1", 0))
        port = str(taken.getsockname()[1])
        cases = {
            ("--drones", "0"): "--drones=0",
            ("--drones", "2", "--remote-port", "1", "2", "3"): "--remote-port",
            ("--telemetry-hz", "30"): "--telemetry-hz",
            ("--real-time-factor", "inf"): "--real-time-factor",
            ("--airframe", "no-such-airframe"): "airframe",
            ("--port", port): "cannot bind UDP",
            ("--speed", "x"): "argument",
        }
        for args, expected in cases.items():
            result = _run_cli(*args)
            assert result.returncode == 2, (args, result.stderr)
            lines = result.stderr.strip().splitlines()
            assert len(lines) == 1 and expected in lines[0] and "Traceback" not in result.stderr, (args, result.stderr)


def test_config_validation_names_the_field():
    with pytest.raises(ConfigError, match="ports"):
        MavlinkLinkConfig(n_drones=2, ports=(14580, 14580)).validate()
    with pytest.raises(ConfigError, match="origin"):
        MavlinkLinkConfig(origin="home").validate()
    assert MavlinkLinkConfig(n_drones=3, ports=(0,), remote_ports=(14540,)).offboard_ports() == [14540, 14541, 14542]
