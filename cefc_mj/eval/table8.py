"""The Table VIII protocol: every condition x c = 5..8 x K seeds, on a local process pool or a Ray
cluster (`cefc_mj.executors`, docs/scaling.md).

Finished episodes are appended to a JSON-lines cell file as they complete, so an interrupted run
keeps them and a re-run skips them. A cell is reused only under the same key: the SHA-256 of the
policy file of its c, the code digest (`cefc_mj.provenance.code_version`) and every field of its
`EpisodeSpec` (condition, steps, seed, formation, backend, ...), so a cache never serves a number
that other code, another policy or another condition produced. The report (`table8.md`), a CSV, a
JSON and a PNG of ours beside the paper's numbers are written atomically at the end.
"""

from __future__ import annotations

import csv
import dataclasses
import functools
import hashlib
import io
import json
import os
from collections.abc import Callable, Iterator
from contextlib import closing
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from cefc_mj import paths
from cefc_mj.errors import ConfigError
from cefc_mj.eval.runner import (
    CONDITIONS,
    HISTOGRAM_EDGES_MS,
    TABLE8_STEPS,
    EpisodeResult,
    EpisodeSpec,
    airframe_files,
    cell_flag,
    fault_lines,
    format_mean_std,
    load_policy_for,
    retention,
    run_episode,
    summarize,
)
from cefc_mj.executors import ExecutorConfig, map_unordered
from cefc_mj.fileio import write_atomic

PAPER_TABLES = paths.EVAL_DIR / "paper_tables.json"
TABLE8_ROWS = (*CONDITIONS, "SITL-M")
"""The rows of Table VIII: the 7 conditions of the one-process runner, and SITL-M (`--sitl-m`)."""
CELL_SCHEMA = 2
"""Version of the cell key; rows written under another schema (or none) are never reused."""


@functools.lru_cache(maxsize=1)
def _paper_table8_rows() -> dict:
    return json.loads(PAPER_TABLES.read_text())["table8_sitl"]


def paper_table8() -> dict[str, dict[str, dict[str, float]]]:
    """{"5": {"SITL-S": {"F":..,"N":..,"C":..}, ...}} from the shipped transcription of the paper."""
    raw = _paper_table8_rows()
    return {c: {cond: dict(zip("FNC", v)) for cond, v in rows.items()} for c, rows in raw.items() if c.isdigit()}


def table8_specs(
    formations,
    episodes: int,
    seed: int,
    steps: int,
    backend: str,
    policy: str,
    airframe: str = "iris",
    estimator: str = "fused",
    offboard: str = "velocity",
    guard: bool = True,
    wind_direction: float | None = None,
    rotor_actuation: str = "auto",
    accel_max: float | None = None,
    push_observer: float | None = None,
) -> list[EpisodeSpec]:
    """The grid, seeds seed .. seed+K-1 for every cell (the same layouts under every condition);
    `wind_direction` (degrees) points the Wind rows' wind (None: drawn per episode from the seed);
    `accel_max` the action bound and `push_observer` the agents' push observer (None: each policy's own)."""
    return [
        EpisodeSpec(
            formation=c,
            seed=seed + k,
            backend=backend,
            wind=wind,
            deviation=dev,
            steps=steps,
            policy=policy,
            airframe=airframe,
            estimator=estimator,
            offboard=offboard,
            guard=guard,
            wind_direction=wind_direction if wind else None,
            rotor_actuation=rotor_actuation,
            accel_max=accel_max,
            push_observer=push_observer,
        )
        for c in formations
        for name, (wind, dev) in CONDITIONS.items()
        for k in range(episodes)
    ]


# ---------------------------------------------------------------------------- the cell cache
@dataclass(frozen=True)
class Cell:
    """One episode of the grid with its cache key."""

    spec: EpisodeSpec
    """What to fly."""
    key: str
    """SHA-256 (hex) of `key_fields` as canonical JSON."""
    key_fields: dict
    """Everything the result depends on: schema, every EpisodeSpec field, policy sha256, code digest
    (and the SITL-M deployment settings for the SITL-M row)."""
    sitl: object = None
    """A `cefc_mj.deploy.SitlConfig` for the SITL-M row (every UAV's policy in its own process), else None."""


