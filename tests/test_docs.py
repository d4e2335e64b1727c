"""README.md and docs/: a short front page, links that resolve, pages that stand alone, and every
number that the README and docs/results.md quote equal to the report it comes from.

The numbers are read from the shipped reports under eval/reports/ (the Markdown a report ships, or its
JSON where it has no Markdown) and compared with what the pages print: a report flown again, or a
page edited by hand, that no longer agree fail here.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
REPORTS = ROOT / "eval" / "reports"

pytestmark = pytest.mark.skipif(not (DOCS / "index.md").is_file(), reason="needs a checkout with docs/")

SET_UP = (
    "python3 -m venv .venv && . .venv/bin/activate && pip install -q -e . && cefc-eval --wind 8 --deviation 0.5",
    "python3 -m venv .venv && . .venv/bin/activate && pip install -q -e '.[test]' && python -m pytest -q",
)
USER_WORD_BUDGET = 35_000
NUMBER = re.compile(r"(?<![\w.])-?\d+(?:\.\d+)?")


def _text(path: Path) -> str:
    return path.read_text(encoding="utf-8")


def _pages() -> list[Path]:
    return [ROOT / "README.md", *sorted(DOCS.rglob("*.md"))]


def _section(text: str, heading: str) -> str:
    """The text under the first heading that starts with `heading`, up to the next heading of its level."""
    match = re.search(rf"^(#+) {re.escape(heading)}.*$", text, re.M)
    assert match, f"no heading {heading!r}"
    level = len(match.group(1))
    rest = text[match.end() :]
    end = re.search(rf"^#{{1,{level}}} ", rest, re.M)
    return rest[: end.start()] if end else rest


def _rows(markdown: str) -> list[str]:
    """Table rows, without the header separators."""
    return [line for line in markdown.splitlines() if line.startswith("|") and not line.startswith("|---")]


def _slug(heading: str) -> str:
    """GitHub's anchor for a heading: lower case, punctuation dropped, spaces to hyphens."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def _report_rows(path: Path) -> dict[tuple[str, str], list[str]]:
    """A Table VIII style Markdown report's rows, keyed by (c, condition), as cell lists."""
    rows = {}
    for line in _rows(_text(path))[1:]:
        cells = [cell.strip() for cell in line.strip("|").split("|")]
        rows[(cells[0], cells[1])] = cells
    return rows


def test_readme_is_a_short_front_page():
    readme = _text(ROOT / "README.md")
    assert len(readme.splitlines()) <= 120
    assert "CI-HRL** (Consensus Inference-based Hierarchical Reinforcement Learning;" in " ".join(readme.split())
    for command in SET_UP:  # .ci/run and tests/test_readme_commands.py run these verbatim
        assert command in readme, command
    picture = re.search(r"!\[[^\]]*\]\(([^)]+\.png)\)", readme)
    assert picture and (ROOT / picture.group(1)).is_file()
    results = [line for line in _section(readme, "Results").splitlines() if line.strip()]
    assert len(results) <= 10, results
    assert "docs/results.md" in _section(readme, "Results")


def test_every_page_and_anchor_named_exists():
    """Links between pages, and every `docs/...md` path named in the pages or in the code, resolve."""
    missing = []
    for page in _pages():
        text = _text(page)
        for target, anchor in re.findall(r"\]\(([^)#\s]*)(#[^)\s]*)?\)", text):
            if target.startswith(("http://", "https://", "mailto:")):
                continue
            path = (page.parent / target).resolve() if target else page
            if not path.exists():
                missing.append(f"{page.relative_to(ROOT)}: {target}")
            elif anchor and path.suffix == ".md":
                headings = re.findall(r"^#+ (.*)$", _text(path), re.M)
                if anchor[1:] not in {_slug(h) for h in headings}:
                    missing.append(f"{page.relative_to(ROOT)}: {target}{anchor}")
    sources = [*_pages(), *sorted((ROOT / "cefc_mj").rglob("*.py")), *sorted((ROOT / "tests").glob("*.py"))]
    sources += [*sorted((ROOT / "benchmarks").glob("*.py")), *sorted((ROOT / "examples").glob("*.py"))]
    for source in sources:
        for path in set(re.findall(r"docs/(?:[\w-]+/)*[\w-]+\.md", _text(source))):
            if not (ROOT / path).is_file():
                missing.append(f"{source.relative_to(ROOT)}: {path}")
    assert not missing, missing


