"""Airframes: the shipped Crazyflie-class micro quad flies (hover, acceleration step, a Table VIII-like
episode), any MJCF quadrotor with four site-mounted thrust motors and a params file flies, and a file
that is not such a quadrotor is refused with one clear line."""

from __future__ import annotations

import math

import numpy as np
import pytest

from cefc_mj.control.airframe import load_airframe
from cefc_mj.control.params import load_params
from cefc_mj.env import BatchedCEFCEnv
from cefc_mj.errors import ConfigError
from cefc_mj.eval.runner import EpisodeSpec, load_policy_for
from cefc_mj.paths import CONTROLLERS_DIR
from cefc_mj.sim.mujoco_world import MujocoWorld, MujocoWorldConfig, make_mujoco_world

G = 9.81
ALL = np.ones(1, dtype=bool)


def single_drone(airframe, wind=None, **config):
    world = MujocoWorld(
        MujocoWorldConfig(airframe=str(airframe), **config),
        n_envs=1,
        n_agents=1,
        n_obstacles=0,
        with_adversary=False,
        wind=wind,
        seed=3,
    )
    world.reset(ALL, np.zeros((1, 1, 2)), np.zeros((1, 2)), np.zeros((1, 0, 2)))
    return world


def fly(world, accel, steps):
    """Hold accel [2] for `steps` decision steps; positions [steps, 3] of UAV 0."""
    a = np.broadcast_to(np.asarray(accel, dtype=float), (1, world.n_agents, 2))
    out = []
    for _ in range(steps):
        world.step(a, np.zeros((1, 2)))
        out.append(world.drone_positions[0, 0].copy())
    return np.array(out)


# ----------------------------------------------------------------------------- the shipped micro quad
def test_crazyflie_airframe_is_the_public_micro_quad():
    cf, iris = load_airframe("crazyflie"), load_airframe("iris")
    assert 0.027 <= cf.mass <= 0.030 and cf.mass / iris.mass < 0.02
    np.testing.assert_allclose(np.linalg.norm(cf.rotor_pos[:, :2], axis=1), 0.046, rtol=1e-5)  # 92 mm motor to motor
    assert cf.spin.tolist() == [1, 1, -1, -1]  # PX4 quad-X order, as iris
    assert cf.max_thrust == pytest.approx(0.1597, abs=1e-4)  # Foerster: 0.1597 N at full command
    assert 4 * cf.max_thrust / (cf.mass * G) == pytest.approx(2.41, abs=0.01)  # thrust-to-weight
    assert cf.hover_rot_velocity() == pytest.approx(1965, abs=1)
    assert load_params("crazyflie")["MPC_THR_HOVER"] == pytest.approx(cf.hover_thrust(), abs=0.01)


def test_crazyflie_hovers_and_tracks_an_acceleration_step():
    world = single_drone("crazyflie")
    assert world.params_file == CONTROLLERS_DIR / "crazyflie.params"
    assert world.models[0].nu == 4 and world.models[0].body_mass[1] == pytest.approx(0.027)
    start = world.drone_positions[0, 0].copy()
    hover = fly(world, (0.0, 0.0), 100)  # 10 s
    assert np.linalg.norm(hover - start, axis=1).max() < 0.02
    np.testing.assert_allclose(world.motor_thrusts[0, 0], 0.027 * G / 4, rtol=0.01)
    np.testing.assert_array_equal(world.datas[0].ctrl, world.motor_thrusts[0, 0])  # MuJoCo's actuators carry them
    step = fly(world, (0.25, 0.0), 20)  # 2 s
    v_at_2s = world.agent_vel[0, 0].copy()
    settle = fly(world, (0.0, 0.0), 5)
    assert v_at_2s[0] == pytest.approx(0.5, rel=0.10)
    assert world.agent_vel[0, 0, 0] == pytest.approx(0.5, rel=0.05)
    assert abs(world.agent_vel[0, 0, 1]) < 1e-6
    assert np.abs(np.concatenate([hover, step, settle])[:, 2] - 2.0).max() < 0.02
    assert world.tilt_deg().max() < 45.0


