"""The compiled PX4-like cascade against a slow, obvious numpy reference; parameter and airframe errors."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cefc_mj.control import cascade as C
from cefc_mj.control.airframe import load_airframe, px4_mixer
from cefc_mj.control.params import PARAM_NAMES, load_params, parse_params
from cefc_mj.errors import ConfigError
from cefc_mj.paths import CONTROLLERS_DIR


# ----------------------------------------------------------------------------- numpy reference
def qmul(a, b):
    """Hamilton product of [w, x, y, z] quaternions."""
    w1, v1 = a[0], np.asarray(a[1:])
    w2, v2 = b[0], np.asarray(b[1:])
    return np.concatenate([[w1 * w2 - v1 @ v2], w1 * v2 + w2 * v1 + np.cross(v1, v2)])


def conj(q):
    return np.array([q[0], -q[1], -q[2], -q[3]])


def rot(q):
    """Body -> world rotation matrix of a [w, x, y, z] quaternion (scipy wants [x, y, z, w])."""
    return Rotation.from_quat([q[1], q[2], q[3], q[0]]).as_matrix()


def quat_of(matrix):
    x, y, z, w = Rotation.from_matrix(matrix).as_quat()
    q = np.array([w, x, y, z])
    return q if q[0] >= 0 else -q


def lowpass_alpha(cutoff, dt):
    return 1.0 if cutoff <= 0 else dt / (dt + 1.0 / (2 * math.pi * cutoff))


def desaturate(u, vec, umin, umax, reduce_only):
    def gain(u):
        ks = [0.0]
        for i in range(4):
            if abs(vec[i]) < 0.2:
                continue
            if u[i] < umin:
                ks.append((umin - u[i]) / vec[i])
            if u[i] > umax:
                ks.append((umax - u[i]) / vec[i])
        return min(ks) + max(ks)

    g = gain(u)
    if reduce_only and g > 0:
        return u
    u = u + g * vec
    return u + 0.5 * gain(u) * vec


def reference_tick(tick, qpos, qvel, s, sp, wind, p, k, mix, eff, rotors):
    """One physics step of the cascade for one drone, written for reading, not speed.

    qpos [7], qvel [6], s [N_STATE] (copied), sp [4], p {PX4 name: value}, k the constants array.
    Returns (s, xfrc): the new state and the wrench on the body (world frame, about the CoM).
    """
    s = s.copy()
    g, m, dt_phys = k[C.K_G], k[C.K_MASS], k[C.K_DT]
    pos, q, v, body_rate = qpos[:3], qpos[3:], qvel[:3], qvel[3:]
    R = rot(q)
    omega = s[C.S_OMEGA : C.S_OMEGA + 4]

    if tick % int(k[C.K_POS_DIV]) == 0:
        dt = dt_phys * k[C.K_POS_DIV]
        drag_gain = k[C.K_CRD] * np.abs(omega).sum() / m
        mode = k[C.K_OFFBOARD]
        velocity_mode = mode in (C.OFFBOARD_VELOCITY, C.OFFBOARD_HOLD)
        measured = (v[:2] - s[C.S_VXY_PREV : C.S_VXY_PREV + 2]) / dt
        s[C.S_VXY_PREV : C.S_VXY_PREV + 2] = v[:2]
        if velocity_mode:  # PX4 _velocityControl on the ramped setpoint, feed-forward = ramp slope
            if mode == C.OFFBOARD_HOLD:  # PX4 _positionControl: v_sp = MPC_XY_P x position error, capped
                v_sp = k[C.K_HOLD_P] * (s[C.S_HOLD : C.S_HOLD + 2] - pos[:2])
                if np.linalg.norm(v_sp) > sp[C.SP_VMAX]:
                    v_sp = v_sp / np.linalg.norm(v_sp) * sp[C.SP_VMAX]
                s[C.S_VSP : C.S_VSP + 2] = v_sp
                ff = np.zeros(2)
            else:
                ff = sp[C.SP_AX : C.SP_AX + 2]
                s[C.S_VSP : C.S_VSP + 2] += ff * dt
            s[C.S_VEL_DOT : C.S_VEL_DOT + 2] += lowpass_alpha(p["MPC_VELD_LP"], dt) * (
                measured - s[C.S_VEL_DOT : C.S_VEL_DOT + 2]
            )
            err_xy = s[C.S_VSP : C.S_VSP + 2] - v[:2]
            acc = (
                ff
                + p["MPC_XY_VEL_P_ACC"] * err_xy
                + s[C.S_VEL_INT : C.S_VEL_INT + 2]
                - p["MPC_XY_VEL_D_ACC"] * s[C.S_VEL_DOT : C.S_VEL_DOT + 2]
            )
        elif mode == C.OFFBOARD_ACCELERATION:  # PX4: the setpoint itself
            acc = sp[C.SP_AX : C.SP_AX + 2].copy()
        else:  # "acceleration-assisted"
            explained = s[C.S_THRUST_N : C.S_THRUST_N + 4].sum() / m * R[:2, 2] - drag_gain * v[:2]
            beta = dt / (dt + k[C.K_DIST_TAU])
            s[C.S_DIST : C.S_DIST + 2] += beta * (measured - explained - s[C.S_DIST : C.S_DIST + 2])
            push = s[C.S_DIST : C.S_DIST + 2]
            acc = sp[C.SP_AX : C.SP_AX + 2].copy()
            tau, vmax = k[C.K_SPEED_TAU], sp[C.SP_VMAX]
            predicted = v[:2] + (acc + push) * tau
            if np.linalg.norm(predicted) > vmax:
                acc = (predicted / np.linalg.norm(predicted) * vmax - v[:2]) / tau - push
        if mode in (C.OFFBOARD_VELOCITY, C.OFFBOARD_ACCELERATION_ASSISTED):
            acc = acc + drag_gain * v[:2]
        s[C.S_ACC_CMD : C.S_ACC_CMD + 2] = acc

        vz_sp = np.clip(p["MPC_Z_P"] * (sp[C.SP_Z] - pos[2]), -p["MPC_Z_VEL_MAX_DN"], p["MPC_Z_VEL_MAX_UP"])
        vz_dot = (v[2] - s[C.S_VZ_PREV]) / dt
        s[C.S_VZ_PREV] = v[2]
        err_z = vz_sp - v[2]
        az = p["MPC_Z_VEL_P_ACC"] * err_z + s[C.S_Z_INT] - p["MPC_Z_VEL_D_ACC"] * vz_dot
        body_z = np.array([acc[0], acc[1], g]) / np.linalg.norm([acc[0], acc[1], g])
        tilt, max_tilt = math.acos(body_z[2]), math.radians(p["MPC_TILTMAX_AIR"])
        if tilt > max_tilt:
            horizontal = body_z[:2] / np.linalg.norm(body_z[:2])
            body_z = np.array([*(math.sin(max_tilt) * horizontal), math.cos(max_tilt)])
        hover = p["MPC_THR_HOVER"]
        collective = max((az * hover / g + hover) / body_z[2], p["MPC_THR_MIN"])
        thr = body_z * collective
        if (thr[2] <= p["MPC_THR_MIN"] and err_z <= 0) or (thr[2] >= p["MPC_THR_MAX"] and err_z >= 0):
            err_z = 0.0
        txy = np.linalg.norm(thr[:2])
        thr[2] = min(thr[2], math.sqrt(p["MPC_THR_MAX"] ** 2 - min(txy, p["MPC_THR_XY_MARG"]) ** 2))
        txy_max = math.sqrt(max(p["MPC_THR_MAX"] ** 2 - thr[2] ** 2, 0.0))
        if txy > txy_max:
            thr[:2] *= txy_max / txy
        s[C.S_Z_INT] = np.clip(s[C.S_Z_INT] + err_z * p["MPC_Z_VEL_I_ACC"] * dt, -g, g)
        if velocity_mode:  # tracking anti-windup: the acceleration the saturated thrust still produces
            produced = thr[:2] * g / hover
            if acc @ acc > produced @ produced:
                err_xy = err_xy - 2.0 / p["MPC_XY_VEL_P_ACC"] * (acc - produced)
            s[C.S_VEL_INT : C.S_VEL_INT + 2] += err_xy * p["MPC_XY_VEL_I_ACC"] * dt
        z_axis = thr / np.linalg.norm(thr)
        x_axis = np.cross([0.0, 1.0, 0.0], z_axis)
        x_axis /= np.linalg.norm(x_axis)
        s[C.S_QSP : C.S_QSP + 4] = quat_of(np.column_stack([x_axis, np.cross(z_axis, x_axis), z_axis]))
        s[C.S_THRUST] = np.linalg.norm(thr)

    u = s[C.S_U : C.S_U + 4].copy()
    if tick % int(k[C.K_RATE_DIV]) == 0:
        dt = dt_phys * k[C.K_RATE_DIV]
        qd = s[C.S_QSP : C.S_QSP + 4]
        e_z, e_zd = R[:, 2], rot(qd)[:, 2]
        axis = np.cross(e_z, e_zd)
        angle = math.atan2(np.linalg.norm(axis), e_z @ e_zd)
        rv = axis / np.linalg.norm(axis) * angle if np.linalg.norm(axis) > 0 else np.zeros(3)
        qd_red = qmul(quat_of(Rotation.from_rotvec(rv).as_matrix()), q)
        q_mix = qmul(conj(qd_red), qd)
        q_mix = q_mix if q_mix[0] >= 0 else -q_mix
        w = p["MC_YAW_WEIGHT"]
        qd = qmul(qd_red, [math.cos(w * math.acos(min(q_mix[0], 1.0))), 0, 0, math.sin(w * math.asin(q_mix[3]))])
        qe = qmul(conj(q), qd)
        qe = qe if qe[0] >= 0 else -qe
        gains = np.array([p["MC_ROLL_P"], p["MC_PITCH_P"], p["MC_YAW_P"] / w])
        limits = np.radians([p["MC_ROLLRATE_MAX"], p["MC_PITCHRATE_MAX"], p["MC_YAWRATE_MAX"]])
        rate_sp = np.clip(2 * qe[1:] * gains, -limits, limits)

        axes = [("MC_ROLLRATE_", "MC_RR_INT_LIM"), ("MC_PITCHRATE_", "MC_PR_INT_LIM"), ("MC_YAWRATE_", "MC_YR_INT_LIM")]
        ang_acc = (body_rate - s[C.S_RATE_PREV : C.S_RATE_PREV + 3]) / dt
        s[C.S_RATE_PREV : C.S_RATE_PREV + 3] = body_rate
        s[C.S_ANG_ACC : C.S_ANG_ACC + 3] += lowpass_alpha(p["IMU_DGYRO_CUTOFF"], dt) * (
            ang_acc - s[C.S_ANG_ACC : C.S_ANG_ACC + 3]
        )
        err = rate_sp - body_rate
        torque = np.array(
            [
                p[a + "K"] * (p[a + "P"] * err[i] - p[a + "D"] * s[C.S_ANG_ACC + i])
                + s[C.S_RATE_INT + i]
                + p[a + "FF"] * rate_sp[i]
                for i, (a, _) in enumerate(axes)
            ]
        )
        s[C.S_YAW_TQ] += lowpass_alpha(p["MC_YAW_TQ_CUTOFF"], dt) * (torque[2] - s[C.S_YAW_TQ])
        control = np.array([torque[0], torque[1], s[C.S_YAW_TQ], s[C.S_THRUST]])
        u = mix[:, 0] * control[0] + mix[:, 1] * control[1] + mix[:, 3] * control[3]
        u = desaturate(u, mix[:, 3], 0, 1, True)
        u = desaturate(u, mix[:, 0], 0, 1, False)
        u = desaturate(u, mix[:, 1], 0, 1, False)
        u = desaturate(u + mix[:, 2] * control[2], mix[:, 2], 0, 1.15, False)
        u = np.clip(desaturate(u, mix[:, 3], 0, 1, True), 0, 1)
        unallocated = control[:3] - (eff @ u)[:3]
        for i, (a, lim) in enumerate(axes):
            e = err[i]
            s[C.S_SAT_POS + i] = float(unallocated[i] > 1e-6)
            s[C.S_SAT_NEG + i] = float(unallocated[i] < -1e-6)
            if unallocated[i] > 1e-6:
                e = min(e, 0.0)
            if unallocated[i] < -1e-6:
                e = max(e, 0.0)
            factor = max(0.0, 1 - (e / math.radians(400)) ** 2)
            s[C.S_RATE_INT + i] = np.clip(
                s[C.S_RATE_INT + i] + factor * p[a + "I"] * p[a + "K"] * e * dt, -p[lim], p[lim]
            )
        s[C.S_U : C.S_U + 4] = u

    # motors: asymmetric first-order lag on the rotor speed, thrust k omega^2
    reference = k[C.K_WMAX] * np.sqrt(np.clip(u, 0, 1))
    alpha = np.where(reference > omega, k[C.K_ALPHA_UP], k[C.K_ALPHA_DOWN])
    omega = alpha * omega + (1 - alpha) * reference
    s[C.S_OMEGA : C.S_OMEGA + 4] = omega
    force, torque = np.zeros(3), np.zeros(3)
    drag_force, drag_torque = np.zeros(3), np.zeros(3)
    for i in range(4):
        r_body = rotors[i, :3]
        v_rotor = v + R @ np.cross(body_rate, r_body) - wind
        along = v_rotor @ R[:, 2]
        v_perp = v_rotor - along * R[:, 2]
        thrust = k[C.K_KT] * omega[i] ** 2 * np.clip(1 - abs(along) / 25, 0, 1)
        s[C.S_THRUST_N + i] = thrust
        f = -abs(omega[i]) * k[C.K_CRD] * v_perp
        drag_force += f
        drag_torque += np.cross(R @ r_body, f) - abs(omega[i]) * rotors[i, 3] * k[C.K_CRM] * v_perp
        # what MuJoCo's <motor site=rotor_i gear="0 0 1 0 0 -spin_i km"> applies: the thrust along the
        # rotor axis at the rotor, plus the yaw reaction torque about the rotor axis
        f_thrust = thrust * R[:, 2]
        force += f_thrust
        torque += np.cross(R @ r_body, f_thrust) - rotors[i, 3] * k[C.K_KM] * thrust * R[:, 2]
    s[C.S_DRAG : C.S_DRAG + 6] = np.concatenate([drag_force, drag_torque])
    return s, np.concatenate([force + drag_force, torque + drag_torque])


def random_case(rng, cascade, n_drones):
    """Random but physical states: tilts up to ~35 deg, speeds up to 3 m/s, spinning rotors."""
    qpos = np.zeros((n_drones, 7))
    qpos[:, :2] = rng.uniform(-5, 5, (n_drones, 2))
    qpos[:, 2] = rng.uniform(1.5, 2.5, n_drones)
    rv = rng.normal(0, 0.35, (n_drones, 3))
    xyzw = Rotation.from_rotvec(rv).as_quat()
    qpos[:, 3:] = xyzw[:, [3, 0, 1, 2]]
    qvel = rng.normal(0, 1.0, (n_drones, 6))
    s = np.zeros((n_drones, C.N_STATE))
    s[:, C.S_THRUST_N : C.S_THRUST_N + 4] = rng.uniform(2, 6, (n_drones, 4))
    s[:, C.S_OMEGA : C.S_OMEGA + 4] = rng.uniform(500, 1000, (n_drones, 4))
    s[:, C.S_U : C.S_U + 4] = rng.uniform(0.3, 0.7, (n_drones, 4))
    s[:, C.S_QSP : C.S_QSP + 4] = Rotation.from_rotvec(rng.normal(0, 0.2, (n_drones, 3))).as_quat()[:, [3, 0, 1, 2]]
    s[:, C.S_THRUST] = rng.uniform(0.3, 0.8, n_drones)
    for col, scale in (
        (C.S_RATE_INT, 0.1),
        (C.S_RATE_PREV, 1.0),
        (C.S_ANG_ACC, 5.0),
        (C.S_DIST, 1.0),
        (C.S_VXY_PREV, 1.0),
        (C.S_VSP, 1.0),
        (C.S_VEL_INT, 1.0),
        (C.S_VEL_DOT, 2.0),
        (C.S_HOLD, 3.0),
    ):
        width = 2 if col in (C.S_DIST, C.S_VXY_PREV, C.S_VSP, C.S_VEL_INT, C.S_VEL_DOT, C.S_HOLD) else 3
        s[:, col : col + width] = rng.normal(0, scale, (n_drones, width))
    s[:, C.S_YAW_TQ] = rng.normal(0, 0.05, n_drones)
    s[:, C.S_Z_INT] = rng.normal(0, 0.5, n_drones)
    s[:, C.S_VZ_PREV] = rng.normal(0, 0.3, n_drones)
    sp = np.column_stack([rng.uniform(-2, 2, (n_drones, 2)), np.full(n_drones, 2.0), np.full(n_drones, 1.0)])
    wind = np.array([*rng.normal(0, 4, 2), 0.0])
    return qpos, qvel, s, sp, wind


@pytest.fixture(scope="module", params=["velocity", "acceleration", "acceleration-assisted", "hold"])
def cascade(request):
    cascade = C.Px4Cascade(
        load_airframe("iris"),
        load_params("iris"),
        C.CascadeTiming(0.002, 2, 5),
        n_envs=1,
        n_drones=6,
        offboard="velocity" if request.param == "hold" else request.param,
    )
    if request.param == "hold":  # the position hold before an episode (Px4Cascade.holding)
        cascade.k[C.K_OFFBOARD] = C.OFFBOARD_HOLD
    return cascade


@pytest.mark.parametrize("tick", [0, 1, 2, 5])  # all loops / motors only / + rate loop / + position loop
def test_compiled_cascade_matches_numpy_reference(cascade, tick):
    rng = np.random.default_rng(tick)
    p = dict(zip(PARAM_NAMES, cascade.prm))
    for _ in range(5):
        qpos, qvel, s, sp, wind = random_case(rng, cascade, 6)
        if tick == 0:  # large setpoints: the tilt limit and the horizontal anti-windup engage
            sp[:3, C.SP_AX : C.SP_AY + 1] *= 6.0
        s_fast, xfrc_fast = s.copy(), np.zeros((6, 6))
        bad = C.cascade_step(
            tick,
            qpos,
            qvel,
            xfrc_fast,
            s_fast,
            sp,
            wind,
            cascade.prm,
            cascade.k,
            cascade.mix,
            cascade.eff,
            cascade.rotors,
        )
        assert bad == -1
        for d in range(6):
            s_ref, xfrc_ref = reference_tick(
                tick, qpos[d], qvel[d], s[d], sp[d], wind, p, cascade.k, cascade.mix, cascade.eff, cascade.rotors
            )
            # atol 1e-6: a motor command saturated at 0 is 0 +- 1e-15 in either implementation, and
            # the rotor speed follows sqrt(command) (rad/s of order 1e3 elsewhere)
            np.testing.assert_allclose(s_fast[d], s_ref, rtol=1e-9, atol=1e-6)
            np.testing.assert_allclose(xfrc_fast[d], xfrc_ref, rtol=1e-7, atol=1e-9)


def px4_thrust_setpoint(acc_sp_ned, p, g=9.81):
    """PX4's thrust setpoint (normalised, NED) for a horizontal acceleration setpoint with the horizontal
    position and velocity setpoints NaN, transcribed from PX4-Autopilot
    src/modules/mc_pos_control/PositionControl/PositionControl.cpp: `_accelerationControl` (body_z =
    normalize(-a_x, -a_y, g), ControlMath::limitTilt to MPC_TILTMAX_AIR, collective thrust =
    (a_z T_h / g - T_h) / cos(tilt), at most -MPC_THR_MIN), then `_velocityControl`'s saturation (the
    vertical axis first, keeping MPC_THR_XY_MARG, then the horizontal). `_velocityControl` adds nothing
    to the horizontal setpoint here: its P + I + D term is NaN for a NaN velocity setpoint
    (ControlMath::addIfNotNanVector3f)."""
    acc = np.asarray(acc_sp_ned, dtype=np.float64)
    hover = p["MPC_THR_HOVER"]
    body_z = np.array([-acc[0], -acc[1], g]) / np.linalg.norm([-acc[0], -acc[1], g])
    # ControlMath::limitTilt(body_z, (0, 0, 1), MPC_TILTMAX_AIR)
    world_z = np.array([0.0, 0.0, 1.0])
    dot = body_z @ world_z
    angle = min(math.acos(dot), math.radians(p["MPC_TILTMAX_AIR"]))
    rejection = body_z - dot * world_z
    if rejection @ rejection < np.finfo(np.float32).eps:
        rejection = np.array([1.0, 0.0, 0.0])
    body_z = math.cos(angle) * world_z + math.sin(angle) * rejection / np.linalg.norm(rejection)
    collective = (acc[2] * hover / g - hover) / (world_z @ body_z)
    thr = body_z * min(collective, -p["MPC_THR_MIN"])
    # _velocityControl: vertical priority with a horizontal margin, then the horizontal limit
    thr_max = p["MPC_THR_MAX"]
    xy = np.linalg.norm(thr[:2])
    thr[2] = max(thr[2], -math.sqrt(thr_max**2 - min(xy, p["MPC_THR_XY_MARG"]) ** 2))
    xy_max = math.sqrt(max(thr_max**2 - thr[2] ** 2, 0.0))
    if xy > xy_max:
        thr[:2] *= xy_max / xy
    return thr


# (acceleration setpoint ENU m/s^2, velocity m/s, altitude below the setpoint m): level, against a
# fast motion (no speed limit, no drag feed-forward), beyond the tilt limit, and a climb that saturates
PX4_WORKED_CASES = [
    ((2.0, 0.0), (0.0, 0.0), 0.0),
    ((-1.5, 1.0), (5.0, -3.0), 0.0),
    ((12.0, 0.0), (0.0, 0.0), 0.0),
    ((0.0, -3.0), (0.0, 4.0), 0.3),
    ((8.0, 8.0), (1.0, 1.0), 3.0),
]


def test_acceleration_interface_flies_px4s_position_control_mapping():
    """offboard = "acceleration" is PX4's: the attitude and collective thrust setpoints the cascade
    makes of an acceleration setpoint are those of PX4's PositionControl (px4_thrust_setpoint) for the
    same setpoint and the vertical acceleration its altitude loop asks, case by case: tilt, thrust
    direction, collective thrust, tilt limit and saturation; the velocity integral neither acts nor
    moves, and a fast motion is not braked."""
    params = load_params("iris")
    cascade = C.Px4Cascade(
        load_airframe("iris"),
        params,
        C.CascadeTiming(0.002, 2, 5),
        n_envs=1,
        n_drones=len(PX4_WORKED_CASES),
        offboard="acceleration",
    )
    cascade.reset(0)
    n = len(PX4_WORKED_CASES)
    qpos, qvel = np.zeros((n, 7)), np.zeros((n, 6))
    qpos[:, 3] = 1.0
    qpos[:, 2] = 2.0 - np.array([case[2] for case in PX4_WORKED_CASES])
    qvel[:, :2] = [case[1] for case in PX4_WORKED_CASES]
    cascade.setpoint[0, :, C.SP_Z] = 2.0
    cascade.setpoint[0, :, C.SP_VMAX] = 1.0
    cascade.state[0, :, C.S_VEL_INT : C.S_VEL_INT + 2] = (3.0, -2.0)  # left from a hold: must not act
    cascade.command(np.array([[case[0] for case in PX4_WORKED_CASES]]), 0.1)
    s = cascade.state[0]
    assert (
        C.cascade_step(0, qpos, qvel, np.zeros((n, 6)), s, cascade.setpoint[0], np.zeros(3), *_kernel_args(cascade))
        == -1
    )
    g = cascade.gravity
    for d, (acc, _, below) in enumerate(PX4_WORKED_CASES):
        # PX4's altitude loop at this state: v_z = MPC_Z_P x error (capped), a_z = MPC_Z_VEL_P_ACC x v_z (up)
        vz_sp = min(params["MPC_Z_P"] * below, params["MPC_Z_VEL_MAX_UP"])
        a_up = params["MPC_Z_VEL_P_ACC"] * vz_sp
        thr_ned = px4_thrust_setpoint((acc[0], acc[1], -a_up), params, g)
        thr_px4 = np.array([thr_ned[0], thr_ned[1], -thr_ned[2]])  # the cascade's frame: PX4's with z up
        body_z = rot(s[d, C.S_QSP : C.S_QSP + 4])[:, 2]
        collective = s[d, C.S_THRUST]
        np.testing.assert_allclose(collective, np.linalg.norm(thr_px4), rtol=1e-9)
        np.testing.assert_allclose(body_z, thr_px4 / np.linalg.norm(thr_px4), atol=1e-9)
        tilt = math.degrees(math.acos(body_z[2]))
        assert tilt <= params["MPC_TILTMAX_AIR"] + 1e-9
        np.testing.assert_allclose(s[d, C.S_ACC_CMD : C.S_ACC_CMD + 2], acc, rtol=0, atol=0)  # passed as is
    # worked numbers: 2 m/s^2 tilts atan(2 / g) = 11.52 deg at T_h / cos(tilt); 12 m/s^2 hits 45 deg
    body_z = [rot(s[d, C.S_QSP : C.S_QSP + 4])[:, 2] for d in range(n)]
    assert math.degrees(math.acos(body_z[0][2])) == pytest.approx(math.degrees(math.atan2(2.0, g)), abs=1e-9)
    assert s[0, C.S_THRUST] == pytest.approx(params["MPC_THR_HOVER"] / math.cos(math.atan2(2.0, g)), rel=1e-12)
    assert math.degrees(math.acos(body_z[2][2])) == pytest.approx(45.0, abs=1e-9)
    assert s[4, C.S_THRUST] == pytest.approx(params["MPC_THR_MAX"], rel=1e-12)  # the climb saturates
    np.testing.assert_array_equal(s[:, C.S_VEL_INT : C.S_VEL_INT + 2], np.tile([3.0, -2.0], (n, 1)))


def _kernel_args(cascade):
    return cascade.prm, cascade.k, cascade.mix, cascade.eff, cascade.rotors


def test_kernel_writes_rotor_thrusts_to_actuator_controls(cascade):
    """With ctrl given (live actuators) the kernel writes each rotor's thrust there and only the drag to
    xfrc; the state, and the thrusts, are those of the external-wrench kernel to the last bit."""
    rng = np.random.default_rng(11)
    args = (cascade.prm, cascade.k, cascade.mix, cascade.eff, cascade.rotors)
    for tick in (0, 1, 5):
        qpos, qvel, s, sp, wind = random_case(rng, cascade, 6)
        s_ext, xfrc_ext = s.copy(), np.zeros((6, 6))
        s_act, xfrc_act, ctrl = s.copy(), np.full((6, 6), np.nan), np.full((6, 4), np.nan)
        assert C.cascade_step(tick, qpos, qvel, xfrc_ext, s_ext, sp, wind, *args) == -1
        assert C.cascade_step(tick, qpos, qvel, xfrc_act, s_act, sp, wind, *args, ctrl) == -1
        np.testing.assert_array_equal(s_act, s_ext)
        np.testing.assert_array_equal(ctrl, s_act[:, C.S_THRUST_N : C.S_THRUST_N + 4])
        np.testing.assert_array_equal(xfrc_act, s_act[:, C.S_DRAG : C.S_DRAG + 6])
        # what the actuators must add: thrust along body z at each rotor (+ moment) and the yaw reaction
        for d in range(6):
            R = rot(qpos[d, 3:])
            force, torque = np.zeros(3), np.zeros(3)
            for i in range(4):
                f = ctrl[d, i] * R[:, 2]
                force += f
                torque += np.cross(R @ cascade.rotors[i, :3], f) - cascade.rotors[i, 3] * cascade.k[C.K_KM] * f
            np.testing.assert_allclose(
                xfrc_ext[d] - xfrc_act[d], np.concatenate([force, torque]), rtol=1e-9, atol=1e-12
            )


def test_kernel_flags_nan_and_flipped_drones(cascade):
    rng = np.random.default_rng(7)
    qpos, qvel, s, sp, wind = random_case(rng, cascade, 6)
    args = (cascade.prm, cascade.k, cascade.mix, cascade.eff, cascade.rotors)
    qpos[3, 0] = np.nan
    assert C.cascade_step(0, qpos, qvel, np.zeros((6, 6)), s, sp, wind, *args) == 3
    qpos[3, 0] = 0.0
    qpos[4, 3:] = (0.0, 1.0, 0.0, 0.0)  # upside down
    assert C.cascade_step(0, qpos, qvel, np.zeros((6, 6)), s, sp, wind, *args) == 4


def test_velocity_command_integrates_like_the_particle_world():
    """Ten position ticks per decision step of slope x period land v_sp on clip_norm(v_sp + a dt)."""
    cascade = C.Px4Cascade(
        load_airframe("iris"), load_params("iris"), C.CascadeTiming(0.002, 2, 5), n_envs=2, n_drones=3
    )
    cascade.setpoint[..., C.SP_VMAX] = 1.0
    rng = np.random.default_rng(0)
    v = np.zeros((2, 3, 2))
    for _ in range(30):
        a = rng.uniform(-2, 2, (2, 3, 2))
        cascade.command(a, 0.1)
        for _ in range(10):  # what the position loop does at each of its ticks (0.01 s)
            cascade.state[..., C.S_VSP : C.S_VSP + 2] += cascade.setpoint[..., C.SP_AX : C.SP_AY + 1] * 0.01
        v = v + a * 0.1
        v = v * np.minimum(1.0, 1.0 / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-12))
        np.testing.assert_allclose(cascade.state[..., C.S_VSP : C.S_VSP + 2], v, atol=1e-12)
    # the feed-forward is the acceleration itself until the speed limit clips
    cascade.reset(0)
    cascade.reset(1)
    cascade.command(np.full((2, 3, 2), 0.3), 0.1)
    np.testing.assert_allclose(cascade.setpoint[..., C.SP_AX : C.SP_AY + 1], 0.3)


# ----------------------------------------------------------------------------- mixer and airframe
def test_mixer_inverts_the_rotor_effectiveness():
    airframe = load_airframe("iris")
    mix, eff = px4_mixer(airframe)
    torque_per_unit = airframe.effectiveness() @ mix
    # normalised axes are decoupled; roll and pitch share one scale (PX4's normalisation)
    assert np.allclose(torque_per_unit - np.diag(np.diag(torque_per_unit)), 0, atol=1e-9)
    assert torque_per_unit[0, 0] == pytest.approx(torque_per_unit[1, 1])
    # collective thrust 1 = all motors at full thrust
    assert np.allclose(mix[:, 3], 1.0) and torque_per_unit[3, 3] == pytest.approx(4 * airframe.max_thrust)
    # equal commands make no torque: hover needs no trim
    assert np.allclose((airframe.effectiveness() @ np.full(4, 0.5))[:3], 0, atol=1e-12)
    assert np.allclose(eff @ mix, np.eye(4))


def test_rotor_spin_directions_are_quad_x():
    airframe = load_airframe("iris")
    # PX4 quad-X: motors 1, 2 (front-right, back-left) counter-clockwise; 3, 4 clockwise
    assert airframe.spin.tolist() == [1, 1, -1, -1]
    assert airframe.rotor_pos[0, :2].tolist() == [0.13, -0.22] and airframe.rotor_pos[2, :2].tolist() == [0.13, 0.22]
    assert airframe.max_thrust == pytest.approx(5.84e-6 * 1100**2)


def test_unknown_airframe_is_a_config_error():
    with pytest.raises(ConfigError, match="unknown airframe 'iriss'"):
        load_airframe("iriss")


# ----------------------------------------------------------------------------- parameter files
def iris_text():
    return (CONTROLLERS_DIR / "iris.params").read_text()


@pytest.mark.parametrize(
    "name, value",
    [("MC_ROLLRATE_P", "0.9"), ("MPC_TILTMAX_AIR", "95"), ("MC_YAW_WEIGHT", "-0.1"), ("MPC_THR_HOVER", "nan")],
)
def test_parameter_outside_px4_range_is_named(name, value):
    lines = [f"{name} {value}" if line.split()[:1] == [name] else line for line in iris_text().splitlines()]
    with pytest.raises(ConfigError, match=rf"parameter {name} = .* outside PX4's range") as info:
        parse_params("\n".join(lines), "iris.params")
    assert "\n" not in str(info.value)


def test_parameter_file_errors():
    with pytest.raises(ConfigError, match="unknown parameter file 'nope'"):
        load_params("nope")
    with pytest.raises(ConfigError, match="unknown parameter MC_ROLL_PP"):
        parse_params(iris_text() + "\nMC_ROLL_PP 1.0\n")
    with pytest.raises(ConfigError, match="missing parameter MC_YAW_P"):
        parse_params("\n".join(line for line in iris_text().splitlines() if not line.startswith("MC_YAW_P ")))
    with pytest.raises(ConfigError, match="MC_ROLL_P = 'fast' is not a number"):
        parse_params(iris_text().replace("MC_ROLL_P         6.5", "MC_ROLL_P fast"))
    with pytest.raises(ConfigError, match="MC_ROLL_P is set twice"):
        parse_params(iris_text() + "\nMC_ROLL_P 6.0\n")


def test_shipped_parameter_file_loads():
    params = load_params("iris")
    assert set(params) == set(PARAM_NAMES)
    assert params["MPC_THR_HOVER"] == pytest.approx(load_airframe("iris").hover_thrust(), abs=0.005)
