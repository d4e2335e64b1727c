"""cefc-eval: fly the shipped policies and report the paper's metrics.

Examples:
  cefc-eval --wind 8 --deviation 0.5            # Table VIII episode, c = 5..8, vs calm
  cefc-eval --protocol table8 --workers 2       # the full grid, resumable; reports in ./cefc-eval-reports/
  cefc-eval --protocol table8 --executor ray --address HEAD:6379   # the grid on a Ray cluster
  cefc-eval --backend particle --protocol table3 --json t3.json
  cefc-eval --formation 6 --rrd run.rrd         # record for Rerun (`rerun run.rrd`)

Bad input ends in one line on stderr and exit code 2, before anything is flown or written.
Protocols, outputs, the table8 cell cache and the JSON schema: docs/evaluation.md.
"""

from __future__ import annotations

import argparse
import math
import os
import re
import shlex
import sys
import time
from pathlib import Path

from cefc_mj.errors import CefcError
from cefc_mj.eval import DEFAULT_POLICY
from cefc_mj.fileio import can_write_in
from cefc_mj.sim.wind import MAX_WIND_SPEED

EXIT_USAGE = 2
EXIT_OUTPUT = 1
EXIT_INTERRUPTED = 130
PROG = "cefc-eval"

MAX_EPISODES = 10_000
"""Seeds per cell at most (checked before any list of episodes is built)."""
MAX_STEPS = 100_000
"""Decision steps per episode at most (10 000 s of flight)."""
MAX_WORKERS = 64
MAX_DEVIATION = 10.0
"""Sensing deviation at most (m): beyond it every perceived position is noise (observation range is 3 m)."""
MAX_LINK_MS = 10_000.0
"""SITL-M link delay and jitter at most (ms)."""
MAX_SEED = 2**32 - 1
"""Seeds are 32-bit unsigned: --seed + --episodes - 1 must not pass it."""
PAPER_STEPS = 1000
"""Length of a Table VIII episode in the paper (decision steps)."""

SYSTEM_FOLDERS = frozenset({
    "/", "/bin", "/boot", "/dev", "/etc", "/lib", "/lib32", "/lib64", "/libx32", "/opt", "/proc", "/run", "/sbin",
    "/snap", "/srv", "/sys", "/usr", "/usr/bin", "/usr/lib", "/usr/local", "/usr/sbin", "/usr/share", "/var",
    "/var/lib",
})
"""Folders in which cefc-eval never creates a missing output folder (even when run as root)."""

class _Parser(argparse.ArgumentParser):
    """argparse with its errors on one line (no usage block), exit code 2."""

    def error(self, message: str):  # noqa: D102 (argparse API)
        usage_error(f"{message} (see {PROG} --help)")


