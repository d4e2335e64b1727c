"""Train the runs of the pre-registered Table V (docs/research/preregistration.md), resumably, one after another.

    python examples/prereg_table5.py --list              # every planned run and whether it is done
    python examples/prereg_table5.py --max-runs 4        # the next 4 runs not yet done (primary pair first)
    python examples/prereg_table5.py --max-runs 40 --start-before 17:30   # start no run after 17:30

Two drivers can run side by side (one per core): each claims a run with a lock file in runs/prereg/
and skips runs the other one holds.

A run is done when its policy file is in policies/prereg/; a run whose folder is in runs/prereg/ but
has no policy yet (an interrupted session) is continued with --resume. A finished run's config.json
and progress.csv are kept in eval/training_logs/prereg/<run>/ (runs/ is not part of the repository).
The plan below is the pre-registration's table of rows and seeds; nothing here chooses or drops a run
by its results.
"""

from __future__ import annotations

import argparse
import csv
import fcntl
import shlex
import shutil
import subprocess
import sys
import time
from datetime import datetime
from pathlib import Path

from cefc_mj.eval.prereg import planned_runs

ROOT = Path(__file__).resolve().parent.parent
OUT = "runs/prereg"
POLICIES = "policies/prereg"
LOGS = "eval/training_logs/prereg"
COMMON = ["--adversary", "adversary_ppo_nearest_group_intercept", "--threads", "1", "--out", OUT]


def command(stem: str, args: list[str]) -> list[str]:
    """The cefc-train command of a run, with --resume when an interrupted run of it is under runs/prereg."""
    budget = [] if "--budget" in args else ["--budget", "75it"]
    resume = ["--resume"] if (ROOT / OUT / stem).is_dir() else []
    return ["cefc-train", *args, *COMMON, *budget, "--policies-dir", POLICIES, *resume]


def done(stem: str) -> bool:
    return (ROOT / POLICIES / f"{stem}.pt").is_file()


def keep_log(stem: str) -> None:
    """Copy a finished run's config.json and progress.csv into LOGS/<stem>/."""
    for name in ("config.json", "progress.csv"):
        source = ROOT / OUT / stem / name
        if source.is_file():
            (ROOT / LOGS / stem).mkdir(parents=True, exist_ok=True)
            shutil.copy2(source, ROOT / LOGS / stem / name)


def train_seconds(stem: str) -> float | None:
    """A finished run's training wall-clock (the last wall_s of its kept progress.csv), None when not kept."""
    progress = ROOT / LOGS / stem / "progress.csv"
    if not progress.is_file():
        return None
    with progress.open() as handle:
        rows = list(csv.DictReader(handle))
    return float(rows[-1]["wall_s"]) if rows else None


def claim_run(stem: str):
    """An open, exclusively locked claim file for the run, or None when another driver holds it."""
    (ROOT / OUT).mkdir(parents=True, exist_ok=True)
    handle = open(ROOT / OUT / f"{stem}.lock", "w")  # noqa: SIM115 - held for the run's duration
    try:
        fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        handle.close()
        return None
    if done(stem):  # finished by the other driver between our check and the lock
        handle.close()
        return None
    return handle


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--list", action="store_true", help="print every planned run and its state, then exit")
    p.add_argument("--max-runs", type=int, default=1, metavar="K", help="train at most K runs (default 1)")
    p.add_argument(
        "--start-before",
        metavar="HH:MM",
        help="start no new run after this local time today (a run already started finishes); "
        "useful when the machine will be taken away and an unfinished run would be wasted",
    )
    args = p.parse_args(argv)
    start_before = None
    if args.start_before is not None:
        try:
            clock = datetime.strptime(args.start_before, "%H:%M")
        except ValueError:
            p.error(f"--start-before {args.start_before!r}: expected HH:MM")
        start_before = datetime.now().replace(hour=clock.hour, minute=clock.minute, second=0, microsecond=0)
    runs = planned_runs()
    if args.list:
        seconds = []
        for stem, run_args in runs:
            cost = train_seconds(stem) if done(stem) else None
            if cost is not None:
                seconds.append(cost)
            state = f"done {cost / 60:5.1f} min" if cost is not None else ("done" if done(stem) else "todo")
            print(f"{state:<16}{shlex.join(command(stem, run_args))}")
        print(
            f"{sum(done(stem) for stem, _ in runs)} of {len(runs)} runs done; training time of the done runs: "
            f"{sum(seconds) / 3600:.1f} core-hours (one core per run)"
        )
        return 0
    if args.max_runs < 1:
        p.error(f"--max-runs {args.max_runs}: must be >= 1")
    trained = 0
    for stem, run_args in runs:
        if trained == args.max_runs:
            break
        if done(stem):
            continue
        if start_before is not None and datetime.now() >= start_before:
            print(f"prereg: it is past {args.start_before}; no new run started", flush=True)
            break
        claim = claim_run(stem)
        if claim is None:  # another driver is training it
            continue
        trained += 1
        cmd = command(stem, run_args)
        print(f"prereg: {shlex.join(cmd)}", flush=True)
        start = time.monotonic()
        code = subprocess.run([*cmd, "--no-progress"], cwd=ROOT).returncode
        print(f"prereg: {stem} exited {code} after {time.monotonic() - start:.0f} s", flush=True)
        if code != 0:
            return code
        keep_log(stem)
        claim.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
