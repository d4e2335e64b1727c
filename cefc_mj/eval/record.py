"""What one evaluation episode leaves behind: `EpisodeRecord`, saved as `.npz` and replotted later.

The evaluation runner fills an `EpisodeRecord` with one row per decision step (dt = 0.1 s). The
Rerun logger (`cefc_mj/viz/rerun_log.py`) and the top-down PNG (`cefc_mj/viz/plots.py`) read only
this record, so both work the same for the MuJoCo and the particle backend, live or after the fact.

Shapes: T decision steps, N UAVs, M LiDAR beams, K obstacles, J targets. World frame ENU, metres,
seconds; quaternions are (w, x, y, z) as in MuJoCo.

>>> rec = synthetic_record(n_steps=50, n_agents=5)
>>> rec.n_steps, rec.n_agents, rec.agent_pos.shape
(50, 5, (50, 5, 3))
"""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from cefc_mj.errors import ConfigError
from cefc_mj.fileio import atomic_write

PART_KINDS = ("box", "cylinder", "capsule", "sphere", "ellipsoid")


@dataclass(frozen=True)
class AirframePart:
    """One primitive of the drone body, in the drone's root-body frame.

    `size` follows MuJoCo's geom convention: box (half x, half y, half z); cylinder and capsule
    (radius, half length along local z, unused); sphere (radius, unused, unused); ellipsoid
    (semi-axes x, y, z). `quat` is (w, x, y, z), `rgba` in [0, 1].
    """

    name: str
    kind: str
    size: np.ndarray
    pos: np.ndarray
    quat: np.ndarray
    rgba: np.ndarray

    def __post_init__(self) -> None:
        if self.kind not in PART_KINDS:
            raise ConfigError(f"airframe part {self.name!r}: kind {self.kind!r} is not one of {PART_KINDS}")


def airframe_parts_from_mjcf(path: str | os.PathLike) -> list[AirframePart]:
    """The visual geoms of the first body under the world body, in that body's frame.

    Loads the MJCF with `mujoco.MjModel.from_xml_path`, poses the model at qpos0 and expresses the
    geoms of the first top-level body's subtree (rotor bodies included) relative to that body.
    Visual geoms are those that collide with nothing (contype = conaffinity = 0, how MJCF marks
    visual-only geoms, as `assets/mjcf/iris.xml` does), so the collision footprint does not hide the
    frame; a body without any takes all its geoms. A mesh becomes its bounding box; planes, height
    fields and SDFs raise `ConfigError`. Colours come from the geom's material if it has one.
    """
    import mujoco

    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"airframe MJCF {path}: no such file")
    model = mujoco.MjModel.from_xml_path(str(path))
    data = mujoco.MjData(model)
    mujoco.mj_kinematics(model, data)
    roots = [b for b in range(1, model.nbody) if model.body_parentid[b] == 0]
    if not roots:
        raise ConfigError(f"airframe MJCF {path}: no body under the world body")
    root = roots[0]
    root_pos = data.xpos[root].copy()
    root_rot = data.xmat[root].reshape(3, 3).copy()
    gt = mujoco.mjtGeom
    kind_of = {
        int(gt.mjGEOM_BOX): "box",
        int(gt.mjGEOM_CYLINDER): "cylinder",
        int(gt.mjGEOM_CAPSULE): "capsule",
        int(gt.mjGEOM_SPHERE): "sphere",
        int(gt.mjGEOM_ELLIPSOID): "ellipsoid",
    }
    geoms = [g for g in range(model.ngeom) if model.body_rootid[model.geom_bodyid[g]] == root]
    visual = [g for g in geoms if model.geom_contype[g] == 0 and model.geom_conaffinity[g] == 0]
    parts: list[AirframePart] = []
    for g in visual or geoms:
        name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_GEOM, g) or f"geom{g}"
        rot = root_rot.T @ data.geom_xmat[g].reshape(3, 3)
        pos = root_rot.T @ (data.geom_xpos[g] - root_pos)
        size = model.geom_size[g].copy()
        geom_type = int(model.geom_type[g])
        if geom_type == int(gt.mjGEOM_MESH):
            kind = "box"
            pos = pos + rot @ model.geom_aabb[g, :3]
            size = model.geom_aabb[g, 3:].copy()
        elif geom_type in kind_of:
            kind = kind_of[geom_type]
        else:
            raise ConfigError(f"airframe MJCF {path}: geom {name!r} has a type that cannot be drawn as a part")
        quat = np.empty(4)
        mujoco.mju_mat2Quat(quat, rot.reshape(-1))
        matid = model.geom_matid[g]
        rgba = model.mat_rgba[matid].copy() if matid >= 0 else model.geom_rgba[g].copy()
        parts.append(AirframePart(name=name, kind=kind, size=size, pos=pos, quat=quat, rgba=rgba))
    if not parts:
        raise ConfigError(f"airframe MJCF {path}: the first body has no geom")
    return parts


