"""Rerun logging: write an .rrd from a synthetic episode, read it back (docs/research/dependency_facts.md)
and check it."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import rerun as rr
from rerun.chunk import RrdReader
from rrd_reader import read_rrd, rerun_listener

from cefc_mj.errors import ConfigError
from cefc_mj.eval.record import airframe_parts_from_mjcf, synthetic_record
from cefc_mj.provenance import code_version, library_versions
from cefc_mj.viz import rerun_log
from cefc_mj.viz.rerun_log import (
    check_spawn_possible,
    close_recording,
    group_colors,
    log_episode,
    log_static,
    log_steps,
    open_recording,
)

MINI_QUAD = Path(__file__).parent / "data" / "mini_quad.xml"
T, N, M = 300, 5, 12  # 300 steps: the anchor jumps once, at step 250

pytestmark = pytest.mark.usefixtures("strict_rerun")


@pytest.fixture(scope="module")
def episode(tmp_path_factory):
    record = synthetic_record(n_steps=T, n_agents=N, n_beams=M, airframe_parts=airframe_parts_from_mjcf(MINI_QUAD))
    record.policy, record.policy_sha256, record.deviation = "atm_c5_step3", "5e" * 32, 0.5
    path = tmp_path_factory.mktemp("rrd") / "episode.rrd"
    recording = open_recording(rrd_path=path)
    log_episode(record, recording)
    close_recording(recording)
    return record, path, read_rrd(path)


def test_entity_paths_name_what_they_hold(episode):
    record, _, data = episode
    expected = {
        "/world",
        "/world/obstacles",
        "/world/anchor",
        "/world/anchor/zone",
        "/world/targets",
        "/world/adversary",
        "/world/trails",
        "/world/template",
        "/world/collisions",
        "/world/wind",
        "/events/collisions",
        "/episode",
        "/__properties/provenance",
        *(f"/metrics/{name}" for name in record.scalars),
        *(f"/world/uav_{i}{sub}" for i in range(N) for sub in ("", "/body", "/lidar", "/lidar/hits")),
    }
    assert expected <= set(data)
    assert {f"/world/uav_0/body/{kind}" for kind in ("boxes", "cylinders", "capsules", "ellipsoids")} <= set(data)


def test_recording_carries_its_provenance(episode):
    """Policy, its file's digest, condition, size, final F/N/C and the code that flew it, as
    recording properties (the viewer's recording panel)."""
    record, _, data = episode
    prov = {name: values[None][0] for name, values in data["/__properties/provenance"].items()}
    assert prov["policy"] == "atm_c5_step3" and prov["policy_sha256"] == "5e" * 32
    assert (prov["backend"], prov["condition"], prov["formation"], prov["seed"]) == ("particle", "Synthetic", N, 0)
    assert (prov["wind"], prov["deviation"], prov["steps"], prov["dt"]) == (8.0, 0.5, T, 0.1)
    for m in "FNC":
        assert prov[m] == pytest.approx(record.scalars[f"{m}_so_far"][-1])
    assert prov["F"] > 0
    assert prov["code_version"] == code_version() and len(prov["git_commit"]) in (3, 40)  # "n/a" off a checkout
    for name in ("numpy", "numba", "mujoco", "torch", "python"):
        assert prov[name] == library_versions()[name]
    text = data["/episode"]["TextDocument:text"][None][0]
    assert "atm_c5_step3" in text and "5e" * 32 in text and code_version() in text


def test_wind_arrow_above_the_swarm(episode):
    record, _, data = episode
    wind = data["/world/wind"]
    assert sorted(wind["Arrows3D:vectors"]) == list(range(T))
    for t in (0, 151, T - 1):
        vector = np.array(wind["Arrows3D:vectors"][t][0])
        np.testing.assert_allclose(vector, [*record.wind_vector[t], 0.0], atol=1e-5)
        assert np.linalg.norm(vector) == pytest.approx(record.scalars["wind_speed"][t], abs=1e-5)  # 1 m per m/s
        centre = record.agent_pos[t].mean(axis=0)
        np.testing.assert_allclose(wind["Arrows3D:origins"][t][0], centre + [0, 0, 0.6], atol=1e-5)
        assert wind["Arrows3D:labels"][t] == [f"wind {record.scalars['wind_speed'][t]:.1f} m/s"]


def test_calm_episode_draws_no_wind_arrow(tmp_path):
    record = synthetic_record(n_steps=10, n_agents=3)
    record.wind_vector[:] = 0.0
    path = tmp_path / "calm.rrd"
    recording = open_recording(rrd_path=path)
    log_episode(record, recording)
    close_recording(recording)
    data = read_rrd(path)
    assert "/world/wind" not in data and "/world/uav_2" in data


def test_drone_pose_and_group_colour_at_a_step(episode):
    record, _, data = episode
    t, i = 137, 3
    translation = data[f"/world/uav_{i}"]["Transform3D:translation"][t]
    np.testing.assert_allclose(translation, [record.agent_pos[t, i]], atol=1e-5)
    quat_xyzw = data[f"/world/uav_{i}/body"]["Transform3D:quaternion"][t]
    np.testing.assert_allclose(quat_xyzw, [record.agent_quat[t, i, [1, 2, 3, 0]]], atol=1e-6)
    r, g, b = group_colors(record.group_id[t, i])
    assert data[f"/world/uav_{i}"]["Points3D:colors"][t] == [(int(r) << 24) | (int(g) << 16) | (int(b) << 8) | 255]
    assert len(data[f"/world/uav_{i}"]["Transform3D:translation"]) == T


def test_anchor_follows_its_jumps(episode):
    record, _, data = episode
    anchor = data["/world/anchor"]["Transform3D:translation"]
    assert not np.allclose(record.anchor[0], record.anchor[250])
    for t in (0, 249, 250, T - 1):
        np.testing.assert_allclose(anchor[t], [[*record.anchor[t], record.flight_altitude]], atol=1e-5)


def test_obstacles_are_static_cylinders(episode):
    record, _, data = episode
    k = len(record.obstacles)
    assert k > 0
    cylinders = data["/world/obstacles"]
    assert set(cylinders["Cylinders3D:centers"]) == {None}  # static
    centers = np.array(cylinders["Cylinders3D:centers"][None])
    assert centers.shape == (k, 3)
    np.testing.assert_allclose(centers[:, :2], record.obstacles, atol=1e-5)
    np.testing.assert_allclose(cylinders["Cylinders3D:radii"][None], [record.obstacle_radius] * k, atol=1e-6)


def test_scalar_series_one_value_per_step(episode):
    record, _, data = episode
    for name, series in record.scalars.items():
        logged = data[f"/metrics/{name}"]["Scalars:scalars"]
        assert sorted(logged) == list(range(T))
        np.testing.assert_allclose([logged[t][0] for t in range(T)], series)


def test_lidar_beams_and_hits_in_the_drone_frame(episode):
    record, _, data = episode
    i = 0
    hits_per_step = (record.lidar_ranges[:, i] < record.lidar_range).sum(axis=1)
    t = int(np.argmax(hits_per_step))
    assert hits_per_step[t] > 0
    beams = np.array(data[f"/world/uav_{i}/lidar"]["LineStrips3D:strips"][t])  # [M, 2, 3]
    assert beams.shape == (M, 2, 3)
    origin = record.lidar_origins[t, i] - record.agent_pos[t, i, :2]
    np.testing.assert_allclose(beams[:, 0, :2], np.broadcast_to(origin, (M, 2)), atol=1e-5)
    lengths = np.linalg.norm(beams[:, 1] - beams[:, 0], axis=1)
    np.testing.assert_allclose(lengths, record.lidar_ranges[t, i], atol=1e-5)
    assert np.allclose(beams[:, :, 2], 0.0)
    hits = data[f"/world/uav_{i}/lidar/hits"]["Points3D:positions"]
    assert [len(hits[s]) for s in range(T)] == hits_per_step.tolist()


def test_collisions_marked_and_logged_as_events(episode):
    record, _, data = episode
    marked = data["/world/collisions"]["Points3D:positions"]
    assert [len(marked[t]) for t in range(T)] == record.collision.sum(axis=1).tolist()
    events = data["/events/collisions"]["TextLog:text"]
    assert list(events) == [30]  # the synthetic agent 0 collides during steps 30-34: one onset
    assert events[30][0].startswith("uav 0 collision at step 30")


def test_template_and_trails_per_step(episode):
    record, _, data = episode
    template = data["/world/template"]["Points3D:positions"]
    has_point = ~np.isnan(record.template_world).any(axis=-1)
    assert [len(template[t]) for t in range(T)] == has_point.sum(axis=1).tolist()
    trails = data["/world/trails"]["LineStrips3D:strips"]
    segment = np.array(trails[120][2])
    np.testing.assert_allclose(segment, record.agent_pos[119:121, 2], atol=1e-5)
    isolated = np.argwhere(record.group_id == -1)
    assert len(isolated)
    t, i = isolated[0]
    grey = data["/world/trails"]["LineStrips3D:colors"][t][i]
    assert grey == (90 << 24) | (90 << 16) | (90 << 8) | 255


def test_body_parts_from_the_mjcf(episode):
    record, _, data = episode
    cylinders = data["/world/uav_2/body/cylinders"]
    prop = next(p for p in record.airframe_parts if p.name == "prop_fr")
    np.testing.assert_allclose(cylinders["Cylinders3D:centers"][None], [prop.pos], atol=1e-6)
    np.testing.assert_allclose(cylinders["Cylinders3D:lengths"][None], [2 * prop.size[1]], atol=1e-6)
    # A capsule is centred in MuJoCo but runs from its translation along its local +z in Rerun:
    # the logged one must span the arm's fromto endpoints.
    capsules = data["/world/uav_2/body/capsules"]
    start = np.array(capsules["Capsules3D:translations"][None][0])
    x, y, z, w = capsules["Capsules3D:quaternions"][None][0]
    axis = np.array([2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)])  # R(q) @ e_z
    end = start + capsules["Capsules3D:lengths"][None][0] * axis
    endpoints = sorted([start.round(4).tolist(), end.round(4).tolist()])
    assert endpoints == [[-0.13, -0.22, 0.0], [0.13, 0.22, 0.0]]


