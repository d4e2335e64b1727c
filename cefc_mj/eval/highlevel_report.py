"""The reports of Tables V-VII: the plain-text table (`format_highlevel_table`), Table V's statistics
over training seeds as text (`seed_table_lines`, `equivalence_lines`, `aggregate_lines`) and as
Markdown (`table5_markdown`), Table IV's message sizes, and the figure (`plot_highlevel_table`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from cefc_mj.eval.highlevel import adversary_text, paper_table, where_text
from cefc_mj.eval.highlevel_comparison import (
    ADVERSARY_MARGIN,
    AGGREGATE_METRICS,
    MARGIN_TEXT,
    MARGINS,
    PRIMARY,
    REFERENCE_METHOD,
    SEED_METRICS,
)
from cefc_mj.game_protocol import COLUMNS, DT, EPISODES


def format_highlevel_table(result: dict) -> str:
    """Plain text: per method ours (in seconds of flight) and the paper's row. A row over training seeds
    has two lines of ours: its first seed's policy alone ("seed k": mean ± std over that policy's
    episodes) and the row over its seeds ("N seeds": mean ± std over the seeds' episode means, the
    figures the comparisons use); any other row one ("ours": mean ± std over episodes)."""
    from cefc_mj.eval.runner import format_mean_std

    proto = result["protocol"]
    per_agent = result["schema"] == "cefc-eval/table7"
    table_name = {"cefc-eval/table6": "Table VI", "cefc-eval/table7": "Table VII"}.get(result["schema"], "Table V")
    adversary = adversary_text(proto["adversary"])
    lines = [
        f"{table_name} protocol ({where_text(proto)}, N = "
        f"{', '.join(map(str, proto['n_agents'])) if per_agent else proto['n_agents']}, "
        f"density {proto['density']}/m^2, "
        f"{proto['episodes']} "
        f"episodes x {proto['steps']} steps, seed {proto['seed']}, adversary {adversary}, low level "
        f"{proto['low_level']['name']}).",
        "R_H = R_t + R_n + R_e (weighted reward terms) and E (time with an agent within 2 m of the adversary), "
        "summed over each episode and given in seconds of flight (x 0.1 s), the scale of the paper's values; "
        "ours: mean ± sample std over episodes."
        + (
            " Rows over training seeds: 'seed k' is that one training seed's policy (mean ± sample std over "
            "its episodes), 'N seeds' the row (mean ± sample std over the seeds' episode means)."
            if any(len(r.get("training_seeds", {}).get("seeds", [])) > 1 for r in result["rows"].values())
            else ""
        )
        + (f" Table VII: per agent (divided by N), {proto['policy']} trained with N = 8." if per_agent else ""),
    ]
    if proto["episodes"] != EPISODES:
        lines.append(f"{proto['episodes']} episodes; the paper evaluates {EPISODES}.")
    if proto["backend"] != "particle" or proto["wind"] or proto["deviation"]:
        lines.append(
            "The paper's rows are from its MPE (particles, calm, exact sensing): shown for scale, not like-for-like."
        )
    header = [f"{m}/N" for m in COLUMNS] if per_agent else list(COLUMNS)
    table = [["method", "", *header, "F (steps)", "C (%)"]]
    for method, row in result["rows"].items():
        label = method if result["schema"] != "cefc-eval/table6" else f"{method} ({row['adversary']})"
        figures, spread = (
            (row["per_agent"], row["per_agent_std"]) if per_agent else (row["seconds"], row["seconds_std"])
        )
        seeds = row.get("training_seeds")
        over_seeds = bool(seeds) and len(seeds["seeds"]) > 1
        table.append(
            [label, f"seed {seeds['seeds'][0]}" if over_seeds else "ours"]
            + [format_mean_std(figures[m], spread[m], ".2f" if per_agent else ".1f") for m in COLUMNS]
            + [format_mean_std(row["F"], row["F_std"], ".0f"), format_mean_std(row["C"], row["C_std"], ".2f")]
        )
        if over_seeds:
            table.append(
                ["", f"{len(seeds['seeds'])} seeds"]
                + [format_mean_std(seeds["mean"][m] * DT, seeds["std"][m] * DT, ".1f") for m in COLUMNS]
                + ["", ""]
            )
        paper = row.get("paper") or {}
        table.append(
            ["", "paper"] + ["-" if paper.get(m) is None else format(paper[m], ".2f") for m in COLUMNS] + ["-", "-"]
        )
    widths = [max(len(r[i]) for r in table) for i in range(len(table[0]))]
    for r in table:
        lines.append(
            "  ".join(cell.ljust(w) if i < 2 else cell.rjust(w) for i, (cell, w) in enumerate(zip(r, widths))).rstrip()
        )
    for method, row in result["rows"].items():
        for key in ("differs", "low_level_differs", "adversary_differs"):
            if row.get(key):
                lines.append(f"{method}: {row[key]}")
        if row.get("low_level"):
            lines.append(f"{method}: flown over {row['low_level']['name']} ({row['low_level']['kind']})")
    if proto.get("missing"):
        lines.append("missing policies: " + ", ".join(proto["missing"]))
    if result["schema"] == "cefc-eval/table5" and table4_line(result):
        lines.append(table4_line(result))
    if result["schema"] == "cefc-eval/table5" and any("training_seeds" in r for r in result["rows"].values()):
        lines += seed_table_lines(result)
    return "\n".join(lines)


def _ci_text(ci: dict, scale: float = 1.0, fmt: str = ".1f") -> str:
    mean = format(ci["mean"] * scale, fmt)
    if ci["ci_low"] is None:
        return f"{mean} (1 seed)"
    return f"{mean} [{format(ci['ci_low'] * scale, fmt)}, {format(ci['ci_high'] * scale, fmt)}]"


def seed_table_lines(result: dict) -> list[str]:
    """Over training seeds: mean [95 % CI] of each metric against the game's adversary and E against
    the nearest-group rule, and Welch's p against CI-HRL with the verdict (p < 0.05, else "no
    significant difference"); the differences that survive the adjustment; where the result has them
    (`add_comparisons`), the comparison that can say "alike" (`equivalence_lines`), the adversary's
    non-inferiority beside its strength, and the aggregates (`aggregate_lines`)."""
    from cefc_mj.eval.stats import ALPHA

    lines = [
        "",
        f"Over training seeds (each seed's mean over the {result['protocol']['episodes']} episodes; mean "
        "[95 % CI of the mean, Student's t]). E: steps with any agent within 2 m of the adversary, in steps "
        "and in seconds (x 0.1 s); E_agents: agent-steps within 2 m. R_* are per-episode sums, not "
        "scaled; R_e sums over the agents, R_e/N is its per-agent mean. p: Welch's t-test against CI-HRL "
        "over the seeds; a difference counts only where "
        f"p < {ALPHA}.",
    ]
    header = [
        "method",
        "seeds",
        "R_H",
        "R_t",
        "R_n",
        "R_e",
        "R_e/N",
        "E (steps)",
        "E (s)",
        "E_agents",
        "E vs rule (s)",
        "p R_H",
        "p R_t",
        "p E",
        "vs CI-HRL (R_H / E)",
    ]
    table = [header]
    for method, row in result["rows"].items():
        seeds = row.get("training_seeds")
        if not seeds:
            continue
        ci = seeds["ci95"]
        rule = row.get("against_rule", {}).get("ci95", {}).get("E")
        vs = row.get("vs_reference")

        def p(m, vs=vs):
            return "-" if not vs or vs[m]["p"] is None else f"{vs[m]['p']:.3f}"

        table.append(
            [
                method,
                str(len(seeds["seeds"])),
                _ci_text(ci["R_H"], fmt=".0f"),
                _ci_text(ci["R_t"]),
                _ci_text(ci["R_n"], fmt=".0f"),
                _ci_text(ci["R_e"], fmt=".0f"),
                _ci_text(ci["R_e"], 1 / result["protocol"]["n_agents"], ".0f"),
                _ci_text(ci["E"]),
                _ci_text(ci["E"], DT, ".2f"),
                _ci_text(ci["E_agents"], fmt=".0f"),
                "-" if rule is None else _ci_text(rule, DT, ".2f"),
                p("R_H"),
                p("R_t"),
                p("E"),
                "reference"
                if method == REFERENCE_METHOD
                else "-"
                if not vs
                else f"{vs['R_H']['verdict']} / {vs['E']['verdict']}",
            ]
        )
    widths = [max(len(r[i]) for r in table) for i in range(len(header))]
    lines += [
        "  ".join(cell.ljust(w) if i == 0 else cell.rjust(w) for i, (cell, w) in enumerate(zip(r, widths)))
        for r in table
    ]
    lines += _unadjusted_lines(result["rows"])
    lines += _fdr_lines(result["rows"])
    lines += equivalence_lines(result)
    lines += paired_lines(result)
    strength = {m: r["adversary_strength"] for m, r in result["rows"].items() if r.get("adversary_strength")}
    if strength:
        rows = result["rows"]
        noninferior = any("adversary_noninferiority" in rows[m] for m in strength)
        lines += [
            "",
            "Adversary strength: E against the game's adversary over E against the nearest-group rule (means "
            "over training seeds, the same policies and games); p: one-sided paired t-test over the seeds "
            f"that the adversary is weaker than the rule (weaker where p < {ALPHA})."
            + (
                f" Non-inferiority: one-sided paired t-test over the seeds of H0 E(adversary) <= "
                f"{1 - ADVERSARY_MARGIN:g} x E(rule) (the adversary more than {100 * ADVERSARY_MARGIN:g} % weaker), "
                f"rejected where p < {ALPHA}."
                if noninferior
                else ""
            ),
            *(
                f"  {m}: {'-' if a['ratio'] is None else format(a['ratio'], '.2f')}, p "
                f"{'-' if a['p_weaker'] is None else format(a['p_weaker'], '.3f')}: {a['verdict']}"
                + _noninferiority_text(rows[m].get("adversary_noninferiority"))
                for m, a in strength.items()
            ),
        ]
    lines += aggregate_lines(result)
    return lines


def _p_text(p: float | None, adjusted: float | None = None) -> str:
    if p is None:
        return "-"
    return f"{p:.3f}" + ("" if adjusted is None else f" ({adjusted:.3f})")


def _difference_text(d: dict | None, m: str) -> str:
    """A difference of means [95 % Welch CI] (`eval.stats.welch_difference`) in metric m's printed unit."""
    if d is None:
        return "-"
    factor, unit, fmt = _scale(m)
    return (
        f"{format(d['difference'] * factor, '+' + fmt)}{unit} "
        f"[{format(d['ci_low'] * factor, fmt)}, {format(d['ci_high'] * factor, fmt)}]"
    )


