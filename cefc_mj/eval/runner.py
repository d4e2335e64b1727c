"""Run evaluation episodes: a low-level policy flies the Table VIII game in either backend.

The Table VIII episode (docs/design.md §6): one group of c UAVs, no adversary or targets, obstacles at
0.03 per m^2, 1000 decision steps, the anchor redrawn every 250 steps, under a wind and/or sensing
deviation condition. `run_episode` returns the episode's metrics and, on request, an
`EpisodeRecord` for Rerun and the top-down plot.
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, field

import numpy as np
import torch

from cefc_mj.env import BatchedCEFCEnv
from cefc_mj.errors import ConfigError, SimulationDiverged
from cefc_mj.eval import DEFAULT_POLICY
from cefc_mj.eval.record import EpisodeRecord, airframe_parts_from_mjcf
from cefc_mj.nn.policy_io import Policy, load_policy
from cefc_mj.nn.registry import policy_name_for
from cefc_mj.paths import MJCF_DIR
from cefc_mj.sim.backends import make_world
from cefc_mj.task.config import TaskConfig
from cefc_mj.task.formation import formation_template
from cefc_mj.task.guard import guarded
from cefc_mj.task.observation import layout_for

TABLE8_DENSITY = 0.03
TABLE8_STEPS = 1000
TABLE8_ANCHOR_REDRAW = 250
TABLE8_FORMATIONS = (5, 6, 7, 8)
FLIGHT_ALTITUDE = 2.0
OBSTACLE_HEIGHT = 4.0

CONDITIONS: dict[str, tuple[float, float]] = {
    "SITL-S": (0.0, 0.0),
    "Wind-3": (3.0, 0.0),
    "Wind-5": (5.0, 0.0),
    "Wind-8": (8.0, 0.0),
    "Deviation-0.3": (0.0, 0.3),
    "Deviation-0.5": (0.0, 0.5),
    "Deviation-0.8": (0.0, 0.8),
}
"""Table VIII conditions: name -> (mean wind speed m/s, sensing deviation m). SITL-M is separate."""


def condition_name(wind: float, deviation: float) -> str:
    """The paper's name for a condition ("SITL-S", "Wind-8", "Deviation-0.5") or a combined one."""
    parts = []
    if wind:
        parts.append(f"Wind-{wind:g}")
    if deviation:
        parts.append(f"Deviation-{deviation:g}")
    return "+".join(parts) if parts else "SITL-S"


def load_policy_for(choice: str, formation: int) -> Policy:
    """Load the policy `choice` for formation c and check that it reads this game's observations."""
    policy = load_policy(policy_name_for(choice, formation))
    expected = layout_for(EpisodeSpec(formation=formation, seed=0).task_config()).size
    if policy.obs_dim != expected:
        raise ConfigError(
            f"policy {policy.name!r} was trained for observations of size {policy.obs_dim}; "
            f"the c = {formation} game gives {expected}"
        )
    return policy


