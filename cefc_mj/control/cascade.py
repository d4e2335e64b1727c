"""PX4-like cascaded multicopter controller, vectorized over drones, compiled with numba.

One call of `cascade_step` runs one physics step (default 500 Hz) for all D drones of one env,
reading MuJoCo's qpos/qvel and writing the rotor thrusts to `data.ctrl` (the airframe's site-mounted
`<motor>` actuators, which MuJoCo turns into the thrust along each rotor axis and the yaw reaction
torque through their gear) and the rotor drag to `xfrc_applied`; `run_physics` runs a whole stretch
of physics steps (cascade + `mj_step`) in one compiled call:

    offboard interface (position-loop rate, default 100 Hz), one of
        "velocity": the action integrated into a velocity setpoint (ramped over the decision step,
        norm-clipped to the speed limit, as the particle world integrates velocity) + its derivative
        as acceleration feed-forward -> PX4's horizontal velocity PID (integral with PX4's tracking
        anti-windup, D on the low-passed velocity derivative)
        "acceleration": PX4's own semantics (PositionControl with the horizontal position and
        velocity setpoints NaN): the acceleration setpoint goes straight to the tilt, no feedback,
        no integral, no speed limit, no drag compensation
        "acceleration-assisted": not PX4's; the earlier interface, kept to reproduce results made
        with it: the acceleration setpoint open loop -> speed limiter (with an external-push
        estimate) -> calm-air rotor-drag feed-forward
        "velocity" adds the calm-air rotor-drag feed-forward too
    hold (internal, before an episode): PX4's Position-mode hold, v_sp = MPC_XY_P x position error
        (norm-limited to the speed limit) -> the same horizontal velocity PID, no feed-forward
    PositionControl (same rate): altitude P -> climb-rate PID (integral, anti-windup) ->
        thrust vector: body_z = normalize(a_x, a_y, g), tilt <= MPC_TILTMAX_AIR, collective =
        hover-scaled vertical thrust / cos(tilt) >= MPC_THR_MIN, vertical-priority saturation ->
        attitude setpoint (bodyzToAttitude, yaw setpoint 0)
    AttitudeControl (rate-loop rate, default 250 Hz): reduced-attitude quaternion P with yaw weight
        -> rate setpoint, limited
    RateControl (same rate): PID with feed-forward, I-factor, saturation-aware anti-windup,
        integrator limits; yaw torque low-pass
    ControlAllocationSequentialDesaturation (airmode off): pseudo-inverse mix, thrust reduced only,
        roll/pitch desaturation, yaw mixed last with 15 % headroom
    motor model (every physics step): omega -> omega_ref with the asymmetric first-order lag
        (exact discretisation), thrust = k omega^2 (reduced with axial airspeed as Gazebo) -> ctrl,
        one rotor thrust (N) per actuator; rotor drag and rolling moment on the relative airspeed,
        summed into xfrc_applied (world frame, about the centre of mass). The lag stays here, not in
        MuJoCo's actuator dynamics: it is asymmetric and acts on the rotor speed (thrust ~ omega^2),
        which dyntype="filter" (symmetric, linear in ctrl) cannot express, and the drag needs omega.
        Without actuators in the scene (MujocoWorldConfig.rotor_actuation = "external") the same
        thrust wrench (thrust along body z at each rotor, its moment, the yaw reaction torque) is
        summed into xfrc_applied instead.

Frames: world ENU, body FLU (MuJoCo's). PX4 works in NED/FRD; every formula here is PX4's with
z (and the sign of vertical quantities) flipped, e.g. body_z = normalize(-a_x, -a_y, g) in NED is
normalize(a_x, a_y, g) here. Quaternions are MuJoCo's [w, x, y, z] (body -> world).

`Px4Cascade` holds the constants and the per-drone state it works on; tests/test_controller.py holds
the slow numpy reference that it is checked against.
"""

from __future__ import annotations

import math
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np
from llvmlite import ir
from numba.core import types
from numba.extending import intrinsic

from cefc_mj.control.airframe import Airframe, px4_mixer
from cefc_mj.control.params import PARAM_NAMES
from cefc_mj.jit import njit

# ----------------------------------------------------------------------------- layouts
# parameter positions (numba folds module-level ints into constants)
(
    MPC_Z_P,
    MPC_Z_VEL_P_ACC,
    MPC_Z_VEL_I_ACC,
    MPC_Z_VEL_D_ACC,
    MPC_Z_VEL_MAX_UP,
    MPC_Z_VEL_MAX_DN,
    MPC_XY_VEL_P_ACC,
    MPC_XY_VEL_I_ACC,
    MPC_XY_VEL_D_ACC,
    MPC_VELD_LP,
    MPC_TILTMAX_AIR,
    MPC_THR_HOVER,
    MPC_THR_MIN,
    MPC_THR_MAX,
    MPC_THR_XY_MARG,
    MC_ROLL_P,
    MC_PITCH_P,
    MC_YAW_P,
    MC_YAW_WEIGHT,
    MC_ROLLRATE_MAX,
    MC_PITCHRATE_MAX,
    MC_YAWRATE_MAX,
    MC_ROLLRATE_P,
    MC_ROLLRATE_I,
    MC_ROLLRATE_D,
    MC_ROLLRATE_FF,
    MC_ROLLRATE_K,
    MC_RR_INT_LIM,
    MC_PITCHRATE_P,
    MC_PITCHRATE_I,
    MC_PITCHRATE_D,
    MC_PITCHRATE_FF,
    MC_PITCHRATE_K,
    MC_PR_INT_LIM,
    MC_YAWRATE_P,
    MC_YAWRATE_I,
    MC_YAWRATE_D,
    MC_YAWRATE_FF,
    MC_YAWRATE_K,
    MC_YR_INT_LIM,
    MC_YAW_TQ_CUTOFF,
    IMU_DGYRO_CUTOFF,
) = range(42)
assert len(PARAM_NAMES) == 42 and PARAM_NAMES[MPC_VELD_LP] == "MPC_VELD_LP" and PARAM_NAMES[MC_ROLL_P] == "MC_ROLL_P"
assert PARAM_NAMES[IMU_DGYRO_CUTOFF] == "IMU_DGYRO_CUTOFF"

