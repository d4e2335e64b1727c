"""Train the budget ladder (docs/research/budget_ladder.md), resumably, and draw its learning curves.

    python examples/budget_ladder.py --list              # every planned run, its state and estimated cost
    python examples/budget_ladder.py                     # train the runs not yet done, one after another
    python examples/budget_ladder.py --jobs 2            # two at a time (one core each)
    python examples/budget_ladder.py --report            # E and R_H against updates -> runs/ladder/ladder.png
    python examples/budget_ladder.py --keep              # copy every run's progress into policies/ladder/ (tracked)

CI-HRL (`--variant consmac-a`) and MAPPO+AT-M (`--variant mappo`) at 75, 300 and 1,500 updates of 20
envs, training seeds 300, 301 and 302, against the pre-registered Table V's adversary over the default
(student) low level. The 1,500 rung is the paper's schedule (`--schedule paper`); the shorter ones
are the paper's schedule shrunk in its proportions (`--schedule paper-scaled --budget Nit`: the
first 2N/3 updates pre-training, ConsMAC 5,000 steps of 2,048 after every 20).

Rung N's runs live in <out>/u<N>/ (their policies in <out>/u<N>/policies/, each run's output in
<out>/logs/). A run is done when its policy file is there; a run with a saved state but no policy
(an interrupted session) is continued with --resume. Each run is claimed by a lock file, so two
drivers never train the same run. The plan is fixed here; nothing chooses or drops a run by its results.

The ladder outlives a session through a tracked copy, `policies/ladder/` (`--kept`; a ladder in
another --out has none unless --kept names one): `--keep` copies each finished run's policy files and
logs there, and each unfinished run's logs with its resumable state when that state leaves out the
ConsMAC replay's rows (`cefc_mj.train.kept_runs`). Training and --report start by copying back into
<out> whatever the kept copy holds beyond it, so a fresh checkout continues where the kept copy stands.
"""

from __future__ import annotations

import argparse
import dataclasses
import shlex
import sys
from pathlib import Path

from cefc_mj.errors import CefcError, ConfigError, OneLineParser
from cefc_mj.eval.learning_curves import group_curves, read_run, write_csv
from cefc_mj.eval.requests import check_output
from cefc_mj.train import kept_runs
from cefc_mj.train.kept_runs import keep, restore, saved_iteration  # noqa: F401 - the script's API

ROOT = Path(__file__).resolve().parent.parent
OUT = Path("runs/ladder")
KEPT = Path("policies/ladder")
"""The tracked copy of the ladder's progress (--keep): u<N>/<policy files>, u<N>/training/<stem>/ (logs, state)."""
RUNGS = (75, 300, 1500)
"""Updates (iterations of 20 envs) of each rung; 1,500 is the paper's schedule."""
SEEDS = (300, 301, 302)
"""Training seeds: apart from the shipped runs' (0..4) and the pre-registered Table V's (100..119)."""
METHODS = (("CI-HRL", "consmac-a", "cihrl_consmac_a"), ("MAPPO+AT-M", "mappo", "cihrl_mappo"))
"""(label, --variant, run folder stem before _seed<k>)."""
ADVERSARY = "adversary_ppo_nearest_group_intercept"
"""The pre-registered Table V's adversary (docs/research/preregistration.md)."""
CORE_HOURS_AT_PAPER = {"CI-HRL": 3.26, "MAPPO+AT-M": 0.70}
"""Measured cost of one run at the paper's 1,500 updates on one core (docs/research/highlevel_speed.md);
a rung of N updates is estimated at N / 1500 of it (paper-scaled keeps ConsMAC's 250 steps per update)."""
SMOKE_RUNGS = (3, 6)
SMOKE_SEEDS = (300,)
SMOOTH = 10
"""Iterations of the trailing moving average of each seed's curve before the mean over seeds."""
PANELS = (("metric/E", "E (steps within 2 m of the adversary)"), ("episode_return", "R_H per episode"))


def shown(path: Path) -> str:
    """`path` relative to the repository root where it is inside it (the commands run there)."""
    return str(path.relative_to(ROOT)) if path.is_relative_to(ROOT) else str(path)


