"""What cefc-eval is asked to run: one frozen request per protocol, every value defaulted and
range-checked here, once (the backend, wind and deviation in `cefc_mj.eval.conditions`), with a
one-line ConfigError naming the flag that sets it.

- `SingleRequest`: one condition (wind and/or deviation) against calm air;
- `Table8Request`: the paper's Table VIII grid (7 conditions, MuJoCo);
- `Table3Request`: the paper's Table III (the particle world);
- `GameTablesRequest`: the high level's game, Tables V, VI and VII.

They share `Conditions` (backend, wind, deviation), `Flight` (how the agents and quadrotors fly) and
`SitlM` (the SITL-M link). Output paths are checked here too, so that bad input ends before anything is
flown or written. `cefc_mj/cli/eval.py` translates the flags into a request; `cefc_mj/cli/eval_*.py`
run it.
"""

from __future__ import annotations

import os
import re
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from cefc_mj.errors import CefcError, ConfigError
from cefc_mj.eval import DEFAULT_POLICY
from cefc_mj.eval.conditions import Conditions, check_wind_direction, is_number_in, number_text
from cefc_mj.eval.highlevel import GAME_POLICY
from cefc_mj.eval.runner import TABLE8_FORMATIONS, TABLE8_STEPS
from cefc_mj.eval.table3 import TABLE3_FORMATIONS
from cefc_mj.executors import ExecutorConfig, usable_cpus
from cefc_mj.fileio import can_write_in
from cefc_mj.game_protocol import EPISODES as GAME_EPISODES
from cefc_mj.nn.registry import GAME_ADVERSARY, WITHDRAWN
from cefc_mj.table3_protocol import TABLE3_EPISODES, TABLE3_STEPS
from cefc_mj.task.config import MAX_ACCEL
from cefc_mj.task.estimator import POSITION_ESTIMATORS
from cefc_mj.task.push_observer import MAX_PUSH_OBSERVER_S

MAX_EPISODES = 10_000
"""Seeds per cell at most (checked before any list of episodes is built)."""
MAX_STEPS = 100_000
"""Decision steps per episode at most (10 000 s of flight)."""
MAX_WORKERS = 64
"""Processes flying episodes at most."""
MAX_LINK_MS = 10_000.0
"""SITL-M link delay and jitter at most (ms)."""
MAX_SEED = 2**32 - 1
"""Seeds are 32-bit unsigned: seed + episodes - 1 must not pass it."""
FORMATIONS = range(3, 9)
"""The formation sizes c with shipped policies."""
DEFAULT_AIRFRAME = "iris"
"""The MuJoCo airframe flown unless --airframe names another."""
TABLE8_EPISODES = 5
"""Seeds per cell of a Table VIII grid by default."""
SINGLE_EPISODES = TABLE8_EPISODES
"""Seeds per c of --protocol single (the main job) by default. One seed is one layout of obstacles and
anchors, and layouts differ widely (the sample std of the cells of eval/reports/table8.md), so one
seed is not a measurement. The same count as Table VIII's grid, so that from seed 0 the
calm reference flies the grid's SITL-S episodes."""
SINGLE_WORKERS = 2
"""Processes --protocol single flies its lock-step episodes on by default (fewer where this process may
use fewer CPUs); SITL-M and recorded episodes fly one at a time in this process."""
TABLE8_BACKEND = "mujoco"
"""Table VIII is flown on quadrotors (its Wind conditions need the wind model)."""
GAME_TABLES = ("table5", "table6", "table7")

SYSTEM_FOLDERS = frozenset(
    {
        "/",
        "/bin",
        "/boot",
        "/dev",
        "/etc",
        "/lib",
        "/lib32",
        "/lib64",
        "/libx32",
        "/opt",
        "/proc",
        "/run",
        "/sbin",
        "/snap",
        "/srv",
        "/sys",
        "/usr",
        "/usr/bin",
        "/usr/lib",
        "/usr/local",
        "/usr/sbin",
        "/usr/share",
        "/var",
        "/var/lib",
    }
)
"""Folders in which cefc-eval never creates a missing output folder (even when run as root)."""