# constants array `k`
(
    K_DT,
    K_RATE_DIV,
    K_POS_DIV,
    K_G,
    K_MASS,
    K_KT,
    K_WMAX,
    K_ALPHA_UP,
    K_ALPHA_DOWN,
    K_CRD,
    K_CRM,
    K_SPEED_TAU,
    K_COS_FLIP,
    K_DIST_TAU,
    K_KM,
    K_OFFBOARD,
    K_HOLD_P,
) = range(17)
N_CONSTS = 17

# offboard interfaces (k[K_OFFBOARD])
OFFBOARD_ACCELERATION = 0
OFFBOARD_VELOCITY = 1
OFFBOARD_ACCELERATION_ASSISTED = 2
OFFBOARD_HOLD = 3  # not an interface: the position hold flown before an episode (Px4Cascade.holding)
OFFBOARD_MODES = {
    "velocity": OFFBOARD_VELOCITY,
    "acceleration": OFFBOARD_ACCELERATION,
    "acceleration-assisted": OFFBOARD_ACCELERATION_ASSISTED,
}
HOLD_POSITION_GAIN = 0.95
"""Position gain (1/s) of the hold before an episode: PX4's MPC_XY_P default."""

# per-drone state columns `s`
S_OMEGA = 0  # 4 rotor speeds (rad/s)
S_U = 4  # 4 normalised motor commands held between rate ticks
S_QSP = 8  # attitude setpoint quaternion [w, x, y, z]
S_THRUST = 12  # collective thrust setpoint (normalised)
S_RATE_INT = 13  # 3 rate integrators
S_RATE_PREV = 16  # 3 body rates at the previous rate tick
S_ANG_ACC = 19  # 3 filtered angular accelerations (D term)
S_YAW_TQ = 22  # low-passed yaw torque
S_Z_INT = 23  # vertical velocity integrator (m/s^2)
S_VZ_PREV = 24  # climb rate at the previous position tick
S_SAT_POS = 25  # 3 flags: allocator saturated in the positive direction
S_SAT_NEG = 28  # 3 flags: ... negative direction
S_ACC_CMD = 31  # 2 horizontal acceleration actually commanded (after limiter + feed-forward)
S_DIST = 33  # 2 low-passed external horizontal acceleration estimate (wind push), m/s^2
S_VXY_PREV = 35  # 2 horizontal velocity at the previous position tick
S_THRUST_N = 37  # 4 rotor thrusts (N) applied at the last physics step
S_VSP = 41  # 2 horizontal velocity setpoint (offboard "velocity")
S_VEL_INT = 43  # 2 horizontal velocity integrator (m/s^2)
S_VEL_DOT = 45  # 2 low-passed horizontal velocity derivative (D term)
S_DRAG = 47  # 6 rotor drag + rolling moment (world force N, torque N m about the CoM), last physics step
S_HOLD = 53  # 2 horizontal position the hold before an episode keeps (m)
N_STATE = 55

# per-drone setpoint columns `sp`: SP_AX, SP_AY = the acceleration setpoint ("acceleration") or the
# feed-forward, i.e. the slope of the velocity-setpoint ramp ("velocity"; see Px4Cascade.command)
SP_AX, SP_AY, SP_Z, SP_VMAX = range(4)


# ----------------------------------------------------------------------------- math helpers
@njit(inline="always")
def _qmul(a0, a1, a2, a3, b0, b1, b2, b3):
    return (
        a0 * b0 - a1 * b1 - a2 * b2 - a3 * b3,
        a0 * b1 + a1 * b0 + a2 * b3 - a3 * b2,
        a0 * b2 - a1 * b3 + a2 * b0 + a3 * b1,
        a0 * b3 + a1 * b2 - a2 * b1 + a3 * b0,
    )


@njit(inline="always")
def _dcm_z(w, x, y, z):
    return 2.0 * (x * z + w * y), 2.0 * (y * z - w * x), w * w - x * x - y * y + z * z


@njit(inline="always")
def _quat_between(ux, uy, uz, vx, vy, vz):
    """Shortest rotation taking unit vector u to unit vector v (PX4 matrix::Quaternion(src, dst))."""
    cx = uy * vz - uz * vy
    cy = uz * vx - ux * vz
    cz = ux * vy - uy * vx
    dot = ux * vx + uy * vy + uz * vz
    if math.sqrt(cx * cx + cy * cy + cz * cz) < 1e-5 and dot < 0.0:
        # antiparallel: rotate by pi about an axis orthogonal to u
        ax, ay, az = abs(ux), abs(uy), abs(uz)
        if ax < ay:
            ex, ey, ez = (1.0, 0.0, 0.0) if ax < az else (0.0, 0.0, 1.0)
        else:
            ex, ey, ez = (0.0, 1.0, 0.0) if ay < az else (0.0, 0.0, 1.0)
        w = 0.0
        cx, cy, cz = uy * ez - uz * ey, uz * ex - ux * ez, ux * ey - uy * ex
    else:
        w = dot + 1.0
    n = math.sqrt(w * w + cx * cx + cy * cy + cz * cz)
    return w / n, cx / n, cy / n, cz / n


@njit(inline="always")
def _dcm_to_quat(r00, r01, r02, r10, r11, r12, r20, r21, r22):
    """Rotation matrix -> unit quaternion [w, x, y, z] with w >= 0 (Shepperd's method)."""
    tr = r00 + r11 + r22
    if tr > 0.0:
        t = math.sqrt(tr + 1.0) * 2.0
        w, x, y, z = 0.25 * t, (r21 - r12) / t, (r02 - r20) / t, (r10 - r01) / t
    elif r00 > r11 and r00 > r22:
        t = math.sqrt(1.0 + r00 - r11 - r22) * 2.0
        w, x, y, z = (r21 - r12) / t, 0.25 * t, (r01 + r10) / t, (r02 + r20) / t
    elif r11 > r22:
        t = math.sqrt(1.0 + r11 - r00 - r22) * 2.0
        w, x, y, z = (r02 - r20) / t, (r01 + r10) / t, 0.25 * t, (r12 + r21) / t
    else:
        t = math.sqrt(1.0 + r22 - r00 - r11) * 2.0
        w, x, y, z = (r10 - r01) / t, (r02 + r20) / t, (r12 + r21) / t, 0.25 * t
    if w < 0.0:
        w, x, y, z = -w, -x, -y, -z
    return w, x, y, z


