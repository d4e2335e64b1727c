"""Backend selection: the physics world of a backend name (`make_world`), re-exported as
`cefc_mj.make_world` for users."""

from __future__ import annotations

from cefc_mj.errors import ConfigError
from cefc_mj.task.config import TaskConfig

BACKENDS = ("particle", "mujoco")


def make_world(
    backend: str,
    config: TaskConfig,
    n_envs: int = 1,
    wind: float = 0.0,
    seed: int | None = None,
    airframe: str | None = None,
    offboard: str | None = None,
    wind_direction: float | None = None,
    rotor_actuation: str | None = None,
):
    """The physics world for `backend` ("particle" or "mujoco"); wind (m/s mean speed), wind_direction
    (degrees the air moves towards, ENU: 0 = +x, 90 = +y; None = drawn per episode from the seed),
    airframe (a shipped name such as "iris" or "crazyflie", or an MJCF path; docs/research/mujoco_world.md) and
    offboard (what the PX4-like interface makes of a setpoint: "velocity", the default,
    "acceleration" or "acceleration-assisted"; docs/px4_interface.md) and rotor_actuation ("auto", the
    default, "actuators" or "external": docs/research/mujoco_world.md) are MuJoCo's."""
    if backend not in BACKENDS:
        raise ConfigError(f"backend={backend!r}: must be one of {', '.join(BACKENDS)}")
    if not isinstance(wind, (int, float)) or not wind == wind or wind < 0:
        raise ConfigError(f"wind={wind!r}: must be a number >= 0 (mean wind speed, m/s)")
    if backend == "particle":
        if wind:
            raise ConfigError("wind: the particle backend has no wind model; use backend='mujoco'")
        if wind_direction is not None:
            raise ConfigError("wind_direction: the particle backend has no wind model; use backend='mujoco'")
        if airframe is not None:
            raise ConfigError("airframe: the particle backend has no airframe; use backend='mujoco'")
        if offboard is not None:
            raise ConfigError("offboard: the particle backend has no offboard interface; use backend='mujoco'")
        if rotor_actuation is not None:
            raise ConfigError("rotor_actuation: the particle backend has no rotors; use backend='mujoco'")
        from cefc_mj.sim.particle import ParticleWorld

        return ParticleWorld(config, n_envs, seed=seed)
    from cefc_mj.sim.mujoco_world import MujocoWorldConfig, make_mujoco_world

    options = {k: v for k, v in (("offboard", offboard), ("rotor_actuation", rotor_actuation)) if v is not None}
    world_config = MujocoWorldConfig(**options) if options else None
    return make_mujoco_world(
        config,
        n_envs=n_envs,
        wind=wind,
        seed=seed,
        airframe=airframe,
        config=world_config,
        wind_direction=wind_direction,
    )
