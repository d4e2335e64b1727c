"""examples/straggler_probe.py: the hand-built case is the documented situation, it is flown through
the env's own reset(scenario=...), the straggler can rejoin no faster than the speed limit allows,
--png draws the failures, and bad input exits 2 with one line. Also the env's check of a hand-built
scenario."""

import importlib.util
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from cefc_mj.env import BatchedCEFCEnv
from cefc_mj.errors import ConfigError
from cefc_mj.eval.runner import EpisodeSpec, load_policy_for
from cefc_mj.task.scenario import START_DISC_MARGIN

SCRIPT = Path(__file__).resolve().parents[1] / "examples" / "straggler_probe.py"


def load_script():
    spec = importlib.util.spec_from_file_location("straggler_probe", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_case_puts_a_lone_uav_behind_obstacles_with_the_group_at_the_anchor():
    probe = load_script()
    cfg = EpisodeSpec(formation=6, seed=0).task_config()
    for seed in range(50):
        sc = probe.straggler_layout(6, cfg.n_obstacles, seed)
        start, others, anchor = sc.agent_pos[0, 0], sc.agent_pos[0, 1:], sc.anchor[0]
        assert 4.5 <= np.linalg.norm(anchor - start) <= 7.0
        assert np.linalg.norm(others - start, axis=-1).min() > cfg.observation_distance  # no neighbour in sight
        near = sc.obstacles[0, :2]
        assert np.linalg.norm(near - start, axis=-1).min() >= cfg.obstacle_radius + cfg.uav_radius + START_DISC_MARGIN
        ahead = (anchor - start) / np.linalg.norm(anchor - start)
        assert ((near - start) @ ahead > 0.9).all()  # both between the straggler and the anchor
        assert (np.abs(sc.obstacles[0, 2:, 0]) > 40).all()  # the rest parked out of every beam


@pytest.mark.usefixtures("one_torch_thread")
def test_a_case_flies_through_the_env_and_respects_the_speed_limit():
    probe = load_script()
    policy = load_policy_for("nav", 5)
    results = [probe.fly_case(5, seed, "particle", policy) for seed in range(4)]
    for seed, (joined, trace) in enumerate(results):
        positions = trace["positions"]
        np.testing.assert_allclose(trace["anchor"], probe.straggler_layout(5, 12, seed).anchor[0])
        start_gap = np.linalg.norm(probe.straggler_layout(5, 12, seed).agent_pos[0, 0] - trace["anchor"])
        if joined is not None:
            assert len(positions) == joined and np.linalg.norm(positions[-1, 0] - trace["anchor"]) < 2.0
            assert joined * 0.1 * 1.0 >= start_gap - 2.0 - 1e-6  # 1 m/s for 0.1 s a step, no faster
        else:
            assert len(positions) == probe.PROBE_STEPS
    assert any(joined is not None for joined, _ in results)


@pytest.mark.usefixtures("one_torch_thread")
def test_png_draws_the_failures(tmp_path, capsys):
    # AT-M Step 3 of c = 8 leaves the straggler behind in some of the first cases
    assert load_script().main(["--formations", "8", "--cases", "6", "--policy", "atm", "--png", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    escaped = int(out.strip().splitlines()[-1].split()[1].split("/")[0])
    pictures = sorted(p.name for p in tmp_path.iterdir())
    assert pictures == ([] if escaped == 6 else ["c8_failures.png"])
    for p in tmp_path.iterdir():
        assert p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.parametrize(
    "argv, needle",
    [
        (["--formations", "9"], "--formations [9]"),
        (["--cases", "0"], "--cases 0"),
        (["--seed", "-1"], "--seed -1"),
        (["--policy", "no_such_policy", "--formations", "5"], "--policy no_such_policy"),
        (["--png", "/proc/no_such_dir"], "--png /proc/no_such_dir: cannot write there"),
    ],
)
def test_bad_input_exits_2_with_one_line(argv, needle):
    run = subprocess.run([sys.executable, str(SCRIPT), *argv], capture_output=True, text=True, timeout=120)
    assert run.returncode == 2 and run.stdout == ""
    assert needle in run.stderr and len(run.stderr.strip().splitlines()) == 1


def test_reset_checks_a_hand_built_scenario():
    probe = load_script()
    env = BatchedCEFCEnv(EpisodeSpec(formation=5, seed=0).task_config(), n_envs=1, seed=0)
    sc = probe.straggler_layout(5, env.config.n_obstacles, 3)
    env.reset(scenario=sc)
    np.testing.assert_array_equal(env.world.agent_pos, sc.agent_pos)
    np.testing.assert_array_equal(env.anchor, sc.anchor)
    sc.obstacles = sc.obstacles[:, :3]
    with pytest.raises(ConfigError, match=rf"scenario.obstacles: expected shape \(1, {env.config.n_obstacles}, 2\)"):
        env.reset(scenario=sc)
    sc = probe.straggler_layout(5, env.config.n_obstacles, 3)
    sc.anchor = np.full((1, 2), np.nan)
    with pytest.raises(ConfigError, match="scenario.anchor: contains NaN"):
        env.reset(scenario=sc)