@njit(inline="always")
def _lowpass_alpha(cutoff_hz, dt):
    """PX4 AlphaFilter gain for a cutoff frequency; 1 (no filtering) when the cutoff is 0."""
    if cutoff_hz <= 0.0:
        return 1.0
    return dt / (dt + 1.0 / (2.0 * math.pi * cutoff_hz))


# ----------------------------------------------------------------------------- loops
@njit(inline="always")
def _position_loop(d, qpos, qvel, s, sp, prm, k):
    """Offboard interface + PositionControl for drone d: writes the attitude and thrust setpoints."""
    dt = k[K_DT] * k[K_POS_DIV]
    g = k[K_G]
    vx, vy, vz = qvel[d, 0], qvel[d, 1], qvel[d, 2]
    om_sum = 0.0
    for i in range(4):
        om_sum += abs(s[d, S_OMEGA + i])
    drag_gain = k[K_CRD] * om_sum / k[K_MASS]
    mode = k[K_OFFBOARD]
    velocity_mode = mode == OFFBOARD_VELOCITY or mode == OFFBOARD_HOLD

    if velocity_mode:
        if mode == OFFBOARD_HOLD:
            # PX4 _positionControl: v_sp = MPC_XY_P (p_sp - p), its norm limited; no feed-forward
            hx = k[K_HOLD_P] * (s[d, S_HOLD] - qpos[d, 0])
            hy = k[K_HOLD_P] * (s[d, S_HOLD + 1] - qpos[d, 1])
            hn = math.sqrt(hx * hx + hy * hy)
            if hn > sp[d, SP_VMAX]:
                hx, hy = hx * sp[d, SP_VMAX] / hn, hy * sp[d, SP_VMAX] / hn
            s[d, S_VSP], s[d, S_VSP + 1] = hx, hy
            ff_x = ff_y = 0.0
        else:
            # the velocity setpoint ramps with the feed-forward slope (Px4Cascade.command makes it land
            # on the particle world's velocity at the end of the decision step)
            ff_x, ff_y = sp[d, SP_AX], sp[d, SP_AY]
            s[d, S_VSP] += ff_x * dt
            s[d, S_VSP + 1] += ff_y * dt
        # PX4 _velocityControl with the derivative of the measured velocity low-passed at MPC_VELD_LP
        a_vd = _lowpass_alpha(prm[MPC_VELD_LP], dt)
        s[d, S_VEL_DOT] += a_vd * ((vx - s[d, S_VXY_PREV]) / dt - s[d, S_VEL_DOT])
        s[d, S_VEL_DOT + 1] += a_vd * ((vy - s[d, S_VXY_PREV + 1]) / dt - s[d, S_VEL_DOT + 1])
        s[d, S_VXY_PREV] = vx
        s[d, S_VXY_PREV + 1] = vy
        err_x = s[d, S_VSP] - vx
        err_y = s[d, S_VSP + 1] - vy
        ax = ff_x + prm[MPC_XY_VEL_P_ACC] * err_x + s[d, S_VEL_INT] - prm[MPC_XY_VEL_D_ACC] * s[d, S_VEL_DOT]
        ay = ff_y + prm[MPC_XY_VEL_P_ACC] * err_y + s[d, S_VEL_INT + 1] - prm[MPC_XY_VEL_D_ACC] * s[d, S_VEL_DOT + 1]
    elif mode == OFFBOARD_ACCELERATION:
        # PX4 PositionControl with the horizontal position and velocity setpoints NaN: _velocityControl
        # adds nothing (and leaves its integral alone), the setpoint goes to _accelerationControl as is
        s[d, S_VXY_PREV] = vx
        s[d, S_VXY_PREV + 1] = vy
        ax, ay = sp[d, SP_AX], sp[d, SP_AY]
        err_x = err_y = 0.0
    else:
        # "acceleration-assisted" (not PX4's). External horizontal acceleration the vehicle does not
        # command (wind): measured acceleration
        # minus what the thrust vector and the modelled calm-air rotor drag explain, low-passed
        w, x, y, z = qpos[d, 3], qpos[d, 4], qpos[d, 5], qpos[d, 6]
        thrust_n = 0.0
        for i in range(4):
            thrust_n += s[d, S_THRUST_N + i]
        a_thr = thrust_n / k[K_MASS]
        dist_x = (vx - s[d, S_VXY_PREV]) / dt - a_thr * 2.0 * (x * z + w * y) + drag_gain * vx
        dist_y = (vy - s[d, S_VXY_PREV + 1]) / dt - a_thr * 2.0 * (y * z - w * x) + drag_gain * vy
        beta = dt / (dt + k[K_DIST_TAU])
        s[d, S_DIST] += beta * (dist_x - s[d, S_DIST])
        s[d, S_DIST + 1] += beta * (dist_y - s[d, S_DIST + 1])
        s[d, S_VXY_PREV] = vx
        s[d, S_VXY_PREV + 1] = vy

        # the setpoint passes unchanged (open loop, as PX4 treats an acceleration setpoint) unless
        # the speed it leads to within tau would exceed vmax; then a velocity loop of gain 1/tau,
        # which also cancels the estimated external push, pulls the speed onto the limit
        ax, ay = sp[d, SP_AX], sp[d, SP_AY]
        tau = k[K_SPEED_TAU]
        vmax = sp[d, SP_VMAX]
        ex, ey = s[d, S_DIST], s[d, S_DIST + 1]
        px, py = vx + (ax + ex) * tau, vy + (ay + ey) * tau
        pn = math.sqrt(px * px + py * py)
        if pn > vmax:
            ax = (px * vmax / pn - vx) / tau - ex
            ay = (py * vmax / pn - vy) / tau - ey
        err_x = err_y = 0.0
    if mode == OFFBOARD_VELOCITY or mode == OFFBOARD_ACCELERATION_ASSISTED:
        # calm-air rotor-drag feed-forward (the vehicle knows its rotor speeds, not the wind)
        ax += drag_gain * vx
        ay += drag_gain * vy
    s[d, S_ACC_CMD] = ax
    s[d, S_ACC_CMD + 1] = ay

    # altitude: position P -> climb-rate PID (PX4 _positionControl / _velocityControl, z only)
    vz_sp = prm[MPC_Z_P] * (sp[d, SP_Z] - qpos[d, 2])
    vz_sp = min(max(vz_sp, -prm[MPC_Z_VEL_MAX_DN]), prm[MPC_Z_VEL_MAX_UP])
    vz_dot = (vz - s[d, S_VZ_PREV]) / dt
    s[d, S_VZ_PREV] = vz
    err_z = vz_sp - vz
    az = prm[MPC_Z_VEL_P_ACC] * err_z + s[d, S_Z_INT] - prm[MPC_Z_VEL_D_ACC] * vz_dot

    # _accelerationControl (MPC_ACC_DECOUPLE = 1): tilt from the horizontal acceleration only
    bx, by, bz = ax, ay, g
    n = math.sqrt(bx * bx + by * by + bz * bz)
    bx, by, bz = bx / n, by / n, bz / n
    # ControlMath::limitTilt
    angle = math.acos(min(max(bz, -1.0), 1.0))
    max_tilt = math.radians(prm[MPC_TILTMAX_AIR])
    if angle > max_tilt:
        rn = math.sqrt(bx * bx + by * by)
        bx, by, bz = math.sin(max_tilt) * bx / rn, math.sin(max_tilt) * by / rn, math.cos(max_tilt)
    hover = prm[MPC_THR_HOVER]
    thr_up = az * hover / g + hover
    collective = max(thr_up / bz, prm[MPC_THR_MIN])
    tx, ty, tz = bx * collective, by * collective, bz * collective

    # vertical integrator anti-windup
    if (tz <= prm[MPC_THR_MIN] and err_z <= 0.0) or (tz >= prm[MPC_THR_MAX] and err_z >= 0.0):
        err_z = 0.0
    # saturation with vertical priority and a horizontal margin
    thr_max2 = prm[MPC_THR_MAX] * prm[MPC_THR_MAX]
    txy = math.sqrt(tx * tx + ty * ty)
    margin = min(txy, prm[MPC_THR_XY_MARG])
    tz = min(tz, math.sqrt(thr_max2 - margin * margin))
    rem = thr_max2 - tz * tz
    txy_max = math.sqrt(rem) if rem > 0.0 else 0.0
    if txy > txy_max:
        tx, ty = tx * txy_max / txy, ty * txy_max / txy
    z_int = s[d, S_Z_INT] + err_z * prm[MPC_Z_VEL_I_ACC] * dt
    s[d, S_Z_INT] = min(max(z_int, -g), g)
    if velocity_mode:
        # PX4's tracking anti-windup: while the thrust saturation (tilt limit, vertical priority)
        # cuts the horizontal acceleration, the integrator is driven to unsaturate it
        prod_x, prod_y = tx * g / hover, ty * g / hover
        if ax * ax + ay * ay > prod_x * prod_x + prod_y * prod_y:
            arw = 2.0 / prm[MPC_XY_VEL_P_ACC]
            err_x -= arw * (ax - prod_x)
            err_y -= arw * (ay - prod_y)
        s[d, S_VEL_INT] += err_x * prm[MPC_XY_VEL_I_ACC] * dt
        s[d, S_VEL_INT + 1] += err_y * prm[MPC_XY_VEL_I_ACC] * dt

    # ControlMath::thrustToAttitude / bodyzToAttitude with yaw setpoint 0
    thrust = math.sqrt(tx * tx + ty * ty + tz * tz)
    zx, zy, zz = tx / thrust, ty / thrust, tz / thrust
    # body_x = y_C x body_z with y_C = (-sin yaw, cos yaw, 0) = (0, 1, 0)
    xx, xy, xz = zz, 0.0, -zx
    xn = math.sqrt(xx * xx + xz * xz)
    xx, xz = xx / xn, xz / xn
    yx, yy, yz = zy * xz - zz * xy, zz * xx - zx * xz, zx * xy - zy * xx
    w, x, y, z = _dcm_to_quat(xx, yx, zx, xy, yy, zy, xz, yz, zz)
    s[d, S_QSP], s[d, S_QSP + 1], s[d, S_QSP + 2], s[d, S_QSP + 3] = w, x, y, z
    s[d, S_THRUST] = thrust