@dataclasses.dataclass(frozen=True)
class LadderRun:
    """One training run of the ladder."""

    method: str
    variant: str
    rung: int
    seed: int
    stem: str
    out: Path

    @property
    def rung_dir(self) -> Path:
        return self.out / f"u{self.rung}"

    @property
    def run_dir(self) -> Path:
        return self.rung_dir / self.stem

    @property
    def policy(self) -> Path:
        return self.rung_dir / "policies" / f"{self.stem}.pt"

    @property
    def log(self) -> Path:
        return self.out / "logs" / f"u{self.rung}_{self.stem}.log"

    @property
    def label(self) -> str:
        return f"{self.stem} (u{self.rung})"

    @property
    def claim_dir(self) -> Path:
        return self.rung_dir

    @property
    def core_hours(self) -> float:
        return CORE_HOURS_AT_PAPER[self.method] * self.rung / RUNGS[-1]

    def done(self) -> bool:
        return self.policy.is_file()

    def policy_files(self, folder: Path) -> list[Path]:
        return kept_runs.exported_files(self.stem, folder)

    def kept_dir(self, kept: Path) -> Path:
        return kept / f"u{self.rung}" / "training" / self.stem  # not "runs": .gitignore ignores every runs/

    def kept_policy_dir(self, kept: Path) -> Path:
        return kept / f"u{self.rung}"

    def command(self, smoke: bool = False) -> list[str]:
        """The cefc-train command (run from the repository root), with --resume when the run has a saved state."""
        schedule = ["--schedule", "paper"] if self.rung == RUNGS[-1] else ["--schedule", "paper-scaled"]
        schedule += ["--budget", f"{self.rung}it"]
        resume = ["--resume"] if (self.run_dir / "state.pt").is_file() else []
        extra = ["--eval-episodes", "0"] if smoke else []
        return [
            "cefc-train",
            "highlevel",
            "--variant",
            self.variant,
            "--seed",
            str(self.seed),
            *schedule,
            "--adversary",
            ADVERSARY,
            "--threads",
            "1",
            "--out",
            shown(self.rung_dir),
            "--policies-dir",
            shown(self.rung_dir / "policies"),
            *extra,
            *resume,
            "--no-progress",
        ]

    def state(self) -> str:
        return kept_runs.progress_state(self, self.rung)


def planned_runs(out: Path, smoke: bool = False) -> list[LadderRun]:
    """Every run of the ladder: the shortest rung first, then by seed, the two methods interleaved."""
    rungs, seeds = (SMOKE_RUNGS, SMOKE_SEEDS) if smoke else (RUNGS, SEEDS)
    return [
        LadderRun(method, variant, rung, seed, f"{stem}_seed{seed}", out)
        for rung in rungs
        for seed in seeds
        for method, variant, stem in METHODS
    ]


def list_runs(runs: list[LadderRun], smoke: bool) -> str:
    lines = []
    for run in runs:
        lines.append(f"{run.state():<12}{run.core_hours:6.2f} h  {shlex.join(run.command(smoke))}")
    total = sum(r.core_hours for r in runs)
    todo = sum(r.core_hours for r in runs if not r.done())
    lines.append(
        f"{sum(r.done() for r in runs)} of {len(runs)} runs done; estimated cost {total:.1f} core-hours in all, "
        f"{todo:.1f} for the runs not done (one core per run; docs/research/highlevel_speed.md)"
    )
    return "\n".join(lines)


# ---------------------------------------------------------------------------- report
def ladder_curves(runs: list[LadderRun], smooth: int) -> tuple[dict[tuple[str, int], dict], list[str]]:
    """{(method, rung): `learning_curves.group_curves` entry} over the runs with a progress.csv, and the
    planned runs without one (missing) or not done (partial: the group's curve stops at its shortest seed)."""
    found, notes = {}, []
    for run in runs:
        if not (run.run_dir / "progress.csv").is_file():
            notes.append(f"missing: {run.stem} at {run.rung} updates")
            continue
        if not run.done():
            notes.append(f"not done: {run.stem} at {run.rung} updates ({run.state()})")
        found.setdefault((run.method, run.rung), []).append(
            dataclasses.replace(read_run(run.run_dir), group=f"{run.method}@{run.rung}")
        )
    curves = {}
    for key, members in found.items():
        curves[key] = group_curves(members, smooth)[f"{key[0]}@{key[1]}"]
    return curves, notes


def plot_ladder(curves: dict[tuple[str, int], dict], path: Path, title: str) -> None:
    """One figure, a panel each for E and R_H against updates (log scale): per method (colour) and rung
    (line style), the mean over seeds with its 95 % Student-t band; a dotted mark at each rung's switch
    from pre-training to fine-tuning."""
    import io

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from cefc_mj.fileio import write_atomic

    colours = {label: f"C{i}" for i, (label, _, _) in enumerate(METHODS)}
    rungs = sorted({rung for _, rung in curves})
    styles = dict(zip(rungs, ("-", "--", ":", "-.")))
    fig, axes = plt.subplots(1, len(PANELS), figsize=(6.2 * len(PANELS), 4.6), constrained_layout=True)
    for ax, (metric, label) in zip(axes, PANELS):
        for (method, rung), c in sorted(curves.items()):
            x = c["iterations"]
            (line,) = ax.plot(
                x,
                c[metric]["mean"],
                color=colours[method],
                ls=styles[rung],
                lw=1.5,
                label=f"{method}, {rung} updates ({len(c['seeds'])} seed{'s' * (len(c['seeds']) != 1)})",
            )
            ax.fill_between(x, c[metric]["low"], c[metric]["high"], color=line.get_color(), alpha=0.12, lw=0)
        for rung in rungs:
            ax.axvline(2 * rung / 3, color="0.6", ls=styles[rung], lw=0.8)
        ax.set_xscale("log")
        ax.set_xlabel("updates (iterations of 20 envs; log scale)")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7, loc="best")
    fig.suptitle(title, fontsize=10)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)
    write_atomic(path, buf.getvalue())


