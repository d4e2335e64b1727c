"""Two Table VIII reports flown on the same seeds, compared seed by seed (docs/research/training_in_mujoco.md).

    python -m cefc_mj.eval.paired BEFORE/table8.json AFTER/table8.json [--md OUT.md]

Per c and condition, from each report's per-episode details: F, N and C as mean ± std over seeds,
retention per seed (F + N over the same seed's calm F + N), and the paired difference after - before
of retention and of C over the seeds both reports flew (the same layouts), tested with the Wilcoxon
signed-rank test (two-sided; `scipy.stats.wilcoxon`), Holm-adjusted over the c of each condition and
metric. Verdicts: "better" / "worse" where the adjusted p is below alpha, else "undecided" (with the
number of seeds). This compares two policies on these games; with one training seed per policy it says
nothing about the training recipe's spread.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
from scipy import stats

from cefc_mj.errors import ConfigError
from cefc_mj.eval.stats import ALPHA, holm_adjusted
from cefc_mj.fileio import write_atomic

CALM = "SITL-S"


def per_seed(report: dict) -> dict[tuple[int, str], dict[int, dict[str, float]]]:
    """{(c, condition): {seed: {"F", "N", "C"}}} from a table8.json's per-episode details."""
    out: dict[tuple[int, str], dict[int, dict[str, float]]] = {}
    for c, conditions in report["rows"].items():
        for condition, cell in conditions.items():
            if not cell.get("valid", True):
                raise ConfigError(f"c = {c} {condition}: the cell is not a measurement (faulted episodes)")
            out[(int(c), condition)] = {
                int(e["seed"]): {k: float(e[k]) for k in ("F", "N", "C")} for e in cell["episodes_detail"]
            }
    return out