@njit(inline="always")
def _attitude_control(q0, q1, q2, q3, d0, d1, d2, d3, prm):
    """PX4 AttitudeControl::update: reduced attitude first, yaw weighted; returns the rate setpoint."""
    ezx, ezy, ezz = _dcm_z(q0, q1, q2, q3)
    edx, edy, edz = _dcm_z(d0, d1, d2, d3)
    r0, r1, r2, r3 = _quat_between(ezx, ezy, ezz, edx, edy, edz)
    if abs(r1) > 1.0 - 1e-5 or abs(r2) > 1.0 - 1e-5:
        r0, r1, r2, r3 = d0, d1, d2, d3
    else:
        r0, r1, r2, r3 = _qmul(r0, r1, r2, r3, q0, q1, q2, q3)
    m0, m1, m2, m3 = _qmul(r0, -r1, -r2, -r3, d0, d1, d2, d3)
    if m0 < 0.0:
        m0, m1, m2, m3 = -m0, -m1, -m2, -m3
    m0 = min(max(m0, -1.0), 1.0)
    m3 = min(max(m3, -1.0), 1.0)
    yw = min(max(prm[MC_YAW_WEIGHT], 0.0), 1.0)
    d0, d1, d2, d3 = _qmul(r0, r1, r2, r3, math.cos(yw * math.acos(m0)), 0.0, 0.0, math.sin(yw * math.asin(m3)))
    e0, e1, e2, e3 = _qmul(q0, -q1, -q2, -q3, d0, d1, d2, d3)
    if e0 < 0.0:
        e1, e2, e3 = -e1, -e2, -e3
    yaw_gain = prm[MC_YAW_P] / yw if yw > 1e-4 else prm[MC_YAW_P]
    rx = min(max(2.0 * e1 * prm[MC_ROLL_P], -math.radians(prm[MC_ROLLRATE_MAX])), math.radians(prm[MC_ROLLRATE_MAX]))
    ry = min(max(2.0 * e2 * prm[MC_PITCH_P], -math.radians(prm[MC_PITCHRATE_MAX])), math.radians(prm[MC_PITCHRATE_MAX]))
    rz = min(max(2.0 * e3 * yaw_gain, -math.radians(prm[MC_YAWRATE_MAX])), math.radians(prm[MC_YAWRATE_MAX]))
    return rx, ry, rz


