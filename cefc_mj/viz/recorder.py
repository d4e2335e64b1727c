"""Rerun recording of a `CEFCParallelEnv` (cefc_mj.pettingzoo_env): `RerunRecorder` logs its episodes
step by step with the project's episode logging (`cefc_mj.viz.rerun_log`), to `.rrd` files and/or a
live viewer (`spawn_viewer` starts one, or finds one listening on `RERUN_VIEWER_PORT`);
`render_mode="human"` uses it. Rerun itself is imported only when a recording starts.
"""

from __future__ import annotations

import os
import socket
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Protocol

import numpy as np

from cefc_mj.errors import ConfigError
from cefc_mj.sim.particle import ParticleWorld

if TYPE_CHECKING:
    from cefc_mj.env import BatchedCEFCEnv
    from cefc_mj.task.config import TaskConfig

RERUN_VIEWER_PORT = 9876  # where rr.spawn starts (or finds) the viewer, and where rr.GrpcSink() sends
FLIGHT_ALTITUDE = 2.0  # the particle world is 2D; Rerun draws it at the quadrotors' altitude (m)
OBSTACLE_HEIGHT = 4.0  # likewise, the height of the drawn obstacle cylinders (m)


def has_display() -> bool:
    """Whether a display to open windows on is set (X11 or Wayland)."""
    return any(os.environ.get(k) for k in ("DISPLAY", "WAYLAND_DISPLAY", "WAYLAND_SOCKET"))


def _viewer_listening(port: int = RERUN_VIEWER_PORT) -> bool:
    with socket.socket() as s:
        s.settimeout(0.5)
        return s.connect_ex(("127.0.0.1", port)) == 0


def spawn_viewer() -> None:
    """Start a Rerun viewer (or find one listening); ConfigError when none can show up."""
    if _viewer_listening():
        return
    if sys.platform.startswith("linux") and not has_display():
        raise ConfigError(
            "render_mode='human': no display for a Rerun viewer (DISPLAY is unset) and none listening "
            f"on port {RERUN_VIEWER_PORT}; use render_mode='rgb_array'"
        )
    import rerun as rr

    try:
        rr.spawn(port=RERUN_VIEWER_PORT, connect=False)
    except Exception as e:  # the viewer executable is missing or cannot start
        raise ConfigError(
            f"render_mode='human': cannot start the Rerun viewer ({e}); use render_mode='rgb_array'"
        ) from None


_SCALARS = ("hd_error", "anchor_distance", "wind_speed", "F_so_far", "N_so_far", "C_so_far")
"""The per-step series RerunRecorder logs under metrics/ (the names cefc-eval's recordings use)."""


class RecordableEnv(Protocol):
    """What `RerunRecorder` reads of an env; `cefc_mj.pettingzoo_env.CEFCParallelEnv` is one (named here
    by its fields, not imported: the PettingZoo front end sits above this layer and imports the recorder)."""

    batched: BatchedCEFCEnv
    """The batched env underneath (one env): its world, step counter and state."""
    config: TaskConfig
    """The task's configuration (agents, LiDAR rays, episode length)."""
    episode_seed: int | None
    """The seed of the episode in progress (None before the first reset)."""


