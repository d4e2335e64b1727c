"""One hierarchical episode recorded for Rerun and drawn as message-similarity matrices
(cefc_mj/viz/highlevel_log.py).

Real particle games of 50 low-level steps (5 decisions) flown by the shipped student under freshly
built (untrained) high-level policies; the .rrd files are read back with tests/rrd_reader.py.
"""

from __future__ import annotations

import dataclasses
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from rerun.chunk import RrdReader
from rrd_reader import read_rrd

from cefc_mj.errors import ConfigError
from cefc_mj.game_protocol import evaluate_highlevel_episodes, game_task
from cefc_mj.hierarchy import HierarchicalCEFCEnv, load_low_level
from cefc_mj.nn.highlevel_policy import HighLevelPolicy
from cefc_mj.viz.highlevel_log import (
    REWARD_PARTS,
    message_similarity,
    play_highlevel_episode,
    plot_similarity_matrices,
    record_highlevel_episode,
)
from cefc_mj.viz.rerun_log import group_colors

pytestmark = pytest.mark.usefixtures("one_torch_thread", "strict_rerun")

STEPS, INTERVAL, SEED = 50, 10, 3
K = STEPS // INTERVAL


@pytest.fixture(scope="module")
def game():
    task = dataclasses.replace(game_task(), episode_steps=STEPS)
    return task, load_low_level("atm_student", task)


@pytest.fixture(scope="module")
def consmac(game):
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # built before the per-test fixture applies
    task, low_level = game
    policy = HighLevelPolicy.build("consmac-a", game_task(), seed=0)
    episode = play_highlevel_episode(policy, task, low_level, seed=SEED)
    episode.policy, episode.policy_sha256 = "cihrl_test", "ab" * 32
    torch.set_num_threads(threads)
    return policy, episode


@pytest.fixture(scope="module")
def recorded(consmac, tmp_path_factory):
    _, episode = consmac
    path = record_highlevel_episode(episode, tmp_path_factory.mktemp("rrd") / "game.rrd")
    return path, read_rrd(path)


def test_shapes_of_one_episode(consmac):
    _, ep = consmac
    n, j, m = 8, 2, len(ep.obstacles)
    assert (ep.n_steps, ep.n_agents, ep.n_decisions) == (STEPS, n, K)
    for name in ("agent_pos", "agent_vel"):
        assert getattr(ep, name).shape == (STEPS + 1, n, 2)
    assert ep.adversary_pos.shape == ep.adversary_goal.shape == (STEPS + 1, 2)
    assert ep.urgency.shape == (STEPS + 1, j) and ep.targets.shape == (j, 2)
    assert ep.group_label.shape == ep.group_size.shape == (STEPS + 1, n)
    assert ep.reward.shape == (STEPS,) and all(ep.reward_parts[p].shape == (STEPS,) for p in REWARD_PARTS)
    assert ep.anchor_index.shape == (K, n) and ep.anchors.shape == (K, n, 2)
    assert ep.messages.shape == (K, n, 64) and ep.similarity.shape == (K, n, n) and ep.received.shape == (K, n)
    assert m == game_task().n_obstacles > 0 and ep.obstacles.shape == (m, 2)
    np.testing.assert_array_equal(ep.anchors, ep.anchor_grid[ep.anchor_index])
    assert ep.received[0].tolist() == [0] * n  # each episode starts silent
    # group sizes agree with the labels; urgency starts at 1 and never grows
    for s in (0, STEPS):
        counts = {g: int((ep.group_label[s] == g).sum()) for g in ep.group_label[s]}
        assert ep.group_size[s].tolist() == [counts[g] for g in ep.group_label[s]]
    assert (ep.urgency[0] == 1).all() and (np.diff(ep.urgency, axis=0) <= 0).all()
    np.testing.assert_allclose(ep.reward, sum(ep.reward_parts[p] for p in REWARD_PARTS), rtol=1e-12, atol=1e-9)
    assert set(ep.metrics) == {"F", "N", "C", "E"} and set(ep.returns) == {"R_H", *REWARD_PARTS}


def test_same_episode_as_the_evaluation(consmac, game):
    """Seed s is env 0 of a 1-episode evaluation with seed s: bit-identical R_H, parts and metrics."""
    policy, ep = consmac
    task, low_level = game
    evaluated = evaluate_highlevel_episodes(policy, task, low_level, 1, seed=SEED)
    assert ep.returns == {name: float(evaluated[name][0]) for name in ("R_H", *REWARD_PARTS)}
    assert {m: ep.metrics[m] for m in ("E", "F", "C")} == {m: float(evaluated[m][0]) for m in ("E", "F", "C")}
    assert ep.reward.sum() == pytest.approx(ep.returns["R_H"], rel=1e-12)


