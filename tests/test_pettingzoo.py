"""The PettingZoo env as its users meet it: finite spaces that real episodes respect, the centralized
state, clear errors, frames on both backends, Rerun streaming, `Policy.act` on env observations and
the example script."""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "egl")  # headless MuJoCo frames; MuJoCo reads it when first imported

import importlib.util
import subprocess
import sys
from pathlib import Path

import gymnasium
import numpy as np
import pytest
from pettingzoo.test.state_test import test_parallel_env as pettingzoo_state_check
from rrd_reader import port_open, read_rrd, rerun_listener

import cefc_mj
from cefc_mj.errors import ConfigError
from cefc_mj.nn.policy_io import load_policy
from cefc_mj.pettingzoo_env import CEFCParallelEnv, ResetNeeded
from cefc_mj.viz.recorder import RERUN_VIEWER_PORT, RerunRecorder

REPO = Path(__file__).resolve().parents[1]
EXAMPLE = REPO / "examples" / "fly_shipped_policy.py"


# ------------------------------------------------------------------------------------ spaces
@pytest.mark.parametrize(
    "backend, mode, options",
    [
        ("particle", "formation", dict(deviation=0.5)),
        ("particle", "cefc", dict(deviation=0.8, velocity_noise=0.3, response_time=0.2)),
        ("mujoco", "formation", dict(wind=8.0, deviation=0.5)),
        ("mujoco", "cefc", dict(wind=8.0)),
    ],
)
def test_real_episodes_stay_inside_the_finite_boxes(backend, mode, options):
    """300 steps of bang-bang random actions (the hardest push on speeds and positions) in a dense
    obstacle field: every observation and state lies in its Box, and the Boxes are finite."""
    env = cefc_mj.make_env(
        backend=backend, n_agents=5, mode=mode, obstacle_density=0.05, seed=3, episode_steps=300, **options
    )
    obs_space, state_space = env.observation_space("uav_0"), env.state_space
    assert np.isfinite(obs_space.low).all() and np.isfinite(obs_space.high).all()
    assert np.isfinite(state_space.low).all() and np.isfinite(state_space.high).all()
    rng = np.random.default_rng(0)
    observations, _ = env.reset(seed=3)
    seen = []
    while env.agents:
        for agent, o in observations.items():
            assert obs_space.contains(o), (agent, np.flatnonzero((o < obs_space.low) | (o > obs_space.high)))
        assert state_space.contains(env.state())
        seen.append(np.stack(list(observations.values())))
        actions = {a: rng.choice([-2.0, 2.0], size=2).astype(np.float32) for a in env.agents}
        observations, *_ = env.step(actions)
    layout, seen = env.layout, np.stack(seen)
    # The bounds come from the layout: LiDAR [0, range], masks [0, 1]; and the LiDAR does read obstacles.
    np.testing.assert_array_equal(obs_space.low[layout["lidar"]], 0.0)
    np.testing.assert_array_equal(obs_space.high[layout["lidar"]], 3.0)
    np.testing.assert_array_equal(obs_space.high[layout["neighbour_mask"]], 1.0)
    assert seen[..., layout["lidar"]].min() < 1.0 and seen[..., layout["neighbour_mask"]].max() == 1.0
    if backend == "particle" and mode == "formation":  # exact speed clip: the velocity bound is the limit itself
        np.testing.assert_array_equal(obs_space.high[layout["own_velocity"]], 1.0)
        assert np.abs(seen[..., layout["own_velocity"]]).max() > 0.9


def test_state_is_the_centralized_state_in_its_box():
    env = cefc_mj.make_env(n_agents=4, mode="formation", obstacle_density=0.03, seed=0)
    pettingzoo_state_check(env)  # PettingZoo's own check: a Box, and state() inside it
    _, infos = env.reset(seed=1)
    _, _, _, _, infos = env.step({a: np.array([1.0, -1.0]) for a in env.agents})
    state = env.state()
    assert state.dtype == np.float32 and state.shape == env.state_space.shape == (env.batched.state_size,)
    # documented layout: per agent [position - anchor, velocity, LiDAR], agents in order
    per_agent = state.reshape(4, -1)
    anchor = env.batched.anchor[0]
    for i, agent in enumerate(env.possible_agents):
        np.testing.assert_allclose(per_agent[i, :2], infos[agent]["position"] - anchor, rtol=1e-6)
        np.testing.assert_allclose(per_agent[i, 2:4], infos[agent]["velocity"], rtol=1e-6)
    cefc_env = cefc_mj.make_env(n_agents=4, seed=0)
    cefc_env.reset(seed=0)
    assert cefc_env.state_space.contains(cefc_env.state()) and cefc_env.state_space.shape == (4 * 28 + 4 + 3 * 2,)