@njit(inline="always")
def _desaturation_gain(vec, u, umin, umax):
    kmin = 0.0
    kmax = 0.0
    for i in range(4):
        if abs(vec[i]) < 0.2:
            continue
        if u[i] < umin:
            kk = (umin - u[i]) / vec[i]
            kmin = min(kmin, kk)
            kmax = max(kmax, kk)
        if u[i] > umax:
            kk = (umax - u[i]) / vec[i]
            kmin = min(kmin, kk)
            kmax = max(kmax, kk)
    return kmin + kmax


@njit(inline="always")
def _desaturate(u, vec, umin, umax, reduce_only):
    """ControlAllocationSequentialDesaturation::desaturateActuators (thrust vector: reduce only)."""
    gain = _desaturation_gain(vec, u, umin, umax)
    if reduce_only and gain > 0.0:
        return
    for i in range(4):
        u[i] += gain * vec[i]
    gain = 0.5 * _desaturation_gain(vec, u, umin, umax)
    for i in range(4):
        u[i] += gain * vec[i]


@njit(inline="always")
def _allocate(c0, c1, c2, c3, mix, u):
    """Airmode-disabled mixing of control (roll, pitch, yaw, thrust) into motor commands u in [0, 1]."""
    for i in range(4):
        u[i] = mix[i, 0] * c0 + mix[i, 1] * c1 + mix[i, 3] * c3
    _desaturate(u, mix[:, 3], 0.0, 1.0, True)
    _desaturate(u, mix[:, 0], 0.0, 1.0, False)
    _desaturate(u, mix[:, 1], 0.0, 1.0, False)
    for i in range(4):
        u[i] += mix[i, 2] * c2
    _desaturate(u, mix[:, 2], 0.0, 1.15, False)  # allow some yaw response at full thrust
    _desaturate(u, mix[:, 3], 0.0, 1.0, True)
    for i in range(4):
        u[i] = min(max(u[i], 0.0), 1.0)


@njit(inline="always")
def _rate_pid(d, ax, rate_sp, qvel, s, prm, dt, a_acc):
    """RateControl::update for one axis (P, I, D on the filtered angular acceleration, FF): (torque, error)."""
    base = MC_ROLLRATE_P + 6 * ax  # P, I, D, FF, K, INT_LIM per axis
    gain_k = prm[base + 4]
    rate = qvel[d, 3 + ax]
    acc = (rate - s[d, S_RATE_PREV + ax]) / dt
    s[d, S_RATE_PREV + ax] = rate
    s[d, S_ANG_ACC + ax] += a_acc * (acc - s[d, S_ANG_ACC + ax])
    err = rate_sp - rate
    torque = (
        gain_k * prm[base] * err
        + s[d, S_RATE_INT + ax]
        - gain_k * prm[base + 2] * s[d, S_ANG_ACC + ax]
        + prm[base + 3] * rate_sp
    )
    return torque, err


@njit(inline="always")
def _rate_integral(d, ax, err, requested, u, s, prm, eff, dt):
    """Saturation flags from the achieved control, then RateControl::updateIntegral for one axis."""
    achieved = eff[ax, 0] * u[0] + eff[ax, 1] * u[1] + eff[ax, 2] * u[2] + eff[ax, 3] * u[3]
    sat_pos = requested - achieved > 1e-6
    sat_neg = requested - achieved < -1e-6
    s[d, S_SAT_POS + ax] = 1.0 if sat_pos else 0.0
    s[d, S_SAT_NEG + ax] = 1.0 if sat_neg else 0.0
    if sat_pos:
        err = min(err, 0.0)
    if sat_neg:
        err = max(err, 0.0)
    base = MC_ROLLRATE_P + 6 * ax
    i_factor = err / math.radians(400.0)
    i_factor = max(0.0, 1.0 - i_factor * i_factor)
    lim = prm[base + 5]
    val = s[d, S_RATE_INT + ax] + i_factor * prm[base + 1] * prm[base + 4] * err * dt
    s[d, S_RATE_INT + ax] = min(max(val, -lim), lim)


@njit(inline="always")
def _rate_loop(d, qpos, qvel, s, prm, k, mix, eff):
    """AttitudeControl + RateControl + allocation for drone d: writes the motor commands."""
    dt = k[K_DT] * k[K_RATE_DIV]
    rx, ry, rz = _attitude_control(
        qpos[d, 3],
        qpos[d, 4],
        qpos[d, 5],
        qpos[d, 6],
        s[d, S_QSP],
        s[d, S_QSP + 1],
        s[d, S_QSP + 2],
        s[d, S_QSP + 3],
        prm,
    )
    a_acc = _lowpass_alpha(prm[IMU_DGYRO_CUTOFF], dt)
    c0, e0 = _rate_pid(d, 0, rx, qvel, s, prm, dt, a_acc)
    c1, e1 = _rate_pid(d, 1, ry, qvel, s, prm, dt, a_acc)
    c2, e2 = _rate_pid(d, 2, rz, qvel, s, prm, dt, a_acc)
    s[d, S_YAW_TQ] += _lowpass_alpha(prm[MC_YAW_TQ_CUTOFF], dt) * (c2 - s[d, S_YAW_TQ])
    c2 = s[d, S_YAW_TQ]
    u = s[d, S_U : S_U + 4]
    _allocate(c0, c1, c2, s[d, S_THRUST], mix, u)
    _rate_integral(d, 0, e0, c0, u, s, prm, eff, dt)
    _rate_integral(d, 1, e1, c1, u, s, prm, eff, dt)
    _rate_integral(d, 2, e2, c2, u, s, prm, eff, dt)


