"""The rule-driven teams of the adversary's training population pick the anchors their rules say,
from the game's true state, and play whole games as a high level does."""

import numpy as np
import pytest

from cefc_mj.errors import ConfigError
from cefc_mj.game_protocol import game_task, play_highlevel
from cefc_mj.hierarchy import HierarchicalCEFCEnv, load_low_level
from cefc_mj.rule_teams import RULE_TEAMS, RuleTeam

pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def game():
    task = game_task()
    g = HierarchicalCEFCEnv(task, load_low_level("navigation", task), n_envs=3, seed=0)
    g.reset(seed=5)
    return g


def _anchor_points(game, name):
    index, message = RuleTeam(name, game).decide(None, None)
    assert message is None and index.shape == (3, 8)
    return game.decode(index)


def test_urgent_sends_everyone_to_the_most_urgent_target(game):
    env = game.env
    env.urgency[:] = [[1.0, 0.4], [0.2, 0.9], [0.5, 0.5]]
    points = _anchor_points(game, "rule-urgent")
    expected = env.targets[np.arange(3), [0, 1, 0]]
    np.testing.assert_array_equal(points, np.repeat(expected[:, None], 8, axis=1))


def test_split_sends_the_halves_to_the_two_targets_and_a_covered_targets_half_to_the_other(game):
    env = game.env
    env.urgency[:] = [[1.0, 1.0], [0.0, 1.0], [1.0, 0.0]]
    points = _anchor_points(game, "rule-split")
    np.testing.assert_array_equal(points[0, :4], np.repeat(env.targets[0, :1], 4, axis=0))
    np.testing.assert_array_equal(points[0, 4:], np.repeat(env.targets[0, 1:], 4, axis=0))
    np.testing.assert_array_equal(points[1], np.repeat(env.targets[1, 1:], 8, axis=0))
    np.testing.assert_array_equal(points[2], np.repeat(env.targets[2, :1], 8, axis=0))


def test_evade_picks_the_open_target_farthest_from_the_adversary(game):
    env = game.env
    env.urgency[:] = 1.0
    env.world.adversary_pos[:] = env.targets[:, 0] * 0.9  # next to target 0
    np.testing.assert_array_equal(_anchor_points(game, "rule-evade")[:, 0], env.targets[:, 1])
    env.urgency[:] = 0.0  # nothing left: the anchor farthest from the adversary
    far = _anchor_points(game, "rule-evade")[:, 0]
    assert (np.linalg.norm(far - env.world.adversary_pos, axis=-1) > 15).all()


@pytest.mark.parametrize("name", RULE_TEAMS)
def test_each_rule_team_plays_a_game(name):
    task = game_task()
    g = HierarchicalCEFCEnv(task, load_low_level("navigation", task), n_envs=2, seed=0)
    result = play_highlevel(RuleTeam(name, g), g, seed=3)
    assert np.isfinite(result["R_H"]).all() and (result["E"] >= 0).all()


def test_unknown_rule_is_refused(game):
    with pytest.raises(ConfigError, match="rule team"):
        RuleTeam("rule-nope", game)