# ---------------------------------------------------------------------------- shared checks
def check_output(flag: str, path: Path, is_dir: bool = False) -> None:
    """ConfigError for an output path that cannot be written. Missing folders are created later, right
    before writing, and only below an existing folder that is writable and is not `/` or another system
    folder (SYSTEM_FOLDERS)."""
    path = Path(path)
    if not is_dir and path.is_dir():
        raise ConfigError(f"{flag} {path}: is a folder; give a file name")
    if not is_dir and path.exists() and not os.access(path, os.W_OK):
        raise ConfigError(f"{flag} {path}: the file exists and is not writable")
    if is_dir and path.exists() and not path.is_dir():
        raise ConfigError(f"{flag} {path}: is a file, not a folder")
    folder = (path if is_dir else path.parent).absolute()
    ancestor, missing = folder, []
    while not ancestor.exists():
        missing.append(ancestor)
        ancestor = ancestor.parent
    if not ancestor.is_dir():
        raise ConfigError(f"{flag} {path}: {ancestor} is a file, not a folder")
    if missing and (str(ancestor) in SYSTEM_FOLDERS or ancestor == Path(ancestor.anchor)):
        raise ConfigError(f"{flag} {path}: will not create {missing[-1]} inside the system folder {ancestor}")
    if not can_write_in(ancestor):
        raise ConfigError(f"{flag} {path}: {ancestor} is not writable")


def _check_outputs(*outputs: tuple[str, Path | None, bool]) -> None:
    """check_output of each (flag, path or None, is_dir) given."""
    for flag, path, is_dir in outputs:
        if path is not None:
            check_output(flag, path, is_dir)


def _is_int(value: object) -> bool:
    return isinstance(value, (int, np.integer)) and not isinstance(value, bool)


def _check_count(flag: str, value: object, most: int) -> None:
    if not (_is_int(value) and 1 <= value <= most):
        raise ConfigError(f"{flag} {value}: must be in 1..{most}")


def _check_seed(seed: object) -> None:
    if not (_is_int(seed) and seed >= 0):
        raise ConfigError(f"--seed {seed}: must be >= 0")


def _check_last_seed(seed: int, episodes: int) -> None:
    """Episode k flies seed + k: the last must still be a 32-bit seed."""
    if seed + episodes - 1 > MAX_SEED:
        raise ConfigError(f"--seed {seed}: seeds up to {seed + episodes - 1} pass the largest seed {MAX_SEED}")


def _formations(formations: object) -> tuple[int, ...]:
    """The formation sizes as a tuple, each with shipped policies and none twice."""
    formations = tuple(formations)
    if not formations:
        raise ConfigError("--formation: give at least one formation size c")
    for c in formations:
        if not (_is_int(c) and c in FORMATIONS):
            raise ConfigError(f"--formation {c}: formations exist for c = {FORMATIONS[0]}..{FORMATIONS[-1]}")
    if len(set(formations)) != len(formations):
        raise ConfigError(f"--formation {' '.join(map(str, formations))}: a formation is listed twice")
    return tuple(int(c) for c in formations)


def check_policy_name(policy: object, orca: bool = False) -> None:
    """ConfigError for a --policy name that is withdrawn, or ORCA-F outside Table III (orca=False)."""
    if not isinstance(policy, str) or not policy:
        raise ConfigError(f"--policy {policy!r}: must be a policy name or a .pt path")
    if policy in WITHDRAWN:
        raise ConfigError(f"--policy {policy}: {WITHDRAWN[policy]}")
    if policy == "orca" and not orca:
        raise ConfigError(
            "--policy orca: the ORCA-F baseline is a Table III row (--backend particle --protocol table3)"
        )