@njit(inline="always")
def _motors_and_drag(d, qpos, qvel, xfrc, ctrl, s, k, rotors, wind):
    """Motor lag, then for drone d: the rotor thrusts into ctrl [D, 4] (MuJoCo's site-mounted <motor>
    actuators apply them with their yaw reaction torques) and rotor drag + rolling moments into
    xfrc_applied (world frame, about the centre of mass). With an empty ctrl ([0, 4]: no actuators in
    the scene) the thrust wrench the actuators would apply is summed into xfrc_applied as well."""
    w, x, y, z = qpos[d, 3], qpos[d, 4], qpos[d, 5], qpos[d, 6]
    # body -> world rotation
    r00, r01, r02 = 1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)
    r10, r11, r12 = 2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)
    r20, r21, r22 = 2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)
    wx, wy, wz = qvel[d, 3], qvel[d, 4], qvel[d, 5]
    fx = fy = fz = 0.0
    mx = my = mz = 0.0
    thrust = tbx = tby = tbz = 0.0  # total thrust (N) and its torque in the body frame
    for i in range(4):
        # motor lag towards the commanded speed; thrust = k omega^2 is linear in the command
        ref = k[K_WMAX] * math.sqrt(min(max(s[d, S_U + i], 0.0), 1.0))
        om = s[d, S_OMEGA + i]
        alpha = k[K_ALPHA_UP] if ref > om else k[K_ALPHA_DOWN]
        om = alpha * om + (1.0 - alpha) * ref
        s[d, S_OMEGA + i] = om
        # rotor velocity relative to the air, split along / across the rotor axis (body z)
        px, py, pz = rotors[i, 0], rotors[i, 1], rotors[i, 2]
        cx, cy, cz = wy * pz - wz * py, wz * px - wx * pz, wx * py - wy * px  # omega x r (body)
        vx = qvel[d, 0] + r00 * cx + r01 * cy + r02 * cz - wind[0]
        vy = qvel[d, 1] + r10 * cx + r11 * cy + r12 * cz - wind[1]
        vz = qvel[d, 2] + r20 * cx + r21 * cy + r22 * cz - wind[2]
        vpar = vx * r02 + vy * r12 + vz * r22
        vx, vy, vz = vx - vpar * r02, vy - vpar * r12, vz - vpar * r22
        scalar = min(max(1.0 - abs(vpar) / 25.0, 0.0), 1.0)  # Gazebo: no thrust at 25 m/s axial airspeed
        t_i = k[K_KT] * om * om * scalar
        s[d, S_THRUST_N + i] = t_i
        # a <motor site=rotor_i gear="0 0 1 0 0 -spin_i km">: force t_i along body z at the rotor,
        # torque r_i x (0, 0, t_i) + (0, 0, -spin_i km t_i) (a CCW rotor pushes the body clockwise)
        thrust += t_i
        tbx += py * t_i
        tby -= px * t_i
        tbz -= rotors[i, 3] * k[K_KM] * t_i
        drag = -abs(om) * k[K_CRD]
        dfx, dfy, dfz = drag * vx, drag * vy, drag * vz
        fx += dfx
        fy += dfy
        fz += dfz
        # torque about the centre of mass: (R r) x F + rolling moment
        rx = r00 * px + r01 * py + r02 * pz
        ry = r10 * px + r11 * py + r12 * pz
        rz = r20 * px + r21 * py + r22 * pz
        roll = -abs(om) * rotors[i, 3] * k[K_CRM]
        mx += ry * dfz - rz * dfy + roll * vx
        my += rz * dfx - rx * dfz + roll * vy
        mz += rx * dfy - ry * dfx + roll * vz
    s[d, S_DRAG], s[d, S_DRAG + 1], s[d, S_DRAG + 2] = fx, fy, fz
    s[d, S_DRAG + 3], s[d, S_DRAG + 4], s[d, S_DRAG + 5] = mx, my, mz
    if ctrl.shape[0] > 0:  # live actuators: MuJoCo applies the thrusts, xfrc_applied carries the drag
        for i in range(4):
            ctrl[d, i] = s[d, S_THRUST_N + i]
        xfrc[d, 0], xfrc[d, 1], xfrc[d, 2] = fx, fy, fz
        xfrc[d, 3], xfrc[d, 4], xfrc[d, 5] = mx, my, mz
        return
    xfrc[d, 0] = fx + r02 * thrust
    xfrc[d, 1] = fy + r12 * thrust
    xfrc[d, 2] = fz + r22 * thrust
    xfrc[d, 3] = mx + r00 * tbx + r01 * tby + r02 * tbz
    xfrc[d, 4] = my + r10 * tbx + r11 * tby + r12 * tbz
    xfrc[d, 5] = mz + r20 * tbx + r21 * tby + r22 * tbz


@njit
def cascade_step(tick, qpos, qvel, xfrc, s, sp, wind, prm, k, mix, eff, rotors, ctrl=None):
    """One physics step of the cascade for all drones of one env.

    ctrl: MuJoCo's `data.ctrl` as [D, 4] (the scene's rotor actuators, drone by drone, in the
    airframe's motor order): the rotor thrusts go there and xfrc [D, 6] gets the rotor drag only.
    Omitted (or [0, 4]): no actuators, the whole rotor wrench goes into xfrc.

    Returns -1, or the index of the first drone whose state is non-finite or tilted past the flip
    threshold (the caller raises SimulationDiverged).
    """
    if ctrl is None:
        return _cascade_tick(tick, qpos, qvel, xfrc, np.empty((0, 4)), s, sp, wind, prm, k, mix, eff, rotors)
    return _cascade_tick(tick, qpos, qvel, xfrc, ctrl, s, sp, wind, prm, k, mix, eff, rotors)


