"""The dm_control suite of the swarm (cefc_mj.suite, docs/dm_control.md) on real MuJoCo: dm_env's own
conformance tests, bit-for-bit equality with the PettingZoo env and with cefc-eval's episode loop,
headless rendering of the world's own MjData, the viewer's runtime driving it, the docs example, and
`cefc-view`'s one-line refusals."""

from __future__ import annotations

import os
import re
import subprocess
import sys
import textwrap
import warnings
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("dm_control")

import dm_env  # noqa: E402
from absl.testing import absltest  # noqa: E402
from dm_env import test_utils  # noqa: E402

import cefc_mj  # noqa: E402
from cefc_mj import suite  # noqa: E402
from cefc_mj.errors import ConfigError  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
SHORT = 6
"""Decision steps of the conformance tests' episodes: the mixin's 20-action sequences cross several LASTs."""


def _random_actions(env, rng):
    spec = env.action_spec()
    return rng.uniform(spec.minimum, spec.maximum, spec.shape)


# ---------------------------------------------------------------------------------------- dm_env conformance
class FormationConformanceTest(test_utils.EnvironmentTestMixin, absltest.TestCase):
    """dm_env's contract on formation_c3 in wind with sensing deviation and cefc-eval's agent."""

    task_kwargs = {"seed": 0, "wind": 4.0, "deviation": 0.3, "evaluator_agent": True, "episode_steps": SHORT}
    task_name = "formation_c3"

    def make_object_under_test(self):
        return suite.load("cefc", self.task_name, task_kwargs=self.task_kwargs)

    def make_action_sequence(self):
        rng = np.random.default_rng(0)
        for _ in range(20):
            yield _random_actions(self.environment, rng)


class GameConformanceTest(FormationConformanceTest):
    """The same on the full game (targets, the adversary)."""

    task_kwargs = {"seed": 1, "episode_steps": SHORT}
    task_name = "cefc_game"


# ---------------------------------------------------------------------------------------- same numbers
def test_steps_bit_for_bit_like_the_pettingzoo_env():
    """Same seed, same random actions: observations, rewards, the step that ends the episode, the episode
    metrics and the next episode's start equal the PettingZoo env's (wind, deviation, estimate, guard)."""
    task_kwargs = {"seed": 7, "wind": 6.0, "deviation": 0.4, "evaluator_agent": True, "episode_steps": 20}
    env = suite.load("cefc", "formation_c5", task_kwargs=task_kwargs)
    options = {**suite.TASKS["formation_c5"].options, **task_kwargs}
    parallel = cefc_mj.make_env(backend="mujoco", **options)
    agents = parallel.possible_agents
    rng = np.random.default_rng(3)

    time_step = env.reset()
    observations, _ = parallel.reset(seed=7)
    assert time_step.first()
    assert np.array_equal(suite.stack_observations(time_step.observation), np.stack([observations[a] for a in agents]))
    for k in range(20):
        action = _random_actions(env, rng)
        time_step = env.step(action)
        observations, rewards, _, truncations, infos = parallel.step({a: action[i] for i, a in enumerate(agents)})
        for i, agent in enumerate(agents):
            assert np.array_equal(np.concatenate(list(time_step.observation[i].values())), observations[agent]), k
            assert time_step.reward[i] == rewards[agent] and type(time_step.reward[i]) is np.float64
        assert time_step.last() == all(truncations.values()) == (k == 19)
        assert env.physics.data.qpos.reshape(-1, 7)[:5, :2].tolist() == [infos[a]["position"].tolist() for a in agents]
    assert time_step.discount == 1.0
    assert env.task.infos["uav_0"]["metrics"] == infos["uav_0"]["metrics"]
    # the next episode continues the seed's streams, as reset(seed=None) does
    time_step = env.step(np.zeros((5, 2)))
    observations, _ = parallel.reset()
    assert time_step.first()
    assert np.array_equal(suite.stack_observations(time_step.observation), np.stack([observations[a] for a in agents]))
    env.close()


def test_flies_like_cefc_eval():
    """A shipped policy through the dm_env API with cefc-eval's agent flies cefc-eval's episode
    (`run_episode`, the Table VIII loop) bit for bit: the same drone positions at every step, F, N, C."""
    from cefc_mj.eval.runner import EpisodeSpec, run_episode
    from cefc_mj.nn.policy_io import load_policy

    steps = 40
    reference = run_episode(EpisodeSpec(formation=4, seed=2, steps=steps, wind=3.0), record=True)
    env = suite.load(
        "cefc", "formation_c4", task_kwargs={"seed": 2, "wind": 3.0, "evaluator_agent": True, "episode_steps": 1000}
    )
    policy = load_policy(suite.TASKS["formation_c4"].policy)
    time_step, positions = env.reset(), []
    for _ in range(steps):
        time_step = env.step(policy.act(suite.stack_observations(time_step.observation)))
        positions.append(env.physics.data.qpos.reshape(-1, 7)[:4, :3].copy())
    assert np.array_equal(np.stack(positions), reference.record.agent_pos)
    metrics = env.task.parallel_env.batched.episode_metrics()
    assert (metrics["F"][0], metrics["N"][0], metrics["C"][0]) == (reference.F, reference.N, reference.C)
    env.close()