def recording_refused(flag: str) -> ConfigError:
    """The error of a recording flag (--rrd, --png, --spawn) where nothing is recorded."""
    return ConfigError(f"{flag}: recording works with --protocol single, or table5 with --policy NAME (--rrd, --png)")


def adversary_refused(adversary: str) -> ConfigError:
    """The error of --adversary outside Tables V and VII."""
    return ConfigError(
        f"--adversary {adversary}: chooses the adversary of --protocol table5 and table7 (table6 "
        "plays each adversary of the paper's table in turn; the other protocols have none)"
    )


def parse_drop(text: str) -> tuple[int, int]:
    """ "K@STEP" (e.g. "2@500") -> (2, 500); ConfigError for anything else (the range is checked
    against the episode by check_drop)."""
    parts = str(text).split("@")
    if len(parts) != 2 or not all(p.strip().isdigit() for p in parts):
        raise ConfigError(f"--drop {text}: must be K@STEP, e.g. 2@500 (K agents drop out before step STEP)")
    return int(parts[0]), int(parts[1])


def check_drop(drop, formation: int, steps: int) -> tuple[int, int] | None:
    """(k, step) validated for a c-agent episode of `steps` steps (ConfigError naming the problem)."""
    if drop is None:
        return None
    try:
        k, step = drop
    except (TypeError, ValueError):
        raise ConfigError(f"drop={drop!r}: must be (k, step)") from None
    for name, value in (("k", k), ("step", step)):
        if not _is_int(value):
            raise ConfigError(f"drop={drop!r}: {name} must be an integer")
    if not 1 <= k <= formation - 3:
        raise ConfigError(f"drop={drop!r}: k must be in 1..{formation - 3} (at least 3 UAVs must stay to form)")
    if not 1 <= step < steps:
        raise ConfigError(f"drop={drop!r}: step must be in 1..{steps - 1}")
    return int(k), int(step)


def _policy_label(choice: str) -> str:
    """A file-name-safe label of a --policy value (a path becomes its stem)."""
    label = Path(choice).stem if choice.endswith(".pt") or os.sep in choice else choice
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", label) or "policy"


def default_report_dir(policy: str, backend: str) -> Path:
    """A fresh folder ./cefc-eval-reports/table8-<policy>-<backend>-<YYYYmmdd-HHMMSS>[-n]/."""
    stamp = time.strftime("%Y%m%d-%H%M%S")
    base = Path.cwd() / "cefc-eval-reports" / f"table8-{_policy_label(policy)}-{backend}-{stamp}"
    path, n = base, 1
    while path.exists():
        n += 1
        path = base.with_name(f"{base.name}-{n}")
    return path


def _path(value: object) -> Path | None:
    return None if value is None else Path(value)


