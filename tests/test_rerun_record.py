"""EpisodeRecord (what the Rerun logger and the PNG read): validation, npz round trip, airframe parts."""

from __future__ import annotations

from pathlib import Path

import mujoco
import numpy as np
import pytest

from cefc_mj.errors import ConfigError
from cefc_mj.eval.record import EpisodeRecord, airframe_parts_from_mjcf, synthetic_record
from cefc_mj.paths import MJCF_DIR

MINI_QUAD = Path(__file__).parent / "data" / "mini_quad.xml"


def test_save_load_round_trip(tmp_path):
    record = synthetic_record(n_steps=40, n_agents=4, n_beams=8, airframe_parts=airframe_parts_from_mjcf(MINI_QUAD))
    path = record.save(tmp_path / "ep.npz")
    assert [p.name for p in tmp_path.iterdir()] == ["ep.npz"]  # no temp file left behind
    loaded = EpisodeRecord.load(path)
    for name in ("backend", "condition", "formation", "seed", "dt", "flight_altitude", "obstacle_radius"):
        assert getattr(loaded, name) == getattr(record, name)
    for name in ("agent_pos", "agent_quat", "anchor", "lidar_ranges", "group_id", "template_world",
                 "collision", "adversary_pos", "targets", "obstacles"):
        np.testing.assert_array_equal(getattr(loaded, name), getattr(record, name))
    assert loaded.scalars.keys() == record.scalars.keys()
    np.testing.assert_array_equal(loaded.scalars["hd_error"], record.scalars["hd_error"])
    assert [(p.name, p.kind) for p in loaded.airframe_parts] == [(p.name, p.kind) for p in record.airframe_parts]
    np.testing.assert_array_equal(loaded.airframe_parts[2].quat, record.airframe_parts[2].quat)


def test_round_trip_without_adversary_targets_or_parts(tmp_path):
    record = synthetic_record(n_steps=10, n_agents=3)
    record.adversary_pos = None
    record.targets = np.zeros((0, 2))
    loaded = EpisodeRecord.load(record.save(tmp_path / "ep.npz"))
    assert loaded.adversary_pos is None and loaded.targets.shape == (0, 2) and loaded.airframe_parts == []


def test_failed_save_keeps_the_old_file(tmp_path, monkeypatch):
    path = tmp_path / "ep.npz"
    path.write_bytes(b"old")

    def boom(*args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr(np, "savez_compressed", boom)
    with pytest.raises(OSError, match="disk full"):
        synthetic_record(n_steps=5, n_agents=3).save(path)
    assert path.read_bytes() == b"old"
    assert [p.name for p in tmp_path.iterdir()] == ["ep.npz"]


def test_shape_mismatch_names_the_field():
    good = synthetic_record(n_steps=10, n_agents=3)
    with pytest.raises(ConfigError, match="lidar_origins"):
        EpisodeRecord(**{**vars(good), "lidar_origins": np.zeros((10, 2, 2))})
    with pytest.raises(ConfigError, match="hd_error"):
        EpisodeRecord(**{**vars(good), "scalars": {"hd_error": np.zeros(9)}})
    with pytest.raises(ConfigError, match="backend"):
        EpisodeRecord(**{**vars(good), "backend": "gazebo"})


def test_airframe_parts_in_the_root_body_frame():
    parts = {p.name: p for p in airframe_parts_from_mjcf(MINI_QUAD)}
    # The floor (world body) and the collision footprint are not part of the drawn body.
    assert set(parts) == {"core", "arm", "battery", "camera", "prop_fr", "prop_bl"}
    assert parts["core"].kind == "box" and np.allclose(parts["core"].rgba, [0.2, 0.2, 0.25, 1.0])  # material
    np.testing.assert_allclose(parts["prop_fr"].pos, [0.13, -0.22, 0.03])  # child body, relative to the root
    yaw = 2 * np.arctan2(parts["prop_fr"].quat[3], parts["prop_fr"].quat[0])
    assert np.degrees(yaw) == pytest.approx(30.0)
    assert parts["arm"].kind == "capsule" and parts["arm"].size[1] == pytest.approx(np.hypot(0.13, 0.22))
    # The mesh becomes its bounding box: half extents 0.02 x 0.03 x 0.01 in some axis order.
    assert parts["camera"].kind == "box"
    np.testing.assert_allclose(sorted(parts["camera"].size), [0.01, 0.02, 0.03], atol=1e-9)
    np.testing.assert_allclose(parts["camera"].pos, [0.1, 0.0, -0.03], atol=1e-9)


def test_airframe_without_visual_geoms_draws_its_collision_geoms(tmp_path):
    path = tmp_path / "ball.xml"
    path.write_text('<mujoco><worldbody><body name="b"><freejoint/><geom name="ball" size="0.2"/>'
                    '<geom name="rod" type="box" size="0.3 0.01 0.01"/></body></worldbody></mujoco>')
    parts = airframe_parts_from_mjcf(path)
    assert [(p.name, p.kind) for p in parts] == [("ball", "sphere"), ("rod", "box")]


def test_airframe_missing_file_is_a_config_error(tmp_path):
    with pytest.raises(ConfigError, match="no such file"):
        airframe_parts_from_mjcf(tmp_path / "iris.xml")


def test_shipped_airframe_draws_its_visual_geoms_only():
    path = MJCF_DIR / "iris.xml"
    if not path.is_file():
        pytest.skip("assets/mjcf/iris.xml is not there yet")
    model = mujoco.MjModel.from_xml_path(str(path))
    parts = airframe_parts_from_mjcf(path)
    assert parts
    for part in parts:
        g = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, part.name)
        assert model.geom_contype[g] == 0 and model.geom_conaffinity[g] == 0, part.name