def cell_key_fields(spec: EpisodeSpec, policy_sha256: str, code_version: str, sitl=None) -> dict:
    """The inputs that determine an episode's result (the cell key is their digest)."""
    fields = {
        "schema": CELL_SCHEMA,
        "spec": asdict(spec),
        "policy_sha256": policy_sha256,
        "code_version": code_version,
        "airframe": airframe_files(spec),
    }
    if sitl is not None:
        fields["sitl"] = asdict(sitl)
    return fields


def plan_cells(specs: list[EpisodeSpec], policy_sha256: dict[int, str], code_version: str, sitl=None) -> list[Cell]:
    """Key every spec; `policy_sha256` maps each c to the SHA-256 of the policy file flown for it;
    `sitl` (a SitlConfig) makes them SITL-M cells."""
    cells = []
    for spec in specs:
        fields = cell_key_fields(spec, policy_sha256[spec.formation], code_version, sitl)
        key = hashlib.sha256(json.dumps(fields, sort_keys=True).encode()).hexdigest()
        cells.append(Cell(spec=spec, key=key, key_fields=fields, sitl=sitl))
    return cells


def load_cells(path: Path) -> dict[str, dict]:
    """Finished episodes from the cell file by key (a torn last line from a kill is ignored, and so is
    an episode with faults: it is not a result to reuse)."""
    done: dict[str, dict] = {}
    if not path.is_file():
        return done
    for line in path.read_text().splitlines():
        try:
            row = json.loads(line)
        except json.JSONDecodeError:
            continue
        if isinstance(row, dict) and "key" in row and not row.get("faults"):
            done[row["key"]] = row  # (a faulted episode stays in the file for the record but is flown again)
    return done


# ---------------------------------------------------------------------------- flying
@dataclass(frozen=True)
class RowRunners:
    """The episode runners of the rows the lock-step runner does not fly, given by the caller
    (`cefc-eval` passes `cefc_mj.deploy`'s), so that evaluation never imports the agent-process layer.
    Module-level functions, so that pool workers receive them by reference."""

    sitl: Callable | None = None
    """`run_sitl_episode(spec, sitl, record=...)`: SITL-M, every UAV's policy in its own process."""
    dropout: Callable | None = None
    """`run_dropout_episode(spec, drop, policy=...)`: lock-step, agents leaving mid-episode."""
    game: Callable | None = None
    """`run_sitl_game(GameSpec, sitl)`: the CI-HRL game, every UAV's hierarchy in its own process."""


def _runner(runners: RowRunners | None, row: str) -> Callable:
    run = getattr(runners, row, None)
    if run is None:
        raise ValueError(
            f"the {row} row needs runners=RowRunners({row}=...), cefc_mj.deploy's runner (as cefc-eval passes it)"
        )
    return run


@functools.lru_cache(maxsize=32)
def cached_policy(choice: str, formation: int):
    """The policy for (choice, c), loaded once per process (pool workers fly many episodes each)."""
    return load_policy_for(choice, formation)


def _fly(
    spec: EpisodeSpec,
    record: bool = False,
    sitl=None,
    drop: tuple[int, int] | None = None,
    runners: RowRunners | None = None,
):
    import torch

    torch.set_num_threads(1)
    if sitl is not None:  # SITL-M: every UAV's policy in its own process (cefc_mj/deploy)
        return _runner(runners, "sitl")(spec, sitl, record=record)
    if drop is not None:  # lock-step with agents leaving mid-episode
        return _runner(runners, "dropout")(spec, drop, policy=cached_policy(spec.policy, spec.formation))
    return run_episode(spec, cached_policy(spec.policy, spec.formation), record=record)