def test_crazyflie_flies_a_table8_like_episode_without_diverging():
    """The shipped AT-M policy for c = 5 flies five micro quads for 30 s in Wind-3 through the task core,
    as run_episode does (only the airframe differs). The footprint disc stays the task's uav_radius."""
    spec = EpisodeSpec(formation=5, seed=0, steps=300, wind=3.0)
    config = spec.task_config()
    world = make_mujoco_world(config, wind=spec.wind, seed=spec.seed, airframe="crazyflie")
    assert world.airframe.name == "crazyflie" and world.models[0].nu == 4 * 5
    assert world.models[0].geom("uav0_footprint").size[0] == config.uav_radius
    env = BatchedCEFCEnv(config, n_envs=1, seed=spec.seed, world=world)
    policy = load_policy_for("atm", 5)
    obs = env.reset()
    altitudes, tilts = [], []
    for _ in range(spec.steps):
        obs, _, done, _ = env.step(policy.act(obs))  # SimulationDiverged would fail the test
        altitudes.append(world.drone_positions[0, :, 2].copy())
        tilts.append(world.tilt_deg().max())
    assert int(env.t[0]) == spec.steps
    assert np.abs(np.array(altitudes) - 2.0).max() < 0.1 and max(tilts) < 45.0
    assert np.linalg.norm(world.agent_vel[0], axis=-1).max() < 2.0


def test_iris_gains_on_the_micro_quad_are_refused():
    with pytest.raises(
        ConfigError, match=r"MPC_THR_HOVER = 0.52 in iris.params but airframe 'crazyflie' hovers at 0.415"
    ) as info:
        MujocoWorld(MujocoWorldConfig(airframe="crazyflie", params="iris"), 1, 1, 0)
    assert "\n" not in str(info.value)


# ----------------------------------------------------------------------------- bring your own airframe
# A Skydio-X2-like file in MuJoCo Menagerie's style: mass from geoms (no <inertial>), collision geoms of
# its own, no footprint, rotor sites at two heights, its own motor order (back-right, back-left,
# front-left, front-right), an IMU site with sensors and a keyframe, plus the motor model.
# (Menagerie's x2.xml gives both right rotors one spin and both left rotors the other, so its yaw torque
# is a multiple of its roll torque; here the diagonal pairs share a spin, as on a real quad-X.)
QUAD = """
<mujoco model="quad">
  <compiler autolimits="true"/>
  <custom>
    <numeric name="motor_constant" data="9.0278e-06"/>
    <numeric name="max_rot_velocity" data="1200"/>
    <numeric name="time_constant_up" data="0.0125"/>
    <numeric name="time_constant_down" data="0.025"/>
    <numeric name="rotor_drag_coefficient" data="1.75e-04"/>
    <numeric name="rolling_moment_coefficient" data="1e-06"/>
  </custom>
  <default>
    <default class="quad">
      <geom mass="0"/>
      <motor ctrlrange="0 13"/>
      <default class="collision"><geom group="3" type="box"/></default>
      <default class="rotor"><geom type="ellipsoid" size=".13 .13 .01"/></default>
      <site group="5"/>
    </default>
  </default>
  <worldbody>
    <body name="quad" pos="0 0 0.1" childclass="quad">
      <freejoint/>
      <site name="imu" pos="0 0 .02"/>
      <geom class="collision" size=".06 .027 .02" pos=".04 0 .02"/>
      <geom class="collision" size=".05 .027 .02" pos="-.07 0 .065"/>
      <geom name="rotor1" class="rotor" pos="-.14 -.18 .05" mass=".25"/>
      <geom name="rotor2" class="rotor" pos="-.14 .18 .05" mass=".25"/>
      <geom name="rotor3" class="rotor" pos=".14 .18 .08" mass=".25"/>
      <geom name="rotor4" class="rotor" pos=".14 -.18 .08" mass=".25"/>
      <geom size=".16 .04 .02" pos="0 0 0.02" type="ellipsoid" mass=".325"/>
      <site name="thrust1" pos="-.14 -.18 .05"/>
      <site name="thrust2" pos="-.14 .18 .05"/>
      <site name="thrust3" pos=".14 .18 .08"/>
      <site name="thrust4" pos=".14 -.18 .08"/>
    </body>
  </worldbody>
  <actuator>
    <motor class="quad" name="thrust1" site="thrust1" gear="0 0 1 0 0 -.0201"/>
    <motor class="quad" name="thrust2" site="thrust2" gear="0 0 1 0 0 .0201"/>
    <motor class="quad" name="thrust3" site="thrust3" gear="0 0 1 0 0 -.0201"/>
    <motor class="quad" name="thrust4" site="thrust4" gear="0 0 1 0 0 .0201"/>
  </actuator>
  <sensor>
    <gyro name="body_gyro" site="imu"/>
  </sensor>
  <keyframe>
    <key name="hover" qpos="0 0 .3 1 0 0 0"/>
  </keyframe>
</mujoco>
"""
QUAD_HOVER = 1.325 * G / (4 * 13.0)  # 1.325 kg on four 13 N rotors: 0.25