def _noninferiority_text(test: dict | None) -> str:
    if not test:
        return ""
    return f"; non-inferiority p {_p_text(test['p'])}: {test['verdict']}"


def _scale(m: str) -> tuple[float, str, str]:
    """(factor from the per-seed figure to the printed one, unit, format) of a compared metric."""
    return (DT, " s", ".2f") if m == "E" else (DT, "", ".0f") if m in ("R_H", "R_t", "R_n", "R_e") else (1.0, "", ".1f")


def equivalence_lines(result: dict) -> list[str]:
    """The comparison with CI-HRL that can say "alike": per row and metric of MARGINS the difference of
    means [95 % Welch CI], Welch's p and the TOST p with their adjustments over the rows, the verdict;
    then the minimum detectable differences and the primary comparison. [] for a result without them."""
    from cefc_mj.eval.stats import ALPHA, POWER

    comparison = result.get("comparison")
    if not comparison:
        return []
    metrics = [m for m in MARGINS if m in SEED_METRICS]
    units = ", ".join(f"{m} {'in s' if m == 'E' else 'per episode x 0.1 s'}, margin {MARGIN_TEXT[m]}" for m in metrics)
    lines = [
        "",
        f"Against {REFERENCE_METHOD}: the row's mean over training seeds minus {REFERENCE_METHOD}'s [95 % Welch CI]; "
        "p: Welch's two-sided t-test; TOST p: two one-sided Welch tests of equivalence within the margin; in "
        f"brackets each adjusted over the {comparison['rows_compared']} rows (Benjamini-Hochberg); verdict from "
        f"the adjusted p's at {ALPHA}: better / worse where p is below it, else equivalent where the TOST p is, "
        f"else undecided (underpowered). {units}.",
    ]
    header = ["method", "seeds"]
    for m in metrics:
        header += [f"{m} difference [95 % CI]", f"p {m}", f"TOST p {m}", f"verdict {m}"]
    table = [header]
    for method, row in result["rows"].items():
        vs = row.get("vs_reference")
        if not vs:
            continue
        cells = [method, str(len(row["training_seeds"]["seeds"]))]
        for m in metrics:
            cells += [
                _difference_text(vs[m].get("difference"), m),
                _p_text(vs[m]["p"], vs[m].get("p_fdr")),
                _p_text(vs[m].get("tost_p"), vs[m].get("tost_p_fdr")),
                vs[m].get("decision", "-"),
            ]
        table.append(cells)
    widths = [max(len(r[i]) for r in table) for i in range(len(header))]
    lines += [
        "  ".join(cell.ljust(w) if i == 0 else cell.rjust(w) for i, (cell, w) in enumerate(zip(r, widths))).rstrip()
        for r in table
    ]
    pooled = comparison["pooled_sd"]
    sds = ", ".join(
        f"{m} {format(pooled[m]['sd'] * _scale(m)[0], _scale(m)[2])}{_scale(m)[1]}" for m in metrics if pooled.get(m)
    )
    pairs: dict[tuple[int, int], dict[str, float]] = {}
    for row in result["rows"].values():
        vs = row.get("vs_reference")
        if vs:
            key = (
                len(row["training_seeds"]["seeds"]),
                len(result["rows"][REFERENCE_METHOD]["training_seeds"]["seeds"]),
            )
            pairs.setdefault(key, {m: vs[m]["mdd"] for m in metrics})
    mdds = "; ".join(
        f"{n} vs {n_ref} seeds: "
        + ", ".join(
            f"{m} {format(v * _scale(m)[0], _scale(m)[2])}{_scale(m)[1]}" for m, v in values.items() if v is not None
        )
        for (n, n_ref), values in sorted(pairs.items())
    )
    if mdds and sds:
        df = next(pooled[m]["df"] for m in metrics if pooled.get(m))
        lines.append(
            f"Minimum detectable difference, unadjusted ({100 * POWER:.0f} % power, two-sided alpha {ALPHA}; "
            f"noncentral t of Student's two-sample test with the SD pooled over every row's seeds, {sds}, df {df}): "
            f"{mdds}{holm_mdd_text(comparison)}. "
            "A true difference smaller than these is more likely to read undecided than different."
        )
    lines += _primary_lines(result)
    return lines


