"""cefc-eval: fly the shipped policies and report the paper's metrics.

Examples:
  cefc-eval --wind 8 --deviation 0.5            # Table VIII episode, c = 5..8, vs calm
  cefc-eval --protocol table8 --workers 2       # the full grid, resumable, eval/reports/table8.md
  cefc-eval --backend particle --protocol table3 --json t3.json
  cefc-eval --formation 6 --rrd run.rrd         # record for Rerun (`rerun run.rrd`)
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shlex
import sys
from pathlib import Path

from cefc_mj.errors import CefcError

EXIT_USAGE = 2


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="cefc-eval", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--backend", choices=["mujoco", "particle"], default="mujoco",
                   help="physics: MuJoCo quadrotors with the PX4-like controller (default) or the particle world")
    p.add_argument("--protocol", choices=["single", "table8", "table3"], default="single",
                   help="single: one condition (from --wind/--deviation) vs calm; table8: all 7 conditions; "
                        "table3: the paper's MPE Table III (particle backend)")
    p.add_argument("--wind", type=float, default=0.0, metavar="MPS", help="mean wind speed in m/s (default 0)")
    p.add_argument("--deviation", type=float, default=0.0, metavar="M", help="sensing deviation in m (default 0)")
    p.add_argument("--formation", type=int, nargs="+", metavar="C",
                   help="formation sizes c (default 5 6 7 8; table3: 6 7 8)")
    p.add_argument("--episodes", type=int, metavar="K", help="seeds per cell (default 1; table8 5; table3 50)")
    p.add_argument("--steps", type=int, metavar="T", help="decision steps per episode (default 1000; table3 100)")
    p.add_argument("--seed", type=int, default=0, metavar="S", help="first seed; episode k uses S+k (default 0)")
    p.add_argument("--policy", default="atm", metavar="NAME|PATH",
                   help="atm (AT-M Step 3 of each c, default), safe, robust (AT-M-Robust, c = 5..8), quad "
                        "(AT-M-Quad, c = 5..8), student, a name in policies/, or a .pt path")
    p.add_argument("--sitl-m", action="store_true", help="run every UAV's policy in its own process (SITL-M)")
    p.add_argument("--rrd", type=Path, metavar="PATH", help="record the episodes to a Rerun .rrd file")
    p.add_argument("--spawn", action="store_true", help="stream the episodes to a live Rerun viewer")
    p.add_argument("--png", type=Path, metavar="DIR", help="write a top-down PNG of each episode into DIR")
    p.add_argument("--json", type=Path, metavar="PATH", help="write the results as JSON (schema in README)")
    p.add_argument("--workers", type=int, default=1, metavar="W", help="processes for table8 (default 1)")
    p.add_argument("--report-dir", type=Path, default=None, metavar="DIR",
                   help="where table8 writes table8.md/.csv/.png and its resumable cell file (default eval/reports)")
    return p


def usage_error(message: str) -> None:
    print(f"cefc-eval: error: {message}", file=sys.stderr)
    raise SystemExit(EXIT_USAGE)


def _check_writable(flag: str, path: Path | None, is_dir: bool = False) -> None:
    if path is None:
        return
    target = path if is_dir else path.parent
    probe = target
    while not probe.exists():
        probe = probe.parent
    if not probe.is_dir() or not os.access(probe, os.W_OK):
        usage_error(f"{flag} {path}: {probe} is not a writable directory")
    if not is_dir and path.is_dir():
        usage_error(f"{flag} {path}: is a directory")


def validate(args: argparse.Namespace) -> None:
    """Every flag checked before any work starts; one clear line each."""
    for flag, value in (("--wind", args.wind), ("--deviation", args.deviation)):
        if not math.isfinite(value) or value < 0:
            usage_error(f"{flag} {value}: must be a finite number >= 0")
    if args.formation is not None:
        for c in args.formation:
            if not 3 <= c <= 8:
                usage_error(f"--formation {c}: formations exist for c = 3..8")
    if args.episodes is not None and args.episodes < 1:
        usage_error(f"--episodes {args.episodes}: must be >= 1")
    if args.steps is not None and args.steps < 1:
        usage_error(f"--steps {args.steps}: must be >= 1")
    if args.workers < 1:
        usage_error(f"--workers {args.workers}: must be >= 1")
    if args.sitl_m:
        usage_error("--sitl-m: SITL-M (one process per UAV) is not implemented yet in this testbed")
    if args.backend == "particle" and args.wind:
        usage_error("--wind: the particle backend has no wind model; use --backend mujoco")
    if args.protocol == "table3" and args.backend != "particle":
        usage_error("--protocol table3 is the paper's MPE protocol: add --backend particle")
    _check_writable("--json", args.json)
    _check_writable("--rrd", args.rrd)
    _check_writable("--png", args.png, is_dir=True)
    _check_writable("--report-dir", args.report_dir, is_dir=True)


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    validate(args)
    os.environ.setdefault("MUJOCO_GL", "egl")
    try:
        if args.protocol == "table3":
            return _table3(args)
        if args.protocol == "table8":
            return _table8(args, argv)
        return _single(args)
    except CefcError as e:
        usage_error(str(e))
    except KeyboardInterrupt:
        print("\ncefc-eval: interrupted; finished episodes were kept", file=sys.stderr)
        return 130
    return 0


# ---------------------------------------------------------------------------- protocols
def _single(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from cefc_mj.eval.runner import EpisodeSpec, condition_name, load_policy_for, run_episode, summarize
    from cefc_mj.eval.table8 import paper_table8
    from cefc_mj.fileio import write_atomic

    formations = args.formation or [5, 6, 7, 8]
    episodes = args.episodes or 1
    steps = args.steps or 1000
    condition = condition_name(args.wind, args.deviation)
    conditions = [(args.wind, args.deviation)] + ([(0.0, 0.0)] if condition != "SITL-S" else [])
    policies = {c: load_policy_for(args.policy, c) for c in formations}  # fail before flying
    seeds = list(range(args.seed, args.seed + episodes))
    print(f"cefc-eval: {args.backend}, condition {condition}, policy {args.policy}, c = {formations}, "
          f"seeds {seeds}, {steps} steps per episode")
    recorded: list[Path] = []
    results: dict[tuple[int, str], list] = {}
    total = len(formations) * len(conditions) * episodes
    try:
        with tqdm(total=total, desc="episodes", unit="ep", file=sys.stderr) as bar:
            for c in formations:
                for wind, dev in conditions:
                    for seed in seeds:
                        spec = EpisodeSpec(formation=c, seed=seed, backend=args.backend, wind=wind, deviation=dev,
                                           steps=steps, policy=args.policy)
                        want_record = (args.rrd or args.spawn or args.png) and (wind, dev) == conditions[0]
                        result = run_episode(spec, policies[c], record=bool(want_record))
                        if result.diverged:
                            tqdm.write(f"c={c} seed={seed} {spec.condition}: simulation diverged at step "
                                       f"{result.steps} ({result.diverged}); episode stopped", file=sys.stderr)
                        if result.record is not None:
                            recorded += _emit_record(result.record, args, many=len(formations) * episodes > 1)
                        results.setdefault((c, spec.condition), []).append(result.to_dict())
                        bar.update(1)
    finally:
        summary = {
            "protocol": "single", "backend": args.backend, "policy": args.policy, "condition": condition,
            "wind": args.wind, "deviation": args.deviation, "steps": steps, "seeds": seeds,
            "rows": {
                str(c): {
                    cond: {**summarize(rows), "episodes_detail": rows}
                    for (cc, cond), rows in results.items() if cc == c
                }
                for c in formations
            },
        }
        if args.json is not None:
            write_atomic(args.json, json.dumps(summary, indent=2))
    print(_single_table(summary, paper_table8()))
    for path in ([args.json] if args.json is not None else []) + recorded:
        print(f"wrote {path}" + (f"  (open with: rerun {path})" if path.suffix == ".rrd" else ""))
    return 0


def _single_table(summary: dict, paper: dict) -> str:
    cond = summary["condition"]
    names = ["SITL-S"] + [n for n in cond.split("+") if n != "SITL-S"]
    head = f"{'c':>2} {'F':>7} {'N':>7} {'C%':>6} {'retention':>9}  " + "  ".join(f"paper {n:<14}" for n in names)
    lines = [f"\nTable VIII metrics, condition {cond} (F, N in steps of {summary['steps']}; C in % of agent-steps)", head]
    for c, rows in summary["rows"].items():
        cell, calm = rows.get(cond), rows.get("SITL-S")
        if not cell:
            continue
        ret = (cell["F"] + cell["N"]) / (calm["F"] + calm["N"]) if calm and calm["F"] + calm["N"] > 0 else float("nan")
        ref = []
        for n in names:
            p = paper.get(c, {}).get(n)
            ref.append(f"{p['F']:>5.0f} {p['N']:>5.0f} {p['C']:>4.2f}" if p else f"{'-':>16}")
        lines.append(f"{c:>2} {cell['F']:>7.1f} {cell['N']:>7.1f} {cell['C']:>6.2f} {ret:>9.1%}  " + "  ".join(
            f"{r:<20}" for r in ref))
    return "\n".join(lines)


def _table8(args: argparse.Namespace, argv: list[str] | None) -> int:
    from tqdm import tqdm

    from cefc_mj import paths
    from cefc_mj.eval.runner import load_policy_for
    from cefc_mj.eval.table8 import aggregate, report_csv, report_markdown, report_plot, run_grid, table8_specs
    from cefc_mj.fileio import write_atomic

    formations = args.formation or [5, 6, 7, 8]
    episodes = args.episodes or 5
    steps = args.steps or 1000
    for c in formations:
        load_policy_for(args.policy, c)  # a missing or misfit checkpoint fails before the pool starts
    out = args.report_dir or (paths.EVAL_DIR / "reports")
    specs = table8_specs(formations, episodes, args.seed, steps, args.backend, args.policy)
    cell_file = out / f"table8_cells_{args.backend}.jsonl"
    print(f"cefc-eval table8: {len(specs)} episodes ({len(formations)} c x 7 conditions x {episodes} seeds), "
          f"{args.workers} worker(s); finished episodes are kept in {cell_file}")
    with tqdm(total=len(specs), desc="episodes", unit="ep", file=sys.stderr) as bar:
        rows = run_grid(specs, cell_file, workers=args.workers, progress=bar)
    table = aggregate(rows)
    command = "cefc-eval " + " ".join(shlex.quote(a) for a in (argv if argv is not None else sys.argv[1:]))
    meta = {"command": command, "backend": args.backend, "policy": args.policy, "episodes": episodes,
            "seed": args.seed, "steps": steps}
    write_atomic(out / "table8.md", report_markdown(table, meta))
    write_atomic(out / "table8.csv", report_csv(table))
    report_plot(table, out / "table8.png")
    if args.json is not None:
        write_atomic(args.json, json.dumps({"protocol": "table8", **meta, "rows": table}, indent=2))
    print(report_markdown(table, meta))
    print(f"wrote {out / 'table8.md'}, {out / 'table8.csv'}, {out / 'table8.png'}")
    return 0


def _table3(args: argparse.Namespace) -> int:
    from cefc_mj.eval.table3 import format_table3, run_table3

    result = run_table3(
        formations=tuple(args.formation or (6, 7, 8)), episodes=args.episodes or 50, seed=args.seed,
        json_path=args.json,
    )
    print(format_table3(result))
    return 0


# ---------------------------------------------------------------------------- recording
def _emit_record(record, args: argparse.Namespace, many: bool) -> list[Path]:
    """Send one episode to Rerun (a recording per episode: `--rrd run.rrd` becomes run_c5_s0.rrd etc.
    when several episodes are recorded) and/or draw its top-down PNG. Returns the files written."""
    written: list[Path] = []
    tag = f"c{record.formation}_s{record.seed}"
    if args.rrd is not None or args.spawn:
        from cefc_mj.viz.rerun_log import close_recording, log_episode, open_recording

        rrd = args.rrd
        if rrd is not None and many:
            rrd = rrd.with_name(f"{rrd.stem}_{tag}{rrd.suffix or '.rrd'}")
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