class _VersionAction(argparse.Action):
    """--version, computed only when asked (it imports torch, numba and mujoco)."""

    def __init__(self, option_strings, dest, **kwargs):
        super().__init__(option_strings, dest, nargs=0, default=argparse.SUPPRESS, **kwargs)

    def __call__(self, parser, namespace, values, option_string=None):
        from cefc_mj.provenance import version_line

        print(version_line(PROG))
        parser.exit(0)


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog=PROG, description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--version", action=_VersionAction, help="print the version, code digest and libraries, then exit")
    p.add_argument("--backend", choices=["mujoco", "particle"], default="mujoco",
                   help="physics: MuJoCo quadrotors with the PX4-like controller (default) or the particle world")
    p.add_argument("--protocol", choices=["single", "table8", "table3", "table5", "table6", "table7"],
                   default="single",
                   help="single: one condition (from --wind/--deviation) vs calm; table8: the paper's 7 conditions "
                        "(MuJoCo); table3: the paper's MPE Table III (particle backend); table5 / table6 / table7: "
                        "the high level's game, CI-HRL against the baselines / against adversary strategies / with "
                        "N = 8, 9, 10, 12, 15 UAVs (the paper's on --backend particle; also on quadrotors, with "
                        "--wind and --deviation)")
    p.add_argument("--wind", type=float, default=None, metavar="MPS",
                   help=f"mean wind speed in m/s, 0..{MAX_WIND_SPEED:g} (single, table5-7; MuJoCo; default 0)")
    p.add_argument("--wind-direction", type=float, default=None, metavar="DEG",
                   help="the direction the wind blows towards, degrees, ENU (0 = +x, east; 90 = +y, north); default: "
                        "drawn per episode from the seed (single and table5-7 with --wind; table8's Wind rows; MuJoCo)")
    p.add_argument("--deviation", type=float, default=None, metavar="M",
                   help=f"sensing deviation in m, 0..{MAX_DEVIATION:g} (single, table5-7; default 0)")
    p.add_argument("--formation", type=int, nargs="+", metavar="C",
                   help="formation sizes c in 3..8 (default 5 6 7 8; table3: 6 7 8)")
    p.add_argument("--episodes", type=int, metavar="K",
                   help=f"seeds per cell, 1..{MAX_EPISODES} (default 1; table8 5; table3, table5-7 50)")
    p.add_argument("--steps", type=int, metavar="T",
                   help=f"decision steps per episode, 1..{MAX_STEPS} (default 1000; table3 100); F and N are "
                        "comparable to the paper only at the default")
    p.add_argument("--seed", type=int, default=0, metavar="S", help="first seed (>= 0); episode k uses S+k (default 0)")
    p.add_argument("--policy", default=None, metavar="NAME|PATH",
                   help="nav (AT-M-Nav of each c, the default), atm (AT-M Step 3 of each c, the paper's), safe, "
                        "clm (the CL-M baseline, where trained), student, orca (the ORCA-F baseline, table3 "
                        "only), a name in policies/, or a .pt path; "
                        "table3 without it evaluates every method; table5: one high-level policy (default every "
                        "method); table6, table7: the high-level policy to play (default cihrl_consmac_a)")
    p.add_argument("--adversary", default=None, metavar="RULE|NAME|PATH",
                   help="table5, table7: the game's adversary, a rule (nearest_group, r_nearest, r_largest, none) "
                        "or a trained adversary's policy name or file (default adversary_ppo, the PPO adversary); "
                        "table6 plays each adversary in turn")
    p.add_argument("--sitl-m", action="store_true",
                   help="SITL-M: every UAV's policy in its own OS process over ZeroMQ, asynchronous (single: the "
                        "asked condition flown that way, vs the one-process calm reference; table8: adds the SITL-M "
                        "row); docs/sitl_m.md")
    p.add_argument("--link-delay", type=float, default=None, metavar="MS",
                   help="SITL-M: one-way network delay in simulated ms, each way (default 0)")
    p.add_argument("--jitter", type=float, default=None, metavar="MS",
                   help="SITL-M: each direction adds a uniform draw from [0, MS] ms (default 0)")
    p.add_argument("--drop", default=None, metavar="K@STEP",
                   help="agent dropout (single): K UAVs leave the swarm before decision step STEP, the rest re-form "
                        "with c - K (fly --policy student for the paper's experiment); lock-step, or SITL-M with "
                        "--sitl-m (their processes are killed); prints F/N/C before and after")
    p.add_argument("--airframe", default=None, metavar="NAME|PATH",
                   help="MuJoCo airframe: iris (default), crazyflie (a 27 g micro quad), or your own MJCF quadrotor with "
                        "four site-mounted thrust motors and a PX4-style .params file (docs/mujoco_world.md)")
    p.add_argument("--estimator", choices=("fused", "raw"), default=None,
                   help="the agents' position estimate: fused (default; an onboard filter of the noisy fixes with the "
                        "agent's own velocity) or raw (each fix as it is, the paper's memoryless agent); "
                        "docs/design.md")
    p.add_argument("--guard", choices=("on", "off"), default=None,
                   help="the agents' separation guard: on (default; each agent limits its closing speed towards "
                        "neighbours and LiDAR hits so that a lagging quadrotor stops in time; docs/decisions.md) or "
                        "off (the policy's actions as they are, the paper's agent); single and table8")
    p.add_argument("--offboard", choices=("velocity", "acceleration"), default=None,
                   help="MuJoCo: what the PX4-like offboard interface makes of the policy's acceleration setpoint: "
                        "velocity (default; integrated into a velocity setpoint) or acceleration (sent as PX4 "
                        "acceleration setpoints, as the paper does); single and table8, not with --sitl-m or --drop")
    p.add_argument("--rotor-actuation", choices=("auto", "actuators", "external"), default=None,
                   help="MuJoCo: how the rotor thrusts reach the physics: auto (default; live actuators up to 16 "
                        "drones per env, the same forces through xfrc_applied above, where the actuators' cost grows "
                        "with the square of the swarm), actuators or external (docs/mujoco_world.md); single, "
                        "table8")
    p.add_argument("--rrd", type=Path, metavar="PATH",
                   help="record the episodes to a Rerun .rrd file (single; table5 with --policy: one game)")
    p.add_argument("--spawn", action="store_true", help="stream the episodes to a live Rerun viewer (single)")
    p.add_argument("--png", type=Path, metavar="DIR",
                   help="write a top-down PNG of each episode into DIR (single; table5 with --policy: the game's "
                        "message-similarity matrices)")
    p.add_argument("--json", type=Path, metavar="PATH", help="also write the results as JSON (docs/evaluation.md)")
    p.add_argument("--workers", type=int, default=1, metavar="W",
                   help=f"processes flying episodes, 1..{MAX_WORKERS} (single without recording, table8; default 1)")
    p.add_argument("--executor", choices=["local", "ray"], default="local",
                   help="table8 only: local flies the grid on --workers processes here (default); ray flies each "
                        "episode as a Ray task, on the cluster at --address or on a Ray instance started here with "
                        "--workers CPUs (needs the ray extra; docs/scaling.md)")
    p.add_argument("--address", default=None, metavar="HOST:PORT",
                   help="with --executor ray: the head of a running Ray cluster (`ray start --head`); its CPUs "
                        "decide how many episodes fly at once")
    p.add_argument("--report-dir", type=Path, default=None, metavar="DIR",
                   help="table8: where table8.md/.csv/.json/.png and the resumable cell file go (default a new "
                        "folder ./cefc-eval-reports/table8-<policy>-<backend>-<time>/); give the folder of an "
                        "interrupted run to resume it. table5-7: where table<k>.md/.json/.png go (none by "
                        "default)")
    p.add_argument("--fresh", action="store_true",
                   help="table8 only: fly every episode anew; an existing cell file is moved aside, not reused")
    return p


def usage_error(message: str):
    print(f"{PROG}: error: {message}", file=sys.stderr)
    raise SystemExit(EXIT_USAGE)


# ---------------------------------------------------------------------------- output paths
def check_output(flag: str, path: Path, is_dir: bool = False) -> None:
    """Refuse (one line, exit 2) an output path that cannot be written, before any work.

    Missing folders are created later, right before writing, and only below an existing folder that
    is writable and is not `/` or another system folder (SYSTEM_FOLDERS)."""
    path = Path(path)
    if not is_dir and path.is_dir():
        usage_error(f"{flag} {path}: is a folder; give a file name")
    if not is_dir and path.exists() and not os.access(path, os.W_OK):
        usage_error(f"{flag} {path}: the file exists and is not writable")
    if is_dir and path.exists() and not path.is_dir():
        usage_error(f"{flag} {path}: is a file, not a folder")
    folder = (path if is_dir else path.parent).absolute()
    ancestor, missing = folder, []
    while not ancestor.exists():
        missing.append(ancestor)
        ancestor = ancestor.parent
    if not ancestor.is_dir():
        usage_error(f"{flag} {path}: {ancestor} is a file, not a folder")
    if missing and (str(ancestor) in SYSTEM_FOLDERS or ancestor == Path(ancestor.anchor)):
        usage_error(f"{flag} {path}: will not create {missing[-1]} inside the system folder {ancestor}")
    if not can_write_in(ancestor):
        usage_error(f"{flag} {path}: {ancestor} is not writable")


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


def is_shipped_reports(path: Path) -> bool:
    """Whether `path` is the shipped eval/reports folder or inside it."""
    from cefc_mj import paths

    shipped = (paths.EVAL_DIR / "reports").resolve()
    resolved = Path(path).resolve()
    return resolved == shipped or shipped in resolved.parents