def write_quad(folder, text=QUAD, params=True, name="quad"):
    path = folder / f"{name}.xml"
    path.write_text(text)
    if params:
        gains = (
            (CONTROLLERS_DIR / "iris.params").read_text().replace("MPC_THR_HOVER     0.52", "MPC_THR_HOVER     0.25")
        )
        (folder / f"{name}.params").write_text(gains)
    return path


def test_your_own_mjcf_quadrotor_flies_with_its_actuators_live(tmp_path):
    path = write_quad(tmp_path)
    airframe = load_airframe(path)
    assert airframe.body_name == "quad" and airframe.rotor_sites == ("thrust1", "thrust2", "thrust3", "thrust4")
    assert airframe.mass == pytest.approx(1.325) and airframe.spin.tolist() == [1, -1, 1, -1]
    assert airframe.hover_thrust() == pytest.approx(QUAD_HOVER, rel=1e-4)
    world = MujocoWorld(MujocoWorldConfig(airframe=str(path)), n_envs=1, n_agents=2, n_obstacles=0, seed=0)
    world.reset(ALL, np.array([[[0.0, 0.0], [2.0, 0.0]]]), np.array([[0.0, 4.0]]), np.zeros((1, 0, 2)))
    model = world.models[0]
    assert world.params_file == tmp_path / "quad.params"
    assert model.nu == 12 and model.nsensordata == 4 and model.nkey == 0  # its gyro and keyframe are left out
    assert model.actuator(4).name == "uav1_thrust1" and model.site(model.actuator_trnid[4, 0]).name == "uav1_thrust1"
    np.testing.assert_allclose(model.body_mass[1:4], 1.325)  # kept though its geoms are gone
    assert model.geom("uav0_footprint").size[0] == world.uav_radius  # added by the world
    start = world.drone_positions[0].copy()
    for _ in range(30):  # 3 s of hover
        world.step(np.zeros((1, 2, 2)), np.zeros((1, 2)))
    assert np.linalg.norm(world.drone_positions[0] - start, axis=-1).max() < 0.05
    np.testing.assert_array_equal(world.datas[0].ctrl.reshape(3, 4), world.motor_thrusts[0])
    np.testing.assert_allclose(world.motor_thrusts[0].sum(-1), 1.325 * G, rtol=0.01)
    for _ in range(20):  # 2 s at 0.25 m/s^2
        world.step(np.full((1, 2, 2), [0.25, 0.0]), np.zeros((1, 2)))
    np.testing.assert_allclose(world.agent_vel[0, :, 0], 0.5, rtol=0.1)
    assert world.tilt_deg().max() < 45.0 and np.abs(world.drone_positions[0, :, 2] - 2.0).max() < 0.1


def _variant(old: str, new: str) -> str:
    assert old in QUAD
    return QUAD.replace(old, new)


THIRD_ACTUATOR = '<motor class="quad" name="thrust4" site="thrust4" gear="0 0 1 0 0 .0201"/>'