def holm_mdd_text(comparison: dict) -> str:
    """ "; at the Holm level of the primary comparison ...: n vs n_ref seeds: E .. s, R_H .." (the
    MDD at alpha over the primary metrics, `comparison.primary.mdd_holm`), or "" without it."""
    holm = (comparison.get("primary") or {}).get("mdd_holm")
    if not holm:
        return ""
    n, n_ref = holm["seeds"]
    figures = ", ".join(
        f"{m} {format(holm[m] * _scale(m)[0], _scale(m)[2])}{_scale(m)[1]}" for m in PRIMARY[1] if holm.get(m)
    )
    return (
        f"; at the Holm level of the primary comparison (alpha {holm['alpha']:g}, the first step of Holm over "
        f"{', '.join(PRIMARY[1])}), {n} vs {n_ref} seeds: {figures}"
    )


def table5_markdown(result: dict) -> str:
    """Table V's comparison with CI-HRL as a Markdown table (the report's `.md` and the README's):
    per row the seeds, E against the game's adversary and against the rule, the adversary's
    non-inferiority p, R_H, and per metric of MARGINS the difference [95 % Welch CI], Welch / TOST p
    (Benjamini-Hochberg-adjusted) and verdict; then the primary comparison. "" without a comparison."""
    from cefc_mj.eval.stats import ALPHA

    if not result.get("comparison"):
        return ""
    metrics = [m for m in MARGINS if m in SEED_METRICS]

    def interval(block: dict, m: str) -> str:
        factor, _, fmt = _scale(m)
        return _ci_text(block["ci95"][m], factor, fmt)

    header = ["method", "seeds", "E vs adversary (s)", "E vs rule (s)", "adversary non-inferior: p", "R_H (x 0.1 s)"]
    for m in metrics:
        header += [f"{m} minus {REFERENCE_METHOD} [95 % CI]", f"p / TOST p {m} (BH)", f"verdict {m}"]
    header.append("paper E / R_H")
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for method, row in result["rows"].items():
        seeds = row.get("training_seeds")
        if not seeds:
            continue
        rule = row.get("against_rule")
        test = row.get("adversary_noninferiority")
        cells = [
            f"**{method}**" if method == REFERENCE_METHOD else method,
            str(len(seeds["seeds"])),
            interval(seeds, "E"),
            interval(rule, "E") if rule else "-",
            "-"
            if not test
            else _p_text(test["p"]) + ("" if test["p"] is not None and test["p"] < ALPHA else " (not shown)"),
            interval(seeds, "R_H"),
        ]
        vs = row.get("vs_reference")
        for m in metrics:
            if not vs:
                cells += ["reference", "-", "-"]
                continue
            cells += [
                _difference_text(vs[m].get("difference"), m),
                f"{_p_text(vs[m].get('p_fdr'))} / {_p_text(vs[m].get('tost_p_fdr'))}",
                vs[m].get("decision", "-"),
            ]
        paper = row.get("paper")
        cells.append(f"{paper['E']:g} / {paper['R_H']:g}" if paper else "-")
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines + _primary_lines(result) + paired_lines(result))


