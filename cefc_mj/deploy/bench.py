"""SITL-M against SITL-S on the same seeds: F, N, C, timing, real-time factor.

    python -m cefc_mj.deploy.bench --formation 5 6 7 8 --seeds 0 1 2 --steps 1000

For every (c, seed) it flies the lock-step episode (SITL-S, `run_episode`) and the SITL-M episode
(`run_sitl_episode`, one process per UAV) and prints one row each, then per c the SITL-M share of
SITL-S's F + N (the paper: 97.1 % for AT-M). `--json PATH` writes every row with the SITL-M
timing summaries (p50/p99 of decision latency, round trip and command age per agent).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from cefc_mj.eval import DEFAULT_POLICY


def _fmt(values) -> str:
    return "/".join(f"{v:.2f}" for v in values)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m cefc_mj.deploy.bench", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--formation", type=int, nargs="+", default=[5, 6, 7, 8], metavar="C")
    p.add_argument("--seeds", type=int, nargs="+", default=[0], metavar="S")
    p.add_argument("--steps", type=int, default=1000, metavar="T")
    p.add_argument("--policy", default=DEFAULT_POLICY)
    p.add_argument("--backend", default="mujoco", choices=["mujoco", "particle"])
    p.add_argument("--link-delay", type=float, default=0.0, metavar="MS")
    p.add_argument("--jitter", type=float, default=0.0, metavar="MS")
    p.add_argument("--no-lockstep", action="store_true", help="fly only the SITL-M episodes")
    p.add_argument(
        "--latency-model",
        action="store_true",
        help="also fly the one-process latency model (run_latency_model_episode, one tick)",
    )
    p.add_argument("--json", type=Path, metavar="PATH")
    args = p.parse_args(argv)

    from cefc_mj.deploy.episode import SitlConfig, run_latency_model_episode, run_sitl_episode
    from cefc_mj.eval.runner import EpisodeSpec, run_episode

    sitl = SitlConfig(link_delay_ms=args.link_delay, jitter_ms=args.jitter)
    rows = []
    print(
        f"{'c':>2} {'seed':>4} | {'SITL-S F/N/C':>18} | {'SITL-M F/N/C':>18} | {'RTT p50/p99 ms':>14} | "
        f"{'latency p50/p99':>15} | {'age p50':>7} | {'late':>4} | {'RTF':>5} | {'startup s':>9}"
    )
    for c in args.formation:
        for seed in args.seeds:
            spec = EpisodeSpec(formation=c, seed=seed, steps=args.steps, backend=args.backend, policy=args.policy)
            ref = None if args.no_lockstep else run_episode(spec)
            res = run_sitl_episode(spec, sitl)
            model = run_latency_model_episode(spec) if args.latency_model else None
            s = res.sitl.summary()
            rtt, lat, age = (s[k]["all"] for k in ("round_trip_ms", "decision_latency_ms", "command_age_ms"))
            row = {
                "formation": c,
                "seed": seed,
                "steps": args.steps,
                "SITL-S": None if ref is None else {"F": ref.F, "N": ref.N, "C": ref.C, "wall_s": ref.wall_s},
                "SITL-M": {"F": res.F, "N": res.N, "C": res.C, "wall_s": res.wall_s, "faults": res.faults()},
                "sitl": s,
                "latency_model": None if model is None else {"F": model.F, "N": model.N, "C": model.C},
            }
            rows.append(row)
            ref_txt = "-" if ref is None else f"{ref.F:.0f}/{ref.N:.0f}/{ref.C:.2f}"
            print(
                f"{c:>2} {seed:>4} | {ref_txt:>18} | {f'{res.F:.0f}/{res.N:.0f}/{res.C:.2f}':>18} | "
                f"{_fmt([rtt['p50'], rtt['p99']]):>14} | {_fmt([lat['p50'], lat['p99']]):>15} | {age['p50']:>7.1f} | "
                f"{sum(s['late_commands']):>4} | {s['real_time_factor']:>5.1f} | {s['startup_s']:>9.1f}"
                + ("" if model is None else f" | model {model.F:.0f}/{model.N:.0f}/{model.C:.2f}"),
                flush=True,
            )
    if not args.no_lockstep:
        print("\nSITL-M share of SITL-S F + N:")
        total_m = total_s = 0.0
        for c in args.formation:
            mine = [r for r in rows if r["formation"] == c]
            fn_s = sum(r["SITL-S"]["F"] + r["SITL-S"]["N"] for r in mine)
            fn_m = sum(r["SITL-M"]["F"] + r["SITL-M"]["N"] for r in mine)
            total_s, total_m = total_s + fn_s, total_m + fn_m
            print(f"  c = {c}: {100 * fn_m / fn_s:.1f} %" if fn_s else f"  c = {c}: SITL-S F + N is 0")
        if total_s:
            print(f"  all: {100 * total_m / total_s:.1f} %")
    rtt_all = np.concatenate([np.asarray([u["p50"] for u in r["sitl"]["round_trip_ms"]["per_uav"]]) for r in rows])
    print(f"per-agent RTT p50: median {np.median(rtt_all):.2f} ms, worst {rtt_all.max():.2f} ms")
    if args.json:
        args.json.write_text(json.dumps({"command": " ".join(sys.argv), "rows": rows}, indent=1))
    faults = [f"c = {r['formation']} seed {r['seed']}: {line}" for r in rows for line in r["SITL-M"]["faults"]]
    for line in faults:  # a SITL-M episode that lost agents is not a measurement (docs/evaluate.md)
        print(f"python -m cefc_mj.deploy.bench: fault: {line}", file=sys.stderr)
    return 3 if faults else 0


if __name__ == "__main__":
    try:
        raise SystemExit(main())
    except KeyboardInterrupt:
        print("\npython -m cefc_mj.deploy.bench: interrupted", file=sys.stderr)
        raise SystemExit(130) from None