@pytest.mark.parametrize(
    "text, message",
    [
        (_variant(THIRD_ACTUATOR, ""), "has 3 actuators; a quadrotor airframe needs exactly four <motor> actuators"),
        (
            _variant(
                THIRD_ACTUATOR,
                THIRD_ACTUATOR + '<motor class="quad" site="imu" gear="0 0 1 0 0 .0201"/>'
                '<motor class="quad" site="thrust1" gear="0 0 1 0 0 .0201"/>',
            ),
            "has 6 actuators",
        ),
        (
            _variant('site="thrust2" gear', 'site="thrust1" gear'),
            "actuator thrust2 acts on site 'thrust1' like another actuator",
        ),
        (
            _variant(
                '<motor class="quad" name="thrust1" site="thrust1"', '<motor class="quad" name="thrust1" joint="root"'
            ).replace("<freejoint/>", '<freejoint name="root"/>'),
            "actuator thrust1 must act on a rotor site .* not through a joint transmission",
        ),
        (
            _variant(
                'gear="0 0 1 0 0 -.0201"/>\n    <motor class="quad" name="thrust2"',
                'gear="0 0 0 1 0 0"/>\n    <motor class="quad" name="thrust2"',
            ),
            r"actuator thrust1 gear must be '0 0 1 0 0 \+-km'",
        ),
        (
            _variant(
                'name="thrust3" site="thrust3" gear="0 0 1 0 0 -.0201"',
                'name="thrust3" site="thrust3" gear="0 0 1 0 0 .0201"',
            ),
            "two counter-clockwise and two clockwise rotors",
        ),
        # Menagerie's x2.xml yaw gears: both right rotors one spin, both left the other
        (
            _variant(
                'name="thrust3" site="thrust3" gear="0 0 1 0 0 -.0201"',
                'name="thrust3" site="thrust3" gear="0 0 1 0 0 .0201"',
            ).replace(
                'name="thrust4" site="thrust4" gear="0 0 1 0 0 .0201"',
                'name="thrust4" site="thrust4" gear="0 0 1 0 0 -.0201"',
            ),
            "cannot make independent roll, pitch and yaw torques",
        ),
        (
            _variant(
                '<site name="thrust2" pos="-.14 .18 .05"/>', '<site name="thrust2" pos="-.14 .18 .05" euler="0.3 0 0"/>'
            ),
            "rotor site 'thrust2' must not tilt",
        ),
        (
            _variant('<numeric name="max_rot_velocity" data="1200"/>', ""),
            "lacks <custom><numeric name='max_rot_velocity'>",
        ),
        (
            _variant('<motor ctrlrange="0 13"/>', '<motor ctrlrange="0 12"/>'),
            r"ctrlrange must be 0 .. motor_constant \* max_rot_velocity\^2 = 13",
        ),
        (
            _variant(
                "</body>", '</body><body name="payload" pos="1 0 0"><freejoint/><geom size=".1" mass="1"/></body>'
            ),
            "one body with a free joint .found 2 bodies",
        ),
    ],
)
def test_not_a_site_mounted_quadrotor_is_one_clear_line(tmp_path, text, message):
    path = write_quad(tmp_path, text)
    with pytest.raises(ConfigError, match=message) as info:
        MujocoWorld(MujocoWorldConfig(airframe=str(path)), 1, 1, 0)
    assert "\n" not in str(info.value)


def test_airframe_file_and_params_errors(tmp_path):
    path = write_quad(tmp_path, params=False)
    with pytest.raises(
        ConfigError, match=r"params: no parameter file for airframe 'quad' \(looked for .*quad.params"
    ) as info:
        MujocoWorld(MujocoWorldConfig(airframe=str(path)), 1, 1, 0)
    assert "\n" not in str(info.value)
    with pytest.raises(ConfigError, match="airframe: no MJCF file"):
        MujocoWorldConfig(airframe=str(tmp_path / "missing.xml")).validate()
    with pytest.raises(ConfigError, match=r"unknown airframe 'cf3' \(known: crazyflie, iris"):
        MujocoWorldConfig(airframe="cf3").validate()
    box_footprint = write_quad(
        tmp_path,
        _variant('<site name="imu"', '<geom name="footprint" type="box" size=".2 .2 .05"/><site name="imu"'),
        name="boxed",
    )
    with pytest.raises(ConfigError, match="geom 'footprint' must be a cylinder"):
        MujocoWorld(MujocoWorldConfig(airframe=str(box_footprint)), 1, 1, 0)
    with pytest.raises(ConfigError, match="does not compile"):
        load_airframe(write_quad(tmp_path, "<mujoco><worldbody><body></mujoco>", name="broken"))


def test_make_mujoco_world_takes_an_airframe_and_keeps_the_task_radius(tmp_path):
    from cefc_mj.task.config import TaskConfig

    task = TaskConfig(n_agents=3, mode="formation", obstacle_density=0.0)
    world = make_mujoco_world(task, airframe=write_quad(tmp_path))
    assert world.airframe.name == "quad" and world.config.airframe == str(tmp_path / "quad.xml")
    assert world.models[0].geom("uav2_footprint").size[0] == task.uav_radius
    assert math.isclose(world.cascade.params["MPC_THR_HOVER"], 0.25)
    assert make_mujoco_world(task).airframe.name == "iris"
