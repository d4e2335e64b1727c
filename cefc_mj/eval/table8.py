"""The Table VIII protocol: every condition x c = 5..8 x K seeds, on a local process pool.

Finished episodes are appended to a JSON-lines cell file as they complete, so an interrupted run
keeps them and a re-run skips them. The report (`table8.md`), a CSV and a PNG of ours beside the
paper's numbers are written atomically at the end.
"""

from __future__ import annotations

import csv
import io
import json
import os
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

import numpy as np

from cefc_mj import paths
from cefc_mj.fileio import write_atomic
from cefc_mj.eval.runner import CONDITIONS, EpisodeSpec, run_episode, summarize

PAPER_TABLES = paths.EVAL_DIR / "paper_tables.json"


def paper_table8() -> dict[str, dict[str, dict[str, float]]]:
    """{"5": {"SITL-S": {"F":..,"N":..,"C":..}, ...}} from the shipped transcription of the paper."""
    raw = json.loads(PAPER_TABLES.read_text())["table8_sitl"]
    return {c: {cond: dict(zip("FNC", v)) for cond, v in rows.items()} for c, rows in raw.items() if c.isdigit()}


def table8_specs(formations, episodes: int, seed: int, steps: int, backend: str, policy: str) -> list[EpisodeSpec]:
    """The grid, seeds seed .. seed+K-1 for every cell (the same layouts under every condition)."""
    return [
        EpisodeSpec(formation=c, seed=seed + k, backend=backend, wind=wind, deviation=dev, steps=steps, policy=policy)
        for c in formations
        for name, (wind, dev) in CONDITIONS.items()
        for k in range(episodes)
    ]


def spec_key(spec: EpisodeSpec) -> str:
    return json.dumps({k: getattr(spec, k) for k in ("formation", "seed", "backend", "wind", "deviation", "steps", "policy")}, sort_keys=True)


def load_cells(path: Path) -> dict[str, dict]:
    """Finished episodes from the cell file (a torn last line from a kill is ignored)."""
    done: dict[str, dict] = {}
    if not path.is_file():
        return done
    for line in path.read_text().splitlines():
        try:
            row = json.loads(line)
        except json.JSONDecodeError:
            continue
        done[row["key"]] = row
    return done


def _run_spec(spec: EpisodeSpec) -> dict:
    result = run_episode(spec)
    return {"key": spec_key(spec), **result.to_dict()}


def run_grid(specs: list[EpisodeSpec], cell_file: Path, workers: int = 1, progress=None) -> list[dict]:
    """Run the specs not yet in `cell_file`, appending each finished episode; returns all rows."""
    cell_file.parent.mkdir(parents=True, exist_ok=True)
    done = load_cells(cell_file)
    todo = [s for s in specs if spec_key(s) not in done]
    if progress is not None:
        progress.update(len(specs) - len(todo))
    with open(cell_file, "a") as sink:
        def keep(row: dict) -> None:
            done[row["key"]] = row
            sink.write(json.dumps(row) + "\n")
            sink.flush()
            os.fsync(sink.fileno())
            if progress is not None:
                progress.update(1)

        if workers <= 1:
            for spec in todo:
                keep(_run_spec(spec))
        else:
            with ProcessPoolExecutor(max_workers=workers) as pool:
                futures = [pool.submit(_run_spec, s) for s in todo]
                try:
                    for future in as_completed(futures):
                        keep(future.result())
                except KeyboardInterrupt:
                    for f in futures:
                        f.cancel()
                    raise
    return [done[spec_key(s)] for s in specs if spec_key(s) in done]


def aggregate(rows: list[dict]) -> dict[str, dict[str, dict[str, float]]]:
    """{c: {condition: {F, N, C, episodes}}} averaged over seeds."""
    table: dict[str, dict[str, dict[str, float]]] = {}
    for c in sorted({r["formation"] for r in rows}):
        table[str(c)] = {}
        for cond in CONDITIONS:
            cell = [r for r in rows if r["formation"] == c and r["condition"] == cond]
            if cell:
                table[str(c)][cond] = summarize(cell)
    return table


def retention(table: dict, c: str, cond: str) -> float:
    """(F + N) of a condition relative to the calm condition of the same c."""
    calm, cell = table[c].get("SITL-S"), table[c].get(cond)
    if not calm or not cell or calm["F"] + calm["N"] == 0:
        return float("nan")
    return (cell["F"] + cell["N"]) / (calm["F"] + calm["N"])


def report_markdown(table: dict, meta: dict) -> str:
    paper = paper_table8()
    lines = [
        "# Table VIII on MuJoCo quadrotors",
        "",
        f"Command: `{meta['command']}`  ",
        f"Backend {meta['backend']}, policy `{meta['policy']}`, {meta['episodes']} seeds per cell "
        f"({meta['seed']}..{meta['seed'] + meta['episodes'] - 1}), {meta['steps']} decision steps per episode. "
        "F, N in decision steps; C in % of agent-steps in collision; retention = (F+N) / (F+N at SITL-S).",
        "",
        "SITL-M (agents as separate processes) is not part of this testbed yet: its row is left out.",
        "",
        "| c | condition | F | N | C (%) | retention | paper F | paper N | paper C (%) | paper retention |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for c, rows in table.items():
        for cond, cell in rows.items():
            p = paper.get(c, {}).get(cond)
            p_calm = paper.get(c, {}).get("SITL-S")
            p_ret = (p["F"] + p["N"]) / (p_calm["F"] + p_calm["N"]) if p and p_calm else float("nan")
            lines.append(
                f"| {c} | {cond} | {cell['F']:.1f} | {cell['N']:.1f} | {cell['C']:.2f} | {retention(table, c, cond):.1%} | "
                + (f"{p['F']:.1f} | {p['N']:.1f} | {p['C']:.2f} | {p_ret:.1%} |" if p else "- | - | - | - |")
            )
    return "\n".join(lines) + "\n"


def report_csv(table: dict) -> str:
    out = io.StringIO()
    writer = csv.writer(out)
    writer.writerow(["c", "condition", "F", "N", "C", "retention", "episodes"])
    for c, rows in table.items():
        for cond, cell in rows.items():
            writer.writerow([c, cond, f"{cell['F']:.3f}", f"{cell['N']:.3f}", f"{cell['C']:.4f}",
                             f"{retention(table, c, cond):.4f}", cell["episodes"]])
    return out.getvalue()


def report_plot(table: dict, path: Path) -> None:
    """Bars of F+N per condition and c, ours beside the paper's."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    paper = paper_table8()
    conds = list(CONDITIONS)
    fig, axes = plt.subplots(1, len(table), figsize=(4.2 * len(table), 3.8), squeeze=False, sharey=True)
    x = np.arange(len(conds))
    for ax, (c, rows) in zip(axes[0], table.items()):
        ours = [rows[k]["F"] + rows[k]["N"] if k in rows else np.nan for k in conds]
        theirs = [paper[c][k]["F"] + paper[c][k]["N"] if c in paper and k in paper[c] else np.nan for k in conds]
        ax.bar(x - 0.2, ours, 0.4, label="ours (MuJoCo)")
        ax.bar(x + 0.2, theirs, 0.4, label="paper (Gazebo+PX4)")
        ax.set_xticks(x, conds, rotation=60, ha="right", fontsize=8)
        ax.set_title(f"c = {c}")
        ax.set_ylabel("F + N (steps)")
    axes[0][0].legend(fontsize=8)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)
    write_atomic(path, buf.getvalue())