def test_blueprint_travels_with_the_recording(episode):
    _, path, _ = episode
    reader = RrdReader(path)
    assert len(reader.recordings()) == 1 and len(reader.blueprints()) == 1
    entities = {c.entity_path for c in reader.stream(store=reader.blueprints()[0]).to_chunks()}
    assert any(e.endswith("/overrides/world/trails/visualizers") for e in entities)
    assert "/time_panel" in entities


def test_rrd_verify_cli(episode):
    _, path, _ = episode
    exe = shutil.which("rerun") or str(Path(sys.executable).with_name("rerun"))
    if not os.path.exists(exe):
        pytest.skip("the rerun CLI is not installed")
    result = subprocess.run([exe, "rrd", "verify", str(path)], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr


def test_slices_log_the_same_as_one_call(tmp_path, episode):
    record, _, whole = episode
    path = tmp_path / "sliced.rrd"
    recording = open_recording(rrd_path=path)
    log_static(record, recording)
    for start in range(0, T, 70):
        log_steps(record, recording, start, min(start + 70, T))
    close_recording(recording)
    sliced = read_rrd(path)
    assert set(sliced) == set(whole)
    for entity in sliced:
        if entity != "/__properties":
            assert sliced[entity] == whole[entity], entity


def test_bad_sinks_and_slices_are_config_errors(tmp_path):
    with pytest.raises(ConfigError, match="rrd_path"):
        open_recording()
    with pytest.raises(ConfigError, match="cannot write"):
        open_recording(rrd_path=tmp_path / "missing" / "x.rrd")
    with pytest.raises(ConfigError, match="cannot write"):
        open_recording(rrd_path=tmp_path)
    record = synthetic_record(n_steps=10, n_agents=3)
    recording = open_recording(rrd_path=tmp_path / "x.rrd")
    with pytest.raises(ConfigError, match="outside"):
        log_steps(record, recording, 5, 11)
    close_recording(recording)


def test_unreachable_viewer_does_not_hang_close(tmp_path):
    """A viewer sink nobody listens on (the viewer was closed) next to the file: close still returns."""
    path = tmp_path / "tee.rrd"
    recording = rr.RecordingStream("cefc-mj-test", recording_id="tee")
    recording.set_sinks(rr.FileSink(str(path)), rr.GrpcSink("rerun+http://127.0.0.1:1/proxy"))
    log_episode(synthetic_record(n_steps=20, n_agents=3), recording)
    with pytest.warns(UserWarning, match="Flush timed out"):
        close_recording(recording, timeout_s=0.5)
    assert len(read_rrd(path)["/world/uav_2"]["Transform3D:translation"]) == 20


@pytest.mark.filterwarnings("ignore:RRD file has no footer")  # the interrupted listener writes no footer
def test_spawn_streams_the_episode_to_a_listening_viewer(tmp_path):
    """`cefc-eval --spawn` end to end without a display: a headless `rerun --save` listens where the
    viewer would (port 9876, so spawn connects instead of starting one) and writes what arrives."""
    from cefc_mj.cli.eval import main

    live = tmp_path / "live.rrd"
    with rerun_listener(9876, live):
        assert main(["--backend", "particle", "--formation", "5", "--steps", "20", "--episodes", "1", "--spawn"]) == 0
    data = read_rrd(live)
    assert len(data["/world/uav_4"]["Transform3D:translation"]) == 20
    assert {"/world/obstacles", "/world/anchor", "/metrics/hd_error"} <= set(data)
    assert data["/__properties/provenance"]["backend"][None] == ["particle"]  # the properties reach the viewer


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def no_display(monkeypatch):
    """A headless Linux session with no viewer listening where `--spawn` would look."""
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    monkeypatch.setattr(rerun_log.sys, "platform", "linux")
    port = _free_port()
    monkeypatch.setattr(rerun_log, "VIEWER_PORT", port)
    return port


def test_spawn_without_display_or_viewer_is_a_config_error(no_display, monkeypatch, tmp_path):
    with pytest.raises(ConfigError, match=r"--spawn: no display .* --rrd PATH .* `rerun PATH`"):
        check_spawn_possible()
    monkeypatch.setattr(rr, "spawn", lambda *a, **k: pytest.fail("a viewer was spawned"))
    with pytest.raises(ConfigError, match="no display"):
        open_recording(rrd_path=tmp_path / "x.rrd", spawn=True)
    assert not (tmp_path / "x.rrd").exists()


def test_spawn_is_possible_with_a_display_or_a_listening_viewer(no_display, monkeypatch):
    import socket

    with socket.socket() as server:  # anything accepting connections on the viewer port counts
        server.bind(("127.0.0.1", no_display))
        server.listen()
        check_spawn_possible()
    monkeypatch.setenv("WAYLAND_DISPLAY", "wayland-0")
    check_spawn_possible()
    monkeypatch.delenv("WAYLAND_DISPLAY")
    monkeypatch.setenv("DISPLAY", ":0")
    check_spawn_possible()


def test_cli_spawn_without_display_fails_before_flying(no_display, monkeypatch, capsys):
    """One line, exit code 2, and no episode flown (the CLI checks before its first episode)."""
    from cefc_mj.cli.eval import main
    from cefc_mj.eval import runner

    monkeypatch.setattr(runner, "make_world", lambda *a, **k: pytest.fail("an episode was started"))
    try:
        code = main(["--backend", "particle", "--formation", "5", "--steps", "5", "--spawn"])
    except SystemExit as exit_:
        code = exit_.code
    assert code == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("cefc-eval: error: --spawn: no display") and "\n" not in err