def test_rows_are_the_states_at_each_low_level_step(consmac, game):
    """Row s is the state after s low-level steps: a game driven by hand with the recorded anchor
    choices passes through the recorded positions at every decision."""
    _, ep = consmac
    task, low_level = game
    twin = HierarchicalCEFCEnv(task, low_level, n_envs=1, seed=SEED)
    twin.reset(seed=SEED)
    np.testing.assert_array_equal(ep.agent_pos[0], twin.world.agent_pos[0])
    for k in range(K):
        twin.step(ep.anchor_index[k][None])
        row = (k + 1) * INTERVAL
        np.testing.assert_array_equal(ep.agent_pos[row], twin.world.agent_pos[0])
        np.testing.assert_array_equal(ep.adversary_pos[row], twin.world.adversary_pos[0])
    np.testing.assert_array_equal(ep.anchor_per_row()[[0, 9, 10, STEPS]], ep.anchors[[0, 0, 1, K - 1]])


def test_adversary_goal_is_the_nearest_group_of_three(consmac):
    """The default rule, checked from the recorded state alone: the centre of the nearest group of
    at least 3 agents, else the nearest agent."""
    _, ep = consmac
    assert ep.adversary_rule == "nearest_group"
    for s in range(0, STEPS + 1, 7):
        pos, labels, adv = ep.agent_pos[s], ep.group_label[s], ep.adversary_pos[s]
        centres = [pos[labels == g].mean(axis=0) for g in np.unique(labels) if (labels == g).sum() >= 3]
        if centres:
            expected = min(centres, key=lambda c: np.linalg.norm(c - adv))
        else:
            expected = pos[np.argmin(np.linalg.norm(pos - adv, axis=1))]
        np.testing.assert_allclose(ep.adversary_goal[s], expected, atol=1e-9)


def test_message_similarity_is_the_cosine_matrix(consmac):
    _, ep = consmac
    s = ep.similarity
    np.testing.assert_array_equal(s, np.swapaxes(s, 1, 2))
    np.testing.assert_array_equal(s[:, np.arange(8), np.arange(8)], 1.0)  # LayerNorm'd messages are nonzero
    assert (s >= -1).all() and (s <= 1).all()
    a, b = ep.messages[2, 1].astype(float), ep.messages[2, 5].astype(float)
    assert s[2, 1, 5] == pytest.approx(a @ b / np.linalg.norm(a) / np.linalg.norm(b), abs=1e-12)
    # a zero message is similar to nothing, itself included; opposite messages give -1
    m = np.array([[1.0, 2.0, 0.0], [0.0, 0.0, 0.0], [-2.0, -4.0, 0.0]])
    np.testing.assert_allclose(message_similarity(m), [[1, 0, -1], [0, 0, 0], [-1, 0, 1]], atol=1e-15)


def test_mappo_records_no_messages(game, tmp_path):
    task, low_level = game
    policy = HighLevelPolicy.build("mappo", game_task(), seed=0)
    ep = play_highlevel_episode(policy, task, low_level, seed=SEED)
    assert ep.messages is None and ep.similarity is None and ep.received is None
    assert ep.anchor_index.shape == (K, 8) and ep.agent_pos.shape == (STEPS + 1, 8, 2)
    assert ep.returns["R_H"] == float(evaluate_highlevel_episodes(policy, task, low_level, 1, seed=SEED)["R_H"][0])
    data = read_rrd(record_highlevel_episode(ep, tmp_path / "mappo.rrd"))
    assert "/world/uavs" in data and len(data["/decisions"]["TextLog:text"]) == K
    assert not any(entity.startswith("/messages") for entity in data)
    with pytest.raises(ConfigError, match="sends no messages"):
        plot_similarity_matrices(ep, tmp_path / "x.png")
    assert not (tmp_path / "x.png").exists()


