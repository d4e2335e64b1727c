"""Re-fly a shipped report with the command it records and compare its numbers with the file's.

    python -m cefc_mj.cli.reproduce eval/reports/table3.json
    python -m cefc_mj.cli.reproduce eval/reports/table8.json --keep /tmp/again

The report's own `cefc-eval` command runs again in a fresh process, its outputs sent to a temporary
folder (or `--keep DIR`), never over the shipped files. Every number both reports hold is compared
exactly, apart from what a run cannot repeat: provenance (commit, code digest, library versions),
wall-clock times and the SITL-M rows, whose commands take effect after their measured latency and so
depend on the operating system's scheduling. A
report whose policy files changed since it was flown (their SHA-256 in the report differ from the files
now) cannot be reproduced, and the tool says so instead of comparing. Closed-loop figures repeat bit
for bit on one machine and library build, not across CPUs: run it where the report was made.

A MuJoCo report written before `--offboard acceleration` became PX4's own interface (it records the
offboard "acceleration" and has no "accel_max" setting, which every later report writes) flew what is
now called "acceleration-assisted": it is re-flown under that name (docs/px4_interface.md). A setting
that a later version added and the re-flown report holds at None, its default, is not a difference.

Exit codes: 0 identical, 1 a number differs or the report cannot be reproduced, 2 bad input.
"""

from __future__ import annotations

import argparse
import json
import math
import shlex
import subprocess
import sys
import tempfile
from pathlib import Path

from cefc_mj.provenance import file_sha256

PROG = "python -m cefc_mj.cli.reproduce"
SKIPPED_KEYS = frozenset(
    {
        "provenance",
        "command",
        "report_dir",
        "cell_file",
        "cells_reused",
        "key",
        "key_fields",
        "sitl",
        "wall_s",
        "created_utc",
        "git_commit",
        "code_version",
        "library_versions",
    }
)
"""Keys whose values a second run cannot repeat (or that only say where and when it ran)."""
OUTPUT_FLAGS = ("--report-dir", "--json", "--rrd", "--png")
"""Flags whose value is an output path: redirected into the temporary folder."""


LEGACY_ACCELERATION = "acceleration-assisted"
"""What a report's offboard "acceleration" meant before it became PX4's own interface."""


def flew_legacy_acceleration(report: dict) -> bool:
    """Whether `report` was flown with the offboard interface now named "acceleration-assisted": it
    records "acceleration" and predates the "accel_max" setting that every later report records."""
    return report.get("offboard") == "acceleration" and "accel_max" not in report


def legacy_command(args: list[str]) -> list[str]:
    """`args` with `--offboard acceleration` renamed to the interface it meant then."""
    out = list(args)
    for i, arg in enumerate(out):
        if arg == "--offboard" and i + 1 < len(out) and out[i + 1] == "acceleration":
            out[i + 1] = LEGACY_ACCELERATION
        elif arg == "--offboard=acceleration":
            out[i] = f"--offboard={LEGACY_ACCELERATION}"
    return out


def legacy_names(node):
    """`node` (a re-flown report) with the offboard "acceleration-assisted" named "acceleration" again,
    as the report it is compared with names it."""
    if isinstance(node, dict):
        return {
            k: "acceleration" if k == "offboard" and v == LEGACY_ACCELERATION else legacy_names(v)
            for k, v in node.items()
        }
    if isinstance(node, list):
        return [legacy_names(v) for v in node]
    return node


def recorded_command(report: dict) -> list[str]:
    """The `cefc-eval` arguments the report was written by (its "command", at the top or in "protocol")."""
    protocol = report.get("protocol")
    command = report.get("command") or (protocol.get("command") if isinstance(protocol, dict) else None)
    if not isinstance(command, str) or not command.startswith("cefc-eval"):
        raise ValueError("the report records no cefc-eval command")
    return shlex.split(command)[1:]


def redirected(args: list[str], folder: Path) -> list[str]:
    """args with every output path moved into `folder` (file names kept)."""
    out, i = [], 0
    while i < len(args):
        flag = args[i]
        name, eq, value = flag.partition("=")
        if name in OUTPUT_FLAGS and (eq or i + 1 < len(args)):
            value = value if eq else args[i + 1]
            target = folder / ("reports" if name == "--report-dir" else Path(value).name)
            out += [name, str(target)]
            i += 1 if eq else 2
            continue
        out.append(flag)
        i += 1
    return out


