"""Table VIII with the paper's agent on PX4's own acceleration interface: one table of four grids.

The paper's agent (acceleration setpoints through PX4's acceleration interface, `--offboard
acceleration`: the setpoint straight to tilt and thrust; raw position fixes; no separation guard)
flown on quadrotors for c = 5..8 in calm air, Wind-3/5/8 and Deviation-0.3/0.5/0.8, four ways:

    nav        AT-M-Nav (particle world), 2 m/s^2, the paper's memoryless agent
    mujoco     AT-M-MuJoCo (the shipped fine-tune, trained through the earlier not-PX4 interface), 2 m/s^2
    push       AT-M-Nav fine-tuned in MuJoCo through PX4's interface with the push observer (2 s), 2 m/s^2
    bound3.5   AT-M fine-tuned at 3.5 m/s^2 (particle world, then MuJoCo with the push observer)

and two candidates flown on validation seeds beside the trained ones: AT-M-Nav with the push observer
at 2 m/s^2 (nav-push) and at 3.5 m/s^2 (nav-push-3.5), neither trained with it; TEST_GRIDS names
the grids the test batch flies, chosen on the validation grids before the flight.

    python examples/px4_exact_table8.py --list           # the four cefc-eval commands, and whether each is flown
    python examples/px4_exact_table8.py --fly --validation   # the grids on validation seeds 200..204 (runs/, no ledger)
    python examples/px4_exact_table8.py --fly            # the test batch, once: 70000..70019 (eval/reports/px4_exact/)
    python examples/px4_exact_table8.py --report [--validation]   # the one table and its targets

The test batch (`cefc_mj.seeds.TABLE8_PX4_TEST_SEEDS`) is flown once, after every choice: each grid's
flight appends its line to the test ledger, and --fly refuses a grid that the ledger already holds.
The targets it is read against (written before the flight): with the push observer at 2 m/s^2,
Wind-5 keeps >= 85 % and Wind-3 >= 90 % of calm F+N, calm C 0; at 3.5 m/s^2, Wind-8 keeps >= 85 %,
calm F and N at or above the paper's SITL-S, calm C 0, Deviation-0.8 C below the paper's.
Bad input ends in one line on stderr and exit code 2, before anything is flown.
"""

from __future__ import annotations

import json
import shlex
import subprocess
import sys
from pathlib import Path

from cefc_mj.errors import OneLineParser

ROOT = Path(__file__).resolve().parent.parent
GRIDS = (
    ("nav", "AT-M-Nav", "nav", 2.0, ()),
    ("mujoco", "AT-M-MuJoCo (trained on the earlier interface)", "mujoco", 2.0, ()),
    ("push", "AT-M-MuJoCo with the push observer", "policies/push/atm_c{c}_mujoco.pt", 2.0, ()),
    ("nav-push", "AT-M-Nav with the push observer (not trained with it)", "nav", 2.0, ("--push-observer", "2")),
    ("bound3.5", "AT-M at 3.5 m/s^2 with the push observer", "policies/bound3.5/atm_c{c}_mujoco.pt", 3.5, ()),
    (
        "nav-push-3.5",
        "AT-M-Nav at 3.5 m/s^2 with the push observer (trained at neither)",
        "nav",
        3.5,
        ("--accel-max", "3.5", "--push-observer", "2"),
    ),
)
"""(slug, label, --policy, action bound, further cefc-eval flags); a policy file's bound and push observer
are its own (recorded in the file) unless the flags say otherwise."""
ROLES = {"push": ("push", "nav-push"), "bound3.5": ("bound3.5", "nav-push-3.5")}
"""The two agents the targets are read against, each with its candidates: the one trained with the push
observer and AT-M-Nav flown with one. The test batch flies the candidate chosen on validation seeds."""
TEST_GRIDS = ("nav", "mujoco", "push", "nav-push-3.5")
"""The grids the test batch flies, each role's candidate chosen on the validation grids by the rule
below (docs/research/push_observer.md) and written here before the test flight."""
CHOICE_RULE = (
    "per role, the candidate that meets more of the role's targets on the validation grids (each target "
    "counted once, read as `targets` reads it, lowest or highest over c); a tie goes to the higher mean over "
    "c of the role's wind retentions (push: Wind-3 and Wind-5; bound3.5: Wind-8)"
)
"""How a role's candidate is chosen, fixed before the validation grids were read."""
FLIGHT = ("--protocol", "table8", "--backend", "mujoco", "--offboard", "acceleration", "--estimator", "raw")
FLIGHT += ("--guard", "off", "--workers", "2")
TEST_OUT = Path("eval/reports/px4_exact")
VALIDATION_OUT = Path("runs/px4_exact_validation")
VALIDATION_SEED, VALIDATION_EPISODES = 200, 5
CONDITIONS = ("SITL-S", "Wind-3", "Wind-5", "Wind-8", "Deviation-0.3", "Deviation-0.5", "Deviation-0.8")


