"""Learning curves over training seeds: the paper's Fig. 7 (ConsMAC-A and its ablations) and Fig. 6
(ConsMAC against the other communication methods), drawn from the runs of `cefc-train highlevel`.

Each run folder holds config.json and progress.csv (one row per iteration of 20 episodes). Runs are
grouped by their folder name without the `_seed<k>` suffix (the name `cefc-train highlevel` gives
them: cihrl_consmac_a, cihrl_consmac_a_seed1, ... form one group). Per group and iteration the curve
is the mean over the group's seeds of a moving average over `smooth` iterations (the iteration and
the ones before it), with the 95 % Student-t confidence band of that mean (`eval.stats.seed_interval`;
no band with one seed). An iteration enters a group's curve only where every seed of the group has
it (an interrupted run shortens its group's curve rather than biasing it).

The training curves are what the policies saw while learning (training games, the training
adversary); whether two methods differ is decided on the test games by Table V, not here.

    python -m cefc_mj.eval.learning_curves runs/hl --out fig7              # every run under runs/hl
    python -m cefc_mj.eval.learning_curves runs/hl --figure fig7 --out DIR # only Fig. 7's groups
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import math
import re
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cefc_mj.errors import CefcError, ConfigError, OneLineParser
from cefc_mj.eval.stats import seed_interval
from cefc_mj.fileio import can_write_in, write_atomic
from cefc_mj.provenance import display_run_path, git_commit

EXIT_USAGE = 2
METRICS = ("episode_return", "metric/E", "term/R_t")
"""progress.csv columns drawn, one panel each: the episode's R_H (sum over the 8 agents), the steps
with a UAV within 2 m of the adversary, the target reward."""
METRIC_LABELS = {"episode_return": "R_H per episode", "metric/E": "E (steps)", "term/R_t": "R_t per episode"}
FIGURES = {
    "fig7": {
        "cihrl_consmac_a": "ConsMAC-A",
        "cihrl_consmac_a_wo_com": "ConsMAC-wo-Com",
        "cihrl_consmac_a_wo_mem": "ConsMAC-wo-Mem",
        "cihrl_consmac_a_wo_de": "ConsMAC-wo-DE",
        "cihrl_consmac_a_wt_rl": "ConsMAC-wt-RL",
        "cihrl_consmac_a_consmac_g": "ConsMAC-G",
    },
    "fig6": {
        "cihrl_consmac_a": "ConsMAC-A",
        "cihrl_consmac_o": "ConsMAC-O",
        "cihrl_mappo": "MAPPO",
        "cihrl_tarmac": "TarMAC",
        "cihrl_masia": "MASIA",
        "cihrl_nvif": "NVIF",
    },
}
LABELS = {**FIGURES["fig7"], **FIGURES["fig6"], "cihrl_consmac_a_dt": "CI-HRL-DT (ConsMAC-A)"}
"""The paper's figures of training curves: run group -> the paper's legend label."""
SEED_SUFFIX = re.compile(r"_seed(\d+)$")


@dataclass(frozen=True)
class Run:
    """One training run: its folder, group, seed, and progress columns."""

    folder: Path
    group: str
    seed: int
    columns: dict[str, np.ndarray]
    """progress.csv's numeric columns (iteration, episodes_total, phase, METRICS ...)."""


def find_runs(paths: list[Path]) -> list[tuple[Path, bool]]:
    """Run folders (with progress.csv) among `paths` and their direct subfolders, each with whether it
    was named itself (True) or found inside a named folder; ConfigError naming a path that is neither."""
    found = []
    for path in paths:
        if (path / "progress.csv").is_file():
            found.append((path, True))
            continue
        if not path.is_dir():
            raise ConfigError(f"{path}: not a folder")
        inner = sorted(p for p in path.iterdir() if (p / "progress.csv").is_file())
        if not inner:
            raise ConfigError(f"{path}: no training run (a folder with progress.csv) in it or under it")
        found += [(p, False) for p in inner]
    return found


def run_group(folder: Path) -> tuple[str, int]:
    """A run folder's group (its name without `_seed<k>`) and seed."""
    match = SEED_SUFFIX.search(folder.name)
    return (folder.name[: match.start()], int(match.group(1))) if match else (folder.name, 0)


class NotAHighLevelLog(ConfigError):
    """A progress.csv without the columns of `cefc-train highlevel` (e.g. a BenchMARL run's)."""