def warm_up_here(specs: list[EpisodeSpec]) -> None:
    """Fly a 2-step episode of `specs`' kinds (their largest wind and deviation) in this process before
    a local pool starts: on a cold numba cache it compiles the kernels once, and the workers load them,
    instead of every worker compiling the same kernels at once (tens of CPU-seconds each); warm, it
    costs one world build."""
    probe = dataclasses.replace(
        specs[0],
        steps=2,
        wind=max(s.wind for s in specs),
        wind_direction=None,
        deviation=max(s.deviation for s in specs),
    )
    _fly(probe)


def _fly_row(spec: EpisodeSpec, drop=None, runners: RowRunners | None = None) -> dict:
    return _fly(spec, drop=drop, runners=runners).to_dict()


def _fly_cell(cell: Cell) -> dict:
    """Fly a cell's episode wherever the executor runs it (this process, a pool worker, a Ray node),
    after checking that the code, policy file and airframe files there are the ones its key names:
    a Ray node with another installation would otherwise file its numbers under this machine's key."""
    from cefc_mj.eval.runner import policy_files
    from cefc_mj.provenance import code_version

    spec, expected = cell.spec, cell.key_fields
    here = {
        "code_version": code_version(),
        "policy_sha256": policy_files(spec.policy, [spec.formation])[str(spec.formation)]["sha256"],
        "airframe": airframe_files(spec),
    }
    what = {
        "code_version": f"cefc-mj code (digest {here['code_version']}, the command's {expected['code_version']})",
        "policy_sha256": f"policy file for {spec.policy} c = {spec.formation}",
        "airframe": "airframe files",
    }
    differ = [what[name] for name, value in here.items() if expected[name] != value]
    if differ:
        import platform

        raise ConfigError(
            f"{platform.node()} flies with other {' and other '.join(differ)} than the command that "
            "planned the cell: install the same cefc-mj and policy files on every node (docs/scaling.md)"
        )
    return _fly_row(spec)


@dataclass
class _PooledResult(EpisodeResult):
    """A result flown in a pool worker; `to_dict()` gives the worker's row as it was (a dropout's
    before/after report included)."""

    row: dict = field(default_factory=dict, repr=False)

    def faults(self) -> list[str]:
        return list(self.row.get("faults", super().faults()))

    def to_dict(self) -> dict:
        return dict(self.row)


def fly_episodes(
    specs: list[EpisodeSpec],
    workers: int = 1,
    record: Callable[[EpisodeSpec], bool] | None = None,
    sitl=None,
    drop: tuple[int, int] | None = None,
    runners: RowRunners | None = None,
) -> Iterator[tuple[int, object]]:
    """Fly `specs`, yielding (index into specs, EpisodeResult) as each finishes.

    `record(spec)` says which episodes keep an EpisodeRecord (workers = 1 only). workers > 1 uses a
    local process pool and yields results in completion order. Ctrl-C cancels the episodes not yet
    started. `sitl` (a SitlConfig) flies them as SITL-M, one after the other (each episode already runs
    c + 1 processes); `drop` = (k, step) removes k agents before that step (lock-step). Both fly with
    the episode runners of `runners`.
    """
    if sitl is not None or workers <= 1 or len(specs) <= 1:
        for i, spec in enumerate(specs):
            yield i, _fly(spec, record=bool(record and record(spec)), sitl=sitl, drop=drop, runners=runners)
        return
    if record is not None:
        raise ValueError("fly_episodes: recording needs workers = 1")
    warm_up_here(specs)
    index = {id(spec): i for i, spec in enumerate(specs)}
    fly_row = functools.partial(_fly_row, drop=drop, runners=runners)
    with closing(map_unordered(fly_row, specs, ExecutorConfig(workers=workers))) as rows:
        for spec, row in rows:
            yield (
                index[id(spec)],
                _PooledResult(
                    spec=spec, row=row, **{k: row[k] for k in ("F", "N", "C", "steps", "wall_s", "diverged")}
                ),
            )