def report(runs: list[LadderRun], figure: Path, smooth: int) -> list[str]:
    """Draw the figure (and its numbers beside it, <figure>.csv); the lines to print. ConfigError when no
    planned run has a progress.csv."""
    curves, notes = ladder_curves(runs, smooth)
    if not curves:
        raise ConfigError(f"--report: no ladder run has a progress.csv under {runs[0].out}")
    title = (
        f"Budget ladder (training games, training adversary): mean over seeds of a {smooth}-update moving "
        "average, 95 % t band; grey marks: switch to fine-tuning at 2N/3"
    )
    plot_ladder(curves, figure, title)
    write_csv({f"{m}@{r}": c for (m, r), c in sorted(curves.items())}, figure.with_suffix(".csv"))
    lines = [f"ladder: wrote {figure} and {figure.with_suffix('.csv')}"]
    for (method, rung), c in sorted(curves.items()):
        finals = {m: c[m]["final"] for m, _ in PANELS}
        cells = ", ".join(
            f"{name} {sum(v) / len(v):.4g} (seeds {', '.join(f'{x:.4g}' for x in v)})"
            for name, v in (("E", finals["metric/E"]), ("R_H", finals["episode_return"]))
        )
        lines.append(
            f"  {method} at {rung} updates, last iteration {int(c['iterations'][-1])} (mean of the last {smooth} "
            f"updates; E in steps): {cells}"
        )
    return lines + [f"  {note}" for note in notes]


def build_parser() -> argparse.ArgumentParser:
    p = OneLineParser(prog="budget_ladder", description=__doc__.splitlines()[0])
    p.add_argument("--list", action="store_true", help="print every planned run, its state and cost, then exit")
    p.add_argument("--report", action="store_true", help="draw the learning curves of the runs there, then exit")
    p.add_argument("--out", type=Path, default=None, help=f"the ladder's folder (default {OUT} in the repository)")
    p.add_argument("--figure", type=Path, default=None, help="the report's figure (default <out>/ladder.png)")
    p.add_argument("--keep", action="store_true", help="copy every run's progress into the tracked copy, then exit")
    p.add_argument(
        "--kept",
        type=Path,
        default=None,
        help=f"the tracked copy (default {KEPT} in the repository for the default --out, none for another)",
    )
    p.add_argument("--jobs", type=int, default=1, choices=(1, 2), help="runs trained at a time (default 1)")
    p.add_argument("--smooth", type=int, default=SMOOTH, help=f"moving average in updates (default {SMOOTH})")
    p.add_argument(
        "--smoke",
        action="store_true",
        help=f"a tiny ladder to check the pipeline: rungs {SMOKE_RUNGS}, seed {SMOKE_SEEDS[0]}, no evaluation",
    )
    return p


def main(argv: list[str] | None = None) -> int:
    p = build_parser()
    args = p.parse_args(argv)
    out = ROOT / OUT if args.out is None else args.out.absolute()
    figure = out / "ladder.png" if args.figure is None else args.figure.absolute()
    # the tracked copy belongs to the repository's ladder: another --out uses one only when given
    kept = (ROOT / KEPT if args.out is None else None) if args.kept is None else args.kept.absolute()
    try:
        if args.list + args.report + args.keep > 1:
            raise ConfigError("--list, --report and --keep: give one of them")
        if args.smooth < 1:
            raise ConfigError(f"--smooth {args.smooth}: must be >= 1")
        check_output("--out", out, is_dir=True)
        if kept is not None:
            check_output("--kept", kept, is_dir=True)
        elif args.keep:
            raise ConfigError("--keep: with another --out, give the tracked copy's folder with --kept")
        if args.report:
            check_output("--figure", figure)
        runs = planned_runs(out, args.smoke)
        if args.list:
            print(list_runs(runs, args.smoke))
            return 0
        if args.keep:
            print("\n".join(keep(runs, kept)))
            return 0
        for line in restore(runs, kept) if kept is not None else ():
            print(f"ladder: {line}", flush=True)
        if args.report:
            print("\n".join(report(runs, figure, args.smooth)))
            return 0
    except CefcError as e:
        p.error(str(e))
    todo = [run for run in runs if not run.done()]
    return kept_runs.train_all(todo, len(runs), args.jobs, lambda run: run.command(args.smoke), ROOT, "ladder")


if __name__ == "__main__":
    sys.exit(main())