def code_provenance() -> dict[str, str]:
    """The code that runs now: "git_commit" ("" outside a checkout) and `library_versions()` (package
    version, code digest, python, numpy, numba, mujoco, torch, CPU, MKL_CBWR)."""
    from cefc_mj.provenance import git_commit, library_versions

    return {"git_commit": git_commit() or "", **library_versions()}


@dataclass
class EpisodeRecord:
    """One episode, one row per decision step. Validated on construction (`ConfigError`)."""

    backend: str
    """"mujoco" or "particle"."""
    condition: str
    """Perturbation condition, e.g. "SITL-S", "Wind-8", "Deviation-0.5"."""
    formation: int
    """Formation size c (the number of UAVs in the Table VIII protocol)."""
    seed: int
    dt: float
    """Decision step in seconds (0.1)."""
    flight_altitude: float
    """Commanded altitude in metres (2.0); 2D things (anchor, template, LiDAR) are drawn at it."""
    agent_pos: np.ndarray
    """[T, N, 3] true positions."""
    agent_quat: np.ndarray
    """[T, N, 4] attitudes (w, x, y, z); identity for the particle backend."""
    agent_vel: np.ndarray
    """[T, N, 2] true horizontal velocities."""
    obstacles: np.ndarray
    """[K, 2] cylinder centres."""
    obstacle_radius: float
    obstacle_height: float
    anchor: np.ndarray
    """[T, 2] anchor point in force at each step (it jumps when re-drawn)."""
    targets: np.ndarray
    """[J, 2] target positions (J may be 0)."""
    lidar_origins: np.ndarray
    """[T, N, 2] where each agent cast its beams from (its true or its estimated position)."""
    lidar_ranges: np.ndarray
    """[T, N, M] ranges in metres, clipped to `lidar_range`; beam k points at world angle 2 pi k / M."""
    lidar_range: float
    group_id: np.ndarray
    """[T, N] int group label (connected component), -1 for an isolated agent."""
    template_world: np.ndarray
    """[T, N, 2] the template point assigned to agent i, placed at its group's centre; NaN where none."""
    collision: np.ndarray
    """[T, N] bool: agent i in collision at this step."""
    scalars: dict[str, np.ndarray] = field(default_factory=dict)
    """name -> [T] float per-step series ("hd_error", "anchor_distance", "wind_speed", "F_so_far", ...)."""
    adversary_pos: np.ndarray | None = None
    """[T, 3] or None when the episode has no adversary."""
    airframe_parts: list[AirframePart] = field(default_factory=list)
    """The drone body for the 3D view (`airframe_parts_from_mjcf`); empty draws a marker only."""
    wind_vector: np.ndarray | None = None
    """[T, 2] horizontal wind velocity at the swarm (m/s); None (the default) means zeros, no wind."""
    policy: str = ""
    """Name of the policy that flew (its file's stem, e.g. "atm_c5_step3"); "" when none did."""
    policy_sha256: str = ""
    """SHA-256 of the policy file's bytes (`cefc_mj.eval.runner.policy_files`); "" when none did."""
    wind: float = 0.0
    """Mean wind speed of the condition (m/s)."""
    wind_direction: float | None = None
    """The episode's mean wind direction (degrees the air moves towards, ENU: 0 = +x), given or drawn
    from the seed; None without wind."""
    deviation: float = 0.0
    """Sensing deviation of the condition (m)."""
    provenance: dict[str, str] | None = None
    """The code that flew the episode: git commit, code version and library versions
    (`code_provenance`). None (the default) gathers them when the record is built, in the process
    that flew it; `load` gives back the saved ones ({} for files saved before records had them)."""

    def __post_init__(self) -> None:
        f64 = lambda a: np.asarray(a, dtype=np.float64)  # noqa: E731
        for name in (
            "agent_pos",
            "agent_quat",
            "agent_vel",
            "obstacles",
            "anchor",
            "targets",
            "lidar_origins",
            "lidar_ranges",
            "template_world",
        ):
            setattr(self, name, f64(getattr(self, name)))
        if self.wind_vector is None:
            self.wind_vector = np.zeros((self.agent_pos.shape[0], 2))
        self.wind_vector = f64(self.wind_vector)
        self.policy, self.policy_sha256 = str(self.policy), str(self.policy_sha256)
        self.wind, self.deviation = float(self.wind), float(self.deviation)
        self.wind_direction = None if self.wind_direction is None else float(self.wind_direction)
        if self.provenance is None:
            self.provenance = code_provenance()
        self.provenance = {str(k): str(v) for k, v in self.provenance.items()}
        self.group_id = np.asarray(self.group_id, dtype=np.int64)
        self.collision = np.asarray(self.collision, dtype=bool)
        self.scalars = {str(k): f64(v) for k, v in self.scalars.items()}
        if self.adversary_pos is not None:
            self.adversary_pos = f64(self.adversary_pos)
        self.targets = self.targets.reshape(-1, 2)
        self.obstacles = self.obstacles.reshape(-1, 2)
        self._validate()

    @property
    def n_steps(self) -> int:
        return self.agent_pos.shape[0]

    @property
    def n_agents(self) -> int:
        return self.agent_pos.shape[1]

    @property
    def n_beams(self) -> int:
        return self.lidar_ranges.shape[2]

    @property
    def final_metrics(self) -> dict[str, float]:
        """F, N, C at the last step (from the "F_so_far", ... series; those missing are left out)."""
        return {
            m: float(self.scalars[f"{m}_so_far"][-1])
            for m in "FNC"
            if f"{m}_so_far" in self.scalars and self.n_steps > 0
        }

    def _validate(self) -> None:
        if self.agent_pos.ndim != 3 or self.agent_pos.shape[2] != 3:
            raise ConfigError(f"EpisodeRecord.agent_pos: shape {self.agent_pos.shape}, expected [T, N, 3]")
        t, n = self.agent_pos.shape[:2]
        m = self.lidar_ranges.shape[-1] if self.lidar_ranges.ndim == 3 else -1
        expected = {
            "agent_quat": (t, n, 4),
            "agent_vel": (t, n, 2),
            "anchor": (t, 2),
            "lidar_origins": (t, n, 2),
            "lidar_ranges": (t, n, m),
            "group_id": (t, n),
            "template_world": (t, n, 2),
            "collision": (t, n),
            "wind_vector": (t, 2),
        }
        if self.adversary_pos is not None:
            expected["adversary_pos"] = (t, 3)
        for name, shape in expected.items():
            actual = getattr(self, name).shape
            if actual != shape:
                raise ConfigError(f"EpisodeRecord.{name}: shape {actual}, expected {shape} (T={t}, N={n})")
        for name, series in self.scalars.items():
            if series.shape != (t,):
                raise ConfigError(f"EpisodeRecord.scalars[{name!r}]: shape {series.shape}, expected ({t},)")
        if self.backend not in ("mujoco", "particle"):
            raise ConfigError(f"EpisodeRecord.backend: {self.backend!r}, expected 'mujoco' or 'particle'")
        for name in ("dt", "obstacle_radius", "obstacle_height", "lidar_range"):
            value = float(getattr(self, name))
            if not np.isfinite(value) or value <= 0:
                raise ConfigError(f"EpisodeRecord.{name}: {value}, expected a positive number")

    # ----------------------------------------------------------------------------- persistence

    def save(self, path: str | os.PathLike) -> Path:
        """Write the record to `path` (.npz, compressed) atomically: temp file + `os.replace`."""
        path = Path(path)
        arrays: dict[str, np.ndarray] = {}
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if f.name == "scalars":
                arrays.update({f"scalar/{k}": v for k, v in value.items()})
            elif f.name == "provenance":
                arrays.update({f"provenance/{k}": np.asarray(v) for k, v in value.items()})
            elif f.name == "airframe_parts":
                arrays["part/name"] = np.array([p.name for p in value], dtype=str)
                arrays["part/kind"] = np.array([p.kind for p in value], dtype=str)
                for attr, width in (("size", 3), ("pos", 3), ("quat", 4), ("rgba", 4)):
                    arrays[f"part/{attr}"] = np.array([getattr(p, attr) for p in value]).reshape(-1, width)
            elif value is not None:
                arrays[f.name] = np.asarray(value)
        atomic_write(path, lambda fh: np.savez_compressed(fh, **arrays))
        return path

    @classmethod
    def load(cls, path: str | os.PathLike) -> EpisodeRecord:
        """Read a record written by `save`."""
        with np.load(Path(path), allow_pickle=False) as npz:
            arrays = {k: npz[k] for k in npz.files}
        kwargs: dict = {}
        for f in dataclasses.fields(cls):
            if f.name in arrays:
                value = arrays.pop(f.name)
                kwargs[f.name] = value.item() if value.ndim == 0 else value
        kwargs["scalars"] = {k.removeprefix("scalar/"): v for k, v in arrays.items() if k.startswith("scalar/")}
        kwargs["provenance"] = {
            k.removeprefix("provenance/"): str(v) for k, v in arrays.items() if k.startswith("provenance/")
        }
        kwargs["airframe_parts"] = [
            AirframePart(name=str(name), kind=str(kind), size=size, pos=pos, quat=quat, rgba=rgba)
            for name, kind, size, pos, quat, rgba in zip(
                arrays["part/name"],
                arrays["part/kind"],
                arrays["part/size"],
                arrays["part/pos"],
                arrays["part/quat"],
                arrays["part/rgba"],
            )
        ]
        for name in ("backend", "condition", "policy", "policy_sha256"):
            if name in kwargs:
                kwargs[name] = str(kwargs[name])
        for name in ("formation", "seed"):
            kwargs[name] = int(kwargs[name])
        return cls(**kwargs)