@dataclass(frozen=True)
class EpisodeSpec:
    """One evaluation episode."""

    formation: int
    """c: number of UAVs in the group."""
    seed: int
    """Seeds the scenario, the sensing noise and the wind."""
    backend: str = "mujoco"
    """"mujoco" (quadrotors) or "particle"."""
    wind: float = 0.0
    """Mean wind speed (m/s), MuJoCo only."""
    wind_direction: float | None = None
    """Direction the wind blows towards (degrees, ENU: 0 = +x, 90 = +y); None draws it per episode from
    the seed. Needs wind > 0."""
    deviation: float = 0.0
    """Sensing deviation d (m)."""
    steps: int = TABLE8_STEPS
    """Decision steps (0.1 s each)."""
    policy: str = DEFAULT_POLICY
    """Policy choice (see policy_name_for)."""
    airframe: str = "iris"
    """MuJoCo airframe: a shipped name ("iris", "crazyflie") or an MJCF path (docs/airframes.md);
    the particle backend has none and ignores it."""
    estimator: str = "fused"
    """The agents' position estimate (cefc_mj/task/estimator.py): "fused" (onboard filter of the
    noisy fixes with the agent's own velocity) or "raw" (the paper's memoryless agent); bit-identical
    without sensing deviation."""
    guard: bool = True
    """The agents pass their actions through the separation guard (cefc_mj/task/guard.py), the
    evaluators' default; False flies the policy's actions as they are (the paper's agent)."""
    rotor_actuation: str = "auto"
    """MuJoCo: how the rotor thrusts reach the physics (docs/research/mujoco_world.md): "auto" (live actuators up
    to 16 drones per env, the same forces through xfrc_applied above), "actuators" or "external"; the
    particle backend ignores it."""
    offboard: str = "velocity"
    """MuJoCo's offboard interface (docs/research/mujoco_world.md): "velocity" (the setpoint is integrated
    into a velocity setpoint, the default), "acceleration" (PX4's acceleration setpoints, as the paper
    sends them) or "acceleration-assisted" (not PX4's; docs/px4_interface.md); the particle backend
    ignores it."""

    accel_max: float | None = None
    """The action bound (m/s^2 per axis) the agents fly at (the env's clip and the policy's); None:
    the bound the policy was trained at (its policy file's ATMConfig.accel_max)."""
    push_observer: float | None = None
    """Time constant (s) of the agents' push observer (0: none); None: the one the policy was trained
    with (its policy file's ATMConfig.push_observer_s)."""

    @property
    def mujoco_airframe(self) -> str | None:
        """The airframe to build the world with: None on the particle backend."""
        return self.airframe if self.backend == "mujoco" else None

    @property
    def condition(self) -> str:
        return condition_name(self.wind, self.deviation)

    def task_config(self) -> TaskConfig:
        return TaskConfig(
            n_agents=self.formation,
            mode="formation",
            obstacle_density=TABLE8_DENSITY,
            episode_steps=self.steps,
            anchor_redraw_steps=TABLE8_ANCHOR_REDRAW,
            deviation=self.deviation,
            position_estimator=self.estimator,
            separation_guard=self.guard,
        )


@dataclass
class EpisodeResult:
    """Metrics of one episode (F, N in steps; C in % of agent-steps), plus bookkeeping."""

    spec: EpisodeSpec
    F: float
    N: float
    C: float
    steps: int
    wall_s: float
    diverged: str | None = None
    """The cause, if the simulation diverged and the episode was stopped early."""
    wind_direction_flown: float | None = None
    """The episode's mean wind direction (degrees, ENU), as given or drawn from the seed; None in calm air."""
    record: EpisodeRecord | None = field(default=None, repr=False)

    def faults(self) -> list[str]:
        """Why this episode is not a measurement of the policy, one line per cause (empty: it is one).
        Here: diverged physics; SITL-M adds agents lost or failed safe without being asked to."""
        return diverged_faults(self.steps, self.diverged)

    def to_dict(self) -> dict:
        out = {k: v for k, v in asdict(self).items() if k not in ("record", "spec")}
        out.update(asdict(self.spec), condition=self.spec.condition)
        out["faults"] = self.faults()
        return out


def diverged_faults(steps: int | None, diverged: str | None) -> list[str]:
    """The fault line of an episode whose physics diverged (`EpisodeResult.diverged`), or none."""
    return [f"simulation diverged at step {steps}: {diverged}"] if diverged else []


HISTOGRAM_EDGES_MS = np.concatenate([[0.0], np.logspace(-2, 4, 61)])
"""Bin edges (ms) of the SITL-M timing histograms: 0, then 10 bins per decade from 0.01 ms to 10 s
(`cefc_mj.deploy.results` counts into them, `cefc_mj.eval.table8` draws them)."""


def fly(env, steps: int, act, before_step=None, after_step=None) -> tuple[str | None, float]:
    """The episode loop every one-process runner shares: reset, then up to `steps` decision steps of
    `env.step(act(obs))`, stopping at the episode's end or when the physics diverges. `before_step(k)`
    runs before step k's action is chosen, `after_step()` after each step. Returns (the divergence
    message or None, wall-clock seconds)."""
    start = time.perf_counter()
    obs = env.reset()
    for k in range(steps):
        if before_step is not None:
            before_step(k)
        try:
            obs, _, done, _ = env.step(act(obs))
        except SimulationDiverged as e:
            return str(e), time.perf_counter() - start
        if after_step is not None:
            after_step()
        if done[0]:
            break
    return None, time.perf_counter() - start


def episode_fields(env, spec: EpisodeSpec, diverged: str | None, wall_s: float) -> dict:
    """The fields every episode result shares: spec, F, N, C of env 0, steps flown, wall-clock, divergence."""
    metrics = env.episode_metrics()
    return {
        "spec": spec,
        "F": float(metrics["F"][0]),
        "N": float(metrics["N"][0]),
        "C": float(metrics["C"][0]),
        "steps": int(env.t[0]),
        "wall_s": wall_s,
        "diverged": diverged,
        "wind_direction_flown": wind_direction_flown(env.world),
    }