def _torn_tail(path: Path) -> bool:
    """Whether the file ends without a newline (its last line was cut by a kill)."""
    with open(path, "rb") as fh:
        if fh.seek(0, os.SEEK_END) == 0:
            return False
        fh.seek(-1, os.SEEK_END)
        return fh.read(1) != b"\n"


def run_grid(
    cells: list[Cell],
    cell_file: Path,
    workers: int = 1,
    progress=None,
    fresh: bool = False,
    executor: ExecutorConfig | None = None,
    runners: RowRunners | None = None,
) -> list[dict]:
    """Fly the cells not yet in `cell_file` (all of them with `fresh`), appending each finished
    episode as one JSON line; returns the rows of all `cells` in order.

    `executor` says where the lock-step cells fly (default: a local pool of `workers` processes;
    `ExecutorConfig("ray", ...)`: Ray tasks), with the same cache, rows and resume either way.
    SITL-M cells always fly here, one at a time (each runs c + 1 processes and times them), with
    `runners.sitl`.
    `fresh` moves an existing cell file aside (to `<name>.replaced-<n>`) rather than deleting it.
    The folder is created here, right before the first write.
    """
    executor = executor or ExecutorConfig(workers=workers)
    cell_file.parent.mkdir(parents=True, exist_ok=True)
    if fresh and cell_file.exists():
        n = 1
        while (aside := cell_file.with_name(f"{cell_file.name}.replaced-{n}")).exists():
            n += 1
        cell_file.rename(aside)
    done = load_cells(cell_file)
    todo = [cell for cell in cells if cell.key not in done]
    if progress is not None:
        progress.update(len(cells) - len(todo))
    lockstep = [c for c in todo if c.sitl is None]
    sitl = [c for c in todo if c.sitl is not None]
    with open(cell_file, "a") as sink:
        if _torn_tail(cell_file):  # a kill mid-line: the next row starts on a line of its own, not glued to it
            sink.write("\n")

        def keep(cell: Cell, result: dict) -> None:
            row = {"key": cell.key, "key_fields": cell.key_fields, **result}
            done[cell.key] = row
            sink.write(json.dumps(row) + "\n")  # one whole line, on disk before the next episode is counted
            sink.flush()
            os.fsync(sink.fileno())
            if progress is not None:
                progress.update(1)

        # closing(): an error or Ctrl-C here stops the executor's jobs (and a Ray instance started for them) now
        with closing(map_unordered(_fly_cell, lockstep, executor)) as flown:
            for cell, result in flown:
                keep(cell, result)
        if sitl:
            with closing(fly_episodes([cell.spec for cell in sitl], sitl=sitl[0].sitl, runners=runners)) as flown:
                for i, result in flown:
                    keep(sitl[i], result.to_dict())
    return [done[cell.key] for cell in cells]


# ---------------------------------------------------------------------------- the table
def aggregate(rows: list[dict]) -> dict[str, dict[str, dict]]:
    """{c: {condition: summarize(...) + retention (vs SITL-S of the same c) + the episodes}}."""
    table: dict[str, dict[str, dict]] = {}
    for c in sorted({r["formation"] for r in rows}):
        table[str(c)] = {}
        for cond in TABLE8_ROWS:
            cell = [r for r in rows if r["formation"] == c and r["condition"] == cond]
            if cell:
                table[str(c)][cond] = {**summarize(cell), "episodes_detail": cell}
        calm = table[str(c)].get("SITL-S")
        for cell in table[str(c)].values():
            cell["retention"], cell["retention_note"] = retention(cell, calm)
    return table


def paper_cell(c: str, cond: str) -> dict | None:
    """The paper's F, N, C and retention for (c, condition), or None where it has no such cell."""
    paper = paper_table8()
    p, calm = paper.get(c, {}).get(cond), paper.get(c, {}).get("SITL-S")
    if p is None:
        return None
    return {**p, "retention": retention(p, calm)[0]}


