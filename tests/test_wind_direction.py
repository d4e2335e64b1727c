"""The wind direction can be chosen: make_env(wind_direction=), EpisodeSpec.wind_direction and
cefc-eval --wind-direction DEG point the wind (degrees the air moves towards, ENU); the default stays
the seeded per-episode draw, which the run prints and records (JSON, Rerun)."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest

import cefc_mj
from cefc_mj.cli.eval import main
from cefc_mj.errors import ConfigError
from cefc_mj.eval.runner import EpisodeSpec, run_episode
from cefc_mj.viz.rerun_log import provenance_fields


@pytest.mark.parametrize("degrees", [0.0, 90.0, 225.0])
def test_make_env_points_the_wind(degrees):
    env = cefc_mj.make_env(backend="mujoco", n_agents=3, mode="formation", wind=5.0, wind_direction=degrees, seed=4)
    env.reset(seed=4)
    world = env.batched.world
    assert math.isclose(math.degrees(world.wind.mean_direction[0]) % 360, degrees % 360, abs_tol=1e-9)
    w = world.wind.vector[0, :2]
    expected = np.array([math.cos(math.radians(degrees)), math.sin(math.radians(degrees))])
    assert np.allclose(w / np.linalg.norm(w), expected, atol=1e-9)


def test_default_draws_per_seed_and_records_it():
    a = run_episode(EpisodeSpec(formation=3, seed=1, steps=3, wind=5.0), record=True)
    b = run_episode(EpisodeSpec(formation=3, seed=2, steps=3, wind=5.0))
    assert a.wind_direction_flown is not None and a.wind_direction_flown != b.wind_direction_flown
    assert a.to_dict()["wind_direction_flown"] == a.wind_direction_flown
    assert provenance_fields(a.record)["wind_direction_deg"] == round(a.wind_direction_flown, 3)
    calm = run_episode(EpisodeSpec(formation=3, seed=1, steps=3))
    assert calm.wind_direction_flown is None


def test_bad_wind_direction_is_refused():
    with pytest.raises(ConfigError, match="wind_direction"):
        cefc_mj.make_env(backend="mujoco", n_agents=3, wind_direction=90.0)  # no wind to point
    with pytest.raises(ConfigError, match="wind_direction"):
        cefc_mj.make_env(backend="particle", n_agents=3, wind_direction=90.0)
    with pytest.raises(ConfigError, match="wind_direction"):
        cefc_mj.make_env(backend="mujoco", n_agents=3, wind=3.0, wind_direction=float("nan"))


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--wind-direction", "90"], "no wind to point"),
        (["--backend", "particle", "--wind-direction", "90"], "particle backend"),
        (["--wind", "3", "--wind-direction", "inf"], "finite angle"),
    ],
)
def test_cli_refuses_bad_wind_direction(argv, message, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(argv)
    assert exit_info.value.code == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and message in err


def test_cli_flies_the_given_direction_and_names_the_airframe(tmp_path, capsys):
    out = tmp_path / "r.json"
    assert (
        main(
            [
                "--formation",
                "3",
                "--steps",
                "3",
                "--episodes",
                "1",
                "--workers",
                "1",
                "--wind",
                "4",
                "--wind-direction",
                "135",
                "--airframe",
                "crazyflie",
                "--json",
                str(out),
            ]
        )
        == 0
    )
    printed = capsys.readouterr().out
    assert "crazyflie airframe" in printed and "wind towards 135° (ENU)" in printed
    summary = json.loads(out.read_text())
    assert summary["wind_direction"] == 135.0 and summary["airframe"] == "crazyflie"
    windy = summary["rows"]["3"]["Wind-4"]["episodes_detail"][0]
    assert windy["wind_direction"] == 135.0 and windy["wind_direction_flown"] == 135.0
    calm = summary["rows"]["3"]["SITL-S"]["episodes_detail"][0]
    assert calm["wind_direction"] is None and calm["wind_direction_flown"] is None


def test_sitl_m_and_dropout_episodes_fly_and_record_the_given_direction():
    """The agent processes' episode (real processes over ZeroMQ) and the lock-step dropout path."""
    from cefc_mj.deploy.dropout import run_dropout_episode
    from cefc_mj.deploy.episode import run_sitl_episode

    spec = EpisodeSpec(formation=3, seed=1, steps=5, wind=4.0, wind_direction=300.0)
    assert run_sitl_episode(spec).wind_direction_flown == 300.0
    assert run_dropout_episode(dataclasses.replace(spec, formation=4), (1, 3)).wind_direction_flown == 300.0