def test_docs_stand_alone():
    pattern = re.compile(r"\.\./shared|this machine|\bissues? #?\d+", re.I)
    found = [f"{page.relative_to(ROOT)}: {m.group(0)}" for page in _pages() for m in pattern.finditer(_text(page))]
    assert not found, found


def test_user_pages_fit_the_word_budget():
    """Everything outside docs/research/ is what a user reads; `wc -w` counts the same words."""
    words = sum(len(_text(page).split()) for page in DOCS.glob("*.md"))
    assert words <= USER_WORD_BUDGET, words


def test_results_table8_test_block_is_the_report():
    report = _rows(_text(REPORTS / "table8_test" / "table8_test.md"))
    section = _section(_text(DOCS / "results.md"), "Table VIII on quadrotors, test block")
    assert _rows(section) == report


def test_results_departures_quote_their_reports():
    """The two departures from the paper's agent, as docs/results.md quotes them, read from their reports."""
    section = " ".join(_section(_text(DOCS / "results.md"), "Table VIII on quadrotors, test block").split())
    acceleration = _report_rows(REPORTS / "acceleration" / "table8.md")
    wind8 = " / ".join(acceleration[(str(c), "Wind-8")][5] for c in (5, 6, 7, 8))
    assert f"Wind-8 retention is {wind8} for c = 5..8" in section
    raw = _report_rows(REPORTS / "raw" / "table8.md")
    for condition in ("Deviation-0.8", "Deviation-0.5"):
        collisions = " / ".join(raw[(str(c), condition)][4] for c in (5, 6, 7, 8))
        assert f"{collisions} %" in section, condition


def test_results_finetune_rows_and_counts_are_the_report():
    report = _rows(_text(REPORTS / "mujoco_ft" / "acceleration_paired.md"))
    section = _section(_text(DOCS / "results.md"), "Table VIII with the paper's agent")
    quoted = _rows(section)
    assert quoted[0] == report[0] and set(quoted[1:]) <= set(report[1:]) and len(quoted) > 10
    cells = [[cell.strip() for cell in row.strip("|").split("|")] for row in report[1:]]
    prose = " ".join(section.split())
    c_better = sum(row[6] == "better" for row in cells)
    c_worse = sum(row[6] == "worse" for row in cells)
    assert f"C is lower in {c_better} of the {len(cells)} cells of the grid and higher in none" in prose
    assert c_worse == 0
    windy = [row for row in cells if row[1] in ("Wind-3", "Wind-5")]
    worse = sum("(worse)" in row[4] for row in windy)
    assert f"worse in {worse} of the {len(windy)} cells" in prose and not any("(better)" in r[4] for r in windy)
    calm_f = [int(row[3].split(" ± ")[0]) for row in cells if row[1] == "SITL-S"]
    assert f"calm F {min(calm_f)}-{max(calm_f)}" in prose
    paper = json.loads(_text(ROOT / "eval" / "paper_tables.json"))["table8_sitl"]
    below = []
    for row in cells:
        if row[1] == "Deviation-0.8":
            ours = float(row[3].split(" / ")[2].split(" ± ")[0])
            theirs = paper[row[0]]["Deviation-0.8"][2]
            if ours < theirs:
                below.append((row[0], f"{ours:.3f} against {theirs:g}"))
    assert "at c = " + ", ".join(c for c, _ in below[:-1]) + f" and {below[-1][0]}" in prose
    assert "(" + ", ".join(pair for _, pair in below) + ")" in prose


def test_results_table3_is_the_report():
    result = json.loads(_text(REPORTS / "table3.json"))
    quoted = _rows(_section(_text(DOCS / "results.md"), "Table III in the particle world"))[1:]
    expected = []
    for c in ("6", "7", "8"):
        for method, row in result[c].items():
            paper = row["paper"]
            theirs = f"{paper['F']} / {paper['N']} / {paper['C']}" if paper else "-"
            cells = [f"{row[k]:.{p}f} ± {row[k + '_std']:.{p}f}" for k, p in (("F", 1), ("N", 1), ("C", 2))]
            expected.append(f"| {c} | {method} | {' | '.join(cells)} | {theirs} |")
    assert quoted == expected


