"""cefc-eval: fly the shipped policies and report the paper's metrics.

Examples:
  cefc-eval --wind 8 --deviation 0.5            # the main job: 8 m/s wind and 0.5 m sensing deviation at
                                                # once (a combination the paper does not fly), c = 5..8,
                                                # 5 seeds per c on 2 processes, vs calm air
  cefc-eval --protocol table8 --workers 2       # the paper's Table VIII grid, resumable, into
                                                # a new report folder under ./cefc-eval-reports/
  cefc-eval --protocol table8 --executor ray --address HEAD:6379   # the grid on a Ray cluster
  cefc-eval --backend particle --protocol table3 --json t3.json    # the paper's Table III
  cefc-eval --formation 6 --episodes 1 --rrd run.rrd   # record one episode for Rerun (`rerun run.rrd`)

--protocol single (the default) prints its table and writes no file unless asked (--json, --rrd, --png);
table8 writes a report folder (--report-dir). Bad input ends in one line on stderr and exit code 2,
before anything is flown or written.
Docs: docs/evaluate.md (the main job, Table VIII; protocols, outputs, the table8 cell cache, the JSON
schema); docs/reproduce.md (every table of the paper).
"""

from __future__ import annotations

import argparse
import os
import shlex
import sys
from pathlib import Path

from cefc_mj.cli import eval_game, eval_single, eval_table3, eval_table8
from cefc_mj.cli.eval_common import EXIT_INTERRUPTED, EXIT_NOT_A_RESULT, EXIT_USAGE, PROG
from cefc_mj.cli.eval_single import single_table
from cefc_mj.cli.eval_table8 import is_shipped_reports
from cefc_mj.errors import CefcError, ConfigError
from cefc_mj.eval.conditions import MAX_DEVIATION, Conditions
from cefc_mj.eval.requests import (
    GAME_TABLES,
    MAX_EPISODES,
    MAX_STEPS,
    MAX_WORKERS,
    SINGLE_EPISODES,
    SINGLE_WORKERS,
    TABLE8_EPISODES,
    Flight,
    GameTablesRequest,
    SingleRequest,
    SitlM,
    Table3Request,
    Table8Request,
    adversary_refused,
    default_report_dir,
    parse_drop,
    recording_refused,
)
from cefc_mj.executors import ExecutorConfig
from cefc_mj.nn.registry import GAME_ADVERSARY
from cefc_mj.seeds import GAME_FAMILY, GAME_PAPER_SCHEDULE_TEST_SEED, GAME_PREREGISTERED_TEST_SEED
from cefc_mj.sim.wind import MAX_WIND_SPEED
from cefc_mj.task.config import ADVERSARY_RULES

__all__ = ["build_parser", "default_report_dir", "is_shipped_reports", "main", "single_table", "to_request"]