# ---------------------------------------------------------------------------- shared pieces
@dataclass(frozen=True)
class Flight:
    """How the agents fly (both backends) and, on MuJoCo, the quadrotors they fly (single and table8)."""

    estimator: str = "fused"
    """--estimator: the agents' position estimate, "fused" (an onboard filter of the noisy fixes with the
    agent's own velocity) or "raw" (each fix as it is, the paper's memoryless agent)."""
    guard: bool = True
    """--guard on/off: the agents' separation guard limits their closing speed (off: the paper's agent)."""
    airframe: str = DEFAULT_AIRFRAME
    """--airframe: MuJoCo airframe, a shipped name ("iris", "crazyflie") or an MJCF path."""
    offboard: str = "velocity"
    """--offboard: what the PX4-like interface makes of the acceleration setpoint, "velocity" (integrated
    into a velocity setpoint), "acceleration" (PX4's acceleration setpoints, as the paper sends them) or
    "acceleration-assisted" (not PX4's; docs/px4_interface.md)."""
    rotor_actuation: str = "auto"
    """--rotor-actuation: how the rotor thrusts reach the physics, "auto", "actuators" or "external"."""
    accel_max: float | None = None
    """--accel-max: the action bound (m/s^2 per axis) the agents fly at, in (0, MAX_ACCEL]; None: the
    bound each policy was trained at (its policy file's)."""

    push_observer: float | None = None
    """--push-observer: the time constant (s) of the agents' push observer, in [0, MAX_PUSH_OBSERVER_S]
    (0: none); None: the one each policy was trained with (its policy file's)."""

    def __post_init__(self) -> None:
        if self.push_observer is not None and not is_number_in(self.push_observer, 0.0, MAX_PUSH_OBSERVER_S):
            raise ConfigError(
                f"--push-observer {number_text(self.push_observer)}: must be a number in [0, {MAX_PUSH_OBSERVER_S:g}] s"
            )
        if self.accel_max is not None and not (is_number_in(self.accel_max, 0.0, MAX_ACCEL) and self.accel_max > 0):
            raise ConfigError(
                f"--accel-max {number_text(self.accel_max)}: must be a number in (0, {MAX_ACCEL:g}] m/s^2"
            )
        if self.estimator not in POSITION_ESTIMATORS:
            raise ConfigError(f"--estimator {self.estimator}: must be one of {', '.join(POSITION_ESTIMATORS)}")
        if not isinstance(self.guard, bool):
            raise ConfigError(f"--guard {self.guard!r}: must be True (on) or False (off)")
        if (self.airframe, self.offboard, self.rotor_actuation) != (DEFAULT_AIRFRAME, "velocity", "auto"):
            from cefc_mj.control.cascade import OFFBOARD_MODES  # these import mujoco
            from cefc_mj.sim.mujoco_world import ROTOR_ACTUATIONS, MujocoWorldConfig

            if self.offboard not in OFFBOARD_MODES:
                raise ConfigError(f"--offboard {self.offboard}: must be one of {', '.join(OFFBOARD_MODES)}")
            if self.rotor_actuation not in ROTOR_ACTUATIONS:
                raise ConfigError(
                    f"--rotor-actuation {self.rotor_actuation}: must be one of {', '.join(ROTOR_ACTUATIONS)}"
                )
            try:
                MujocoWorldConfig(airframe=self.airframe).validate()
            except CefcError as e:
                raise ConfigError(f"--airframe {self.airframe}: {e}") from None


@dataclass(frozen=True)
class SitlM:
    """--sitl-m: every UAV's policy in its own OS process over ZeroMQ, asynchronous (docs/sitl_m.md)."""

    link_delay_ms: float = 0.0
    """--link-delay: one-way network delay in simulated ms, each way, 0..MAX_LINK_MS."""
    jitter_ms: float = 0.0
    """--jitter: each direction adds a uniform draw from [0, jitter_ms] ms, 0..MAX_LINK_MS."""

    def __post_init__(self) -> None:
        for flag, value in (("--link-delay", self.link_delay_ms), ("--jitter", self.jitter_ms)):
            if not is_number_in(value, 0.0, MAX_LINK_MS):
                raise ConfigError(f"{flag} {number_text(value)}: must be a number in 0..{MAX_LINK_MS:g} ms")