def _primary_lines(result: dict) -> list[str]:
    from cefc_mj.eval.stats import ALPHA
    from cefc_mj.seeds import GAME_PREREGISTERED_TEST_SEED

    primary = (result.get("comparison") or {}).get("primary")
    if not primary:
        return []
    status = (
        "confirmatory: the pre-registered batch"
        if result["protocol"]["seed"] == GAME_PREREGISTERED_TEST_SEED
        else f"exploratory here: batch seed {result['protocol']['seed']}, not the pre-registered one"
    )
    parts = []
    for m in PRIMARY[1]:
        factor, unit, fmt = _scale(m)
        c = primary[m]
        d = c["difference"]
        diff = "-" if d is None else f"{format(d['difference'] * factor, '+' + fmt)}{unit}"
        parts.append(f"{m} {diff}, p {_p_text(c['p_holm'])}, TOST p {_p_text(c['tost_p_holm'])}: {c['decision']}")
    return [
        "",
        f"Primary comparison (docs/research/preregistration.md; {status}): {primary['method']} against "
        f"{primary['reference']} ({primary['method']} minus {primary['reference']}, "
        f"the verdict {primary['method']}'s), "
        f"p's Holm-adjusted over {', '.join(PRIMARY[1])}, verdicts at {ALPHA}: "
        + "; ".join(parts)
        + "."
        + _primary_mdd_text(result),
    ]