def test_seed() -> int:
    from cefc_mj.seeds import TABLE8_PX4_TEST_SEEDS

    return TABLE8_PX4_TEST_SEEDS[0]


def command(slug: str, validation: bool) -> list[str]:
    from cefc_mj.seeds import TABLE8_PX4_TEST_SEEDS

    policy, extra = next((p, x) for s, _, p, _, x in GRIDS if s == slug)
    out = (VALIDATION_OUT if validation else TEST_OUT) / slug
    seed, episodes = (VALIDATION_SEED, VALIDATION_EPISODES) if validation else (test_seed(), len(TABLE8_PX4_TEST_SEEDS))
    return ["cefc-eval", *FLIGHT, "--policy", policy, *extra, "--seed", str(seed), "--episodes", str(episodes)] + [
        "--report-dir",
        str(out),
    ]


def flown_in_ledger(slug: str) -> bool:
    """Whether the test ledger holds this grid's test flight (its report folder among the outputs)."""
    from cefc_mj.eval.ledger import flights

    folder = str(TEST_OUT / slug)
    return any(any(str(o).startswith(folder) for o in f.outputs) for f in flights("table8", test_seed()))


def fly(slugs: list[str], validation: bool) -> int:
    script = Path(sys.executable).with_name("cefc-eval")
    for slug in slugs:
        cmd = command(slug, validation)
        print(f"px4_exact: {shlex.join(cmd)}", flush=True)
        code = subprocess.run([str(script) if script.is_file() else cmd[0], *cmd[1:]], cwd=ROOT).returncode
        if code:
            print(f"px4_exact: {slug}: cefc-eval exited {code}", file=sys.stderr)
            return code
    return 0


def _pct(value: float | None) -> str:
    return "-" if value is None else f"{value:.1%}"


def _retention(row: dict, calm: dict) -> float | None:
    return row["FN"] / calm["FN"] if calm and calm.get("FN") else None


def report(validation: bool) -> tuple[str, dict]:
    """The one table (Markdown) and its numbers, from the four grids' table8.json."""
    from cefc_mj.eval.table8 import paper_cell

    out = VALIDATION_OUT if validation else TEST_OUT
    grids = {}
    for slug, label, _, bound, _ in GRIDS:
        path = ROOT / out / slug / "table8.json"
        if path.is_file():
            grids[slug] = (label, bound, json.loads(path.read_text()))
    if not grids:
        raise SystemExit(f"px4_exact_table8.py: error: no grid flown yet under {out}")
    lines = [
        "# Table VIII, the paper's agent on PX4's acceleration interface"
        + (" (validation seeds 200..204)" if validation else ""),
        "",
        "Each cell: F+N retention against calm air (mean F+N over the seeds of the condition / of "
        "SITL-S), then C (%); paper: its SITL-S-based retention and C.",
        "",
        "| c | condition | " + " | ".join(f"{grids[s][0]} ({grids[s][1]:g} m/s^2)" for s in grids) + " | paper |",
        "|---|---|" + "---|" * len(grids) + "---|",
    ]
    numbers: dict = {"grids": {s: {"label": g[0], "bound": g[1]} for s, g in grids.items()}, "cells": {}}
    for c in ("5", "6", "7", "8"):
        for cond in CONDITIONS:
            cells = []
            for slug, (_, _, table) in grids.items():
                rows = table["rows"].get(c, {})
                row, calm = rows.get(cond), rows.get("SITL-S")
                if row is None:
                    cells.append("-")
                    continue
                kept = _retention(row, calm)
                numbers["cells"].setdefault(c, {}).setdefault(cond, {})[slug] = {
                    "F": row["F"],
                    "N": row["N"],
                    "C": row["C"],
                    "retention": kept,
                    "episodes": row["episodes"],
                }
                cells.append(f"{_pct(kept)}, C {row['C']:.3f}")
            p = paper_cell(c, cond)
            paper = "-" if p is None else f"{_pct(p['retention'])}, C {p['C']:.2f}"
            lines.append(f"| {c} | {cond} | " + " | ".join(cells) + f" | {paper} |")
    lines += ["", "## Targets", ""]
    lines += [f"- {t}" for t in targets(numbers)]
    return "\n".join(lines) + "\n", numbers