# ----------------------------------------------------------------------------- synthetic episodes


def synthetic_record(
    n_steps: int = 200,
    n_agents: int = 8,
    n_beams: int = 24,
    n_obstacles: int = 12,
    seed: int = 0,
    airframe_parts: list[AirframePart] | None = None,
) -> EpisodeRecord:
    """A deterministic, physics-free episode for tests, benchmarks and trying the viewer.

    The swarm circles the origin in a loose ring; agents 0-2 drift apart every other 100 steps
    (so groups change), the anchor jumps every 250 steps, LiDAR ranges are exact ray-circle
    distances to the obstacles, agent 0 is "in collision" at steps 30-34, the wind blows at about
    8 m/s and veers slowly. F/N/C so far are cumulative counts like the real metrics.
    """
    rng = np.random.default_rng(seed)
    dt, altitude, lidar_range, radius = 0.1, 2.0, 3.0, 0.4
    steps = np.arange(n_steps)
    phase = 2 * np.pi * np.arange(n_agents) / n_agents
    angle = 0.02 * steps[:, None] + phase[None, :]
    ring = 1.0 + 0.3 * ((steps[:, None] // 100) % 2) * (np.arange(n_agents) < 3)[None, :] * 4
    xy = np.stack([ring * np.cos(angle), ring * np.sin(angle)], axis=-1) + 0.01 * steps[:, None, None]
    pos = np.concatenate([xy, np.full((n_steps, n_agents, 1), altitude)], axis=-1)
    vel = np.gradient(xy, dt, axis=0) if n_steps > 1 else np.zeros_like(xy)
    tilt = 0.05 * np.sin(angle)
    quat = np.stack([np.cos(tilt / 2), np.sin(tilt / 2), np.zeros_like(tilt), np.zeros_like(tilt)], axis=-1)
    obstacles = rng.uniform(-8, 8, size=(n_obstacles, 2))
    obstacles = obstacles[np.linalg.norm(obstacles, axis=1) > 3.5]
    anchor_draws = rng.uniform(-5, 5, size=(n_steps // 250 + 1, 2))
    anchor = anchor_draws[steps // 250]
    origins = xy + rng.normal(0.0, 0.05, size=xy.shape)
    beam_angle = 2 * np.pi * np.arange(n_beams) / n_beams
    direction = np.stack([np.cos(beam_angle), np.sin(beam_angle)], axis=-1)  # [M, 2]
    rel = obstacles[None, None, :, :] - origins[:, :, None, :]  # [T, N, K, 2]
    along = np.einsum("tnkd,md->tnmk", rel, direction)
    perp2 = (rel * rel).sum(-1)[:, :, None, :] - along**2
    hit = along - np.sqrt(np.clip(radius**2 - perp2, 0.0, None))
    valid = (perp2 <= radius**2) & (hit > 0)
    ranges = (
        np.where(valid, hit, np.inf).min(axis=-1) if len(obstacles) else np.full((n_steps, n_agents, n_beams), np.inf)
    )
    ranges = np.minimum(ranges, lidar_range)
    apart = ((steps // 100) % 2 == 1)[:, None] & (np.arange(n_agents) < 3)[None, :]
    # Labels follow connected_groups: a component is labelled by its smallest member index.
    group_id = np.where(apart, -1, np.where(apart.any(axis=1, keepdims=True), 3, 0))
    centre = xy.mean(axis=1, keepdims=True)
    template_world = centre + 0.8 * np.stack([np.cos(phase), np.sin(phase)], axis=-1)[None]
    template_world = np.where(apart[..., None], np.nan, template_world)
    collision = np.zeros((n_steps, n_agents), dtype=bool)
    collision[30:35, 0] = True
    wind_speed = np.abs(rng.normal(8.0, 1.6, n_steps))
    wind_heading = 0.3 + 0.002 * steps  # veers slowly
    wind_vector = wind_speed[:, None] * np.stack([np.cos(wind_heading), np.sin(wind_heading)], axis=-1)
    hd = np.abs(ring - 0.8).max(axis=1)
    anchor_distance = np.linalg.norm(centre[:, 0] - anchor, axis=-1)
    return EpisodeRecord(
        backend="particle",
        condition="Synthetic",
        formation=n_agents,
        seed=seed,
        dt=dt,
        flight_altitude=altitude,
        agent_pos=pos,
        agent_quat=quat,
        agent_vel=vel,
        obstacles=obstacles,
        obstacle_radius=radius,
        obstacle_height=4.0,
        anchor=anchor,
        targets=np.array([[8.0, 8.0], [-8.0, 8.0]]),
        lidar_origins=origins,
        lidar_ranges=ranges,
        lidar_range=lidar_range,
        group_id=group_id,
        template_world=template_world,
        collision=collision,
        scalars={
            "hd_error": hd,
            "anchor_distance": anchor_distance,
            "wind_speed": wind_speed,
            "F_so_far": np.cumsum(hd < 1.0).astype(float),
            "N_so_far": np.cumsum(anchor_distance < 1.0).astype(float),
            "C_so_far": 100.0 * np.cumsum(collision.sum(axis=1)) / (n_agents * (steps + 1)),
        },
        adversary_pos=np.concatenate([xy.mean(axis=1) + 4.0, np.full((n_steps, 1), altitude)], axis=-1),
        airframe_parts=list(airframe_parts or []),
        wind_vector=wind_vector,
        wind=8.0,
    )