def _primary_mdd_text(result: dict) -> str:
    """ " Minimum detectable difference (80 % power), unadjusted: ...; at the Holm level ...", or ""."""
    from cefc_mj.eval.stats import ALPHA, POWER

    comparison = result["comparison"]
    vs = result["rows"][comparison["primary"]["method"]].get("vs_reference") or {}
    unadjusted = ", ".join(
        f"{m} {format(vs[m]['mdd'] * _scale(m)[0], _scale(m)[2])}{_scale(m)[1]}"
        for m in PRIMARY[1]
        if vs.get(m, {}).get("mdd") is not None
    )
    if not unadjusted:
        return ""
    return (
        f" Minimum detectable difference ({100 * POWER:.0f} % power), unadjusted (alpha {ALPHA}): {unadjusted}"
        + holm_mdd_text(comparison)
        + "."
    )


def aggregate_lines(result: dict) -> list[str]:
    """rliable's aggregates of the result (`_aggregates`), one line; [] without them."""
    agg = (result.get("comparison") or {}).get("aggregates")
    if not agg:
        return []
    a, b = agg["methods"]
    parts = []
    for m in AGGREGATE_METRICS:
        factor, unit, fmt = _scale(m)

        def iv(x, factor=factor, unit=unit, fmt=fmt):
            return (
                f"{format(x['estimate'] * factor, fmt)}{unit} [{format(x['ci_low'] * factor, fmt)}, "
                f"{format(x['ci_high'] * factor, fmt)}]"
            )

        poi = agg[m]["probability_of_improvement"]
        parts.append(
            f"{m}: IQM {a} {iv(agg[m]['iqm'][a])}, {b} {iv(agg[m]['iqm'][b])}; "
            f"P({a} better than {b}) {poi['estimate']:.2f} [{poi['ci_low']:.2f}, {poi['ci_high']:.2f}]"
        )
    return [
        "",
        f"Aggregates over training seeds (rliable's: interquartile mean, probability of improvement, 95 % "
        f"stratified-bootstrap percentile intervals, {agg['reps']} resamples; lower E is better): "
        + "; ".join(parts)
        + ".",
    ]