def wind_direction_flown(world) -> float | None:
    """Env 0's mean wind direction (degrees in [0, 360), ENU) of a MuJoCo world in wind (SITL-M's ticked
    world included); None in calm air or on particles."""
    inner = getattr(world, "inner", world)
    wind = getattr(inner, "wind", None)
    if wind is None or not wind.config.mean_speed:
        return None
    return round(math.degrees(float(wind.mean_direction[0])) % 360.0, 6)


def episode_env(spec: EpisodeSpec, policy: Policy | None = None) -> tuple[BatchedCEFCEnv, object]:
    """The one-env episode of `spec` and the agents' act function (the policy, guarded as the spec
    says). `policy` defaults to loading `spec.policy` for `spec.formation`."""
    torch.set_num_threads(1)
    if policy is None:
        policy = load_policy_for(spec.policy, spec.formation)
    if spec.accel_max is not None:
        policy = policy.with_action_bound(spec.accel_max)
    if spec.push_observer is not None:
        policy = policy.with_push_observer(spec.push_observer)
    config = policy.task_for(spec.task_config())
    world = make_world(
        spec.backend,
        config,
        n_envs=1,
        wind=spec.wind,
        seed=spec.seed,
        airframe=spec.mujoco_airframe,
        offboard=spec.offboard if spec.backend == "mujoco" else None,
        wind_direction=spec.wind_direction,
        rotor_actuation=spec.rotor_actuation if spec.backend == "mujoco" else None,
    )
    env = BatchedCEFCEnv(config, n_envs=1, seed=spec.seed, world=world)
    # Policy.act's numbers bit for bit without its per-call checks: the compiled kernel on the weights
    # as they are now (fixed for the episode)
    weights = getattr(policy.actor, "inference_weights", None)
    return env, guarded(weights().actions if weights is not None else policy.act, config)


def run_episode(spec: EpisodeSpec, policy: Policy | None = None, record: bool = False) -> EpisodeResult:
    """Fly one episode. `policy` defaults to loading `spec.policy` for `spec.formation`."""
    env, act = episode_env(spec, policy)
    recorder = _Recorder(env, spec) if record else None
    diverged, wall_s = fly(env, spec.steps, act, after_step=recorder.capture if recorder is not None else None)
    return EpisodeResult(
        **episode_fields(env, spec, diverged, wall_s),
        record=recorder.finish() if recorder is not None and int(env.t[0]) > 0 else None,
    )