def read_report(path: Path) -> dict:
    """A table8.json read and checked for what `compare` uses (a "rows" table of cells with
    per-episode F, N and C); ConfigError with one line naming `path` for a missing, unreadable,
    damaged or foreign file."""
    path = Path(path)
    if path.is_dir():
        raise ConfigError(f"{path}: a folder, not a report")
    if not path.is_file():
        raise ConfigError(f"{path}: no such report")
    try:
        report = json.loads(path.read_bytes().decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        reason = e.msg if isinstance(e, json.JSONDecodeError) else "not UTF-8 text"
        raise ConfigError(f"{path}: not a JSON report ({reason})") from None
    except (OSError, RecursionError, ValueError) as e:
        raise ConfigError(f"{path}: cannot be read ({type(e).__name__}: {str(e).strip()[:160]})") from None
    try:
        if not isinstance(report, dict) or not isinstance(report.get("rows"), dict):
            raise ValueError("no table of rows")
        if not all(
            isinstance(cells, dict) and all(isinstance(c, dict) for c in cells.values())
            for cells in report["rows"].values()
        ):
            raise ValueError("a row that is not a table of cells")
        cells = per_seed(report)
        if any((c, CALM) not in cells for c, _ in cells):
            raise ValueError(f"a formation without its {CALM} (calm) cell, the retention reference")
        if any(not np.isfinite(v) for seeds in cells.values() for record in seeds.values() for v in record.values()):
            raise ValueError("a figure that is not a finite number")
    except ConfigError as e:
        raise ConfigError(f"{path}: {e}") from None
    except (KeyError, TypeError, ValueError, AttributeError) as e:
        what = (
            f"missing {e}"
            if isinstance(e, KeyError)
            else str(e).strip().splitlines()[0][:160]
            if str(e).strip()
            else type(e).__name__
        )
        raise ConfigError(f"{path}: not a table8.json report ({what})") from None
    return report


def retention(cells: dict, c: int, condition: str) -> dict[int, float]:
    """Each seed's F + N at `condition` over its calm F + N (percent)."""
    calm = cells[(c, CALM)]
    return {
        s: 100.0 * (v["F"] + v["N"]) / (calm[s]["F"] + calm[s]["N"])
        for s, v in cells[(c, condition)].items()
        if s in calm and calm[s]["F"] + calm[s]["N"] > 0
    }


def _wilcoxon(diff: np.ndarray) -> float | None:
    if len(diff) < 2:
        return None
    if not np.any(diff):  # identical seed by seed: no evidence of a difference
        return 1.0
    return float(stats.wilcoxon(diff).pvalue)


def compare(before: dict, after: dict, alpha: float = ALPHA) -> list[dict]:
    """One row per (c, condition) both reports flew: figures of each and the paired tests."""
    b, a = per_seed(before), per_seed(after)
    keys = sorted(set(b) & set(a), key=lambda k: (k[0], list(before["rows"][str(k[0])]).index(k[1])))
    rows = []
    for c, condition in keys:
        seeds = sorted(set(b[(c, condition)]) & set(a[(c, condition)]))
        row = {"c": c, "condition": condition, "seeds": len(seeds)}
        for name, cells in (("before", b), ("after", a)):
            values = cells[(c, condition)]
            kept = retention(cells, c, condition)
            for metric in ("F", "N", "C"):
                x = np.array([values[s][metric] for s in seeds])
                row[f"{name}_{metric}"], row[f"{name}_{metric}_std"] = float(x.mean()), float(x.std(ddof=1))
            r = np.array([kept[s] for s in seeds if s in kept])
            row[f"{name}_keeps"], row[f"{name}_keeps_std"] = float(r.mean()), float(r.std(ddof=1))
        kept_b, kept_a = retention(b, c, condition), retention(a, c, condition)
        both = [s for s in seeds if s in kept_b and s in kept_a]
        row["p_keeps"] = _wilcoxon(np.array([kept_a[s] - kept_b[s] for s in both])) if condition != CALM else None
        row["p_C"] = _wilcoxon(np.array([a[(c, condition)][s]["C"] - b[(c, condition)][s]["C"] for s in seeds]))
        rows.append(row)
    for metric, higher_is_better in (("keeps", True), ("C", False)):
        for condition in {r["condition"] for r in rows}:
            group = [r for r in rows if r["condition"] == condition]
            for r, p in zip(group, holm_adjusted([r[f"p_{metric}"] for r in group])):
                r[f"p_{metric}_holm"] = p
                delta = r[f"after_{metric}"] - r[f"before_{metric}"]
                if p is None:
                    r[f"verdict_{metric}"] = "-"
                elif p < alpha:
                    r[f"verdict_{metric}"] = "better" if (delta > 0) == higher_is_better else "worse"
                else:
                    r[f"verdict_{metric}"] = f"undecided (n = {r['seeds']})"
    return rows


def format_rows(rows: list[dict], before_name: str, after_name: str) -> str:
    """A markdown table of `compare`'s rows."""
    lines = [
        f"| c | condition | {before_name} F / N / C (%) | {after_name} F / N / C (%) | keeps before -> after "
        "| p keeps (Holm) | C | p C (Holm) |",
        "|---|---|---|---|---|---|---|---|",
    ]

    def p(value):
        return "-" if value is None else f"{value:.2g}"

    for r in rows:
        fig = {
            name: f"{r[f'{name}_F']:.0f} ± {r[f'{name}_F_std']:.0f} / {r[f'{name}_N']:.0f} ± "
            f"{r[f'{name}_N_std']:.0f} / {r[f'{name}_C']:.3f} ± {r[f'{name}_C_std']:.3f}"
            for name in ("before", "after")
        }
        keeps = (
            "-"
            if r["condition"] == CALM
            else f"{r['before_keeps']:.1f} ± {r['before_keeps_std']:.1f} -> {r['after_keeps']:.1f} ± "
            f"{r['after_keeps_std']:.1f} % ({r['verdict_keeps']})"
        )
        lines.append(
            f"| {r['c']} | {r['condition']} | {fig['before']} | {fig['after']} | {keeps} | {p(r['p_keeps'])} "
            f"({p(r['p_keeps_holm'])}) | {r['verdict_C']} | {p(r['p_C'])} ({p(r['p_C_holm'])}) |"
        )
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m cefc_mj.eval.paired", description=__doc__.splitlines()[0])
    p.add_argument("before", type=Path, help="table8.json of the reference policy")
    p.add_argument("after", type=Path, help="table8.json of the policy compared with it (the same seeds)")
    p.add_argument("--md", type=Path, default=None, help="also write the table to this markdown file")
    args = p.parse_args(argv)
    try:
        if args.md is not None and not args.md.parent.is_dir():
            raise ConfigError(f"--md {args.md}: folder {args.md.parent} does not exist")
        reports = [read_report(path) for path in (args.before, args.after)]
        names = [str(r.get("policy")) for r in reports]
        rows = compare(*reports)
        if not rows:
            raise ConfigError("the two reports share no (c, condition) cell")
    except ConfigError as e:
        print(f"paired: error: {e}", file=sys.stderr)
        return 2
    text = format_rows(rows, *names)
    print(text, end="")
    if args.md is not None:
        write_atomic(args.md, text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