def _below_alpha_lines(rows: dict, key: str, label: str, header: str) -> list[str]:
    """Per metric of SEED_METRICS, the rows whose difference from CI-HRL has `key` (a p value of their
    vs_reference, shown as `label`) below ALPHA, after `header`; [] when no row is compared."""
    from cefc_mj.eval.stats import ALPHA

    compared = {method: row["vs_reference"] for method, row in rows.items() if "vs_reference" in row}
    if not compared:
        return []

    def below(m: str) -> str:
        found = [
            f"{method} ({vs[m]['verdict']}, {label} {vs[m][key]:.3f})"
            for method, vs in compared.items()
            if vs[m].get(key) is not None and vs[m][key] < ALPHA
        ]
        return "; ".join(found) or "none"

    return ["", header.format(n=len(compared), alpha=ALPHA), *(f"  {m}: {below(m)}" for m in SEED_METRICS)]


def _fdr_lines(rows: dict) -> list[str]:
    """Which differences from CI-HRL hold once p is adjusted over every row compared (per metric)."""
    return _below_alpha_lines(
        rows,
        "p_fdr",
        "adjusted p",
        "Adjusted for the {n} comparisons per metric (Benjamini-Hochberg over the rows, "
        "scipy.stats.false_discovery_control), the differences from CI-HRL with adjusted p < {alpha}:",
    )


def _unadjusted_lines(rows: dict) -> list[str]:
    """Every difference from CI-HRL with unadjusted Welch p < ALPHA, on every compared metric (before
    any adjustment: the full list, of which `_fdr_lines` keeps those that survive it)."""
    return _below_alpha_lines(
        rows,
        "p",
        "p",
        "Unadjusted (Welch's p over training seeds, before any adjustment), every difference from CI-HRL "
        "with p < {alpha}, per metric (E_agents: agent-steps within 2 m):",
    )


def paired_lines(result: dict) -> list[str]:
    """The paired comparison of the rows that are the same runs as another (`comparison.paired`): per
    metric of MARGINS the mean paired difference [95 % CI] and the paired t-test's p; [] without it."""
    summary = (result.get("comparison") or {}).get("paired")
    if not summary:
        return []
    lines = []
    for method in summary["rows"]:
        paired = result["rows"][method]["vs_reference"]["paired"]
        parts = []
        for m in [m for m in MARGINS if m in SEED_METRICS]:
            d = paired[m]
            factor, unit, fmt = _scale(m)
            interval = (
                ""
                if d["ci_low"] is None
                else f" [{format(d['ci_low'] * factor, fmt)}, {format(d['ci_high'] * factor, fmt)}]"
            )
            parts.append(f"{m} {format(d['mean'] * factor, '+' + fmt)}{unit}{interval}, p {_p_text(d['p'])}")
        lines.append(
            f"Paired (the same runs): {method} is {paired['method']}'s {paired['E']['n']} training runs before "
            f"fine-tuning, so besides the pre-registered Welch test above it is compared with {paired['method']} "
            f"by a paired t-test over the seeds ({method} minus {paired['method']} [95 % CI], unadjusted): "
            + "; ".join(parts)
            + "."
        )
    return ["", *lines]