# ---------------------------------------------------------------------------- the protocols
@dataclass(frozen=True)
class SingleRequest:
    """--protocol single: one condition (wind and/or sensing deviation) against calm air, for each
    formation size c and seed; with SITL-M, dropout and recordings as asked."""

    conditions: Conditions = field(default_factory=Conditions)
    """--backend, --wind, --wind-direction, --deviation: the asked condition (calm air flies alone)."""
    formations: tuple[int, ...] = TABLE8_FORMATIONS
    """--formation: formation sizes c, each in 3..8."""
    episodes: int = SINGLE_EPISODES
    """--episodes: seeds per c, 1..MAX_EPISODES."""
    steps: int = TABLE8_STEPS
    """--steps: decision steps per episode, 1..MAX_STEPS; F and N match the paper's only at 1000."""
    seed: int = 0
    """--seed: the first seed (>= 0); episode k flies seed + k."""
    policy: str = DEFAULT_POLICY
    """--policy: a low-level policy alias (nav, atm, safe, clm, student), a name in policies/ or a .pt path."""
    flight: Flight = field(default_factory=Flight)
    """--estimator, --guard, --airframe, --offboard, --rotor-actuation."""
    sitl: SitlM | None = None
    """--sitl-m (--link-delay, --jitter): the asked condition flown as SITL-M; None: one process."""
    drop: tuple[int, int] | None = None
    """--drop K@STEP: (k, step), k UAVs leave before decision step `step` (k <= c - 3)."""
    workers: int | None = None
    """--workers: processes flying episodes, 1..MAX_WORKERS (1 with SITL-M or a recording); None:
    SINGLE_WORKERS (at most the usable CPUs), or 1 with SITL-M or a recording."""
    rrd: Path | None = None
    """--rrd: record the episodes to this Rerun file (run_c5_s0.rrd etc. for several)."""
    png: Path | None = None
    """--png: draw a top-down PNG of each episode into this folder."""
    spawn: bool = False
    """--spawn: stream the episodes to a live Rerun viewer."""
    json: Path | None = None
    """--json: also write the results here as JSON."""

    def __post_init__(self) -> None:
        if self.sitl is not None and _is_int(self.workers) and self.workers > 1:
            raise ConfigError(
                f"--workers {self.workers}: SITL-M episodes fly one at a time (each runs c + 1 processes)"
            )
        check_policy_name(self.policy)
        object.__setattr__(self, "formations", _formations(self.formations))
        _check_count("--episodes", self.episodes, MAX_EPISODES)
        _check_count("--steps", self.steps, MAX_STEPS)
        _check_seed(self.seed)
        if self.workers is None:
            one_at_a_time = self.sitl is not None or self.recording
            object.__setattr__(self, "workers", 1 if one_at_a_time else min(SINGLE_WORKERS, usable_cpus()))
        _check_count("--workers", self.workers, MAX_WORKERS)
        _check_last_seed(self.seed, self.episodes)
        recording = [flag for flag, on in (("--rrd", self.rrd), ("--png", self.png), ("--spawn", self.spawn)) if on]
        if self.workers > 1 and recording:
            raise ConfigError(f"--workers {self.workers}: {recording[0]} records in this process; use --workers 1")
        for c in self.formations:
            check_drop(self.drop, c, self.steps)
        for name in ("rrd", "png", "json"):
            object.__setattr__(self, name, _path(getattr(self, name)))
        _check_outputs(("--json", self.json, False), ("--rrd", self.rrd, False), ("--png", self.png, True))

    @property
    def recording(self) -> bool:
        """Whether the asked condition's episodes are recorded (Rerun file, viewer or PNG)."""
        return bool(self.rrd or self.spawn or self.png)