def test_results_px4_exact_tables_are_the_report():
    """The PX4-interface section's two tables, rebuilt from px4_exact.json and the paper's cells."""
    from cefc_mj.eval.table8 import paper_cell

    cells = json.loads(_text(REPORTS / "px4_exact" / "px4_exact.json"))["cells"]
    quoted = _rows(_section(_text(DOCS / "results.md"), "Table VIII with the paper's agent on PX4's"))
    grids = ("nav", "mujoco", "push", "nav-push-3.5")
    expected = []
    for c in "5678":
        for cond in ("Wind-3", "Wind-5", "Wind-8"):
            kept = " | ".join(f"{cells[c][cond][g]['retention']:.1%}" for g in grids)
            expected.append(f"| {c} | {cond} | {kept} | {paper_cell(c, cond)['retention']:.1%} |")
    for c in "5678":
        push, bound, dev = (
            cells[c][k][g] for k, g in (("SITL-S", "push"), ("SITL-S", grids[3]), ("Deviation-0.8", grids[3]))
        )
        calm, paper_dev = paper_cell(c, "SITL-S"), paper_cell(c, "Deviation-0.8")
        expected.append(
            f"| {c} | {push['F']:.0f} / {push['N']:.0f} / {push['C']:.3f} | {bound['F']:.0f} / {bound['N']:.0f} / "
            f"{bound['C']:.3f} | {dev['C']:.3f} | {calm['F']:.0f} / {calm['N']:.0f}, {paper_dev['C']:.2f} |"
        )
    assert [row for row in quoted if row[2] in "5678"] == expected


def test_results_table5_decisions_quote_the_report():
    """Every decimal in the Table V section's prose is in the pre-registered report, or derived from
    it (or from the plan's pilot) as this test recomputes."""
    report = _text(REPORTS / "prereg" / "table5.md")
    section = _section(_text(DOCS / "results.md"), "Table V, the hierarchical game, pre-registered")
    prose = "\n".join(line for line in section.splitlines() if not line.startswith(("|", "cefc-eval", "    --")))
    cihrl_e = float(re.search(r"\| \*\*CI-HRL\*\* \| 20 \| ([\d.]+)", report).group(1))
    mappo_e = float(re.search(r"\| MAPPO\+AT-M \| 20 \| ([\d.]+)", report).group(1))
    paper_cihrl, paper_mappo = 4.46, 8.78
    assert f"| {paper_cihrl} / " in report and f"| {paper_mappo} / " in report
    derived = {
        f"{paper_mappo - paper_cihrl:.2f}": "the paper's gap in E",
        f"{cihrl_e / paper_cihrl:.1f}": "our CI-HRL's E over the paper's",
        f"{mappo_e / paper_mappo:.1f}": "our MAPPO's E over the paper's",
        f"{cihrl_e:.1f}": "CI-HRL's E",
        f"{mappo_e:.1f}": "MAPPO's E",
        "20.1": "core-hours of training, docs/research/preregistration.md",
    }
    plan = _text(DOCS / "research" / "preregistration.md")
    assert "pooled SD 1.69 s" in plan and "pooled SD 405.04" in plan and "20.1 core-hours" in plan
    derived |= {"1.69": "the plan's pilot SD of E", "405": "the plan's pilot SD of R_H"}
    reported = {n.lstrip("-+") for n in NUMBER.findall(report)}
    decimals = [n.lstrip("-") for n in re.findall(r"(?<![\w.])-?\d+\.\d+", prose)]
    unknown = [n for n in decimals if n not in reported and n not in derived]
    assert not unknown, unknown
    for number in ("1.81", "375", "1.65", "341", "2.65", "549", "899", "1194"):
        assert re.search(rf"(?<![\d.]){re.escape(number)}(?![\d])", report), number