@njit
def _cascade_tick(tick, qpos, qvel, xfrc, ctrl, s, sp, wind, prm, k, mix, eff, rotors):
    """cascade_step with ctrl always given ([D, 4], or [0, 4] for no actuators)."""
    run_pos = tick % int(k[K_POS_DIV]) == 0
    run_rate = tick % int(k[K_RATE_DIV]) == 0
    bad = -1
    for d in range(qpos.shape[0]):
        finite = True
        for j in range(7):
            if not math.isfinite(qpos[d, j]):
                finite = False
        for j in range(6):
            if not math.isfinite(qvel[d, j]):
                finite = False
        upright = 1.0 - 2.0 * (qpos[d, 4] * qpos[d, 4] + qpos[d, 5] * qpos[d, 5])
        if not finite or upright < k[K_COS_FLIP]:
            if bad < 0:
                bad = d
            continue
        if run_pos:
            _position_loop(d, qpos, qvel, s, sp, prm, k)
        if run_rate:
            _rate_loop(d, qpos, qvel, s, prm, k, mix, eff)
        _motors_and_drag(d, qpos, qvel, xfrc, ctrl, s, k, rotors, wind)
    return bad


@intrinsic
def _call_step(typingctx, fn, model, data):
    """Call the C function `void fn(const mjModel*, mjData*)` at address fn (all three are integers)."""
    sig = types.void(types.uintp, types.uintp, types.uintp)

    def codegen(context, builder, signature, args):
        ptr = ir.IntType(8).as_pointer()
        fnty = ir.FunctionType(ir.VoidType(), [ptr, ptr])
        fptr = builder.inttoptr(args[0], fnty.as_pointer())
        builder.call(fptr, [builder.inttoptr(args[1], ptr), builder.inttoptr(args[2], ptr)])
        return context.get_dummy_value()

    return sig, codegen


@njit
def run_physics(
    tick,
    n_steps,
    step_fn,
    model,
    data,
    qpos,
    qvel,
    xfrc,
    ctrl,
    contacts,
    collided,
    s,
    sp,
    wind,
    prm,
    k,
    mix,
    eff,
    rotors,
):
    """n_steps physics steps of one env from `tick`: the cascade, then MuJoCo's `mj_step` (called
    through its C address `step_fn` on the mjModel/mjData addresses `model`, `data`), all compiled.

    ctrl [D, 4]: the env's `data.ctrl` (rotor thrust actuators), or [0, 4] when the scene has none
    (see cascade_step).

    contacts [N, 2]: per UAV the MuJoCo contact-sensor counts (all contacts of its footprint, those
    with the floor); collided [N] is set where the first exceeds the second after a step.
    Returns (steps run, bad drone or -1); a bad drone (see cascade_step) stops before its mj_step.
    """
    for j in range(n_steps):
        bad = _cascade_tick(tick + j, qpos, qvel, xfrc, ctrl, s, sp, wind, prm, k, mix, eff, rotors)
        if bad >= 0:
            return j, bad
        _call_step(step_fn, model, data)
        for i in range(collided.shape[0]):
            if contacts[i, 0] > contacts[i, 1]:
                collided[i] = True
    return n_steps, -1


@njit
def _velocity_command(accel, dt, state, sp):
    """Px4Cascade.command's velocity interface for every drone: v_sp <- clip_norm(v_sp + a dt, vmax),
    feed-forward (v_sp_new - v_sp) / dt into the setpoints (the state's v_sp advances at position ticks)."""
    for b in range(accel.shape[0]):
        for d in range(accel.shape[1]):
            vx, vy = state[b, d, S_VSP], state[b, d, S_VSP + 1]
            tx, ty = vx + accel[b, d, 0] * dt, vy + accel[b, d, 1] * dt
            speed = math.sqrt(tx * tx + ty * ty)
            vmax = sp[b, d, SP_VMAX]
            scale = vmax / max(speed, 1e-300) if speed > vmax else 1.0
            sp[b, d, SP_AX] = (tx * scale - vx) / dt
            sp[b, d, SP_AY] = (ty * scale - vy) / dt


# ----------------------------------------------------------------------------- wrapper
@dataclass(frozen=True)
class CascadeTiming:
    """Loop rates of the cascade, as divisors of the physics rate."""

    physics_dt: float
    """Physics step (s); the motor model and rotor drag run every step."""
    rate_div: int
    """Attitude + rate loop every this many physics steps (PX4: rate loop on gyro updates)."""
    pos_div: int
    """Offboard interface + position control every this many physics steps (PX4: ~50-100 Hz)."""