RUNNERS = {
    SingleRequest: eval_single,
    Table8Request: eval_table8,
    Table3Request: eval_table3,
    GameTablesRequest: eval_game,
}
"""The module that checks and runs each request (`check(request)`, then `run(request, provenance, command)`)."""


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
    p.add_argument(
        "--backend",
        choices=["mujoco", "particle"],
        default=None,
        help="physics: MuJoCo quadrotors with the PX4-like controller (default) or the particle world",
    )
    p.add_argument(
        "--protocol",
        choices=["single", "table8", "table3", "table5", "table6", "table7"],
        default="single",
        help="single: one condition (from --wind/--deviation) vs calm; table8: the paper's 7 conditions "
        "(MuJoCo); table3: the paper's MPE Table III (particle backend); table5 / table6 / table7: "
        "the high level's game, CI-HRL against the baselines / against adversary strategies / with "
        "N = 8, 9, 10, 12, 15 UAVs (the paper's on --backend particle; also on quadrotors, with "
        "--wind and --deviation)",
    )
    p.add_argument(
        "--wind",
        type=float,
        default=None,
        metavar="MPS",
        help=f"mean wind speed in m/s, 0..{MAX_WIND_SPEED:g} (single, table5-7; MuJoCo; default 0)",
    )
    p.add_argument(
        "--wind-direction",
        type=float,
        default=None,
        metavar="DEG",
        help="the direction the wind blows towards, degrees, ENU (0 = +x, east; 90 = +y, north); default: "
        "drawn per episode from the seed (single and table5-7 with --wind; table8's Wind rows; MuJoCo)",
    )
    p.add_argument(
        "--deviation",
        type=float,
        default=None,
        metavar="M",
        help=f"sensing deviation in m, 0..{MAX_DEVIATION:g} (single, table5-7; default 0)",
    )
    p.add_argument(
        "--formation",
        type=int,
        nargs="+",
        metavar="C",
        help="formation sizes c in 3..8 (default 5 6 7 8; table3: 6 7 8)",
    )
    p.add_argument(
        "--episodes",
        type=int,
        metavar="K",
        help=f"seeds per cell, 1..{MAX_EPISODES} (default: single {SINGLE_EPISODES}, table8 {TABLE8_EPISODES}, "
        "table3 and table5-7 50); one seed is one layout, not a measurement",
    )
    p.add_argument(
        "--steps",
        type=int,
        metavar="T",
        help=f"decision steps per episode, 1..{MAX_STEPS} (default 1000; table3 100); F and N are "
        "comparable to the paper only at the default",
    )
    p.add_argument(
        "--seed", type=int, default=None, metavar="S", help="first seed (>= 0); episode k uses S+k (default 0)"
    )
    p.add_argument(
        "--policy",
        default=None,
        metavar="NAME|PATH",
        help="nav (AT-M-Nav of each c, the default), atm (AT-M Step 3 of each c, the paper's), safe, "
        "clm (the CL-M baseline, where trained), student, orca (the ORCA-F baseline, table3 "
        "only), maddpg (BenchMARL's MADDPG, table3, where trained), a name in policies/, or a .pt path; "
        "table3 without it evaluates every method; table5: one high-level policy (default every "
        "method); table6, table7: the high-level policy to play (default cihrl_consmac_a)",
    )
    p.add_argument(
        "--adversary",
        default=None,
        metavar="RULE|NAME|PATH",
        help=f"table5, table7: the game's adversary, a rule ({', '.join(ADVERSARY_RULES)}) "
        f"or a trained adversary's policy name or file (default {GAME_ADVERSARY}, the game's PPO adversary); "
        "table6 plays each adversary in turn",
    )
    p.add_argument(
        "--sitl-m",
        action="store_true",
        help="SITL-M: every UAV's policy in its own OS process over ZeroMQ, asynchronous (single: the "
        "asked condition flown that way, vs the one-process calm reference; table8: adds the SITL-M "
        "row; table5 with --policy: the game with every UAV's whole hierarchy in its own process, one "
        "game per seed beside the lock-step game); docs/sitl_m.md",
    )
    p.add_argument(
        "--link-delay",
        type=float,
        default=None,
        metavar="MS",
        help="SITL-M: one-way network delay in simulated ms, each way (default 0)",
    )
    p.add_argument(
        "--jitter",
        type=float,
        default=None,
        metavar="MS",
        help="SITL-M: each direction adds a uniform draw from [0, MS] ms (default 0)",
    )
    p.add_argument(
        "--drop",
        default=None,
        metavar="K@STEP",
        help="agent dropout (single): K UAVs leave the swarm before decision step STEP, the rest re-form "
        "with c - K (fly --policy student for the paper's experiment); lock-step, or SITL-M with "
        "--sitl-m (their processes are killed); prints F/N/C before and after",
    )
    p.add_argument(
        "--airframe",
        default=None,
        metavar="NAME|PATH",
        help="MuJoCo airframe: iris (default), crazyflie (a 27 g micro quad), or your own MJCF quadrotor "
        "with four site-mounted thrust motors and a PX4-style .params file (docs/airframes.md)",
    )
    p.add_argument(
        "--estimator",
        choices=("fused", "raw"),
        default=None,
        help="the agents' position estimate: fused (default; an onboard filter of the noisy fixes with the "
        "agent's own velocity) or raw (each fix as it is, the paper's memoryless agent); "
        "docs/design.md",
    )
    p.add_argument(
        "--guard",
        choices=("on", "off"),
        default=None,
        help="the agents' separation guard: on (default; each agent limits its closing speed towards "
        "neighbours and LiDAR hits so that a lagging quadrotor stops in time; docs/research/decisions.md) or "
        "off (the policy's actions as they are, the paper's agent); single and table8",
    )
    p.add_argument(
        "--offboard",
        choices=("velocity", "acceleration", "acceleration-assisted"),
        default=None,
        help="MuJoCo: what the PX4-like offboard interface makes of the policy's acceleration setpoint: "
        "velocity (default; integrated into a velocity setpoint), acceleration (PX4's acceleration "
        "setpoints, as the paper sends them) or acceleration-assisted (not PX4's: the interface "
        "'acceleration' named before, with a speed limiter and a drag feed-forward; docs/px4_interface.md); "
        "single and table8, not with --sitl-m or --drop",
    )
    p.add_argument(
        "--accel-max",
        type=float,
        default=None,
        metavar="MPS2",
        help="the action bound (m/s^2 per axis) the agents fly at, the env's clip and the policy's "
        "(default: the bound each policy was trained at, 2 for the shipped ones; our choice, the paper "
        "states none; docs/px4_interface.md); single and table8, not with --sitl-m or --drop",
    )
    p.add_argument(
        "--push-observer",
        type=float,
        default=None,
        metavar="S",
        help="fly the agents with a push observer of this time constant (s), which cancels the "
        "acceleration each feels beyond its own setpoint within the action bound; 0: none, the paper's "
        "memoryless agent (default: as each policy was trained, none for the shipped ones; "
        "docs/px4_interface.md); single and table8, not with --sitl-m or --drop",
    )
    p.add_argument(
        "--rotor-actuation",
        choices=("auto", "actuators", "external"),
        default=None,
        help="MuJoCo: how the rotor thrusts reach the physics: auto (default; live actuators up to 16 "
        "drones per env, the same forces through xfrc_applied above, where the actuators' cost grows "
        "with the square of the swarm), actuators or external (docs/research/mujoco_world.md); single, "
        "table8",
    )
    p.add_argument(
        "--rrd",
        type=Path,
        metavar="PATH",
        help="record the episodes to a Rerun .rrd file (single: several episodes write one file each, "
        "PATH's name with _c<C>_s<SEED>; table5 with --policy: one game)",
    )
    p.add_argument("--spawn", action="store_true", help="stream the episodes to a live Rerun viewer (single)")
    p.add_argument(
        "--png",
        type=Path,
        metavar="DIR",
        help="write a top-down PNG of each episode into DIR (single; table5 with --policy: the game's "
        "message-similarity matrices; with --sitl-m the paper's Figs. 11 and 12)",
    )
    p.add_argument("--json", type=Path, metavar="PATH", help="also write the results as JSON (docs/evaluate.md)")
    p.add_argument(
        "--workers",
        type=int,
        default=None,
        metavar="W",
        help=f"processes flying episodes, 1..{MAX_WORKERS} (single without recording or SITL-M: default "
        f"{SINGLE_WORKERS}, or the usable CPUs if fewer; table8, table5 over every method: default 1)",
    )
    p.add_argument(
        "--executor",
        choices=["local", "ray"],
        default=None,
        help="table8 only: local flies the grid on --workers processes here (default); ray flies each "
        "episode as a Ray task, on the cluster at --address or on a Ray instance started here with "
        "--workers CPUs (needs the ray extra; docs/scaling.md)",
    )
    p.add_argument(
        "--address",
        default=None,
        metavar="HOST:PORT",
        help="with --executor ray: the head of a running Ray cluster (`ray start --head`); its CPUs "
        "decide how many episodes fly at once",
    )
    p.add_argument(
        "--report-dir",
        type=Path,
        default=None,
        metavar="DIR",
        help="table8: where table8.md/.csv/.json/.png and the resumable cell file go (default a new "
        "folder ./cefc-eval-reports/table8-<policy>-<backend>-<time>/); give the folder of an "
        "interrupted run to resume it. table5-7: where table<k>.md/.json/.png go (none by "
        "default)",
    )
    p.add_argument(
        "--policies-dir",
        type=Path,
        default=None,
        metavar="DIR",
        help="table5 over every method: read the rows' policy files (<stem>.pt, <stem>_seed<k>.pt) from DIR "
        "instead of the shipped policies/ (docs/research/preregistration.md)",
    )
    p.add_argument(
        "--fresh",
        action="store_true",
        help="table8 only: fly every episode anew; an existing cell file is moved aside, not reused",
    )
    p.add_argument(
        "--preregistered-flight",
        action="store_true",
        help=f"table5: fly the pre-registered comparison's test batch (--seed {GAME_PREREGISTERED_TEST_SEED}), "
        "which is flown once, after every planned run is in (docs/research/preregistration.md); refused without it",
    )
    return p