def test_tasks_are_cefc_evals_scenes():
    from cefc_mj.eval.runner import EpisodeSpec
    from cefc_mj.game_protocol import game_task

    assert suite.ALL_TASKS == tuple(("cefc", name) for name in suite.TASKS)
    assert set(suite.TASKS) == {f"formation_c{c}" for c in range(3, 9)} | {"cefc_game"}
    for c in range(3, 9):
        options = suite.TASKS[f"formation_c{c}"].options
        expected = EpisodeSpec(formation=c, seed=0).task_config()  # with cefc-eval's agent
        assert cefc_mj.make_task_config(**options, **cefc_mj.EVALUATOR_AGENT) == expected
    assert cefc_mj.make_task_config(**suite.TASKS["cefc_game"].options) == game_task()


# ---------------------------------------------------------------------------------------- the physics
def test_physics_is_the_worlds_own_mjdata():
    env = suite.load("cefc", "cefc_game", task_kwargs={"seed": 0, "episode_steps": 3})
    world = env.task.parallel_env.batched.world
    assert env.physics.model.ptr is world.models[0] and env.physics.data.ptr is world.datas[0]
    assert isinstance(env, dm_env.Environment) and env.control_timestep() == pytest.approx(0.1)
    env.reset()
    start = env.physics.time()
    env.step(np.zeros((8, 2)))
    assert env.physics.time() == pytest.approx(start + 0.1)
    # the obstacles the world placed (it moves their bodies) are where the physics draws them
    obstacles = env.task.parallel_env.batched.obstacles[0]
    ids = [env.physics.model.name2id(f"obstacle{k}", "body") for k in range(len(obstacles))]
    assert np.array_equal(env.physics.data.xpos[ids, :2], obstacles)
    with pytest.raises(suite.PhysicsStepRefused, match="only through env.step"):
        env.physics.step()
    env.close()


def test_bad_input_is_one_line_before_anything_is_built():
    cases = [
        (("cefc", "formation_c9"), {}, "formation_c3, formation_c4"),
        (("walker", "formation_c6"), {}, "the only domain is 'cefc'"),
        (("cefc", "formation_c6"), {"task_kwargs": {"n_agents": 7}}, "n_agents fixed by the task"),
        (("cefc", "formation_c6"), {"task_kwargs": {"seed": 1, "random": 1}}, "not both"),
        (("cefc", "formation_c6"), {"task_kwargs": {"seed": "zero"}}, "must be an integer"),
        (("cefc", "formation_c6"), {"environment_kwargs": {"flat_observation": True}}, "flat_observation"),
        (("cefc", "formation_c6"), {"environment_kwargs": {"time_limit": 0.25}}, "whole number"),
        (("cefc", "formation_c6"), {"task_kwargs": {"speed": 2}}, "unknown task option"),
    ]
    for args, kwargs, needle in cases:
        with pytest.raises(ConfigError) as info:
            suite.load(*args, **kwargs)
        assert needle in str(info.value) and "\n" not in str(info.value), str(info.value)


def test_time_limit_sets_the_episode_length():
    env = suite.load("cefc", "formation_c3", task_kwargs={"random": 4}, environment_kwargs={"time_limit": 0.3})
    assert env.task.parallel_env.config.steps == 3
    env.reset()
    assert [env.step(np.zeros((3, 2))).step_type for _ in range(4)] == [
        dm_env.StepType.MID,
        dm_env.StepType.MID,
        dm_env.StepType.LAST,
        dm_env.StepType.FIRST,
    ]
    env.close()


# ---------------------------------------------------------------------------------------- rendering
_RENDER_SCRIPT = textwrap.dedent(
    """
    import sys
    import numpy as np
    from cefc_mj import suite

    env = suite.load("cefc", "cefc_game", task_kwargs={"seed": 0, "episode_steps": 50})
    env.reset()
    before = env.physics.render(height=240, width=320)
    for _ in range(20):
        env.step(np.full((8, 2), 2.0))
    after = env.physics.render(height=240, width=320)
    segmentation = env.physics.render(height=240, width=320, segmentation=True)
    model = env.physics.model
    uavs = [model.name2id(f"uav{i}_footprint", "geom") for i in range(8)]
    obstacles = [g for g in range(model.ngeom) if (model.id2name(g, "geom") or "").startswith("obstacle")]
    np.savez(sys.argv[1], before=before, after=after, segmentation=segmentation, uavs=uavs, obstacles=obstacles,
             adversary=model.name2id("adv_footprint", "geom"))
    env.close()
    """
)