def read_run(folder: Path) -> Run:
    """A run's progress.csv (CheckpointError-free: ConfigError naming the file when it is unreadable)."""
    try:
        rows = list(csv.DictReader(io.StringIO((folder / "progress.csv").read_text())))
    except (OSError, UnicodeDecodeError, csv.Error) as e:
        raise ConfigError(f"{folder / 'progress.csv'}: unreadable ({e})") from None
    needed = ("iteration", "episodes_total", *METRICS)
    if not rows or any(k not in rows[0] for k in needed):
        raise NotAHighLevelLog(
            f"{folder / 'progress.csv'}: not a high-level training log (needs columns {', '.join(needed)})"
        )
    columns = {}
    for key in (*needed, "phase"):
        if key in rows[0]:
            columns[key] = np.array([float(r[key]) if r[key] not in ("", None) else math.nan for r in rows])
    return Run(folder, *run_group(folder), columns)


def _smooth(x: np.ndarray, k: int) -> np.ndarray:
    """Trailing moving average over k values (fewer at the start)."""
    c = np.cumsum(np.insert(x, 0, 0.0))
    idx = np.arange(1, x.size + 1)
    lo = np.maximum(idx - k, 0)
    return (c[idx] - c[lo]) / (idx - lo)


def group_curves(runs: list[Run], smooth: int) -> dict[str, dict]:
    """{group: {"seeds", "runs", "episodes", "iterations", "phase_switch" (in episodes), metric: {"mean",
    "low", "high", "final"}}} over the iterations every seed of the group reached."""
    groups: dict[str, list[Run]] = {}
    for run in runs:
        groups.setdefault(run.group, []).append(run)
    out = {}
    for group, members in sorted(groups.items()):
        members.sort(key=lambda r: r.seed)
        length = min(r.columns["iteration"].size for r in members)
        first = members[0].columns
        curve = {
            "seeds": [r.seed for r in members],
            "runs": [r.folder.name for r in members],
            "episodes": first["episodes_total"][:length],
            "iterations": first["iteration"][:length],
            "phase_switch": None,
        }
        phase = first.get("phase", np.zeros(0))[:length]
        if phase.size and phase[0] == 0 and (phase > 0).any():  # not for direct training (no pre-training)
            curve["phase_switch"] = float(first["episodes_total"][int(np.argmax(phase > 0))])
        for metric in METRICS:
            per_seed = np.stack([_smooth(r.columns[metric][:length], smooth) for r in members])
            bands = [seed_interval(per_seed[:, i]) for i in range(length)]
            curve[metric] = {
                "mean": per_seed.mean(axis=0),
                "low": np.array([b["ci_low"] if b["ci_low"] is not None else math.nan for b in bands]),
                "high": np.array([b["ci_high"] if b["ci_high"] is not None else math.nan for b in bands]),
                "final": [float(v) for v in per_seed[:, -1]],
            }
        out[group] = curve
    return out


def write_csv(curves: dict[str, dict], path: Path) -> None:
    """One row per group and iteration: the mean and band of every metric."""
    buf = io.StringIO()
    w = csv.writer(buf)
    w.writerow(["group", "seeds", "episodes", *[f"{m}_{s}" for m in METRICS for s in ("mean", "ci_low", "ci_high")]])
    for group, c in curves.items():
        for i, episodes in enumerate(c["episodes"]):
            cells = [f"{c[m][s][i]:.6g}" for m in METRICS for s in ("mean", "low", "high")]
            w.writerow([group, len(c["seeds"]), int(episodes), *cells])
    write_atomic(path, buf.getvalue())


def plot(curves: dict[str, dict], labels: dict[str, str], path: Path, title: str) -> None:
    """One panel per metric: each group's mean over seeds with its 95 % band."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(METRICS), figsize=(5.2 * len(METRICS), 4.2), constrained_layout=True)
    for ax, metric in zip(axes, METRICS):
        for group, c in curves.items():
            label = f"{labels.get(group, group)} ({len(c['seeds'])} seeds)"
            (line,) = ax.plot(c["episodes"], c[metric]["mean"], label=label, lw=1.6)
            ax.fill_between(
                c["episodes"], c[metric]["low"], c[metric]["high"], color=line.get_color(), alpha=0.18, lw=0
            )
        switches = {c["phase_switch"] for c in curves.values() if c["phase_switch"] is not None}
        for x in sorted(switches):
            ax.axvline(x, color="0.5", ls=":", lw=1)
        ax.set_xlabel("training episodes")
        ax.set_ylabel(METRIC_LABELS[metric])
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8, loc="lower right")
    fig.suptitle(title)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)
    write_atomic(path, buf.getvalue())


def summary(
    curves: dict[str, dict], labels: dict[str, str], smooth: int, command: str, skipped: tuple[str, ...] = ()
) -> str:
    """Markdown: what was drawn, from which runs (and which runs found were not high-level logs), and
    each group's final value per metric."""
    lines = [
        "# Training curves over seeds",
        "",
        f"Command: `{command}`; commit {git_commit() or 'unknown'}.",
        "",
        f"Mean over training seeds of each run's moving average over {smooth} iterations (20 episodes "
        "each), with the 95 % Student-t band of the mean (none with one seed). The dotted line is the "
        "switch from pre-training (navigation-only low level) to fine-tuning over the student, where "
        "the rewards change scale. These are training games against the training adversary: whether "
        "two methods differ is decided by Table V on the test games.",
        "",
        "| method | seeds (runs) | episodes | " + " | ".join(f"final {METRIC_LABELS[m]}" for m in METRICS) + " |",
        "|---|---|---|" + "---|" * len(METRICS),
    ]
    for group, c in curves.items():
        cells = []
        for metric in METRICS:
            ci = seed_interval(c[metric]["final"])
            band = "" if ci["ci_low"] is None else f" [{ci['ci_low']:.0f}, {ci['ci_high']:.0f}]"
            cells.append(f"{ci['mean']:.0f}{band}")
        lines.append(
            f"| {labels.get(group, group)} | {len(c['seeds'])} ({', '.join(c['runs'])}) | {int(c['episodes'][-1])} | "
            + " | ".join(cells)
            + " |"
        )
    if skipped:
        lines += ["", f"Skipped (not `cefc-train highlevel` logs): {', '.join(skipped)}."]
    return "\n".join(lines) + "\n"