def check_preregistered_batch(args: argparse.Namespace) -> None:
    """ConfigError unless a flight of the pre-registered test batch is the one the pre-registration
    plans: asked for by name (--preregistered-flight), table5 over every row of --policies-dir (no
    --policy), the first flight of that batch (the test ledger holds none), every planned run's file in
    the folder. All checked before anything flies."""
    proto, seed = args.protocol, args.seed
    if proto in GAME_TABLES and seed == GAME_PAPER_SCHEDULE_TEST_SEED:
        raise ConfigError(
            f"--seed {seed}: the test batch of Table V at the paper's schedule, reserved for its pre-registered "
            "flight once every planned run is in (docs/research/preregistration_paper_schedule.md)"
        )
    if proto in GAME_TABLES and seed == GAME_PREREGISTERED_TEST_SEED and not args.preregistered_flight:
        raise ConfigError(
            f"--seed {seed}: the pre-registered Table V's test batch, flown once after every planned run is in "
            "(docs/research/preregistration.md); add --preregistered-flight to fly it"
        )
    if not args.preregistered_flight:
        return
    if proto != "table5" or seed != GAME_PREREGISTERED_TEST_SEED or args.policy is not None:
        raise ConfigError(
            f"--preregistered-flight: flies --protocol table5 --seed {GAME_PREREGISTERED_TEST_SEED} over every row "
            "of --policies-dir (no --policy)"
        )
    if args.policies_dir is None:
        raise ConfigError("--preregistered-flight: give --policies-dir, the folder of the planned runs' files")
    from cefc_mj.eval import ledger
    from cefc_mj.eval.prereg import missing_runs, planned_runs

    earlier = [f for f in ledger.flights(seed=seed) if f.family == GAME_FAMILY]
    if earlier:
        raise ConfigError(
            f"--preregistered-flight: batch {seed} was already flown ({ledger.describe(earlier[0])}); "
            "a test batch is flown once"
        )
    missing = missing_runs(args.policies_dir)
    if missing:
        raise ConfigError(
            f"--preregistered-flight: {len(missing)} of {len(planned_runs())} planned runs are not in "
            f"{args.policies_dir} (first: {missing[0]}.pt); the batch is flown once, after every run is in"
        )