class RerunRecorder:
    """Logs a `CEFCParallelEnv`'s episodes to Rerun step by step, with `cefc_mj.viz.rerun_log`
    (the same entities, timelines and blueprint as `cefc-eval --rrd/--spawn`).

    Call `capture()` after `reset()` and after every `step()` (render_mode="human" does it itself).
    Each episode is its own recording: sent to the viewer (`spawn=True`) and/or written to
    `rrd_path` for the first episode and `<stem>_<k><suffix>` for episode k >= 1.

    >>> import cefc_mj, tempfile, pathlib                       # doctest: +SKIP
    >>> env = cefc_mj.make_env(n_agents=3, mode="formation")    # doctest: +SKIP
    >>> with RerunRecorder(env, rrd_path=pathlib.Path(tempfile.mkdtemp()) / "ep.rrd") as rec:  # doctest: +SKIP
    ...     env.reset(seed=0); rec.capture()
    ...     while env.agents:
    ...         env.step({a: env.action_space(a).sample() for a in env.agents}); rec.capture()
    """

    def __init__(self, env: RecordableEnv, rrd_path: str | os.PathLike | None = None, spawn: bool = False):
        if rrd_path is None and not spawn:
            raise ConfigError("RerunRecorder: give rrd_path, spawn=True, or both")
        self.env = env
        self.rrd_path = None if rrd_path is None else Path(rrd_path)
        self.spawn = spawn
        self.episodes = 0
        self.recording = None
        self._rows: dict[str, np.ndarray] = {}
        self._static: dict = {}
        self._airframe_parts = None  # the drone body for the 3D view, read once

    def __enter__(self) -> RerunRecorder:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def capture(self) -> None:
        """Log the env's current state as step t = env.batched.t (t = 0 starts a new episode)."""
        from cefc_mj.viz.rerun_log import log_static, log_steps

        t = int(self.env.batched.t[0])
        if t == 0:
            self._start_episode()
            self._fill(0)
            log_static(self._record(1), self.recording)
            log_steps(self._record(1), self.recording, 0, 1)
            return
        if self.recording is None or t >= len(self._rows["agent_pos"]):
            raise ConfigError("RerunRecorder.capture: capture right after reset() and after every step()")
        self._fill(t)
        log_steps(self._record(t + 1), self.recording, t, t + 1)
        if t == self.env.config.steps:
            self._finish_recording()

    def close(self) -> None:
        self._finish_recording()

    # ------------------------------------------------------------------ internals
    def _episode_path(self) -> Path | None:
        if self.rrd_path is None or self.episodes == 0:
            return self.rrd_path
        return self.rrd_path.with_name(f"{self.rrd_path.stem}_{self.episodes}{self.rrd_path.suffix}")

    def _start_episode(self) -> None:
        from cefc_mj.eval.record import airframe_parts_from_mjcf
        from cefc_mj.paths import MJCF_DIR
        from cefc_mj.task.formation import formation_template
        from cefc_mj.viz.rerun_log import open_recording

        self._finish_recording()
        self.recording = open_recording(rrd_path=self._episode_path(), spawn=self.spawn)
        self.episodes += 1
        env, cfg = self.env.batched, self.env.config
        world = env.world
        rows, n, m = cfg.steps + 1, cfg.n_agents, cfg.n_lidar_rays
        self._rows = {
            "agent_pos": np.zeros((rows, n, 3)),
            "agent_quat": np.zeros((rows, n, 4)),
            "agent_vel": np.zeros((rows, n, 2)),
            "anchor": np.zeros((rows, 2)),
            "lidar_origins": np.zeros((rows, n, 2)),
            "lidar_ranges": np.zeros((rows, n, m)),
            "group_id": np.zeros((rows, n), dtype=np.int64),
            "template_world": np.full((rows, n, 2), np.nan),
            "collision": np.zeros((rows, n), dtype=bool),
            "adversary_pos": np.zeros((rows, 3)),
            **{name: np.zeros(rows) for name in _SCALARS},
        }
        wind = getattr(world, "wind_config", None)
        mujoco_config = None if isinstance(world, ParticleWorld) else getattr(world, "config", None)
        condition = []  # the paper's names, as cefc-eval writes them
        if wind is not None and wind.mean_speed:
            condition.append(f"Wind-{wind.mean_speed:g}")
        if cfg.deviation:
            condition.append(f"Deviation-{cfg.deviation:g}")
        if self._airframe_parts is None:
            airframe = MJCF_DIR / "iris.xml"
            self._airframe_parts = airframe_parts_from_mjcf(airframe) if airframe.is_file() else []
        seed = self.env.episode_seed
        self._static = dict(
            backend="particle" if isinstance(world, ParticleWorld) else "mujoco",
            condition="+".join(condition) or "SITL-S",
            formation=n,
            seed=-1 if seed is None else int(seed),
            dt=cfg.dt,
            flight_altitude=getattr(mujoco_config, "flight_altitude", FLIGHT_ALTITUDE),
            obstacles=env.obstacles[0].copy(),
            obstacle_radius=cfg.obstacle_radius,
            obstacle_height=getattr(mujoco_config, "obstacle_height", OBSTACLE_HEIGHT),
            targets=env.targets[0].copy(),
            lidar_range=cfg.lidar_range,
            airframe_parts=self._airframe_parts,
        )
        self._template = formation_template(n, cfg.formation_spacing) if cfg.mode == "formation" else None
        self._has_adversary = cfg.mode == "cefc" and cfg.adversary != "none"

    def _fill(self, t: int) -> None:
        """Row t of the episode buffers from the env's current state."""
        env, world, rows = self.env.batched, self.env.batched.world, self._rows
        n, alt = env.n_agents, self._static["flight_altitude"]
        if hasattr(world, "drone_positions"):  # quadrotors: 3D poses (UAVs first, then the adversary)
            rows["agent_pos"][t] = world.drone_positions[0, :n]
            rows["agent_quat"][t] = world.drone_quaternions[0, :n]
        else:
            rows["agent_pos"][t, :, :2] = world.agent_pos[0]
            rows["agent_pos"][t, :, 2] = alt
            rows["agent_quat"][t] = (1.0, 0.0, 0.0, 0.0)
        rows["agent_vel"][t] = world.agent_vel[0]
        rows["anchor"][t] = env.anchor[0]
        rows["lidar_origins"][t] = env.perceived_pos[0]
        rows["lidar_ranges"][t] = env.lidar[0]
        rows["group_id"][t] = env.labels[0]
        centre = world.agent_pos[0].mean(axis=0)
        if self._template is not None:
            rows["template_world"][t] = centre + self._template
        rows["collision"][t] = world.collisions()[0]
        rows["adversary_pos"][t] = (*world.adversary_pos[0], alt)
        rows["hd_error"][t] = np.nanmin(env.agent_error[0]) if np.isfinite(env.agent_error[0]).any() else np.nan
        rows["anchor_distance"][t] = np.linalg.norm(centre - env.anchor[0])
        rows["wind_speed"][t] = np.linalg.norm(world.wind_vector[0, :2]) if hasattr(world, "wind_vector") else 0.0
        metrics = env.episode_metrics()
        for key in ("F", "N", "C"):
            rows[f"{key}_so_far"][t] = metrics[key][0]

    def _record(self, length: int):
        """The episode's first `length` rows as an EpisodeRecord (views, no copies)."""
        from cefc_mj.eval.record import EpisodeRecord

        rows = self._rows
        scalars = {k: rows[k][:length] for k in _SCALARS}
        arrays = {
            k: rows[k][:length]
            for k in (
                "agent_pos",
                "agent_quat",
                "agent_vel",
                "anchor",
                "lidar_origins",
                "lidar_ranges",
                "group_id",
                "template_world",
                "collision",
            )
        }
        adversary = rows["adversary_pos"][:length] if self._has_adversary else None
        return EpisodeRecord(**self._static, **arrays, scalars=scalars, adversary_pos=adversary)

    def _finish_recording(self) -> None:
        from cefc_mj.viz.rerun_log import close_recording

        recording, self.recording = self.recording, None
        if recording is not None:
            close_recording(recording)