def build_parser() -> argparse.ArgumentParser:
    p = OneLineParser(
        prog="python -m cefc_mj.eval.learning_curves",
        description="Draw training curves (mean and 95 % band over seeds) from `cefc-train highlevel` runs: "
        "the paper's Fig. 7 (ConsMAC's ablations) or Fig. 6 (communication methods).",
    )
    p.add_argument("runs", nargs="+", type=Path, help="run folders, or folders holding run folders")
    p.add_argument("--out", type=Path, required=True, help="folder for curves.png, curves.csv and README.md (created)")
    p.add_argument(
        "--figure",
        choices=(*FIGURES, "all"),
        default="all",
        help="fig7: ConsMAC-A and its ablations; fig6: the communication methods; all: every group found (default)",
    )
    p.add_argument("--smooth", type=int, default=5, help="moving-average window in iterations (default 5)")
    return p


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    args = build_parser().parse_args(argv)
    try:
        if args.smooth < 1:
            raise ConfigError(f"--smooth {args.smooth}: must be >= 1")
        out = args.out
        parent = out if out.is_dir() else out.parent
        if out.exists() and not out.is_dir():
            raise ConfigError(f"--out {out}: exists and is not a folder")
        if not parent.is_dir() or not can_write_in(parent):
            raise ConfigError(f"--out {out}: cannot write in {parent}")
        folders = find_runs(args.runs)
        if args.figure != "all":
            folders = [(f, named) for f, named in folders if run_group(f)[0] in FIGURES[args.figure]]
            if not folders:
                raise ConfigError(f"--figure {args.figure}: none of its runs ({', '.join(FIGURES[args.figure])}) found")
        runs, skipped = [], []
        for folder, named in folders:
            try:
                runs.append(read_run(folder))
            except NotAHighLevelLog:
                if named:
                    raise
                skipped.append(folder.name)  # another trainer's run beside them (BenchMARL's logs differ)
        if not runs:
            given = ", ".join(map(str, args.runs))
            raise ConfigError(f"{given}: no high-level training run (skipped {', '.join(skipped)})")
        out.mkdir(exist_ok=True)
        curves = group_curves(runs, args.smooth)
        order = list(FIGURES.get(args.figure, {})) or list(curves)
        curves = {g: curves[g] for g in sorted(curves, key=lambda g: order.index(g) if g in order else len(order))}
        command = "python -m cefc_mj.eval.learning_curves " + " ".join(
            [display_run_path(p) for p in args.runs]
            + ["--out", display_run_path(out), "--figure", args.figure, "--smooth", str(args.smooth)]
        )
        title = {"fig7": "Fig. 7: ConsMAC-A and its ablations", "fig6": "Fig. 6: communication methods"}.get(
            args.figure, "Training curves"
        )
        write_csv(curves, out / "curves.csv")
        plot(curves, LABELS, out / "curves.png", title)
        write_atomic(out / "README.md", summary(curves, LABELS, args.smooth, command, tuple(skipped)))
        meta = {g: {"seeds": c["seeds"], "runs": c["runs"]} for g, c in curves.items()}
        write_atomic(out / "runs.json", json.dumps(meta, indent=1) + "\n")
    except CefcError as e:
        print(f"python -m cefc_mj.eval.learning_curves: error: {e}", file=sys.stderr)
        return EXIT_USAGE
    note = f" ({len(skipped)} other runs skipped: {', '.join(skipped)})" if skipped else ""
    print(f"{len(curves)} groups, {len(runs)} runs{note} -> {display_run_path(out)}/curves.png, curves.csv, README.md")
    return 0


if __name__ == "__main__":
    sys.exit(main())