# ------------------------------------------------------------------------------------ errors
def test_misuse_raises_clear_errors():
    env = cefc_mj.make_env(n_agents=3, mode="formation", seed=0, episode_steps=2)
    zero = {a: np.zeros(2) for a in env.possible_agents}
    with pytest.raises(ResetNeeded, match="before reset") as err:
        env.step(zero)
    assert isinstance(err.value, RuntimeError) and isinstance(err.value, gymnasium.error.ResetNeeded)
    env.reset(seed=0)
    with pytest.raises(ConfigError, match=r"missing for agent\(s\) \['uav_1', 'uav_2'\]"):
        env.step({"uav_0": np.zeros(2)})
    with pytest.raises(ConfigError, match=r"unknown agent\(s\) \['uav_7', 'drone'\]"):
        env.step({**zero, "uav_7": np.zeros(2), "drone": np.zeros(2)})
    with pytest.raises(ConfigError, match=r"actions\['uav_2'\]: expected shape \(2,\).*got \(3,\)"):
        env.step({**zero, "uav_2": np.zeros(3)})
    with pytest.raises(ConfigError, match=r"actions\['uav_1'\]: expected shape \(2,\).*got \(1, 2\)"):
        env.step({**zero, "uav_1": np.zeros((1, 2))})
    with pytest.raises(ConfigError, match=r"actions\['uav_0'\]: not numbers"):
        env.step({**zero, "uav_0": "left"})
    with pytest.raises(ConfigError, match="expected a dict"):
        env.step(np.zeros((3, 2)))
    env.step(zero)
    env.step(zero)  # the episode ends here (2 steps)
    assert env.agents == []
    with pytest.raises(ResetNeeded, match="episode ended"):
        env.step(zero)
    with pytest.raises(ConfigError, match="unknown agent 'uav_3'"):
        env.observation_space("uav_3")
    with pytest.raises(ConfigError, match="render_mode='video'"):
        cefc_mj.make_env(n_agents=3, render_mode="video")
    assert CEFCParallelEnv.metadata["render_modes"] == ["rgb_array", "human"]
    assert CEFCParallelEnv.metadata["render_fps"] == 10


# ------------------------------------------------------------------------------------ rendering
@pytest.mark.parametrize("backend", ["particle", "mujoco"])
def test_rgb_array_frames(backend):
    env = cefc_mj.make_env(
        backend=backend, n_agents=4, mode="formation", obstacle_density=0.03, seed=0, render_mode="rgb_array"
    )
    env.reset(seed=0)
    first = env.render()
    assert first.shape == (480, 480, 3) and first.dtype == np.uint8
    assert len(np.unique(first.reshape(-1, 3), axis=0)) > 10  # a scene, not a blank image
    for _ in range(10):
        env.step({a: np.array([2.0, 2.0]) for a in env.agents})
    moved = env.render()
    assert moved.shape == first.shape and not np.array_equal(moved, first)
    if backend == "particle":  # UAV 0 is drawn in tab10 blue at its position
        frames = env._frames
        x, y = env.batched.world.agent_pos[0, 0]
        col = np.argmin(np.abs(frames.x - x))
        row = np.argmin(np.abs(frames.y - y))
        np.testing.assert_array_equal(moved[row, col], [31, 119, 180])
    env.close()
    plain = cefc_mj.make_env(n_agents=3, seed=0)
    plain.reset(seed=0)
    with pytest.warns(UserWarning, match="without a render_mode"):
        assert plain.render() is None


def test_mujoco_frames_without_opengl_fail_at_construction():
    code = (
        "import cefc_mj\n"
        "try:\n"
        "    cefc_mj.make_env(backend='mujoco', n_agents=3, mode='formation', render_mode='rgb_array')\n"
        "except cefc_mj.ConfigError as e:\n"
        "    print('ConfigError:', e)\n"
    )
    env = {**os.environ, "MUJOCO_GL": "disable"}  # MuJoCo without any GL platform
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, env=env)
    assert result.returncode == 0, result.stderr
    assert result.stdout.startswith("ConfigError: render_mode='rgb_array' on MuJoCo needs OpenGL")
    assert "MUJOCO_GL=egl" in result.stdout and "Traceback" not in result.stderr


def test_human_mode_without_display_or_viewer_is_a_config_error(monkeypatch):
    if port_open(RERUN_VIEWER_PORT):
        pytest.skip("a Rerun viewer listens on its port")
    for name in ("DISPLAY", "WAYLAND_DISPLAY", "WAYLAND_SOCKET"):
        monkeypatch.delenv(name, raising=False)
    with pytest.raises(ConfigError, match="render_mode='human': no display.*use render_mode='rgb_array'"):
        cefc_mj.make_env(n_agents=3, render_mode="human")


@pytest.mark.filterwarnings("ignore:RRD file has no footer")  # the interrupted listener writes no footer
def test_human_mode_streams_every_step_to_the_viewer(tmp_path):
    """A headless `rerun --save` listens where the viewer would, so the env connects to it."""
    live = tmp_path / "live.rrd"
    with rerun_listener(RERUN_VIEWER_PORT, live):
        env = cefc_mj.make_env(
            n_agents=3, mode="formation", obstacle_density=0.03, seed=0, episode_steps=8, render_mode="human"
        )
        env.reset(seed=0)
        while env.agents:
            env.step({a: np.array([1.0, 0.0]) for a in env.agents})
        assert env.render() is None
        env.close()
    data = read_rrd(live)
    assert sorted(data["/world/uav_2"]["Transform3D:translation"]) == list(range(9))  # reset + 8 steps
    assert {"/world/obstacles", "/world/anchor", "/metrics/F_so_far"} <= set(data)


