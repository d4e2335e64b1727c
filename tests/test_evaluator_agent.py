"""make_env(evaluator_agent=True) + Policy.act flies the agent cefc-eval flies: the fused estimate
and the separation guard, bit for bit the evaluator's episode; without the switch the policy's raw
actions reach the physics (the paper's agent)."""

from __future__ import annotations

import numpy as np
import pytest

import cefc_mj
from cefc_mj.errors import ConfigError
from cefc_mj.eval.runner import TABLE8_ANCHOR_REDRAW, TABLE8_DENSITY, EpisodeSpec, episode_env, fly, run_episode
from cefc_mj.nn.policy_io import load_policy

pytestmark = pytest.mark.usefixtures("one_torch_thread")
STEPS = 120


def _fly_env(evaluator_agent: bool, c: int, seed: int, deviation: float = 0.0):
    env = cefc_mj.make_env(
        backend="mujoco",
        n_agents=c,
        mode="formation",
        obstacle_density=TABLE8_DENSITY,
        episode_steps=1000,
        anchor_redraw_steps=TABLE8_ANCHOR_REDRAW,
        deviation=deviation,
        seed=seed,
        evaluator_agent=evaluator_agent,
    )
    policy = load_policy(f"atm_c{c}_nav")
    observations, _ = env.reset(seed=seed)
    for _ in range(STEPS):
        observations, *_ = env.step(policy.act(observations))
    metrics = env.batched.episode_metrics()
    return env.batched.world.agent_pos.copy(), {k: float(metrics[k][0]) for k in "FNC"}


@pytest.mark.parametrize("deviation", [0.0, 0.5])
def test_env_with_the_switch_flies_the_evaluators_episode_bit_for_bit(deviation):
    c, seed = 6, 3
    pos, metrics = _fly_env(True, c, seed, deviation)
    spec = EpisodeSpec(formation=c, seed=seed, steps=STEPS, deviation=deviation)
    env, act = episode_env(spec)
    fly(env, STEPS, act)
    np.testing.assert_array_equal(pos, env.world.agent_pos)
    result = run_episode(spec)
    assert metrics == {"F": result.F, "N": result.N, "C": result.C}


def test_the_switch_changes_the_actions_that_reach_the_physics():
    guarded, _ = _fly_env(True, 6, 3)
    raw, _ = _fly_env(False, 6, 3)
    assert not np.array_equal(guarded, raw)


def test_conflicting_options_and_the_game_mode_are_refused():
    with pytest.raises(ConfigError, match="evaluator_agent=True sets separation_guard"):
        cefc_mj.make_env(n_agents=4, mode="formation", evaluator_agent=True, separation_guard=False)
    with pytest.raises(ConfigError, match="separation_guard"):
        cefc_mj.make_env(n_agents=8, evaluator_agent=True)  # the game's observation has no own velocity