def test_renders_headless_through_physics_render(tmp_path):
    """physics.render in a fresh interpreter (dm_control picks its GL backend when first imported): the
    backend CI sets (MUJOCO_GL=egl), else osmesa; skipped only when neither can render."""
    failures = []
    for backend in dict.fromkeys([os.environ.get("MUJOCO_GL") or "egl", "egl", "osmesa"]):
        out = tmp_path / f"{backend}.npz"
        env = {**os.environ, "MUJOCO_GL": backend}
        env.pop("PYOPENGL_PLATFORM", None)
        result = subprocess.run(
            [sys.executable, "-c", _RENDER_SCRIPT, str(out)], capture_output=True, text=True, env=env, timeout=120
        )
        if result.returncode == 0:
            break
        last = (result.stderr.strip().splitlines() or ["no output"])[-1]
        failures.append(f"MUJOCO_GL={backend}: {last[:200]}")
    else:
        pytest.skip("no OpenGL backend can render here (" + "; ".join(failures) + ")")
    frames = np.load(out)
    before, after, segmentation = frames["before"], frames["after"], frames["segmentation"]
    assert before.shape == (240, 320, 3) and before.dtype == np.uint8
    assert before.std() > 10 and len(np.unique(before.reshape(-1, 3), axis=0)) > 100, "a blank frame"
    assert not np.array_equal(before, after), "the frame does not follow the state"
    seen = set(np.unique(segmentation[..., 0]).tolist())
    assert set(frames["uavs"].tolist()) <= seen, "every UAV is drawn (the free camera frames the arena)"
    assert int(frames["adversary"]) in seen, "the adversary's group is drawn"
    assert seen & set(frames["obstacles"].tolist()), "the obstacles are drawn"


# ---------------------------------------------------------------------------------------- viewer and docs
def test_the_viewers_runtime_flies_cefc_views_policy():
    """What `cefc-view` hands dm_control.viewer (its env and policy callable), driven by the viewer's
    own runtime without a window: the shipped policy flies and nothing errs."""
    from cefc_mj.cli import view

    with warnings.catch_warnings():  # importing the viewer imports glfw, which warns without a display
        warnings.simplefilter("ignore")
        from dm_control.viewer import runtime

    args = view.build_parser().parse_args(["formation_c3", "--seed", "5"])
    task_kwargs, policy = view.prepare(args)
    assert task_kwargs["evaluator_agent"] is True and policy.name == "atm_c3_nav"
    env = suite.load("cefc", args.task, task_kwargs=task_kwargs)
    errors = []
    run = runtime.Runtime(env, policy=view.viewer_policy(policy))
    run.on_error += errors.append
    for _ in range(10):
        run.tick(0.2, paused=False)
    assert not errors, errors
    assert env.task.parallel_env.batched.t[0] >= 10
    assert np.abs(env.physics.data.qvel.reshape(-1, 6)[:3, :2]).max() > 0.05, "the policy moves the swarm"
    env.close()


def test_docs_example_runs_as_written():
    text = (REPO / "docs" / "dm_control.md").read_text()
    code = re.search(r"## Fly a shipped policy\n\n```python\n(.*?)```", text, re.S).group(1)
    assert 15 <= len(code.splitlines()) <= 25
    namespace: dict = {}
    exec(compile(code, "docs/dm_control.md", "exec"), namespace)
    assert namespace["time_step"].last()
    assert namespace["metrics"]["C"] >= 0 and 0 <= namespace["metrics"]["F"] <= 300
    assert np.isfinite(namespace["team_return"])


def test_cefc_view_refuses_in_one_line(capsys, monkeypatch):
    from cefc_mj.cli import view

    for name in ("DISPLAY", "WAYLAND_DISPLAY", "WAYLAND_SOCKET"):
        monkeypatch.delenv(name, raising=False)
    for args, needle in [
        (["formation_c9"], "must be one of formation_c3"),
        (["cefc_game", "--policy", "atm_c6_nav"], "reads 63 numbers"),
        (["--policy", "no_such_policy"], "no policy 'no_such_policy'"),
        (["--wind", "-1"], "--wind -1.0"),
        (["--wind-direction", "90"], "no wind to point"),
        (["--seed", "x"], "invalid int value"),
    ]:
        with pytest.raises(SystemExit) as info:
            view.main(args)
        err = capsys.readouterr().err
        assert info.value.code == 2 and err.count("\n") == 1 and needle in err, (args, err)
    with pytest.raises(SystemExit) as info:
        view.main(["--help"])
    out = capsys.readouterr().out
    assert info.value.code == 0 and "formation_c6 (atm_c6_nav)" in out and "cefc_game (none)" in out


def test_cefc_view_without_a_display_exits_2_before_the_viewer():
    """As a user runs it, headless: one line, exit 2, dm_control's viewer (and glfw) never imported."""
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY", "WAYLAND_SOCKET")}
    probe = "import sys; from cefc_mj.cli import view; code = view.main(sys.argv[1:])"
    script = f"import sys\ntry:\n    {probe}\nfinally:\n    print('glfw' in sys.modules)"
    out = subprocess.run(
        [sys.executable, "-c", script, "formation_c4"], capture_output=True, text=True, env=env, timeout=120
    )
    assert out.returncode == 2 and out.stdout.strip() == "False", (out.stdout, out.stderr)
    assert out.stderr.count("\n") == 1 and "no display" in out.stderr and "Traceback" not in out.stderr


if __name__ == "__main__":  # pragma: no cover
    sys.exit(pytest.main([__file__, "-q"]))