@dataclass(frozen=True)
class Table8Request:
    """--protocol table8: the paper's Table VIII, every condition x formation size x seed on MuJoCo
    quadrotors, cached per cell in a resumable report folder; with the SITL-M row as asked."""

    formations: tuple[int, ...] = TABLE8_FORMATIONS
    """--formation: formation sizes c, each in 3..8."""
    episodes: int = TABLE8_EPISODES
    """--episodes: seeds per cell, 1..MAX_EPISODES."""
    steps: int = TABLE8_STEPS
    """--steps: decision steps per episode, 1..MAX_STEPS; F and N match the paper's only at 1000."""
    seed: int = 0
    """--seed: the first seed (>= 0); episode k flies seed + k."""
    policy: str = DEFAULT_POLICY
    """--policy: a low-level policy alias (nav, atm, safe, clm, student), a name in policies/ or a .pt path."""
    flight: Flight = field(default_factory=Flight)
    """--estimator, --guard, --airframe, --offboard, --rotor-actuation."""
    wind_direction: float | None = None
    """--wind-direction: degrees the Wind rows' wind blows towards (ENU); None draws it per episode."""
    sitl: SitlM | None = None
    """--sitl-m (--link-delay, --jitter): adds the SITL-M row; None: the 7 one-process conditions only."""
    executor: ExecutorConfig = field(default_factory=ExecutorConfig)
    """--executor, --workers (1..MAX_WORKERS), --address: where the one-process cells fly."""
    report_dir: Path | None = None
    """--report-dir: the report and cell-file folder (an interrupted run's resumes it); None: a new
    folder ./cefc-eval-reports/table8-<policy>-mujoco-<time>/."""
    fresh: bool = False
    """--fresh: fly every cell anew (an existing cell file is moved aside)."""
    json: Path | None = None
    """--json: also write the table here as JSON."""

    def __post_init__(self) -> None:
        check_policy_name(self.policy)
        object.__setattr__(self, "formations", _formations(self.formations))
        _check_count("--episodes", self.episodes, MAX_EPISODES)
        _check_count("--steps", self.steps, MAX_STEPS)
        _check_seed(self.seed)
        _check_count("--workers", self.executor.workers, MAX_WORKERS)
        _check_last_seed(self.seed, self.episodes)
        check_wind_direction(self.wind_direction)
        executor = self.executor
        if executor.address is not None and executor.kind == "ray" and executor.workers > 1:
            raise ConfigError(
                f"--workers {executor.workers}: with --address the cluster's CPUs decide how many "
                "episodes fly at once; drop --workers"
            )
        executor.validate()
        report_dir = _path(self.report_dir) or default_report_dir(self.policy, self.backend)
        object.__setattr__(self, "report_dir", report_dir)
        object.__setattr__(self, "json", _path(self.json))
        _check_outputs(("--json", self.json, False), ("--report-dir", self.report_dir, True))

    @property
    def backend(self) -> str:
        return TABLE8_BACKEND


@dataclass(frozen=True)
class Table3Request:
    """--protocol table3: the paper's Table III in the particle world (its MPE), every method or one
    policy, all episodes of a c in one batch."""

    formations: tuple[int, ...] = TABLE3_FORMATIONS
    """--formation: formation sizes c, each in 3..8."""
    episodes: int = TABLE3_EPISODES
    """--episodes: episodes per c, 1..MAX_EPISODES."""
    steps: int = TABLE3_STEPS
    """--steps: steps per episode, 1..MAX_STEPS; F and N match the paper's only at 100."""
    seed: int = 0
    """--seed: the batch's seed (>= 0)."""
    policy: str | None = None
    """--policy: one Table III row (an alias, orca included, a name in policies/ or a .pt path); None:
    every method."""
    json: Path | None = None
    """--json: also write the table here as JSON."""

    def __post_init__(self) -> None:
        if self.policy is not None:
            check_policy_name(self.policy, orca=True)
        object.__setattr__(self, "formations", _formations(self.formations))
        _check_count("--episodes", self.episodes, MAX_EPISODES)
        _check_count("--steps", self.steps, MAX_STEPS)
        _check_seed(self.seed)
        _check_last_seed(self.seed, self.episodes)
        object.__setattr__(self, "json", _path(self.json))
        _check_outputs(("--json", self.json, False))