class Px4Cascade:
    """The cascade's constants and per-drone state for B envs x D drones (arguments of `cascade_step`).

    >>> from cefc_mj.control.airframe import load_airframe
    >>> from cefc_mj.control.params import load_params
    >>> c = Px4Cascade(load_airframe("iris"), load_params("iris"), CascadeTiming(0.002, 2, 5), n_envs=1, n_drones=3)
    >>> c.state.shape
    (1, 3, 55)
    """

    def __init__(
        self,
        airframe: Airframe,
        params: dict[str, float],
        timing: CascadeTiming,
        n_envs: int,
        n_drones: int,
        speed_limit_tau: float = 0.35,
        disturbance_tau: float = 0.1,
        flip_tilt_deg: float = 90.0,
        gravity: float = 9.81,
        offboard: str = "velocity",
    ):
        if offboard not in OFFBOARD_MODES:
            raise ValueError(f"offboard must be one of {', '.join(OFFBOARD_MODES)}, got {offboard!r}")
        self.offboard = offboard
        self.airframe = airframe
        self.params = params
        self.timing = timing
        self.prm = np.array([params[n] for n in PARAM_NAMES], dtype=np.float64)
        self.mix, self.eff = px4_mixer(airframe)
        k = np.zeros(N_CONSTS)
        k[K_DT] = timing.physics_dt
        k[K_RATE_DIV] = timing.rate_div
        k[K_POS_DIV] = timing.pos_div
        k[K_G] = gravity
        k[K_MASS] = airframe.mass
        k[K_KT] = airframe.motor_constant
        k[K_WMAX] = airframe.max_rot_velocity
        k[K_ALPHA_UP] = math.exp(-timing.physics_dt / airframe.time_constant_up)
        k[K_ALPHA_DOWN] = math.exp(-timing.physics_dt / airframe.time_constant_down)
        k[K_CRD] = airframe.rotor_drag_coefficient
        k[K_CRM] = airframe.rolling_moment_coefficient
        k[K_SPEED_TAU] = speed_limit_tau
        k[K_COS_FLIP] = math.cos(math.radians(flip_tilt_deg))
        k[K_DIST_TAU] = disturbance_tau
        k[K_KM] = airframe.moment_constant
        k[K_OFFBOARD] = OFFBOARD_MODES[offboard]
        k[K_HOLD_P] = HOLD_POSITION_GAIN
        self.k = k
        self.rotors = np.concatenate([airframe.rotor_pos, airframe.spin[:, None]], axis=1)
        self.gravity = gravity
        self.state = np.zeros((n_envs, n_drones, N_STATE))
        self.setpoint = np.zeros((n_envs, n_drones, 4))

    def reset(self, env: int) -> None:
        """Put env's drones in a level hover (rotors at hover speed, integrators empty); zero acceleration setpoints."""
        s = self.state[env]
        s[:] = 0.0
        hover_u = self.airframe.hover_thrust(self.gravity)
        s[:, S_OMEGA : S_OMEGA + 4] = self.airframe.max_rot_velocity * math.sqrt(hover_u)
        s[:, S_U : S_U + 4] = hover_u
        s[:, S_QSP] = 1.0
        s[:, S_THRUST] = hover_u
        s[:, S_THRUST_N : S_THRUST_N + 4] = hover_u * self.airframe.max_thrust
        self.setpoint[env, :, SP_AX : SP_AY + 1] = 0.0

    def command(self, accel: np.ndarray, decision_dt: float, envs: slice = slice(None)) -> None:
        """Hand the offboard interface one decision step's horizontal acceleration setpoints [B, D, 2]
        (B: the envs selected by `envs`, default all; the others' setpoints are left as they are).

        "acceleration": the setpoint itself. "velocity": the velocity setpoint is integrated as the
        particle world integrates velocity, v_sp <- clip_norm(v_sp + a dt, vmax), and reached by a
        ramp over the decision step: the feed-forward is the ramp's slope (v_sp_new - v_sp) / dt, which
        is a unless the speed limit clips, and the position loop adds slope x its period to v_sp at
        each of its ticks (decision_dt must be a whole number of position-loop periods).
        """
        if self.offboard != "velocity":
            self.setpoint[envs, :, SP_AX : SP_AY + 1] = accel
            return
        _velocity_command(
            np.ascontiguousarray(accel, dtype=np.float64), float(decision_dt), self.state[envs], self.setpoint[envs]
        )

    @contextmanager
    def holding(self, env: int, position: np.ndarray, wind: np.ndarray | None = None):
        """Within the block the cascade flies PX4's position hold at `position` [D, 2] (m) instead of
        the offboard interface: the velocity setpoint is MPC_XY_P x the position error (norm-limited to
        the speed limit) and PX4's horizontal velocity PID, integral included, flies it, as a PX4
        vehicle holds in Position mode before offboard starts. Only env's drones should be advanced
        inside it (the mode is the cascade's, shared by its envs). On leaving, env's velocity setpoints
        are zeroed (an episode's first setpoint starts from rest); the integrals stay.

        wind [3] (m/s): the velocity integrals start where a long hold in this steady wind takes them,
        against the rotor drag at hover (a vehicle that took off into its wind a while ago), so that a
        short hold settles; without it they start empty (PX4's integral, I = MPC_XY_VEL_I_ACC, takes
        tens of seconds to build up a Wind-8 push)."""
        mode = self.k[K_OFFBOARD]
        self.state[env, :, S_HOLD : S_HOLD + 2] = position
        if wind is not None:
            hover_omega = self.airframe.max_rot_velocity * math.sqrt(self.airframe.hover_thrust(self.gravity))
            drag_gain = self.airframe.rotor_drag_coefficient * 4.0 * hover_omega / self.airframe.mass
            self.state[env, :, S_VEL_INT : S_VEL_INT + 2] = -drag_gain * np.asarray(wind, dtype=np.float64)[:2]
        self.setpoint[env, :, SP_AX : SP_AY + 1] = 0.0
        self.k[K_OFFBOARD] = OFFBOARD_HOLD
        try:
            yield
        finally:
            self.k[K_OFFBOARD] = mode
            self.state[env, :, S_VSP : S_VSP + 2] = 0.0

    # read-only views for tests and visualisation
    def motor_speeds(self, env: int) -> np.ndarray:
        """[D, 4] rotor speeds (rad/s)."""
        return self.state[env, :, S_OMEGA : S_OMEGA + 4]

    def motor_thrusts(self, env: int) -> np.ndarray:
        """[D, 4] rotor thrusts (N) applied at the last physics step."""
        return self.state[env, :, S_THRUST_N : S_THRUST_N + 4]

    def drag_wrenches(self, env: int) -> np.ndarray:
        """[D, 6] rotor drag + rolling moment (world force N, torque N m about the CoM), last physics step."""
        return self.state[env, :, S_DRAG : S_DRAG + 6]

    def velocity_setpoints(self, env: int) -> np.ndarray:
        """[D, 2] horizontal velocity setpoints (m/s; offboard "velocity")."""
        return self.state[env, :, S_VSP : S_VSP + 2]
