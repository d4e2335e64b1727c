"""How much a Table V report can tell: the SD over training seeds pooled over its rows, and the minimum
detectable difference and equivalence power at given seed counts (docs/research/preregistration.md, "Power").

    python -m cefc_mj.eval.power                                  # the shipped eval/reports/table5.json
    python -m cefc_mj.eval.power REPORT --pairs 20:20 5:20        # other seed counts
    python -m cefc_mj.eval.power REPORT --reanalyse               # also the report's comparisons, re-analysed

Nothing is flown: the figures come from the report's per-seed values (`training_seeds`).
"""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass
from pathlib import Path

from cefc_mj import paths
from cefc_mj.errors import OneLineParser
from cefc_mj.eval.highlevel_comparison import MARGINS, add_comparisons
from cefc_mj.eval.highlevel_report import equivalence_lines
from cefc_mj.eval.stats import ALPHA, POWER, equivalence_power, minimum_detectable_difference, pooled_sd
from cefc_mj.game_protocol import DT

DEFAULT_PAIRS = ((3, 5), (5, 5), (5, 20), (20, 20))
"""(row's seeds, CI-HRL's seeds): the shipped table's and the pre-registered ones."""


@dataclass(frozen=True)
class MetricPower:
    """One metric's pooled spread over training seeds and what it lets a comparison detect."""

    metric: str
    """R_H or E."""
    pooled_sd: float
    """SD over training seeds pooled over every row (seconds scale: x 0.1 s)."""
    df: int
    """Its degrees of freedom (sum of seeds - 1 over the rows)."""
    margin: float
    """The equivalence margin (seconds scale)."""
    mdd: dict[str, float]
    """"n:n_ref" -> minimum detectable difference at 80 % power, two-sided alpha 0.05 (seconds scale)."""
    equivalence_power: dict[str, float]
    """"n:n_ref" -> power of the TOST within the margin where the true difference is 0."""


def report_power(result: dict, pairs=DEFAULT_PAIRS) -> list[MetricPower]:
    """The power figures of a Table V result (its rows' `training_seeds`), per metric of MARGINS, on the
    seconds scale (per-seed figures x DT)."""
    out = []
    for m in MARGINS:
        groups = [row["training_seeds"][m] for row in result["rows"].values() if "training_seeds" in row]
        sd, df = pooled_sd(groups)
        sd, margin = sd * DT, MARGINS[m] * DT
        out.append(
            MetricPower(
                m,
                sd,
                df,
                margin,
                {f"{n}:{k}": minimum_detectable_difference(n, k, sd, ALPHA, POWER) for n, k in pairs},
                {f"{n}:{k}": equivalence_power(n, k, sd, margin, ALPHA) for n, k in pairs},
            )
        )
    return out


def format_power(figures: list[MetricPower]) -> str:
    lines = [
        f"Pooled SD over training seeds (seconds scale, x {DT} s); minimum detectable difference at "
        f"{100 * POWER:.0f} % power, two-sided alpha {ALPHA} (noncentral t); TOST power within the margin "
        "at a true difference of 0:"
    ]
    for f in figures:
        unit = " s" if f.metric == "E" else ""
        mdd = ", ".join(f"{k.replace(':', ' vs ')} seeds {v:.2f}{unit}" for k, v in f.mdd.items())
        eq = ", ".join(f"{k.replace(':', ' vs ')} {v:.2f}" for k, v in f.equivalence_power.items())
        lines.append(
            f"  {f.metric}: pooled SD {f.pooled_sd:.2f}{unit} (df {f.df}), margin ±{f.margin:g}{unit}; MDD {mdd}; "
            f"equivalence power {eq}"
        )
    return "\n".join(lines)


def _pair(text: str) -> tuple[int, int]:
    try:
        n, k = (int(x) for x in text.split(":"))
    except ValueError:
        raise ValueError(f"{text!r}: give N:N_REF, e.g. 20:20") from None
    if n < 2 or k < 2:
        raise ValueError(f"{text!r}: at least 2 seeds on each side")
    return n, k


def main(argv: list[str] | None = None) -> int:
    parser = OneLineParser(prog="python -m cefc_mj.eval.power", description=__doc__.splitlines()[0])
    parser.add_argument("report", nargs="?", type=Path, default=paths.EVAL_DIR / "reports" / "table5.json")
    parser.add_argument("--pairs", nargs="+", default=None, metavar="N:N_REF", help="seed counts (default 3:5 ...)")
    parser.add_argument("--reanalyse", action="store_true", help="also print the report's comparisons, re-analysed")
    args = parser.parse_args(argv)
    try:
        pairs = tuple(_pair(p) for p in args.pairs) if args.pairs else DEFAULT_PAIRS
        result = json.loads(args.report.read_text())
        if result.get("schema") != "cefc-eval/table5":
            raise ValueError(f"schema {result.get('schema')!r}: not a Table V report")
        print(format_power(report_power(result, pairs)))
    except (OSError, ValueError, KeyError) as e:
        print(f"{parser.prog}: error: {args.report}: {e}", file=sys.stderr)
        return 2
    if args.reanalyse:
        print("\n".join(equivalence_lines(add_comparisons(result))))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