class _Recorder:
    """Collects an EpisodeRecord step by step from the env (true states, perceived LiDAR origins)."""

    def __init__(self, env: BatchedCEFCEnv, spec: EpisodeSpec):
        self.env = env
        self.spec = spec
        self.rows: dict[str, list] = {
            k: []
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
                "hd_error",
                "anchor_distance",
                "wind_speed",
                "wind_vector",
                "F",
                "N",
                "C",
            )
        }
        self.template = formation_template(env.n_agents, env.config.formation_spacing)

    def capture(self) -> None:
        env, world, rows = self.env, self.env.world, self.rows
        n = env.n_agents
        if hasattr(world, "drone_positions"):  # quadrotors: the drones' 3D poses (UAVs come first)
            rows["agent_pos"].append(world.drone_positions[0, :n].copy())
            rows["agent_quat"].append(world.drone_quaternions[0, :n].copy())
        else:
            rows["agent_pos"].append(np.concatenate([world.agent_pos[0], np.full((n, 1), FLIGHT_ALTITUDE)], -1))
            rows["agent_quat"].append(np.tile([1.0, 0.0, 0.0, 0.0], (n, 1)))
        rows["agent_vel"].append(world.agent_vel[0].copy())
        rows["anchor"].append(env.anchor[0].copy())
        rows["lidar_origins"].append(env.perceived_pos[0].copy())
        rows["lidar_ranges"].append(env.lidar[0].copy())
        rows["group_id"].append(env.labels[0].copy())
        centre = world.agent_pos[0].mean(axis=0)
        rows["template_world"].append(centre + self.template)
        rows["collision"].append(world.collisions()[0].copy())
        rows["hd_error"].append(float(env.agent_error[0, 0]))
        rows["anchor_distance"].append(float(np.linalg.norm(centre - env.anchor[0])))
        wind = world.wind_vector[0, :2] if hasattr(world, "wind_vector") else np.zeros(2)
        rows["wind_speed"].append(float(np.linalg.norm(wind)))
        rows["wind_vector"].append(np.array(wind, dtype=np.float64))
        metrics = env.episode_metrics()
        for key in ("F", "N", "C"):
            rows[key].append(float(metrics[key][0]))

    def finish(self) -> EpisodeRecord:
        env, rows = self.env, self.rows
        arr = {k: np.asarray(v) for k, v in rows.items()}
        flown = getattr(getattr(env.world, "inner", env.world), "airframe", None)  # MuJoCo (or SITL-M's ticked) world
        airframe = flown.path if flown is not None else MJCF_DIR / "iris.xml"
        policy = policy_files(self.spec.policy, [self.spec.formation])[str(self.spec.formation)]
        return EpisodeRecord(
            wind_vector=arr["wind_vector"],
            policy=policy["name"],
            policy_sha256=policy["sha256"],
            wind=self.spec.wind,
            deviation=self.spec.deviation,
            backend=self.spec.backend,
            condition=self.spec.condition,
            formation=self.spec.formation,
            seed=self.spec.seed,
            dt=env.config.dt,
            flight_altitude=FLIGHT_ALTITUDE,
            wind_direction=wind_direction_flown(env.world),
            agent_pos=arr["agent_pos"],
            agent_quat=arr["agent_quat"],
            agent_vel=arr["agent_vel"],
            obstacles=env.obstacles[0],
            obstacle_radius=env.config.obstacle_radius,
            obstacle_height=OBSTACLE_HEIGHT,
            anchor=arr["anchor"],
            targets=np.zeros((0, 2)),
            lidar_origins=arr["lidar_origins"],
            lidar_ranges=arr["lidar_ranges"],
            lidar_range=env.config.lidar_range,
            group_id=arr["group_id"],
            template_world=arr["template_world"],
            collision=arr["collision"],
            scalars={
                "hd_error": arr["hd_error"],
                "anchor_distance": arr["anchor_distance"],
                "wind_speed": arr["wind_speed"],
                "F_so_far": arr["F"],
                "N_so_far": arr["N"],
                "C_so_far": arr["C"],
            },
            airframe_parts=airframe_parts_from_mjcf(airframe) if airframe.is_file() else [],
        )


METRICS = ("F", "N", "C")
"""The Table VIII metrics: F, N in decision steps, C in % of agent-steps in collision."""


def _mean_std(values: list[float]) -> tuple[float | None, float | None]:
    """Mean and sample standard deviation (ddof 1); std is None for a single value, both None for none."""
    if not values:
        return None, None
    arr = np.asarray(values, dtype=np.float64)
    return float(arr.mean()), (float(arr.std(ddof=1)) if arr.size > 1 else None)


def episode_stats(per_episode: dict[str, np.ndarray]) -> dict:
    """Per metric of {metric: values over episodes}: the mean under its name, the sample std
    (`<metric>_std`, None for one episode), and the values themselves under "per_episode"."""
    row: dict = {}
    for m, values in per_episode.items():
        row[m], row[f"{m}_std"] = _mean_std([float(v) for v in values])
    row["per_episode"] = {m: [float(v) for v in values] for m, values in per_episode.items()}
    return row


def summarize(episodes: list[dict]) -> dict:
    """Mean and sample std over episodes (`EpisodeResult.to_dict()` rows) of F, N, C and F+N.

    Returns {"F", "F_std", "N", "N_std", "C", "C_std", "FN", "FN_std", "episodes", "diverged",
    "steps", "faults", "faulted", "valid"}: the means under the metric's own name, `*_std` None with fewer than 2
    episodes, every value None with none (never NaN, so JSON stays valid); "steps" is the longest
    episode's length; "faults" the episodes' faults (`episode_faults`), "faulted" how many episodes
    have any, and "valid" False when there are any: the cell is then not a measurement of the policy.
    """
    out: dict = {}
    for metric in METRICS:
        out[metric], out[f"{metric}_std"] = _mean_std([e[metric] for e in episodes])
    out["FN"], out["FN_std"] = _mean_std([e["F"] + e["N"] for e in episodes])
    out["episodes"] = len(episodes)
    out["diverged"] = sum(1 for e in episodes if e.get("diverged"))
    out["steps"] = max((int(e["steps"]) for e in episodes), default=None)
    out["faults"] = episode_faults(episodes)
    out["faulted"] = sum(1 for e in episodes if episode_faults([e]))
    out["valid"] = not out["faults"]
    return out