def targets(numbers: dict) -> list[str]:
    """The issue's targets, each with what the flight measured (the smallest over c), met or missed."""
    from cefc_mj.eval.table8 import paper_cell

    cells = numbers["cells"]
    out = []

    def worst(slug: str, cond: str, key: str, fn=min):
        values = [cells[c][cond][slug][key] for c in cells if slug in cells[c].get(cond, {})]
        return fn(values) if values and None not in values else None

    for role, cond, floor in (("push", "Wind-5", 0.85), ("push", "Wind-3", 0.90), ("bound3.5", "Wind-8", 0.85)):
        for slug in ROLES[role]:
            got = worst(slug, cond, "retention")
            if got is not None:
                verdict = "met" if got >= floor else f"missed by {floor - got:.1%}"
                out.append(f"{slug} {cond} keeps >= {floor:.0%}: lowest over c {got:.1%} ({verdict})")
    for slug in (*ROLES["push"], *ROLES["bound3.5"]):
        got = worst(slug, "SITL-S", "C", max)
        if got is not None:
            out.append(f"{slug} calm C 0: highest over c {got:.3f} % ({'met' if got == 0 else 'missed'})")
    for slug in ROLES["bound3.5"]:
        if not any(slug in cells[c].get("SITL-S", {}) for c in cells):
            continue
        for key in ("F", "N"):
            short = [
                f"c = {c}: {cells[c]['SITL-S'][slug][key]:.0f} < {paper_cell(c, 'SITL-S')[key]:.0f}"
                for c in cells
                if paper_cell(c, "SITL-S") and cells[c]["SITL-S"][slug][key] < paper_cell(c, "SITL-S")[key]
            ]
            out.append(f"{slug} calm {key} at or above the paper's SITL-S: {'met' if not short else '; '.join(short)}")
        high = [
            f"c = {c}: {cells[c]['Deviation-0.8'][slug]['C']:.3f} >= {paper_cell(c, 'Deviation-0.8')['C']:.2f}"
            for c in cells
            if paper_cell(c, "Deviation-0.8")
            and cells[c]["Deviation-0.8"][slug]["C"] >= paper_cell(c, "Deviation-0.8")["C"]
        ]
        out.append(f"{slug} Deviation-0.8 C below the paper's: {'met' if not high else '; '.join(high)}")
    return out


def main(argv: list[str] | None = None) -> int:
    p = OneLineParser(prog="px4_exact_table8.py", description=__doc__.splitlines()[0])
    what = p.add_mutually_exclusive_group(required=True)
    what.add_argument("--list", action="store_true", help="print the four cefc-eval commands, then exit")
    what.add_argument("--fly", action="store_true", help="fly the test batch, once per grid (ledger lines)")
    what.add_argument("--report", action="store_true", help="write the one table from the grids flown")
    p.add_argument("--validation", action="store_true", help="validation seeds 200..204 instead of the test batch")
    p.add_argument(
        "--grid",
        choices=[s for s, *_ in GRIDS],
        action="append",
        help=f"only these grids (repeatable; default: {', '.join(TEST_GRIDS)} for the test batch, every grid for "
        "--validation)",
    )
    args = p.parse_args(argv)
    slugs = args.grid or (list(TEST_GRIDS) if not args.validation else [s for s, *_ in GRIDS])
    if args.list:
        for slug in slugs:
            state = "" if args.validation else ("flown  " if flown_in_ledger(slug) else "todo   ")
            print(f"{state}{shlex.join(command(slug, args.validation))}")
        return 0
    if args.report:
        text, numbers = report(args.validation)
        from cefc_mj.fileio import write_atomic

        out = ROOT / (VALIDATION_OUT if args.validation else TEST_OUT)
        write_atomic(out / "px4_exact.md", text)
        write_atomic(out / "px4_exact.json", json.dumps(numbers, indent=1) + "\n")
        print(text)
        return 0
    if not args.validation:
        done = [slug for slug in slugs if flown_in_ledger(slug)]
        if done:
            p.error(f"--fly: the test batch was flown for {', '.join(done)} (eval/test_ledger.jsonl); it is flown once")
    return fly(slugs, args.validation)


if __name__ == "__main__":
    sys.exit(main())