def test_rerun_recorder_writes_one_file_per_episode(tmp_path):
    env = cefc_mj.make_env(
        backend="mujoco", n_agents=3, mode="formation", obstacle_density=0.03, seed=0, episode_steps=5
    )
    with RerunRecorder(env, rrd_path=tmp_path / "ep.rrd") as recorder:
        for seed in (0, 1):
            env.reset(seed=seed)
            recorder.capture()
            while env.agents:
                env.step({a: np.array([0.0, 1.0]) for a in env.agents})
                recorder.capture()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ep.rrd", "ep_1.rrd"]
    data = read_rrd(tmp_path / "ep_1.rrd")
    positions = data["/world/uav_0"]["Transform3D:translation"]
    assert sorted(positions) == list(range(6))
    last = np.asarray(positions[5]).reshape(3)
    np.testing.assert_allclose(last[:2], env.batched.world.agent_pos[0, 0], atol=1e-5)
    assert last[2] == pytest.approx(2.0, abs=0.1)  # the quadrotor's own altitude
    assert len(data["/world/uav_0/body"]["Transform3D:quaternion"]) == 6
    assert "/world/obstacles" in data and "/metrics/C_so_far" in data


# ------------------------------------------------------------------------------------ Policy.act
def test_policy_acts_on_pettingzoo_observations():
    policy = load_policy("atm_c6_step3")
    env = cefc_mj.make_env(n_agents=6, mode="formation", seed=0, episode_steps=20)
    observations, _ = env.reset(seed=0)
    actions = policy.act(observations)
    assert list(actions) == env.possible_agents
    assert all(
        a.shape == (2,) and a.dtype == np.float32 and env.action_space(k).contains(a) for k, a in actions.items()
    )
    one_env = np.stack([observations[a] for a in env.possible_agents])  # [N, D]
    np.testing.assert_array_equal(np.stack(list(actions.values())), policy.act(one_env))
    assert policy.act(one_env).shape == (6, 2)
    np.testing.assert_array_equal(policy.act(one_env[None])[0], policy.act(one_env))  # [1, N, D]
    assert policy.act({}) == {}
    d = policy.obs_dim
    for bad, pattern in (
        (one_env[0], rf"\[N, {d}\].*got \[{d}\]"),
        (one_env[:, :-1], rf"got \[6, {d - 1}\]"),
        (np.zeros((1, 1, 6, d)), rf"got \[1, 1, 6, {d}\]"),
        ([["a"] * d], "not an array of numbers"),
        ({**observations, "uav_3": observations["uav_3"][:10]}, rf"obs\['uav_3'\]: expected shape \[{d}\], got \[10\]"),
    ):
        with pytest.raises(ConfigError, match=pattern):
            policy.act(bad)
    while env.agents:  # and it flies the env directly
        observations, rewards, _, _, infos = env.step(policy.act(observations))
    assert infos["uav_0"]["metrics"]["C"] == 0.0


# ------------------------------------------------------------------------------------ example
def _example_module():
    spec = importlib.util.spec_from_file_location("fly_shipped_policy", EXAMPLE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_example_script_records_a_flight(tmp_path, capsys):
    example = _example_module()
    with pytest.raises(SystemExit) as done:
        example.main(["--help"])
    assert done.value.code == 0 and "--out" in capsys.readouterr().out
    for argv, pattern in (
        (["--steps", "0"], "--steps 0"),
        (["--policy", "nope"], "no policy 'nope'"),
        (["--out", str(tmp_path / "x.png")], "must end in .gif or .rrd"),
        (["--out", str(tmp_path / "missing" / "x.gif")], "cannot write"),
    ):
        with pytest.raises(SystemExit) as done:
            example.main(argv)
        err = capsys.readouterr().err
        assert done.value.code == 2 and pattern in err and err.count("\n") == 1, err
    rrd = tmp_path / "fly.rrd"
    assert example.main(["--backend", "particle", "--steps", "3", "--out", str(rrd)]) == 0
    assert sorted(read_rrd(rrd)["/world/uav_5"]["Transform3D:translation"]) == [0, 1, 2, 3]
    # As a user runs it: its own process, MuJoCo frames headless without MUJOCO_GL set, a GIF.
    gif = tmp_path / "fly.gif"
    env = {k: v for k, v in os.environ.items() if k not in ("MUJOCO_GL", "PYOPENGL_PLATFORM", "DISPLAY")}
    result = subprocess.run(
        [sys.executable, str(EXAMPLE), "--backend", "mujoco", "--steps", "2", "--out", str(gif)],
        capture_output=True,
        text=True,
        timeout=300,
        env=env,
        cwd=tmp_path,
    )
    assert result.returncode == 0, result.stderr
    assert f"wrote {gif}" in result.stdout
    from PIL import Image

    with Image.open(gif) as image:
        assert image.n_frames == 3 and image.size == (480, 480)