def usage_error(message: str):
    print(f"{PROG}: error: {message}", file=sys.stderr)
    raise SystemExit(EXIT_USAGE)


# ---------------------------------------------------------------------------- flags -> request
def _given(**values) -> dict:
    """The keyword arguments whose flag was given (not None); the request defaults the others."""
    return {name: value for name, value in values.items() if value is not None}


def refuse_flags(args: argparse.Namespace) -> None:
    """ConfigError for a flag the chosen protocol (or backend) has no use for, with the reason. The
    values of the flags a protocol takes are checked by its request."""
    proto = args.protocol
    game = proto in GAME_TABLES
    particle = args.backend == "particle"
    if args.adversary is not None and not game:
        raise adversary_refused(args.adversary)
    if game:
        given = [
            flag
            for flag, on in (
                ("--formation", args.formation is not None),
                ("--steps", args.steps is not None),
                ("--sitl-m", args.sitl_m and proto != "table5"),
                ("--drop", args.drop is not None),
                ("--airframe", args.airframe is not None),
                ("--estimator", args.estimator is not None),
                ("--offboard", args.offboard is not None),
                ("--accel-max", args.accel_max is not None),
                ("--push-observer", args.push_observer is not None),
                ("--guard", args.guard is not None),
                ("--fresh", args.fresh),
            )
            if on
        ]
        if given:
            raise ConfigError(
                f"{given[0]}: --protocol {proto} plays the paper's game as it is (8 UAVs, 400 steps, "
                "the fused estimate); docs/research/high_level.md"
            )
    for flag, value in (("--link-delay", args.link_delay), ("--jitter", args.jitter)):
        if value is not None and not args.sitl_m:
            raise ConfigError(f"{flag}: applies to SITL-M only; add --sitl-m")
    if args.sitl_m and proto == "table3":
        raise ConfigError("--sitl-m: Table III is the particle world's one-process protocol; use single or table8")
    if args.airframe is not None and particle:
        raise ConfigError("--airframe: the particle backend has no airframe; use --backend mujoco")
    if args.offboard is not None:
        if particle:
            raise ConfigError("--offboard: the particle backend has no offboard interface; use --backend mujoco")
        for flag, on in (
            ("--sitl-m", args.sitl_m),
            ("--drop", args.drop is not None),
            ("--protocol table3", proto == "table3"),
        ):
            if on:
                raise ConfigError(f"--offboard: not available with {flag} (single and table8 in one process only)")
    for name, value in (("--accel-max", args.accel_max), ("--push-observer", args.push_observer)):
        if value is None:
            continue
        for flag, on in (
            ("--sitl-m", args.sitl_m),
            ("--drop", args.drop is not None),
            ("--protocol table3", proto == "table3"),
        ):
            if on:
                raise ConfigError(f"{name}: not available with {flag} (single and table8 in one process only)")
    if args.rotor_actuation is not None:
        if particle:
            raise ConfigError("--rotor-actuation: the particle backend has no rotors; use --backend mujoco")
        if game:
            raise ConfigError("--rotor-actuation: the game tables fly 9-16 drones per env, where auto is the actuators")
    if proto == "table3" and args.estimator is not None:
        raise ConfigError("--estimator: Table III is flown with exact sensing, where the estimate is the fix")
    if proto == "table3" and args.guard is not None:
        raise ConfigError("--guard: Table III compares the policies themselves, without the guard")
    if args.drop is not None and proto != "single":
        raise ConfigError(f"--drop: agent dropout is a --protocol single experiment ({proto} flies the paper's table)")
    if proto in ("table8", "table3"):  # the protocols without Conditions: their world is their own
        if particle and args.wind:
            raise ConfigError("--wind: the particle backend has no wind model; use --backend mujoco")
        if args.wind_direction is not None and particle:
            raise ConfigError("--wind-direction: the particle backend has no wind model; use --backend mujoco")
        if args.wind_direction is not None and proto == "table3":
            raise ConfigError("--wind-direction: Table III is flown in the particle world, without wind")
    if args.report_dir is not None and proto not in ("table8", *GAME_TABLES):
        raise ConfigError(
            f"--report-dir: only --protocol table8, table5, table6 and table7 write a report folder "
            f"({proto} writes --json only)"
        )
    if args.policies_dir is not None and proto not in GAME_TABLES:
        raise ConfigError(f"--policies-dir: only --protocol table5 reads its rows from another folder ({proto})")
    if args.fresh and proto != "table8":
        raise ConfigError("--fresh: only --protocol table8 keeps a cell cache")
    check_preregistered_batch(args)
    if proto != "table8":
        if args.executor not in (None, "local"):
            raise ConfigError(
                f"--executor {args.executor}: only --protocol table8 runs on an executor "
                f"({proto} flies here; use --workers)"
            )
        if args.address is not None:
            ExecutorConfig(address=args.address).validate()  # its error: an address needs --executor ray
    if proto == "table8":
        if args.wind is not None or args.deviation is not None:
            flag = "--wind" if args.wind is not None else "--deviation"
            raise ConfigError(
                f"{flag}: --protocol table8 flies its own 7 conditions; use --protocol single for one condition"
            )
        if particle:
            raise ConfigError("--protocol table8 needs --backend mujoco (its Wind conditions need the wind model)")
    if proto == "table3":
        if not particle:
            raise ConfigError("--protocol table3 is the paper's MPE protocol: add --backend particle")
        if args.deviation is not None:
            raise ConfigError(
                "--deviation: Table III is flown with exact sensing; use --protocol single --backend particle"
            )
        if args.workers not in (None, 1):
            raise ConfigError("--workers: table3 flies all its episodes as one batch in one process")
    recording = [flag for flag, on in (("--rrd", args.rrd), ("--png", args.png), ("--spawn", args.spawn)) if on]
    if recording and (proto in ("table8", "table3") or (game and args.spawn)):
        raise recording_refused(recording[0])