def _steps_note(steps: int) -> str | None:
    if steps == TABLE8_STEPS:
        return None
    return (
        f"F, N over {steps} steps; the paper's are over {TABLE8_STEPS}: not comparable "
        "(C and retention are ratios and roughly comparable)"
    )


def _pct(value: float | None) -> str:
    return "-" if value is None else f"{value:.1%}"


def guard_text(record: dict) -> str:
    """How a run record's agents flew: ", separation guard", ", no separation guard", or "" for a
    record older than the guard (which flew without one)."""
    if "guard" not in record:
        return ""
    return ", separation guard" if record["guard"] else ", no separation guard"


def report_markdown(table: dict, meta: dict) -> str:
    """The Markdown report: ours (mean ± std over seeds) beside the paper, then provenance."""
    k = meta["episodes"]
    lines = [
        f"# Table VIII: policy `{meta['policy']}` on the {meta['backend']} backend"
        + (f" ({meta['airframe']} airframe)" if meta.get("airframe") else "")
        + ", "
        f"{meta.get('estimator', 'raw')} position estimate, {meta.get('offboard', 'velocity')} offboard setpoints"
        + (f", action bound {meta['accel_max']:g} m/s^2" if meta.get("accel_max") is not None else "")
        + (f", push observer {meta['push_observer']:g} s" if meta.get("push_observer") else "")
        + guard_text(meta),
        "",
        f"Command: `{meta['command']}`  ",
        f"{k} seed(s) per cell ({meta['seed']}..{meta['seed'] + k - 1}, the same layouts under every condition), "
        + (
            "the Wind rows' direction drawn per episode from the seed, "
            if meta.get("wind_direction") is None
            else f"the Wind rows' wind blowing towards {meta['wind_direction']:g}° (ENU), "
        )
        + f"{meta['steps']} decision steps per episode. F, N: decision steps in formation / with the swarm centre "
        "within 1 m of the anchor; C: % of agent-steps in collision; retention = (F+N) / (F+N at SITL-S, same c). "
        + ("Ours: mean ± sample std over seeds." if k > 1 else "Ours: one seed per cell, no spread."),
        "",
    ]
    note = _steps_note(meta["steps"])
    if note:
        lines += [f"**{note}.**", ""]
    lines += [
        f"{meta['cells_reused']} of {meta['cells_total']} episodes were reused from the cell file "
        f"`{meta['cell_file']}` (same policy file, code and conditions); the rest were flown by this command.",
        "",
        (
            "SITL-M: every UAV's policy in its own process over ZeroMQ, asynchronous (docs/sitl_m.md); its "
            "retention divides by SITL-S of the same seeds."
            if any("SITL-M" in rows for rows in table.values())
            else "SITL-M (every UAV's policy in its own process) is left out: add --sitl-m to fly its row."
        ),
        "",
        "| c | condition | F | N | C (%) | retention | paper F | paper N | paper C (%) | paper retention |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    notes: set[str] = set()
    for c, rows in table.items():
        for cond, cell in rows.items():
            p = paper_cell(c, cond)
            ret = _pct(cell["retention"])
            if cell["retention"] is None:
                notes.add(f"retention -: {cell['retention_note']}")
            lines.append(
                f"| {c} | {cond}{cell_flag(cell)} | {format_mean_std(cell['F'], cell['F_std'])} | "
                f"{format_mean_std(cell['N'], cell['N_std'])} | {format_mean_std(cell['C'], cell['C_std'], '.2f')} | "
                f"{ret} | "
                + (f"{p['F']:.1f} | {p['N']:.1f} | {p['C']:.2f} | {_pct(p['retention'])} |" if p else "- | - | - | - |")
            )
            if p is None:
                notes.add(f"paper -: the paper has no Table VIII row for c = {c}")
    if notes:
        lines += [""] + [f"- {n}" for n in sorted(notes)]
    faults = fault_lines(table)
    if faults:
        lines += ["", "**Not a measurement**: these episodes lost agents, failed safe or diverged:", ""]
        lines += [f"- {line}" for line in faults]
    lines += sitl_timing_lines(table)
    prov = meta["provenance"]
    lines += [
        "",
        "## Provenance",
        "",
        f"- git commit: `{prov['git_commit'] or 'none (not a git checkout)'}`",
        f"- code digest: `{prov['code_version']}`",
    ]
    lines += [
        f"- {name}: {version or '(unset)'}"
        for name, version in prov["library_versions"].items()
        if name != "code_version"
    ]
    lines += [f"- policy c = {c}: `{p['name']}` sha256 `{p['sha256']}`" for c, p in prov["policies"].items()]
    return "\n".join(lines) + "\n"


def report_csv(table: dict) -> str:
    """One row per (c, condition): ours (mean, std) and the paper's numbers; empty where undefined."""

    def num(value, fmt):
        return "" if value is None else format(value, fmt)

    out = io.StringIO()
    writer = csv.writer(out)
    writer.writerow(
        [
            "c",
            "condition",
            "episodes",
            "diverged",
            "F_mean",
            "F_std",
            "N_mean",
            "N_std",
            "C_mean",
            "C_std",
            "retention",
            "paper_F",
            "paper_N",
            "paper_C",
            "paper_retention",
        ]
    )
    for c, rows in table.items():
        for cond, cell in rows.items():
            p = paper_cell(c, cond) or {}
            writer.writerow(
                [
                    c,
                    cond,
                    cell["episodes"],
                    cell["diverged"],
                    num(cell["F"], ".3f"),
                    num(cell["F_std"], ".3f"),
                    num(cell["N"], ".3f"),
                    num(cell["N_std"], ".3f"),
                    num(cell["C"], ".4f"),
                    num(cell["C_std"], ".4f"),
                    num(cell["retention"], ".4f"),
                    num(p.get("F"), "g"),
                    num(p.get("N"), "g"),
                    num(p.get("C"), "g"),
                    num(p.get("retention"), ".4f"),
                ]
            )
    return out.getvalue()


def report_json(table: dict, meta: dict) -> str:
    """The full result: meta, provenance, per cell mean/std, the paper's cell and every episode."""
    rows = {
        c: {cond: {**cell, "paper": paper_cell(c, cond)} for cond, cell in conds.items()} for c, conds in table.items()
    }
    return (
        json.dumps(
            {
                "schema": "cefc-eval/table8",
                "schema_version": 2,
                "protocol": "table8",
                **meta,
                "comparable_to_paper": meta["steps"] == TABLE8_STEPS,
                "rows": rows,
            },
            indent=2,
        )
        + "\n"
    )


def report_plot(table: dict, path: Path, meta: dict) -> None:
    """F+N (top) and C (bottom) per condition and c, ours (mean, error bar = std over seeds) beside the paper's."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    paper = paper_table8()
    conds = [k for k in TABLE8_ROWS if any(k in rows for rows in table.values())]
    x = np.arange(len(conds))
    comparable = meta["steps"] == TABLE8_STEPS
    fig, axes = plt.subplots(2, len(table), figsize=(max(7.0, 4.2 * len(table)), 7.4), squeeze=False, sharey="row")

    def val(v):
        return np.nan if v is None else v

    for col, (c, rows) in enumerate(table.items()):
        for row, (metric, label) in enumerate((("FN", "F + N (steps)"), ("C", "C (% agent-steps in collision)"))):
            ax = axes[row][col]
            ours = [val(rows[k][metric]) if k in rows else np.nan for k in conds]
            err = [val(rows[k][f"{metric}_std"]) if k in rows else np.nan for k in conds]
            ref = paper.get(c, {})
            theirs = [
                (ref[k]["F"] + ref[k]["N"] if metric == "FN" else ref[k]["C"]) if k in ref else np.nan for k in conds
            ]
            ax.bar(x - 0.2, ours, 0.4, yerr=np.nan_to_num(err), capsize=2, label=f"ours ({meta['backend']})")
            if metric == "C" or comparable:  # F+N of a shorter run beside the paper's 1000 steps would mislead
                ax.bar(x + 0.2, theirs, 0.4, label="paper (Gazebo+PX4)", color="tab:orange")
            ax.set_xticks(x, conds if row == 1 else [""] * len(conds), rotation=60, ha="right", fontsize=8)
            if row == 0:
                ax.set_title(f"c = {c}")
            if col == 0:
                ax.set_ylabel(label)
    handles, labels = axes[1][0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=2, fontsize=8)
    k = meta["episodes"]
    title = f"Table VIII, policy {meta['policy']} ({meta['backend']})\n{k} seed(s) per cell, {meta['steps']} steps" + (
        "; error bars: std over seeds" if k > 1 else ""
    )
    if not comparable:
        title += f"\nF+N over {meta['steps']} steps, not comparable to the paper's {TABLE8_STEPS}: paper F+N not drawn"
    fig.suptitle(title, fontsize=10)
    fig.tight_layout(rect=(0, 0.04, 1, 1))
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)
    write_atomic(path, buf.getvalue())


# ---------------------------------------------------------------------------- SITL-M timing
SITL_TIMINGS = {
    "decision_latency_ms": "decision latency (agent's own, wall ms)",
    "round_trip_ms": "round trip (simulator, wall ms)",
    "command_age_ms": "command age when applied (simulated ms)",
}


def _sitl_episodes(table: dict) -> dict[str, list[dict]]:
    return {
        c: [e["sitl"] for e in rows["SITL-M"]["episodes_detail"] if e.get("sitl")]
        for c, rows in table.items()
        if "SITL-M" in rows
    }


def sitl_timing_lines(table: dict) -> list[str]:
    """Markdown lines: per c, the SITL-M timings (median over episodes of each episode's p50, worst p99)."""
    episodes = {c: e for c, e in _sitl_episodes(table).items() if e}
    if not episodes:
        return []
    lines = [
        "",
        "## SITL-M timing",
        "",
        "Per c over its SITL-M episodes: median of the episodes' p50, and the worst p99 "
        "(histograms: `table8_sitl.png`).",
        "",
        "| c | " + " | ".join(f"{label} p50 / p99" for label in SITL_TIMINGS.values()) + " | real time | faults |",
        "|---|" + "---|" * (len(SITL_TIMINGS) + 2),
    ]
    for c, eps in episodes.items():
        cells = []
        for name in SITL_TIMINGS:
            p50 = [e[name]["all"]["p50"] for e in eps if e[name]["all"]["p50"] is not None]
            p99 = [e[name]["all"]["p99"] for e in eps if e[name]["all"]["p99"] is not None]
            cells.append(f"{np.median(p50):.2f} / {max(p99):.2f}" if p50 else "-")
        rtf = np.mean([e["real_time_factor"] for e in eps])
        cells += [f"{rtf:.1f}x", str(sum(len(e["events"]) for e in eps))]
        lines.append(f"| {c} | " + " | ".join(cells) + " |")
    return lines


def report_sitl_histograms(table: dict, path: Path) -> bool:
    """Histograms of the SITL-M timings per c (counts summed over episodes); False if there is no SITL-M row."""
    episodes = {c: e for c, e in _sitl_episodes(table).items() if e}
    if not episodes:
        return False
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(SITL_TIMINGS), figsize=(5.0 * len(SITL_TIMINGS), 3.6), squeeze=False)
    edges = HISTOGRAM_EDGES_MS
    for ax, (name, label) in zip(axes[0], SITL_TIMINGS.items()):
        for c, eps in episodes.items():
            counts = np.sum([e[name]["histogram"] for e in eps], axis=0)
            ax.stairs(counts, np.maximum(edges, edges[1] / 2), label=f"c = {c}")
        ax.set_xscale("log")
        ax.set_xlabel(label)
        ax.set_ylabel("count")
    axes[0][0].legend(fontsize=8)
    fig.suptitle("SITL-M timings, all agents and episodes", fontsize=10)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)
    write_atomic(path, buf.getvalue())
    return True
