"""EpisodeRecord (what the Rerun logger and the PNG read): validation, npz round trip, airframe parts."""

from __future__ import annotations

from pathlib import Path

import mujoco
import numpy as np
import pytest

from cefc_mj.errors import ConfigError
from cefc_mj.eval.record import EpisodeRecord, airframe_parts_from_mjcf, synthetic_record
from cefc_mj.paths import MJCF_DIR
from cefc_mj.provenance import code_version, library_versions

MINI_QUAD = Path(__file__).parent / "data" / "mini_quad.xml"


def test_save_load_round_trip(tmp_path):
    record = synthetic_record(n_steps=40, n_agents=4, n_beams=8, airframe_parts=airframe_parts_from_mjcf(MINI_QUAD))
    path = record.save(tmp_path / "ep.npz")
    assert [p.name for p in tmp_path.iterdir()] == ["ep.npz"]  # no temp file left behind
    loaded = EpisodeRecord.load(path)
    for name in ("backend", "condition", "formation", "seed", "dt", "flight_altitude", "obstacle_radius"):
        assert getattr(loaded, name) == getattr(record, name)
    for name in (
        "agent_pos",
        "agent_quat",
        "anchor",
        "lidar_ranges",
        "group_id",
        "template_world",
        "collision",
        "adversary_pos",
        "targets",
        "obstacles",
    ):
        np.testing.assert_array_equal(getattr(loaded, name), getattr(record, name))
    assert loaded.scalars.keys() == record.scalars.keys()
    np.testing.assert_array_equal(loaded.scalars["hd_error"], record.scalars["hd_error"])
    assert [(p.name, p.kind) for p in loaded.airframe_parts] == [(p.name, p.kind) for p in record.airframe_parts]
    np.testing.assert_array_equal(loaded.airframe_parts[2].quat, record.airframe_parts[2].quat)


def test_provenance_and_wind_round_trip(tmp_path):
    record = synthetic_record(n_steps=20, n_agents=3)
    record.policy, record.policy_sha256, record.deviation = "atm_c3_step3", "ab" * 32, 0.3
    record.provenance["mkl_cbwr"] = ""
    loaded = EpisodeRecord.load(record.save(tmp_path / "ep.npz"))
    assert (loaded.policy, loaded.policy_sha256, loaded.wind, loaded.deviation) == ("atm_c3_step3", "ab" * 32, 8.0, 0.3)
    assert loaded.provenance == record.provenance  # the code that flew it, not the code that loads it
    np.testing.assert_array_equal(loaded.wind_vector, record.wind_vector)
    np.testing.assert_allclose(np.linalg.norm(record.wind_vector, axis=1), record.scalars["wind_speed"])


def test_provenance_is_gathered_when_the_record_is_built():
    prov = synthetic_record(n_steps=5, n_agents=3).provenance
    assert prov["code_version"] == code_version()
    assert {k: prov[k] for k in ("numpy", "numba", "mujoco", "torch")} == {
        k: library_versions()[k] for k in ("numpy", "numba", "mujoco", "torch")
    }
    assert "git_commit" in prov


def test_runner_fills_policy_condition_and_wind():
    """What `run_episode(record=True)` puts in the record: the policy file and its digest, the
    condition, and the wind at every step (Wind-8 on quadrotors, 3 steps)."""
    import hashlib

    from cefc_mj.eval.runner import EpisodeSpec, policy_name_for, run_episode
    from cefc_mj.nn.policy_io import resolve_policy_path

    record = run_episode(EpisodeSpec(formation=5, seed=0, steps=3, wind=8.0, deviation=0.3), record=True).record
    path = resolve_policy_path(policy_name_for(EpisodeSpec.policy, 5))  # the default low level
    assert (record.policy, record.policy_sha256) == (path.stem, hashlib.sha256(path.read_bytes()).hexdigest())
    assert (record.wind, record.deviation) == (8.0, 0.3)
    assert record.wind_vector.shape == (3, 2) and np.all(np.linalg.norm(record.wind_vector, axis=1) > 1.0)
    np.testing.assert_allclose(np.linalg.norm(record.wind_vector, axis=1), record.scalars["wind_speed"])


def test_file_saved_before_provenance_loads_with_defaults(tmp_path):
    path = synthetic_record(n_steps=10, n_agents=3).save(tmp_path / "new.npz")
    with np.load(path) as npz:
        old = {
            k: npz[k]
            for k in npz.files
            if not k.startswith("provenance/")
            and k not in ("wind_vector", "policy", "policy_sha256", "wind", "deviation")
        }
    np.savez_compressed(tmp_path / "old.npz", **old)
    loaded = EpisodeRecord.load(tmp_path / "old.npz")
    assert loaded.provenance == {} and loaded.policy == "" and loaded.wind == 0.0
    np.testing.assert_array_equal(loaded.wind_vector, np.zeros((10, 2)))


def test_final_metrics_are_the_last_step_of_the_series():
    record = synthetic_record(n_steps=40, n_agents=3)
    assert record.final_metrics == {m: record.scalars[f"{m}_so_far"][-1] for m in "FNC"}
    record.scalars = {}
    assert record.final_metrics == {}


def test_shape_mismatch_names_the_field():
    good = synthetic_record(n_steps=10, n_agents=3)
    with pytest.raises(ConfigError, match="lidar_origins"):
        EpisodeRecord(**{**vars(good), "lidar_origins": np.zeros((10, 2, 2))})
    with pytest.raises(ConfigError, match="hd_error"):
        EpisodeRecord(**{**vars(good), "scalars": {"hd_error": np.zeros(9)}})
    with pytest.raises(ConfigError, match="backend"):
        EpisodeRecord(**{**vars(good), "backend": "gazebo"})
    with pytest.raises(ConfigError, match="wind_vector"):
        EpisodeRecord(**{**vars(good), "wind_vector": np.zeros((10, 3))})


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
    path.write_text(
        '<mujoco><worldbody><body name="b"><freejoint/><geom name="ball" size="0.2"/>'
        '<geom name="rod" type="box" size="0.3 0.01 0.01"/></body></worldbody></mujoco>'
    )
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