def test_recording_holds_the_episode(consmac, recorded):
    _, ep = consmac
    _, data = recorded
    expected = {
        "/world",
        "/world/arena",
        "/world/obstacles",
        "/world/anchor_grid",
        "/world/uavs",
        "/world/anchors",
        "/world/anchors/lines",
        "/world/targets",
        "/world/targets/zone",
        "/world/adversary",
        "/world/adversary/goal",
        "/world/adversary/chase",
        "/world/adversary/alert",
        "/messages/similarity",
        "/decisions",
        "/episode",
        "/__properties/provenance",
        *(f"/rewards/{name}" for name in ("R_H", *REWARD_PARTS)),
    }
    assert expected <= set(data)
    uavs = data["/world/uavs"]
    assert sorted(uavs["Points3D:positions"]) == list(range(STEPS + 1))
    s = 37
    np.testing.assert_allclose(np.array(uavs["Points3D:positions"][s])[:, :2], ep.agent_pos[s], atol=1e-5)
    r, g, b = group_colors(ep.group_label[s, 4])
    assert uavs["Points3D:colors"][s][4] == (int(r) << 24) | (int(g) << 16) | (int(b) << 8) | 255
    goal = data["/world/adversary/goal"]["Points3D:positions"]
    assert sorted(goal) == list(range(STEPS + 1))
    np.testing.assert_allclose(goal[s][0][:2], ep.adversary_goal[s], atol=1e-5)
    # each agent's anchor and the line to it switch at the decision rows
    anchors = data["/world/anchors"]["Points3D:positions"]
    np.testing.assert_allclose(np.array(anchors[19])[:, :2], ep.anchors[1], atol=1e-6)
    np.testing.assert_allclose(np.array(anchors[20])[:, :2], ep.anchors[2], atol=1e-6)
    line = np.array(data["/world/anchors/lines"]["LineStrips3D:strips"][s][6])
    np.testing.assert_allclose(line[:, :2], [ep.agent_pos[s, 6], ep.anchors[3, 6]], atol=1e-5)
    # targets: the radius shows the urgency
    radii = data["/world/targets"]["Points3D:radii"]
    np.testing.assert_allclose(radii[STEPS], 0.15 + 0.45 * ep.urgency[STEPS], atol=1e-6)


def test_similarity_tensor_at_each_decision(consmac, recorded):
    _, ep = consmac
    _, data = recorded
    tensors = data["/messages/similarity"]["Tensor:data"]
    assert sorted(tensors) == [k * INTERVAL for k in range(K)]
    for k in range(K):
        tensor = tensors[k * INTERVAL][0]
        assert tensor["shape"] == [8, 8]
        np.testing.assert_allclose(np.array(tensor["buffer"]).reshape(8, 8), ep.similarity[k], atol=1e-6)
    assert len(data["/messages/mean/same_anchor"]["Scalars:scalars"]) >= 1
    lines = data["/decisions"]["TextLog:text"]
    assert sorted(lines) == [k * INTERVAL for k in range(K)] and lines[10][0].startswith("decision 1 at step 10")


def test_rewards_per_step_and_provenance(consmac, recorded):
    _, ep = consmac
    _, data = recorded
    for name in ("R_H", *REWARD_PARTS):
        logged = data[f"/rewards/{name}"]["Scalars:scalars"]
        assert sorted(logged) == list(range(1, STEPS + 1))  # the reward of step s at row s
        series = ep.reward if name == "R_H" else ep.reward_parts[name]
        np.testing.assert_allclose([logged[s][0] for s in range(1, STEPS + 1)], series)
    prov = {name: values[None][0] for name, values in data["/__properties/provenance"].items()}
    assert (prov["policy"], prov["policy_sha256"], prov["variant"]) == ("cihrl_test", "ab" * 32, "consmac-a")
    assert (prov["low_level"], prov["seed"], prov["steps"], prov["adversary"]) == (
        "atm_student",
        SEED,
        STEPS,
        "nearest_group",
    )
    assert len(prov["low_level_sha256"]) == 64
    assert prov["R_H"] == pytest.approx(ep.returns["R_H"]) and prov["E"] == ep.metrics["E"]
    text = data["/episode"]["TextDocument:text"][None][0]
    assert "cihrl_test" in text and "ab" * 32 in text


def test_blueprint_shows_the_similarity_beside_the_arena(recorded):
    path, _ = recorded
    reader = RrdReader(path)
    views = [{c.entity_path.split("/")[-1] for c in reader.stream(store=b).to_chunks()} for b in reader.blueprints()]
    assert any({"TensorScalarMapping", "EyeControls3D"} <= names for names in views)
    exe = shutil.which("rerun") or str(Path(sys.executable).with_name("rerun"))
    if os.path.exists(exe):
        result = subprocess.run([exe, "rrd", "verify", str(path)], capture_output=True, text=True, timeout=60)
        assert result.returncode == 0, result.stderr


def test_similarity_png(consmac, tmp_path):
    _, ep = consmac
    path = plot_similarity_matrices(ep, tmp_path / "similarity.png")
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and path.stat().st_size > 10_000
    assert sorted(p.name for p in tmp_path.iterdir()) == ["similarity.png"]  # no temp file left behind
    plot_similarity_matrices(ep, tmp_path / "two.png", decisions=[0, K - 1])
    assert (tmp_path / "two.png").read_bytes()[:4] == b"\x89PNG"
    with pytest.raises(ConfigError, match="decisions"):
        plot_similarity_matrices(ep, tmp_path / "bad.png", decisions=[K])
    with pytest.raises(ConfigError, match="does not exist"):
        plot_similarity_matrices(ep, tmp_path / "missing" / "x.png")