def test_readme_results_summary_quotes_the_reports():
    summary = " ".join(_section(_text(ROOT / "README.md"), "Results").split())
    test_block = _report_rows(REPORTS / "table8_test" / "table8_test.md")
    by_c = {cells[0]: cells for cells in test_block.values()}
    wind = [float(by_c[c][7].split(" ± ")[0]) for c in "5678"]
    dev = [float(by_c[c][11].split(" ± ")[0]) for c in "5678"]
    assert f"keeps {min(wind)}-{max(wind)} % of its calm F+N at Wind-8 and {min(dev)}-{max(dev)} %" in summary
    paper = by_c["paper (c = 5..8)"]
    assert f"(paper: {paper[7].rstrip(' %')} % and {paper[11].rstrip(' %')} %)" in summary
    collisions = [by_c[c][i].split(" ± ")[0] for c in "5678" for i in (3, 6, 10)]
    assert f"C at most {max(collisions, key=float)} %" in summary and f"Deviation-0.8: {paper[10]})" in summary
    from cefc_mj.eval.table8 import paper_cell

    px4 = json.loads(_text(REPORTS / "px4_exact" / "px4_exact.json"))["cells"]

    def span(grid: str, cond: str, key: str = "retention", scale: float = 100, digits: int = 1) -> str:
        values = [px4[c][cond][grid][key] * scale for c in "5678"]
        return f"{min(values):.{digits}f}-{max(values):.{digits}f}"

    def paper_span(cond: str) -> str:
        values = [paper_cell(c, cond)["retention"] * 100 for c in "5678"]
        return f"{min(values):.1f}-{max(values):.1f}"

    assert (
        f"AT-M-Nav keeps {span('nav', 'Wind-3')} % of its calm F+N at Wind-3 and {span('nav', 'Wind-8')} %" in summary
    )
    assert f"keeps {span('push', 'Wind-3')} % at Wind-3 (paper {paper_span('Wind-3')} %)" in summary
    assert f"and {span('push', 'Wind-5')} % at Wind-5 (paper {paper_span('Wind-5')} %)" in summary
    assert f"keeps {span('nav-push-3.5', 'Wind-8')} % at Wind-8 (paper {paper_span('Wind-8')} %)" in summary
    dev = span("nav-push-3.5", "Deviation-0.8", "C", 1)
    assert f"(Deviation-0.8 C {dev} %, paper 1.2-3.0)" in summary
    table3 = json.loads(_text(REPORTS / "table3.json"))
    step3 = [table3[c]["AT-M-Step3"] for c in "678"]
    f_ours = [f"{row['F']:.1f}" for row in step3]
    f_paper = [row["paper"]["F"] for row in step3]
    c_ours = max(f"{row['C']:.2f}" for row in step3)
    assert f"AT-M Step 3 F {min(f_ours, key=float)}-{max(f_ours, key=float)}" in summary
    assert f"the paper's {min(f_paper)}-{max(f_paper)}, C at most {c_ours} %" in summary
    prereg = _text(REPORTS / "prereg" / "table5.md")
    difference = re.search(r"\| MAPPO\+AT-M \| 20 \|(?:[^|]*\|){4} ([-+\d.]+) s (\[[^]]+\])", prereg)
    assert f"undecided on E ({difference.group(1)} s {difference.group(2)})" in summary
    worse = len(re.findall(r"\| worse \|", _table5_markdown(prereg)))
    assert f"{['no', 'one', 'two', 'three', 'four'][worse]} rows are worse than CI-HRL on E" in summary
    sitl = _text(REPORTS / "table5_sitl_m" / "table5_sitl_m.md")
    share = re.search(r"mean R_t ([\d.]+) % of lock-step", sitl).group(1)
    assert f"R_t {share} % of the one-process game over 100 test games" in summary
    assert "100 game(s)" in sitl


def _table5_markdown(report: str) -> str:
    """The first Markdown table of a table5 report (the comparison against CI-HRL)."""
    lines = report.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith("| method"))
    end = next(i for i in range(start, len(lines)) if not lines[i].startswith("|"))
    return "\n".join(lines[start:end])


def test_results_adversary_order_row_is_the_report():
    """The exploratory adversary-order row quotes its report: who has the lower E against every
    adversary, the range of the E differences and that none survives Holm."""
    report = json.loads(_text(REPORTS / "exploratory" / "adversary_order" / "report.json"))
    row = next(line for line in _text(DOCS / "results.md").splitlines() if "adversary_order/report.md" in line)
    adversaries = report["adversaries"]
    assert len(adversaries) == 5 and "against all five" in row
    assert {a["lower_E"] for a in adversaries} == {"MAPPO+AT-M"} and "MAPPO+AT-M has the lower E" in row
    gaps = sorted(-a["difference"]["E"]["difference"] for a in adversaries)
    assert f"({gaps[0]:.2f}-{gaps[-1]:.2f} s)" in row
    holm = [a["difference"][m]["p_holm"] for a in adversaries for m in ("E", "R_H")]
    assert len(holm) == 10 and min(holm) >= 0.05 and "no difference survives Holm over the ten" in row
