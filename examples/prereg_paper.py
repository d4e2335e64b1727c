"""Train the paper-schedule pre-registration's runs (docs/research/preregistration_paper_schedule.md), resumably.

    python examples/prereg_paper.py --list          # every planned run, its state and estimated cost
    python examples/prereg_paper.py --jobs 2        # train the runs not yet done, two at a time
    python examples/prereg_paper.py --runs 1        # train at most one run
    python examples/prereg_paper.py --keep          # copy unfinished runs' progress into the tracked copy

CI-HRL and MAPPO+AT-M at `--schedule paper`, training seeds 400, 401, ... (`--seeds N` per method,
at least 10, `cefc_mj.eval.prereg.paper_planned_runs`), the two methods interleaved by seed, each run
with the command the plan states: its state and logs in runs/prereg_paper/<stem>/, its policy file and
model card in the tracked policies/prereg_paper/. A run that spans sessions is kept there too, in
policies/prereg_paper/training/<stem>/ (`--keep`: logs and the resumable state when that state holds
no ConsMAC replay rows, `cefc_mj.train.kept_runs`), and training starts by restoring it, so a fresh
checkout continues where the copy stands. Each run is claimed by a lock file, so two drivers never
train the same run. The plan is fixed: nothing chooses, drops or stops a run by its results.
"""

from __future__ import annotations

import dataclasses
import shlex
import sys
from pathlib import Path

from cefc_mj.errors import CefcError, ConfigError, OneLineParser
from cefc_mj.eval.prereg import PAPER_MIN_SEEDS, paper_planned_runs
from cefc_mj.eval.requests import check_output
from cefc_mj.train import kept_runs

ROOT = Path(__file__).resolve().parent.parent
OUT = Path("runs/prereg_paper")
POLICIES = Path("policies/prereg_paper")
"""The runs' policy files (tracked); their kept logs and states in its training/ folder."""
ADVERSARY = "adversary_ppo_nearest_group_intercept"
"""The pre-registered adversary (the first pre-registration's)."""
CORE_HOURS = {"consmac-a": 3.26, "mappo": 0.70}
"""Measured cost of one run at the paper's schedule on one core (docs/research/highlevel_speed.md)."""


def shown(path: Path) -> str:
    """`path` relative to the repository root where it is inside it (the commands run there)."""
    return str(path.relative_to(ROOT)) if path.is_relative_to(ROOT) else str(path)


@dataclasses.dataclass(frozen=True)
class PaperRun:
    """One planned run: its policy stem, its `cefc-train` arguments from the plan and its folders."""

    stem: str
    args: tuple[str, ...]
    out: Path
    policies: Path

    label = property(lambda self: self.stem)
    run_dir = property(lambda self: self.out / self.stem)
    policy = property(lambda self: self.policies / f"{self.stem}.pt")
    log = property(lambda self: self.out / "logs" / f"{self.stem}.log")
    claim_dir = property(lambda self: self.out)

    @property
    def core_hours(self) -> float:
        return CORE_HOURS[self.args[self.args.index("--variant") + 1]]

    def done(self) -> bool:
        return self.policy.is_file()

    def policy_files(self, folder: Path) -> list[Path]:
        return kept_runs.exported_files(self.stem, folder)

    def kept_dir(self, kept: Path) -> Path:
        return kept / "training" / self.stem  # not "runs": .gitignore ignores every runs/

    def kept_policy_dir(self, kept: Path) -> Path:
        return kept

    def command(self) -> list[str]:
        """The plan's command (run from the repository root), with --resume when the run has a saved state."""
        resume = ["--resume"] if (self.run_dir / "state.pt").is_file() else []
        return [
            "cefc-train",
            *self.args,
            "--adversary",
            ADVERSARY,
            "--threads",
            "1",
            "--out",
            shown(self.out),
            "--policies-dir",
            shown(self.policies),
            *resume,
            "--no-progress",
        ]

    def state(self) -> str:
        return kept_runs.progress_state(self, 1500)


def planned_runs(seeds: int, out: Path, policies: Path) -> list[PaperRun]:
    return [PaperRun(stem, tuple(args), out, policies) for stem, args in paper_planned_runs(seeds)]


def list_runs(runs: list[PaperRun]) -> str:
    lines = [f"{run.state():<12}{run.core_hours:6.2f} h  {shlex.join(run.command())}" for run in runs]
    todo = sum(r.core_hours for r in runs if not r.done())
    lines.append(
        f"{sum(r.done() for r in runs)} of {len(runs)} runs done; estimated cost "
        f"{sum(r.core_hours for r in runs):.1f} core-hours in all, {todo:.1f} for the runs not done (one core per run)"
    )
    return "\n".join(lines)


def build_parser() -> OneLineParser:
    p = OneLineParser(prog="prereg_paper", description=__doc__.splitlines()[0])
    what = p.add_mutually_exclusive_group()
    what.add_argument("--list", action="store_true", help="print every planned run, its state and cost, then exit")
    what.add_argument("--keep", action="store_true", help="copy every run's progress into the tracked copy, then exit")
    p.add_argument(
        "--seeds",
        type=int,
        default=PAPER_MIN_SEEDS,
        help=f"training seeds per method, at least {PAPER_MIN_SEEDS} (the plan's n; default {PAPER_MIN_SEEDS})",
    )
    p.add_argument("--jobs", type=int, default=1, choices=(1, 2), help="runs trained at a time (default 1)")
    p.add_argument("--runs", type=int, default=None, metavar="K", help="train at most K runs (default every one)")
    p.add_argument("--out", type=Path, default=None, help=f"the runs' folder (default {OUT} in the repository)")
    p.add_argument(
        "--policies-dir",
        type=Path,
        default=None,
        help=f"policy files and the tracked copy (default {POLICIES} in the repository)",
    )
    return p


def main(argv: list[str] | None = None) -> int:
    p = build_parser()
    args = p.parse_args(argv)
    out = ROOT / OUT if args.out is None else args.out.absolute()
    policies = ROOT / POLICIES if args.policies_dir is None else args.policies_dir.absolute()
    try:
        if args.seeds < PAPER_MIN_SEEDS:
            raise ConfigError(f"--seeds {args.seeds}: the plan trains at least {PAPER_MIN_SEEDS} per method")
        if args.runs is not None and args.runs < 1:
            raise ConfigError(f"--runs {args.runs}: must be >= 1")
        check_output("--out", out, is_dir=True)
        check_output("--policies-dir", policies, is_dir=True)
        runs = planned_runs(args.seeds, out, policies)
        if args.list:
            print(list_runs(runs))
            return 0
        if args.keep:
            print("\n".join(kept_runs.keep(runs, policies)))
            return 0
        for line in kept_runs.restore(runs, policies):
            print(f"prereg_paper: {line}", flush=True)
    except CefcError as e:
        p.error(str(e))
    todo = [run for run in runs if not run.done()][: args.runs]
    return kept_runs.train_all(todo, len(runs), args.jobs, PaperRun.command, ROOT, "prereg_paper")


if __name__ == "__main__":
    sys.exit(main())