def changed_files(report: dict, root: Path) -> list[str]:
    """Files the report names with a SHA-256 (policies, adversaries, low levels) that differ now."""
    changed = []

    def walk(node) -> None:
        if isinstance(node, dict):
            digest = node.get("sha256")
            name = node.get("path") or node.get("policy") or node.get("file")
            if isinstance(digest, str) and isinstance(name, str):
                path = Path(name) if Path(name).is_absolute() else root / name
                if not path.is_file() and not Path(name).is_absolute():
                    path = root / "policies" / name
                if not path.is_file() or file_sha256(path) != digest:
                    changed.append(name)
            for value in node.values():
                walk(value)
        elif isinstance(node, list):
            for value in node:
                walk(value)

    walk(report)
    return sorted(set(changed))


SITL_M = "SITL-M"
"""The asynchronous condition: its agents' commands take effect when their measured latency says, so
its figures depend on the operating system's scheduling and are not compared."""


def _sitl_row(node: dict) -> bool:
    return node.get("condition") == SITL_M or node.get("mode") == SITL_M


def compare(old, new, path: str = "") -> tuple[int, list[str]]:
    """(numbers compared, differences as 'path: old != new') between two reports, skipping SKIPPED_KEYS
    and SITL-M rows (a row marked with its condition, or a table8 cell keyed "SITL-M")."""
    if isinstance(old, dict) and isinstance(new, dict):
        if _sitl_row(old):
            return 0, []
        count, diffs = 0, []
        for key in sorted(set(old) | set(new)):
            if key in SKIPPED_KEYS or key == SITL_M:
                continue
            if key not in old and new[key] is None:  # a setting added later, at its default
                continue
            if key not in old or key not in new:
                diffs.append(f"{path}/{key}: only in the {'shipped' if key in old else 'new'} report")
                continue
            c, d = compare(old[key], new[key], f"{path}/{key}")
            count, diffs = count + c, diffs + d
        return count, diffs
    if isinstance(old, list) and isinstance(new, list):
        if len(old) != len(new):
            return 0, [f"{path}: {len(old)} entries != {len(new)}"]
        count, diffs = 0, []
        for i, (a, b) in enumerate(zip(old, new)):
            c, d = compare(a, b, f"{path}/{i}")
            count, diffs = count + c, diffs + d
        return count, diffs
    numeric = isinstance(old, (int, float)) and not isinstance(old, bool)
    same = old == new or (numeric and isinstance(new, float) and math.isnan(old) and math.isnan(new))
    return int(numeric), [] if same else [f"{path}: {old!r} != {new!r}"]


def _new_report(shipped: Path, folder: Path) -> Path:
    """Where the re-flown run wrote the counterpart of `shipped`."""
    for candidate in (folder / "reports" / shipped.name, folder / shipped.name):
        if candidate.is_file():
            return candidate
    raise FileNotFoundError(f"the re-flown run wrote no {shipped.name} under {folder}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog=PROG, description=__doc__.split("\n\n")[0])
    parser.add_argument("report", type=Path, help="a JSON report written by cefc-eval (e.g. eval/reports/table3.json)")
    parser.add_argument(
        "--keep", type=Path, metavar="DIR", help="write the re-flown outputs here (default: a temp folder)"
    )
    parser.add_argument("--root", type=Path, default=Path.cwd(), help="the checkout the report's paths are relative to")
    args = parser.parse_args(argv)
    try:
        report = json.loads(args.report.read_text())
        command = recorded_command(report)
    except (OSError, ValueError) as e:
        print(f"{PROG}: {args.report}: {e}", file=sys.stderr)
        return 2
    if args.keep is not None and args.keep.exists() and any(args.keep.iterdir()):
        print(f"{PROG}: --keep {args.keep}: not an empty folder", file=sys.stderr)
        return 2
    changed = changed_files(report, args.root)
    if changed:
        print(f"cannot reproduce {args.report}: changed since it was flown: {', '.join(changed)}")
        return 1
    legacy = flew_legacy_acceleration(report)
    if legacy:
        command = legacy_command(command)
        print(f"{args.report} predates PX4's acceleration interface: re-flown with --offboard {LEGACY_ACCELERATION}")
    with tempfile.TemporaryDirectory() as tmp:
        folder = args.keep or Path(tmp)
        folder.mkdir(parents=True, exist_ok=True)
        argv_new = redirected(command, folder)
        print("re-flying: cefc-eval " + shlex.join(argv_new), flush=True)
        done = subprocess.run([sys.executable, "-m", "cefc_mj.cli.eval", *argv_new], cwd=args.root)
        if done.returncode != 0:
            print(f"{PROG}: the re-flown command exited {done.returncode}", file=sys.stderr)
            return 1
        new = json.loads(_new_report(args.report, folder).read_text())
    if legacy:
        new = legacy_names(new)
    count, diffs = compare(report, new)
    if diffs:
        print(f"{len(diffs)} of the numbers differ from {args.report}:")
        print("\n".join(f"  {d}" for d in diffs[:40]))
        return 1
    print(f"{args.report}: all {count} numbers reproduced bit for bit (SITL-M rows and provenance not compared)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