# ---------------------------------------------------------------------------- validation
def validate(args: argparse.Namespace) -> None:
    """Every flag checked before any work starts; one clear line each. Fills in the defaults."""
    proto = args.protocol
    if args.adversary is not None and proto not in ("table5", "table7"):
        usage_error(f"--adversary {args.adversary}: chooses the adversary of --protocol table5 and table7 (table6 "
                    "plays each adversary of the paper's table in turn; the other protocols have none)")
    if proto in HIGHLEVEL_PROTOCOLS:
        _validate_highlevel(args)
    for flag, value in (("--link-delay", args.link_delay), ("--jitter", args.jitter)):
        if value is not None:
            if not args.sitl_m:
                usage_error(f"{flag}: applies to SITL-M only; add --sitl-m")
            if not (math.isfinite(value) and 0 <= value <= MAX_LINK_MS):
                usage_error(f"{flag} {value:g}: must be a number in 0..{MAX_LINK_MS:g} ms")
    if args.sitl_m and proto == "table3":
        usage_error("--sitl-m: Table III is the particle world's one-process protocol; use single or table8")
    if args.sitl_m and proto == "single" and args.workers > 1:
        usage_error(f"--workers {args.workers}: SITL-M episodes fly one at a time (each runs c + 1 processes)")
    if args.airframe is not None:
        if args.backend != "mujoco":
            usage_error("--airframe: the particle backend has no airframe; use --backend mujoco")
        from cefc_mj.sim.mujoco_world import MujocoWorldConfig

        try:
            MujocoWorldConfig(airframe=args.airframe).validate()
        except CefcError as e:
            usage_error(f"--airframe {args.airframe}: {e}")
    args.airframe = args.airframe or "iris"
    if args.offboard is not None:
        if args.backend != "mujoco":
            usage_error("--offboard: the particle backend has no offboard interface; use --backend mujoco")
        for flag, given in (("--sitl-m", args.sitl_m), ("--drop", args.drop is not None), ("--protocol table3",
                                                                                           proto == "table3")):
            if given:
                usage_error(f"--offboard: not available with {flag} (single and table8 in one process only)")
    args.offboard = args.offboard or "velocity"
    if args.rotor_actuation is not None:
        if args.backend != "mujoco":
            usage_error("--rotor-actuation: the particle backend has no rotors; use --backend mujoco")
        if proto in HIGHLEVEL_PROTOCOLS:
            usage_error("--rotor-actuation: the game tables fly 9-16 drones per env, where auto is the actuators")
    args.rotor_actuation = args.rotor_actuation or "auto"
    if args.estimator is not None and proto == "table3":
        usage_error("--estimator: Table III is flown with exact sensing, where the estimate is the fix")
    args.estimator = args.estimator or "fused"
    if args.guard is not None and proto == "table3":
        usage_error("--guard: Table III compares the policies themselves, without the guard")
    args.guard = args.guard != "off"
    from cefc_mj.nn.registry import WITHDRAWN

    if args.policy in WITHDRAWN:
        usage_error(f"--policy {args.policy}: {WITHDRAWN[args.policy]}")
    if args.policy == "orca" and proto != "table3":
        usage_error("--policy orca: the ORCA-F baseline is a Table III row (--backend particle --protocol table3)")
    if args.drop is not None and proto != "single":
        usage_error(f"--drop: agent dropout is a --protocol single experiment ({proto} flies the paper's table)")
    for flag, value, top in (("--wind", args.wind, MAX_WIND_SPEED), ("--deviation", args.deviation, MAX_DEVIATION)):
        if value is not None and not (math.isfinite(value) and 0 <= value <= top):
            unit = "m/s" if flag == "--wind" else "m"
            why = " (the wind model's maximum speed)" if flag == "--wind" else ""
            usage_error(f"{flag} {value:g}: must be a number in 0..{top:g} {unit}{why}")
    if args.formation is not None:
        for c in args.formation:
            if not 3 <= c <= 8:
                usage_error(f"--formation {c}: formations exist for c = 3..8")
        if len(set(args.formation)) != len(args.formation):
            usage_error(f"--formation {' '.join(map(str, args.formation))}: a formation is listed twice")
    if args.episodes is not None and not 1 <= args.episodes <= MAX_EPISODES:
        usage_error(f"--episodes {args.episodes}: must be in 1..{MAX_EPISODES}")
    if args.steps is not None and not 1 <= args.steps <= MAX_STEPS:
        usage_error(f"--steps {args.steps}: must be in 1..{MAX_STEPS}")
    if args.seed < 0:
        usage_error(f"--seed {args.seed}: must be >= 0")
    if not 1 <= args.workers <= MAX_WORKERS:
        usage_error(f"--workers {args.workers}: must be in 1..{MAX_WORKERS}")
    episodes = args.episodes or {"single": 1, "table8": 5}.get(proto, 50)
    if args.seed + episodes - 1 > MAX_SEED:
        usage_error(f"--seed {args.seed}: seeds up to {args.seed + episodes - 1} pass the largest seed {MAX_SEED}")

    if args.backend == "particle" and args.wind:
        usage_error("--wind: the particle backend has no wind model; use --backend mujoco")
    if args.wind_direction is not None:
        from cefc_mj.sim.wind import wind_config_direction

        if args.backend != "mujoco":
            usage_error("--wind-direction: the particle backend has no wind model; use --backend mujoco")
        if proto not in ("table8", "table3") and not args.wind:
            usage_error("--wind-direction: there is no wind to point; add --wind MPS")
        if proto == "table3":
            usage_error("--wind-direction: Table III is flown in the particle world, without wind")
        try:
            wind_config_direction(args.wind_direction)
        except CefcError:
            usage_error(f"--wind-direction {args.wind_direction:g}: must be a finite angle in degrees")
    recording = [flag for flag, on in (("--rrd", args.rrd), ("--png", args.png), ("--spawn", args.spawn)) if on]
    if proto not in ("table8", *HIGHLEVEL_PROTOCOLS) and args.report_dir is not None:
        usage_error(f"--report-dir: only --protocol table8, table5, table6 and table7 write a report folder "
                    f"({proto} writes --json only)")
    if proto != "table8" and args.fresh:
        usage_error("--fresh: only --protocol table8 keeps a cell cache")
    _validate_executor(args)
    if proto == "table8":
        if args.wind is not None or args.deviation is not None:
            flag = "--wind" if args.wind is not None else "--deviation"
            usage_error(f"{flag}: --protocol table8 flies its own 7 conditions; "
                        "use --protocol single for one condition")
        if args.backend != "mujoco":
            usage_error("--protocol table8 needs --backend mujoco (its Wind conditions need the wind model)")
    if proto == "table3":
        if args.backend != "particle":
            usage_error("--protocol table3 is the paper's MPE protocol: add --backend particle")
        if args.deviation is not None:
            usage_error("--deviation: Table III is flown with exact sensing; use --protocol single --backend particle")
        if args.workers > 1:
            usage_error("--workers: table3 flies all its episodes as one batch in one process")
    records_game = proto == "table5" and args.policy is not None and not args.spawn
    if proto != "single" and recording and not records_game:
        usage_error(f"{recording[0]}: recording works with --protocol single, or table5 with --policy NAME "
                    "(--rrd, --png)")
    if proto == "single" and args.workers > 1 and recording:
        usage_error(f"--workers {args.workers}: {recording[0]} records in this process; use --workers 1")
    if args.spawn:
        from cefc_mj.viz.rerun_log import check_spawn_possible

        try:
            check_spawn_possible()
        except CefcError as e:
            usage_error(str(e))

    # defaults, now that the flags are known to be consistent
    args.episodes = episodes
    args.steps = args.steps or {"table3": 100}.get(proto, PAPER_STEPS)
    args.wind = args.wind or 0.0
    args.deviation = args.deviation or 0.0
    args.formation = args.formation or ([6, 7, 8] if proto == "table3" else [5, 6, 7, 8])
    if args.drop is not None:
        from cefc_mj.deploy.dropout import check_drop, parse_drop

        try:
            args.drop = parse_drop(args.drop)
            for c in args.formation:
                check_drop(args.drop, c, args.steps)
        except CefcError as e:
            usage_error(str(e))
    args.sitl = None
    if args.sitl_m:
        from cefc_mj.deploy.episode import SitlConfig

        args.sitl = SitlConfig(link_delay_ms=args.link_delay or 0.0, jitter_ms=args.jitter or 0.0,
                               drop=args.drop if proto == "single" else None)
        try:
            args.sitl.validate()
        except CefcError as e:
            usage_error(str(e))
    if proto == "table8" and args.report_dir is None:
        args.report_dir = default_report_dir(args.policy or DEFAULT_POLICY, args.backend)

    if args.json is not None:
        check_output("--json", args.json)
    if args.rrd is not None:
        check_output("--rrd", args.rrd)
    if args.png is not None:
        check_output("--png", args.png, is_dir=True)
    if args.report_dir is not None:
        check_output("--report-dir", args.report_dir, is_dir=True)