def table4_line(result: dict) -> str | None:
    """The paper's Table IV (numbers each agent sends per decision) for the methods of a Table V
    result, read from the policy files, beside the paper's; None without such a method (--policy)."""
    paper = paper_table("table4_comm_dims")
    named = {
        "MAPPO+AT-M": "MAPPO",
        "MASAC+AT-M (BenchMARL; stands in for HASAC)": "HASAC",
        "TarMAC+AT-M": "TarMAC",
        "MASIA+AT-M": "MASIA",
        "NVIF+AT-M": "NVIF",
        "CI-HRL": "ConsMAC",
    }
    cells = [
        f"{method} {row['message_dim']} (paper {paper[named[method]]})"
        for method, row in result["rows"].items()
        if method in named and "message_dim" in row
    ]
    return "Table IV, message size per agent and decision: " + ", ".join(cells) if cells else None


def plot_highlevel_table(result: dict, path: Path) -> Path:
    """Bars of R_t and E (seconds scale; Table VII per agent) per row beside the paper's. A row over
    training seeds shows the mean over its seeds with the 95 % CI of that mean (Student's t, the
    figures the comparisons use); any other row (one policy) its mean over episodes ± the sample std
    over episodes. The legend and the axis labels say which."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = result["rows"]
    names = list(rows)
    key = "per_agent" if result["schema"] == "cefc-eval/table7" else "seconds"
    over_seeds = [len(rows[n].get("training_seeds", {}).get("seeds", [])) > 1 for n in names]
    labels = [f"{n} ({len(rows[n]['training_seeds']['seeds'])} seeds)" if s else n for n, s in zip(names, over_seeds)]
    x = np.arange(len(names))
    fig, axes = plt.subplots(2, 1, figsize=(max(6.0, 1.5 + 0.7 * len(names)), 8.0))
    for ax, m in zip(axes, ("R_t", "E")):
        ours, low, high = [], [], []
        for n, seeded in zip(names, over_seeds):
            if seeded:  # the row: mean over training seeds, 95 % CI of the mean
                ci = rows[n]["training_seeds"]["ci95"][m]
                mean = ci["mean"] * DT
                ours.append(mean)
                low.append(mean - ci["ci_low"] * DT)
                high.append(ci["ci_high"] * DT - mean)
            else:  # one policy: mean ± sample std over its episodes
                spread = rows[n][f"{key}_std"][m] or 0.0
                ours.append(rows[n][key][m])
                low.append(spread)
                high.append(spread)
        paper = [
            np.nan if not rows[n].get("paper") or rows[n]["paper"].get(m) is None else rows[n]["paper"][m]
            for n in names
        ]
        if all(over_seeds):
            what = "ours: mean over training seeds, 95 % CI"
        elif not any(over_seeds):
            what = "ours: mean ± std over episodes"
        else:
            what = "ours: seeds' mean [95 % CI], else mean ± std over episodes"
        ax.bar(x - 0.2, ours, 0.4, yerr=[low, high], capsize=3, label=what)
        ax.bar(x + 0.2, paper, 0.4, label="paper")
        ax.set_xticks(x, labels, rotation=20, ha="right", fontsize=8)
        unit = "per-episode sum x 0.1 s" if m == "R_t" else "s"
        ax.set_ylabel(f"{m}{'/N' if key == 'per_agent' else ''} ({unit})")
        ax.set_title(f"{m}{'/N' if key == 'per_agent' else ''} ({'higher' if m == 'R_t' else 'lower'} is better)")
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)


def report_markdown(result: dict, text: str) -> str:
    """The report folder's `<protocol>.md` of a Tables V-VII result: for Table V with a comparison its
    Markdown table (`table5_markdown`), then the plain-text report `text` and the command that flew it
    (and, for a re-analysed report, the command that re-analysed it)."""
    proto = result["schema"].removeprefix("cefc-eval/")
    markdown = table5_markdown(result) + "\n\n" if proto == "table5" and "comparison" in result else ""
    command = result["protocol"].get("command", "")
    again = result.get("reanalysis")
    tail = f"\n\nRe-analysed from its JSON, no game flown again: `{again['command']}`" if again else ""
    return f"# {proto}\n\n{markdown}```\n{text}\n```\n\nCommand: `{command}`{tail}\n"