@dataclass(frozen=True)
class GameTablesRequest:
    """--protocol table5/table6/table7: the high level's game as the paper plays it (8 UAVs, 400 steps,
    the fused estimate; Table VII with N = 8..15), on particles or quadrotors, with wind and deviation."""

    protocol: str = "table5"
    """--protocol: "table5" (CI-HRL against the baselines), "table6" (against each adversary strategy)
    or "table7" (N = 8, 9, 10, 12, 15 UAVs)."""
    conditions: Conditions = field(default_factory=Conditions)
    """--backend, --wind, --wind-direction, --deviation: where the game is played."""
    episodes: int = GAME_EPISODES
    """--episodes: episodes in the batch, 1..MAX_EPISODES."""
    seed: int = 0
    """--seed: the batch's seed (>= 0)."""
    policy: str | None = None
    """--policy: the high-level policy to play (name in policies/ or file); None: every method (table5)
    or GAME_POLICY (table6, table7)."""
    adversary: str | None = None
    """--adversary: table5 and table7's adversary, a rule or a trained adversary's name or file; None:
    GAME_ADVERSARY. Table VI plays each adversary in turn and takes none."""
    rrd: Path | None = None
    """--rrd: record one game of --policy (table5) to this Rerun file: the game of --seed (with
    --sitl-m, the SITL-M game of --seed, the first of the batch)."""
    png: Path | None = None
    """--png: draw the game's message-similarity matrices (table5 with --policy) into this folder;
    with --sitl-m the paper's Figs. 11 and 12 of the SITL-M game of --seed."""
    report_dir: Path | None = None
    """--report-dir: where table<k>.md/.json/.png go; None: no report folder."""
    json: Path | None = None
    """--json: also write the table here as JSON."""
    sitl: SitlM | None = None
    """--sitl-m (table5 with --policy): each game played with every UAV's hierarchy in its own process,
    one game per seed, beside the same seeds' lock-step games (docs/sitl_m.md, "The game over SITL-M")."""
    workers: int = 1
    """--workers (table5 over every method): processes flying the policy files' batches, 1..MAX_WORKERS."""
    policies_dir: Path | None = None
    """--policies-dir (table5 over every method): the folder of the rows' policy files (<stem>.pt and
    <stem>_seed<k>.pt); None: the shipped policies/. A trained adversary given by name is looked up
    there too (give the shipped one's file path otherwise)."""

    def __post_init__(self) -> None:
        if self.protocol not in GAME_TABLES:
            raise ConfigError(f"--protocol {self.protocol}: must be one of {', '.join(GAME_TABLES)}")
        if self.sitl is not None:
            if self.protocol != "table5" or self.policy is None:
                raise ConfigError(
                    "--sitl-m: the SITL-M game plays one policy of table5: add --protocol table5 --policy NAME"
                )
        if self.adversary is not None and self.protocol == "table6":
            raise adversary_refused(self.adversary)
        if self.policy is not None:
            check_policy_name(self.policy)
        _check_count("--episodes", self.episodes, MAX_EPISODES)
        _check_seed(self.seed)
        _check_last_seed(self.seed, self.episodes)
        _check_count("--workers", self.workers, MAX_WORKERS)
        if self.workers > 1 and (self.protocol != "table5" or self.policy is not None):
            raise ConfigError(
                f"--workers {self.workers}: only table5 over every method flies on several processes "
                f"({self.protocol}{' with --policy' if self.policy is not None else ''} flies one batch at a time)"
            )
        if self.protocol != "table5" or self.policy is None:
            for flag, path in (("--rrd", self.rrd), ("--png", self.png)):
                if path is not None:
                    raise recording_refused(flag)
        if self.policies_dir is not None:
            if self.protocol != "table5" or self.policy is not None:
                raise ConfigError(
                    "--policies-dir: only table5 over every method reads its rows from another folder "
                    "(give --policy a file path instead)"
                )
            if not Path(self.policies_dir).is_dir():
                raise ConfigError(f"--policies-dir {self.policies_dir}: no such folder")
        for name in ("rrd", "png", "report_dir", "json", "policies_dir"):
            object.__setattr__(self, name, _path(getattr(self, name)))
        _check_outputs(
            ("--json", self.json, False),
            ("--rrd", self.rrd, False),
            ("--png", self.png, True),
            ("--report-dir", self.report_dir, True),
        )

    @property
    def played_policy(self) -> str | None:
        """The high-level policy played: --policy, or GAME_POLICY in table6 and table7; None: every method."""
        return self.policy if self.policy is not None or self.protocol == "table5" else GAME_POLICY

    @property
    def played_adversary(self) -> str:
        """The adversary of table5 and table7: --adversary or GAME_ADVERSARY."""
        return self.adversary or GAME_ADVERSARY