def to_request(args: argparse.Namespace) -> SingleRequest | Table8Request | Table3Request | GameTablesRequest:
    """The request of the parsed flags: each given flag becomes its field, the request defaults and
    checks the rest; ConfigError (naming the flag) for anything it cannot run."""
    refuse_flags(args)
    proto = args.protocol
    sitl = SitlM(**_given(link_delay_ms=args.link_delay, jitter_ms=args.jitter)) if args.sitl_m else None
    if proto in GAME_TABLES:
        return GameTablesRequest(
            protocol=proto,
            conditions=_conditions(args),
            rrd=args.rrd,
            png=args.png,
            report_dir=args.report_dir,
            json=args.json,
            sitl=sitl,
            **_given(
                episodes=args.episodes,
                seed=args.seed,
                policy=args.policy,
                adversary=args.adversary,
                workers=args.workers,
                policies_dir=args.policies_dir,
            ),
        )
    grid = _given(
        formations=args.formation, episodes=args.episodes, steps=args.steps, seed=args.seed, policy=args.policy
    )
    if proto == "table3":
        return Table3Request(json=args.json, **grid)
    flight = Flight(
        **_given(
            estimator=args.estimator,
            guard=None if args.guard is None else args.guard == "on",
            airframe=args.airframe,
            offboard=args.offboard,
            rotor_actuation=args.rotor_actuation,
            accel_max=args.accel_max,
            push_observer=args.push_observer,
        )
    )
    if proto == "table8":
        executor = ExecutorConfig(**_given(kind=args.executor, workers=args.workers, address=args.address))
        return Table8Request(
            flight=flight,
            wind_direction=args.wind_direction,
            sitl=sitl,
            executor=executor,
            report_dir=args.report_dir,
            fresh=args.fresh,
            json=args.json,
            **grid,
        )
    conditions = _conditions(args)
    drop = parse_drop(args.drop) if args.drop is not None else None
    return SingleRequest(
        conditions=conditions,
        flight=flight,
        sitl=sitl,
        drop=drop,
        rrd=args.rrd,
        png=args.png,
        spawn=args.spawn,
        json=args.json,
        **grid,
        **_given(workers=args.workers),
    )


def _conditions(args: argparse.Namespace) -> Conditions:
    return Conditions(
        **_given(backend=args.backend, wind=args.wind, deviation=args.deviation, wind_direction=args.wind_direction)
    )


# ---------------------------------------------------------------------------- main
def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        request = to_request(args)
    except CefcError as e:
        usage_error(str(e))
    os.environ.setdefault("MUJOCO_GL", "egl")
    command = f"{PROG} " + " ".join(shlex.quote(a) for a in (argv if argv is not None else sys.argv[1:]))
    runner = RUNNERS[type(request)]
    try:
        provenance = runner.check(request)
    except CefcError as e:
        usage_error(str(e))
    try:
        return runner.run(request, provenance, command)
    except CefcError as e:
        print(f"{PROG}: error: {e}", file=sys.stderr)
        # agents that could not start, diverged physics, a stalled pool: no result; a bad value: usage
        return EXIT_NOT_A_RESULT if isinstance(e, RuntimeError) else EXIT_USAGE
    except KeyboardInterrupt:
        print(f"\n{PROG}: interrupted; finished episodes were kept", file=sys.stderr)
        return EXIT_INTERRUPTED


if __name__ == "__main__":
    raise SystemExit(main())