def episode_faults(episodes: list[dict]) -> list[str]:
    """The faults of result rows (`EpisodeResult.to_dict()`), each line prefixed with its seed; a row
    from before the field says only whether it diverged."""
    lines = []
    for e in episodes:
        faults = e.get("faults")
        if faults is None:
            faults = diverged_faults(e.get("steps"), e.get("diverged"))
        lines += [f"seed {e.get('seed')}: {line}" for line in faults]
    return lines


def cell_flag(cell: dict) -> str:
    """What a table prints after a cell's condition: " (NOT A MEASUREMENT: 1 of 2 episodes faulted)"
    when an episode lost agents, failed safe or diverged, "" otherwise (a cell from before the fault
    record: " (1 diverged)" when one diverged)."""
    if "valid" not in cell:
        return f" ({cell['diverged']} diverged)" if cell.get("diverged") else ""
    if cell["valid"]:
        return ""
    return f" (NOT A MEASUREMENT: {cell['faulted']} of {cell['episodes']} episodes faulted)"


def fault_lines(table: dict) -> list[str]:
    """One line per cause of every faulted cell of a {c: {condition: cell}} table:
    "c = 6 SITL-M, seed 0: UAVs 0-5: agent process exited at step 1 (t 0.10 s): process gone"."""
    return [
        f"c = {c} {cond}, {line}"
        for c, cells in table.items()
        for cond, cell in cells.items()
        for line in cell.get("faults", [])
    ]


def retention(cell: dict | None, calm: dict | None) -> tuple[float | None, str | None]:
    """(F+N) of a cell over (F+N) of the calm (SITL-S) cell of the same c and seeds.

    Returns (value, None), or (None, why) when it is undefined, so a report prints "-" and the reason
    instead of NaN."""
    if not cell or cell.get("F") is None:
        return None, "no episodes"
    if not calm or calm.get("F") is None:
        return None, "no calm (SITL-S) reference"
    reference = calm["F"] + calm["N"]
    if reference <= 0:
        return None, "calm F+N is 0"
    return (cell["F"] + cell["N"]) / reference, None


def format_mean_std(mean: float | None, std: float | None, fmt: str = ".1f") -> str:
    """ "812.3 ± 12.1", or "812.3" without a spread, or "-" without a value; never "nan"."""
    if mean is None or not math.isfinite(mean):
        return "-"
    if std is None or not math.isfinite(std):
        return format(mean, fmt)
    return f"{format(mean, fmt)} ± {format(std, fmt)}"


def policy_files(choice: str, formations) -> dict[str, dict[str, str]]:
    """{"5": {"name", "file", "sha256"}} of the policy file `choice` resolves to for each c (provenance,
    cache keys). Raises CheckpointError (one line) if a file is missing."""
    from cefc_mj.nn.policy_io import resolve_policy_path
    from cefc_mj.provenance import display_path, file_sha256

    out = {}
    for c in formations:
        path = resolve_policy_path(policy_name_for(choice, c)).resolve()
        out[str(c)] = {"name": path.stem, "file": display_path(path), "sha256": file_sha256(path)}
    return out


def provenance(choice: str, formations) -> dict:
    """What made a result: library versions (with the code digest), git commit, policy files + sha256."""
    from cefc_mj.provenance import git_commit, library_versions

    versions = library_versions()
    return {
        "library_versions": versions,
        "code_version": versions["code_version"],
        "git_commit": git_commit(),
        "policies": policy_files(choice, formations),
    }


def airframe_files(spec: EpisodeSpec) -> dict[str, str] | None:
    """SHA-256 of the airframe MJCF and its params file that `spec` flies (None on particles): a cell
    cache must not serve an episode flown on an edited airframe file of the same name."""
    if spec.mujoco_airframe is None:
        return None
    from cefc_mj.control.airframe import airframe_path
    from cefc_mj.control.params import params_for_airframe
    from cefc_mj.provenance import file_sha256

    path = airframe_path(spec.mujoco_airframe)  # the file only: the CLI validated the airframe up front
    return {"mjcf_sha256": file_sha256(path), "params_sha256": file_sha256(params_for_airframe(path))}