HIGHLEVEL_PROTOCOLS = ("table5", "table6", "table7")


def _validate_highlevel(args: argparse.Namespace) -> None:
    """Tables V and VI play the paper's game as it is (8 UAVs, 400 steps), on particles (the paper's
    MPE) or on MuJoCo quadrotors, with --wind (MuJoCo) and --deviation as perturbations."""
    proto = args.protocol
    given = [flag for flag, on in (
        ("--formation", args.formation is not None), ("--steps", args.steps is not None),
        ("--sitl-m", args.sitl_m), ("--drop", args.drop is not None), ("--airframe", args.airframe is not None),
        ("--estimator", args.estimator is not None), ("--offboard", args.offboard is not None),
        ("--guard", args.guard is not None), ("--fresh", args.fresh)) if on]
    if given:
        usage_error(f"{given[0]}: --protocol {proto} plays the paper's game as it is (8 UAVs, 400 steps, the fused "
                    "estimate); docs/high_level.md")
    if args.workers > 1:
        usage_error(f"--workers: {proto} flies all its episodes as one batch in one process")


def _validate_executor(args: argparse.Namespace) -> None:
    """--executor/--address: table8 only, a well-formed address, --workers unused with a cluster, Ray
    installed; sets args.executor to an ExecutorConfig."""
    from cefc_mj.executors import ExecutorConfig

    if args.executor != "local" and args.protocol != "table8":
        usage_error(f"--executor {args.executor}: only --protocol table8 runs on an executor "
                    f"({args.protocol} flies here; use --workers)")
    if args.address is not None and args.executor == "ray" and args.workers > 1:
        usage_error(f"--workers {args.workers}: with --address the cluster's CPUs decide how many episodes fly "
                    "at once; drop --workers")
    executor = ExecutorConfig(kind=args.executor, workers=args.workers, address=args.address)
    try:
        executor.validate()
    except CefcError as e:
        usage_error(str(e))
    args.executor = executor


