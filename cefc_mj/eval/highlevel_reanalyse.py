"""Re-analyse a Table V report from the per-seed figures it holds, without flying a game:

    python -m cefc_mj.eval.highlevel_reanalyse eval/reports/prereg/table5.json

recomputes its statistics (`highlevel_comparison.add_comparisons`) with this code and writes the report's
JSON (its flight's protocol and provenance kept, the re-analysis recorded under "reanalysis"), Markdown
and figure again. The test ledger is not touched: nothing is flown.
"""

from __future__ import annotations

from pathlib import Path

from cefc_mj.eval.highlevel_report import format_highlevel_table, plot_highlevel_table, report_markdown


def main(argv: list[str] | None = None) -> int:
    """python -m cefc_mj.eval.highlevel_reanalyse REPORT.json: re-analyse a Table V report from the per-seed
    figures it holds (`add_comparisons`) and write it again with its .md and .png beside it (or into
    --report-dir); no game is flown and the test ledger is not touched."""
    import json
    import shlex
    import sys

    from cefc_mj import fileio
    from cefc_mj.errors import CefcError, OneLineParser
    from cefc_mj.eval.highlevel_comparison import add_comparisons
    from cefc_mj.provenance import display_path, git_commit

    parser = OneLineParser(
        prog="python -m cefc_mj.eval.highlevel_reanalyse", description=main.__doc__.splitlines()[0].split(": ", 1)[1]
    )
    parser.add_argument("report", type=Path, help="a Table V report (table5.json of cefc-eval --protocol table5)")
    parser.add_argument("--report-dir", type=Path, default=None, help="where to write (default: the report's folder)")
    args = parser.parse_args(argv)
    out = args.report_dir if args.report_dir is not None else args.report.parent
    try:
        result = json.loads(args.report.read_text())
        schema = result.get("schema") if isinstance(result, dict) else None
        if schema != "cefc-eval/table5":
            raise ValueError(f"schema {schema!r}: not a Table V report")
        if not any("training_seeds" in row for row in result["rows"].values()):
            raise ValueError("no row over training seeds: nothing to re-analyse")
        if not out.is_dir():
            raise ValueError(f"--report-dir {out}: not a folder")
    except (OSError, ValueError, KeyError) as e:
        print(f"{parser.prog}: error: {args.report}: {e}", file=sys.stderr)
        return 2
    add_comparisons(result)
    argv_text = " ".join(shlex.quote(str(a)) for a in (argv if argv is not None else sys.argv[1:]))
    result["reanalysis"] = {"command": f"{parser.prog} {argv_text}".strip(), "git_commit": git_commit()}
    text = format_highlevel_table(result)
    try:
        fileio.write_atomic(out / "table5.json", json.dumps(result, indent=2) + "\n")
        fileio.write_atomic(out / "table5.md", report_markdown(result, text))
        plot_highlevel_table(result, out / "table5.png")
    except (OSError, CefcError) as e:
        print(f"{parser.prog}: error: could not write into {out}: {e}", file=sys.stderr)
        return 1
    for name in ("table5.json", "table5.md", "table5.png"):
        print(f"wrote {display_path(out / name)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