def load_policies(args: argparse.Namespace) -> dict:
    """Resolve, hash and load the policy of every c (a missing or misfit checkpoint fails here, before
    anything flies); returns the provenance dict."""
    from cefc_mj.eval.runner import provenance
    from cefc_mj.eval.table8 import cached_policy

    if args.protocol in HIGHLEVEL_PROTOCOLS:
        from cefc_mj.eval.highlevel import highlevel_policy_path
        from cefc_mj.eval.runner import provenance

        if args.policy is not None or args.protocol in ("table6", "table7"):
            path = highlevel_policy_path(args.policy or "cihrl_consmac_a")  # a missing file fails before any episode
            if args.png is not None and args.protocol == "table5":
                from cefc_mj.errors import ConfigError
                from cefc_mj.nn.highlevel_policy import load_highlevel_policy

                if load_highlevel_policy(path)[0].comm is None:
                    raise ConfigError(f"--png: {args.policy} sends no messages (no communication), so there is no "
                                      "similarity to draw; drop --png")
        if args.protocol in ("table5", "table7"):  # a missing or broken adversary file fails before any episode
            from cefc_mj.eval.highlevel import GAME_ADVERSARY, resolve_adversary

            resolve_adversary(args.adversary or GAME_ADVERSARY)
        return provenance("atm", [])  # the tables record each row's file and sha256 themselves
    if args.protocol == "table3":
        from cefc_mj.baselines.orca import PYRVO_MISSING, pyrvo_available
        from cefc_mj.eval.table3 import POLICY_CHOICES, policy_file_for

        if args.policy == "orca" and not pyrvo_available():
            usage_error(f"--policy orca: {PYRVO_MISSING}")
        if args.policy is None:  # every method: missing files are listed, not fatal (run_table3)
            if not pyrvo_available():
                print(f"note: ORCA-F skipped: {PYRVO_MISSING}", file=sys.stderr)
            return provenance("atm", [])
        for c in args.formation:
            name = policy_file_for(POLICY_CHOICES[args.policy], c) if args.policy in POLICY_CHOICES else args.policy
            if name is not None:  # ORCA-F has no policy file
                cached_policy(name, c)
        return provenance("atm", [])  # table3 records each row's file and sha256 itself
    args.policy = args.policy or DEFAULT_POLICY
    prov = provenance(args.policy, args.formation)
    for c in args.formation:
        cached_policy(args.policy, c)
    return prov


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    validate(args)
    os.environ.setdefault("MUJOCO_GL", "egl")
    args.command = f"{PROG} " + " ".join(shlex.quote(a) for a in (argv if argv is not None else sys.argv[1:]))
    try:
        args.provenance = load_policies(args)
    except CefcError as e:
        usage_error(str(e))
    try:
        if args.protocol == "table3":
            return _table3(args)
        if args.protocol in HIGHLEVEL_PROTOCOLS:
            return _highlevel_table(args)
        if args.protocol == "table8":
            return _table8(args)
        return _single(args)
    except CefcError as e:
        print(f"{PROG}: error: {e}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        print(f"\n{PROG}: interrupted; finished episodes were kept", file=sys.stderr)
        return EXIT_INTERRUPTED


def _write_outputs(writes: list[tuple[Path, object]]) -> list[Path]:
    """Write (path, bytes|str|callable(path)) pairs, creating their folders now; a failure (disk
    full, a folder removed meanwhile) is one line and exit code 1, after everything else was tried."""
    from cefc_mj.fileio import write_atomic

    written, failed = [], []
    for path, data in writes:
        try:
            if callable(data):
                Path(path).parent.mkdir(parents=True, exist_ok=True)
                data(path)
            else:
                write_atomic(path, data)
            written.append(Path(path))
        except OSError as e:
            failed.append(f"{path}: {e.strerror or e}")
    for path in written:
        print(f"wrote {path}")
    if failed:
        print(f"{PROG}: error: could not write " + "; ".join(failed), file=sys.stderr)
        raise SystemExit(EXIT_OUTPUT)
    return written


# ---------------------------------------------------------------------------- single
def _deploy_runners(args: argparse.Namespace):
    """`cefc_mj.deploy`'s episode runners for the rows asked for (--sitl-m, --drop), as table8 takes them;
    deploy is imported only when one is."""
    from cefc_mj.eval.table8 import RowRunners

    sitl = dropout = None
    if args.sitl is not None:
        from cefc_mj.deploy.episode import run_sitl_episode

        sitl = run_sitl_episode
    if args.drop is not None:
        from cefc_mj.deploy.dropout import run_dropout_episode

        dropout = run_dropout_episode
    return RowRunners(sitl=sitl, dropout=dropout)


def _single(args: argparse.Namespace) -> int:
    import json

    from tqdm import tqdm

    from cefc_mj.eval.runner import EpisodeSpec, condition_name, retention, summarize
    from cefc_mj.eval.table8 import fly_episodes, paper_cell

    formations, episodes, steps = args.formation, args.episodes, args.steps
    base = condition_name(args.wind, args.deviation)
    # SITL-M flies the asked condition with one process per UAV; the calm reference stays one process.
    condition = base if args.sitl is None else ("SITL-M" if base == "SITL-S" else f"SITL-M+{base}")
    conditions = [(args.wind, args.deviation)] + ([(0.0, 0.0)] if condition != "SITL-S" else [])
    seeds = list(range(args.seed, args.seed + episodes))
    specs = [EpisodeSpec(formation=c, seed=seed, backend=args.backend, wind=wind, deviation=dev, steps=steps,
                         policy=args.policy, airframe=args.airframe, estimator=args.estimator, offboard=args.offboard,
                         guard=args.guard, wind_direction=args.wind_direction if wind else None,
                         rotor_actuation=args.rotor_actuation)
             for wind, dev in conditions for c in formations for seed in seeds]
    asked = list(range(len(formations) * len(seeds)))  # the first condition's episodes
    calm = list(range(len(asked), len(specs)))
    # (indices into specs, how they fly): the asked condition carries the deployment and the dropout
    batches = [(asked, {"sitl": args.sitl, "drop": None if args.sitl is not None else args.drop,
                        "runners": _deploy_runners(args)}), (calm, {})]
    recording = bool(args.rrd or args.spawn or args.png)
    vs = " vs calm air (SITL-S)" if condition != "SITL-S" else ""
    world = (f"mujoco ({args.airframe} airframe{wind_direction_text(vars(args))}, rotors "
             f"{rotor_text(args.rotor_actuation, formations)})" if args.backend == "mujoco" else args.backend)
    print(f"{PROG}: {condition}{vs}; policy {args.policy}; {world}; c = {', '.join(map(str, formations))}; "
          f"seeds {_seed_range(seeds)} ({episodes} per cell); {steps} steps per episode; {len(specs)} episodes"
          + (f" on {args.workers} workers" if args.workers > 1 else ""))
    finished: dict[int, dict] = {}
    recorded: list[Path] = []
    interrupted = False
    try:
        with tqdm(total=len(specs), desc="episodes", unit="ep", file=sys.stderr) as bar:
            for indices, how in batches:
                record = (lambda s: True) if recording and indices is asked else None
                for j, result in fly_episodes([specs[i] for i in indices], workers=args.workers, record=record,
                                              **how):
                    i = indices[j]
                    spec = specs[i]
                    if result.diverged:
                        tqdm.write(f"c={spec.formation} seed={spec.seed} {spec.condition}: simulation diverged at "
                                   f"step {result.steps} ({result.diverged}); episode stopped", file=sys.stderr)
                    if result.record is not None:
                        recorded += _emit_record(result.record, args, many=len(formations) * episodes > 1)
                    finished[i] = result.to_dict()
                    bar.update(1)
    except KeyboardInterrupt:
        interrupted = True
        print(f"\n{PROG}: interrupted after {len(finished)} of {len(specs)} episodes; the table below holds "
              "the finished ones", file=sys.stderr)
    rows_by_cell: dict[str, dict[str, list]] = {str(c): {} for c in formations}
    for i in sorted(finished):
        row = finished[i]
        rows_by_cell[str(row["formation"])].setdefault(row["condition"], []).append(row)
    table: dict[str, dict] = {}
    for c, conds in rows_by_cell.items():
        table[c] = {cond: {**summarize(rows), "episodes_detail": rows} for cond, rows in conds.items()}
        for cond, cell in table[c].items():
            cell["retention"], cell["retention_note"] = retention(cell, table[c].get("SITL-S"))
            cell["paper"] = paper_cell(c, cond)
    summary = {
        "schema": "cefc-eval/single", "schema_version": 2, "protocol": "single", "command": args.command,
        "complete": not interrupted, "backend": args.backend, "policy": args.policy, "estimator": args.estimator,
        "offboard": args.offboard, "guard": args.guard, "airframe": args.airframe,
        "rotor_actuation": args.rotor_actuation, "wind_direction": args.wind_direction if args.wind else None,
        "condition": condition,
        "wind": args.wind, "deviation": args.deviation, "steps": steps, "seeds": seeds,
        "comparable_to_paper": steps == PAPER_STEPS, "provenance": args.provenance, "rows": table,
    }
    print(single_table(summary))
    for line in _sitl_and_dropout_lines(table, condition):
        print(line)
    writes = [(args.json, json.dumps(summary, indent=2) + "\n")] if args.json is not None else []
    _write_outputs(writes)
    for path in recorded:
        print(f"wrote {path}" + (f"  (open with: rerun {path})" if path.suffix == ".rrd" else ""))
    return EXIT_INTERRUPTED if interrupted else 0


def _sitl_and_dropout_lines(table: dict, condition: str) -> list[str]:
    """Below the single table: SITL-M timing (p50/p99 over every agent's decisions) and, with --drop,
    F/N/C before and after the agents left (mean over seeds)."""
    import numpy as np

    lines = []
    for c, cells in table.items():
        rows = cells.get(condition, {}).get("episodes_detail", [])
        sitl = [r["sitl"] for r in rows if r.get("sitl")]
        if sitl:
            def pct(name, q):
                return max((s[name]["all"][q] or 0.0) for s in sitl)

            rtf = np.mean([s["real_time_factor"] for s in sitl])
            events = sum(len(s["events"]) for s in sitl)
            lines.append(f"  c = {c} SITL-M: decision latency p50 {pct('decision_latency_ms', 'p50'):.2f} ms, round trip "
                         f"p50 {pct('round_trip_ms', 'p50'):.2f} / p99 {pct('round_trip_ms', 'p99'):.2f} ms, command "
                         f"age p99 {pct('command_age_ms', 'p99'):.1f} ms (worst seed); {rtf:.1f}x real time; "
                         f"{events} fault event(s)")
        drops = [r["dropout"] for r in rows if r.get("dropout")]
        if drops:
            phase = {ph: {m: np.mean([d["phases"][ph][m] for d in drops]) for m in ("F", "N", "C", "steps",
                                                                                  "group_size")}
                     for ph in ("before", "after")}
            b, a = phase["before"], phase["after"]
            lines.append(f"  c = {c} dropout at step {drops[0]['step']}: before ({b['group_size']:.0f} UAVs, "
                         f"{b['steps']:.0f} steps) F {b['F']:.1f} N {b['N']:.1f} C {b['C']:.2f} %; after "
                         f"({a['group_size']:.0f} UAVs, {a['steps']:.0f} steps) F {a['F']:.1f} N {a['N']:.1f} "
                         f"C {a['C']:.2f} %")
    return lines


def _seed_range(seeds: list[int]) -> str:
    return str(seeds[0]) if len(seeds) == 1 else f"{seeds[0]}..{seeds[-1]}"


def _render(rows: list[list[str]], right: set[int]) -> list[str]:
    """Rows of cells as aligned text columns (columns in `right` right-aligned)."""
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    return ["  ".join(cell.rjust(w) if i in right else cell.ljust(w)
                      for i, (cell, w) in enumerate(zip(row, widths))).rstrip()
            for row in rows]


def rotor_text(mode: str, formations) -> str:
    """"auto: actuators" (the rotor path each size flies, as `resolve_rotor_actuation` picks it)."""
    from cefc_mj.sim.mujoco_world import resolve_rotor_actuation

    used = sorted({resolve_rotor_actuation(mode, c) for c in formations})
    return f"{mode}: {'/'.join(used)}" if mode == "auto" else mode


def wind_direction_text(summary: dict) -> str:
    """", wind towards 90°" or ", wind direction drawn per episode" where the run has wind; "" otherwise."""
    if not summary.get("wind"):
        return ""
    given = summary.get("wind_direction")
    return ", wind direction drawn per episode from the seed" if given is None else f", wind towards {given:g}° (ENU)"


def single_table(summary: dict) -> str:
    """The single protocol's table: per c, our condition and calm rows, then the paper's rows, every
    column labelled; mean ± std over seeds; '-' with its reason where a value is undefined."""
    from cefc_mj.eval.runner import format_mean_std
    from cefc_mj.eval.table8 import guard_text, paper_cell

    cond, steps = summary["condition"], summary["steps"]
    k = len(summary["seeds"])
    components = [n for n in cond.split("+") if n != "SITL-S"]
    lines = [
        "",
        f"Table VIII metrics, condition {cond}" + (" vs calm air (SITL-S)" if components else ""),
        f"  F = decision steps in formation, N = decision steps with the swarm centre within 1 m of the anchor "
        f"(each out of {steps}),",
        "  C = % of agent-steps in collision, retention = (F+N) / (F+N of the calm row above it: same c, same seeds).",
        f"  ours: {summary['backend']}"
        + (f" ({summary.get('airframe', 'iris')} airframe, rotors {summary.get('rotor_actuation', 'auto')}"
           f"{wind_direction_text(summary)})" if summary['backend'] == "mujoco" else "")
        + f", policy {summary['policy']}, "
        f"{summary.get('estimator', 'raw')} position estimate"
        + guard_text(summary)
        + (f", {summary.get('offboard', 'velocity')} offboard setpoints, " if summary['backend'] == "mujoco" else ", ")
        + (f"mean ± sample std over {k} seeds" if k > 1 else "1 seed (no spread; --episodes K gives mean ± std)")
        + "; paper: its Table VIII (Gazebo + PX4 SITL, 1000 steps).",
    ]
    if steps != PAPER_STEPS:
        lines.append(f"  NOTE: F, N over {steps} steps; the paper's are over {PAPER_STEPS}: not comparable.")
    header = ["c", "source", "condition", "F", "N", "F+N", "C (%)", "retention"]
    rows = [header]
    notes: list[str] = []

    def add(c, source, name, cell, ret, note):
        if ret is None and note:
            notes.append(f"c = {c} {source} {name}: retention - ({note})")
        rows.append([c, source, name, format_mean_std(cell.get("F"), cell.get("F_std")),
                     format_mean_std(cell.get("N"), cell.get("N_std")),
                     format_mean_std(cell.get("FN", _fn(cell)), cell.get("FN_std")),
                     format_mean_std(cell.get("C"), cell.get("C_std"), ".2f"),
                     "-" if ret is None else f"{ret:.1%}"])

    for c, cells in summary["rows"].items():
        if not cells:
            rows.append([c, "ours", cond, "-", "-", "-", "-", "-"])
            notes.append(f"c = {c}: no finished episode")
            continue
        calm = cells.get("SITL-S")
        if components and cond in cells:
            cell = cells[cond]
            diverged = f" ({cell['diverged']} diverged)" if cell["diverged"] else ""
            add(c, "ours", cond + diverged, cell, cell["retention"], cell["retention_note"])
        if calm:
            ret, note = cells["SITL-S"]["retention"], cells["SITL-S"]["retention_note"]
            add(c, "ours", "SITL-S" + (" (calm reference)" if components else ""), calm, ret, note)
        names = ["SITL-S"] + components
        found = False
        for name in names:
            p = paper_cell(c, name)
            if p is not None:
                found = True
                add(c, "paper", name, p, p["retention"], None)
        if not found:
            notes.append(f"c = {c}: the paper has no Table VIII row for this c")
    if len(components) > 1:
        notes.append(f"the paper has no combined {cond} condition: its {' and '.join(components)} rows are shown")
    lines += _render(rows, right={0, 3, 4, 5, 6, 7})
    lines += [f"  {n}" for n in dict.fromkeys(notes)]
    return "\n".join(lines)


def _fn(cell: dict) -> float | None:
    return None if cell.get("F") is None else cell["F"] + cell["N"]


# ---------------------------------------------------------------------------- table8
def _table8(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from cefc_mj.eval.table8 import (
        aggregate,
        load_cells,
        plan_cells,
        report_csv,
        report_json,
        report_markdown,
        report_plot,
        report_sitl_histograms,
        run_grid,
        table8_specs,
    )

    prov = args.provenance
    out: Path = args.report_dir
    specs = table8_specs(args.formation, args.episodes, args.seed, args.steps, args.backend, args.policy,
                         args.airframe, args.estimator, args.offboard, args.guard, args.wind_direction,
                         args.rotor_actuation)
    policy_sha256 = {c: prov["policies"][str(c)]["sha256"] for c in args.formation}
    cells = plan_cells(specs, policy_sha256, prov["code_version"])
    if args.sitl is not None:  # the SITL-M row: the calm specs again, one process per UAV
        cells += plan_cells([s for s in specs if s.condition == "SITL-S"], policy_sha256, prov["code_version"],
                            sitl=args.sitl)
    cell_file = out / f"table8_cells_{args.backend}.jsonl"
    known = {} if args.fresh else load_cells(cell_file)
    reused = sum(cell.key in known for cell in cells)
    rows_desc = "7 conditions" + (" + SITL-M" if args.sitl is not None else "")
    wind_towards = "drawn per episode" if args.wind_direction is None else f"towards {args.wind_direction:g}° (ENU)"
    print(f"{PROG} table8: {len(cells)} episodes ({len(args.formation)} c x {rows_desc} x {args.episodes} seeds, "
          f"{args.steps} steps), {args.airframe} airframe, rotors {rotor_text(args.rotor_actuation, args.formation)}, "
          f"Wind rows' direction {wind_towards}, "
          f"policy {args.policy}, {args.estimator} position estimate, "
          f"{'separation guard' if args.guard else 'no separation guard'}, {args.executor.describe()}"
          + ("; SITL-M episodes fly one at a time" if args.sitl is not None else ""))
    print(f"reports go to {out}" + ("  (the shipped reports folder, as --report-dir asks)"
                                    if is_shipped_reports(out) else ""))
    if args.fresh and cell_file.exists():
        print(f"--fresh: {cell_file} is moved aside; every episode is flown anew")
    else:
        stale = len(known) - reused
        print(f"{reused} of {len(cells)} cells reused from {cell_file}"
              + (f" ({stale} rows there are for other code, policy files or conditions and are not used)"
                 if stale > 0 else ""))
    resume = args.command if "--report-dir" in args.command else f"{args.command} --report-dir {shlex.quote(str(out))}"
    try:
        with tqdm(total=len(cells), desc="episodes", unit="ep", file=sys.stderr) as bar:
            rows = run_grid(cells, cell_file, progress=bar, fresh=args.fresh, executor=args.executor,
                            runners=_deploy_runners(args))
    except KeyboardInterrupt:
        print(f"\n{PROG}: interrupted; finished episodes are kept in {cell_file}; resume with:\n  {resume}",
              file=sys.stderr)
        return EXIT_INTERRUPTED
    table = aggregate(rows)
    meta = {"command": args.command, "backend": args.backend, "policy": args.policy, "estimator": args.estimator,
            "offboard": args.offboard, "guard": args.guard, "airframe": args.airframe,
            "wind_direction": args.wind_direction, "episodes": args.episodes,
            "seed": args.seed, "steps": args.steps, "report_dir": str(out), "cell_file": str(cell_file),
            "cells_reused": reused, "cells_total": len(cells), "provenance": prov}
    markdown = report_markdown(table, meta)
    data = report_json(table, meta)
    print(markdown)
    writes = [(out / "table8.md", markdown), (out / "table8.csv", report_csv(table)), (out / "table8.json", data),
              (out / "table8.png", lambda path: report_plot(table, path, meta))]
    if args.sitl is not None:
        writes.append((out / "table8_sitl.png", lambda path: report_sitl_histograms(table, path)))
    if args.json is not None:
        writes.append((args.json, data))
    _write_outputs(writes)
    return 0


# ---------------------------------------------------------------------------- table3
def _table3(args: argparse.Namespace) -> int:
    import json

    from cefc_mj.eval.table3 import format_table3, run_table3

    print(f"{PROG} table3: particle, c = {', '.join(map(str, args.formation))}, {args.episodes} episodes x "
          f"{args.steps} steps, seed {args.seed}, policy {args.policy or 'every Table III method'}")
    result = run_table3(formations=tuple(args.formation), episodes=args.episodes, seed=args.seed, steps=args.steps,
                        policy=args.policy, provenance={k: v for k, v in args.provenance.items() if k != "policies"})
    result["protocol"]["command"] = args.command
    print(format_table3(result))
    if args.json is not None:
        _write_outputs([(args.json, json.dumps(result, indent=2) + "\n")])
    return 0


# ---------------------------------------------------------------------------- tables V and VI
def _highlevel_table(args: argparse.Namespace) -> int:
    import json

    from cefc_mj.eval.highlevel import (
        GAME_ADVERSARY,
        TABLE7_SIZES,
        Conditions,
        format_highlevel_table,
        plot_highlevel_table,
        run_table5,
        run_table6,
        run_table7,
    )

    proto = args.protocol
    playing = f"policy {args.policy}" if args.policy else "every method" if proto == "table5" else "cihrl_consmac_a"
    uavs = "N = " + ", ".join(map(str, TABLE7_SIZES)) if proto == "table7" else "8"
    world = f"mujoco (iris airframe{wind_direction_text(vars(args))})" if args.backend == "mujoco" else args.backend
    print(f"{PROG} {proto}: {world}, wind {args.wind:g} m/s, deviation {args.deviation:g} m, {uavs} UAVs, "
          f"{args.episodes} episodes x 400 steps, seed {args.seed}, {playing}")
    prov = {k: v for k, v in args.provenance.items() if k != "policies"}
    where = Conditions(args.backend, args.wind, args.deviation, args.wind_direction)
    if proto == "table5":
        result = run_table5(episodes=args.episodes, seed=args.seed, policy=args.policy, provenance=prov, where=where,
                            adversary=args.adversary or GAME_ADVERSARY)
    elif proto == "table6":
        result = run_table6(episodes=args.episodes, seed=args.seed, policy=args.policy or "cihrl_consmac_a",
                            provenance=prov, where=where)
    else:
        result = run_table7(episodes=args.episodes, seed=args.seed, policy=args.policy or "cihrl_consmac_a",
                            provenance=prov, where=where, adversary=args.adversary or GAME_ADVERSARY)
    result["protocol"]["command"] = args.command
    text = format_highlevel_table(result)
    print(text)
    data = json.dumps(result, indent=2) + "\n"
    writes: list[tuple[Path, object]] = []
    if args.report_dir is not None:
        out = args.report_dir
        writes += [(out / f"{proto}.md", f"# {proto}\n\n```\n{text}\n```\n\nCommand: `{args.command}`\n"),
                   (out / f"{proto}.json", data),
                   (out / f"{proto}.png", lambda path: plot_highlevel_table(result, path))]
    if args.json is not None:
        writes.append((args.json, data))
    _write_outputs(writes)
    if proto == "table5" and (args.rrd is not None or args.png is not None):
        for path in _record_highlevel(args, where):
            print(f"wrote {path}")
    return 0


def _record_highlevel(args: argparse.Namespace, where) -> list[Path]:
    """--rrd / --png of table5: one game with --seed, flown by the evaluated policy, recorded (the
    same game as a one-episode evaluation with that seed)."""
    from cefc_mj.eval.highlevel import GAME_ADVERSARY, LOW_LEVEL, game_task, highlevel_policy_path, resolve_adversary
    from cefc_mj.hierarchy import DECISION_INTERVAL, load_low_level
    from cefc_mj.nn.highlevel_policy import load_highlevel_policy
    from cefc_mj.provenance import file_sha256
    from cefc_mj.viz.highlevel_log import play_highlevel_episode, plot_similarity_matrices, record_highlevel_episode

    path = highlevel_policy_path(args.policy)
    policy, meta = load_highlevel_policy(path)
    adversary = args.adversary or GAME_ADVERSARY
    kind, adversary_policy, _ = resolve_adversary(adversary)
    task = game_task(kind, deviation=where.deviation)
    episode = play_highlevel_episode(policy, task, load_low_level(LOW_LEVEL, task), seed=args.seed,
                                     world=where.world(task, 1, args.seed),
                                     decision_interval=int(meta.get("decision_interval", DECISION_INTERVAL)),
                                     adversary_policy=adversary_policy)
    episode.policy, episode.policy_sha256 = path.stem, file_sha256(path)
    episode.adversary_rule = adversary if adversary_policy is None else f"{adversary} (trained)"
    written: list[Path] = []
    if args.rrd is not None:
        args.rrd.parent.mkdir(parents=True, exist_ok=True)
        written.append(record_highlevel_episode(episode, args.rrd, recording_id=f"{path.stem}_s{args.seed}"))
    if args.png is not None:
        args.png.mkdir(parents=True, exist_ok=True)
        written.append(plot_similarity_matrices(episode, args.png / f"similarity_{path.stem}_s{args.seed}.png"))
    return written


# ---------------------------------------------------------------------------- recording
def _emit_record(record, args: argparse.Namespace, many: bool) -> list[Path]:
    """Send one episode to Rerun (a recording per episode: `--rrd run.rrd` becomes run_c5_s0.rrd etc.
    when several episodes are recorded) and/or draw its top-down PNG. Returns the files written."""
    written: list[Path] = []
    tag = f"c{record.formation}_s{record.seed}"
    if args.rrd is not None or args.spawn:
        from cefc_mj.viz.rerun_log import close_recording, log_episode, open_recording

        rrd = args.rrd
        if rrd is not None:
            if many:
                rrd = rrd.with_name(f"{rrd.stem}_{tag}{rrd.suffix or '.rrd'}")
            rrd.parent.mkdir(parents=True, exist_ok=True)  # checked before the run; created when first written
        recording = open_recording(rrd_path=rrd, spawn=args.spawn, recording_id=f"{record.condition}_{tag}")
        try:
            log_episode(record, recording)
        finally:
            close_recording(recording)
        if rrd is not None:
            written.append(rrd)
    if args.png is not None:
        from cefc_mj.viz.plots import plot_episode

        args.png.mkdir(parents=True, exist_ok=True)
        written.append(plot_episode(record, args.png / f"episode_{record.condition}_{tag}.png"))
    return written


if __name__ == "__main__":
    raise SystemExit(main())
