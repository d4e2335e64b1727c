"""cefc-eval --protocol single: one condition (wind and/or sensing deviation) against calm air, per
formation size c and seed, in one process, on a local pool, as SITL-M or with agent dropout; the
paper's Table VIII rows beside ours, optional JSON and recordings (Rerun, PNG)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
from tqdm import tqdm

from cefc_mj.cli.eval_common import (
    EXIT_INTERRUPTED,
    PROG,
    deploy_runners,
    report_faults,
    rotor_text,
    sitl_config,
    wind_direction_text,
    write_outputs,
)
from cefc_mj.eval.ledger import check_before_flight, record_if_test
from cefc_mj.eval.requests import SINGLE_EPISODES, SingleRequest
from cefc_mj.eval.runner import (
    TABLE8_STEPS as PAPER_STEPS,
    EpisodeSpec,
    cell_flag,
    condition_name,
    fault_lines,
    format_mean_std,
    provenance,
    retention,
    summarize,
)
from cefc_mj.eval.table8 import cached_policy, fly_episodes, guard_text, paper_cell


def check(request: SingleRequest) -> dict:
    """Before anything flies: a viewer to stream to (--spawn), and the policy file of every c, resolved,
    hashed and loaded (a missing or misfit checkpoint fails here). Returns the run's provenance."""
    if request.spawn:
        from cefc_mj.viz.rerun_log import check_spawn_possible  # imports rerun

        check_spawn_possible()
    prov = provenance(request.policy, request.formations)
    for c in request.formations:
        cached_policy(request.policy, c)
    check_before_flight("single", request.seed, request.episodes)  # a damaged test ledger: refused here
    return prov


def run(request: SingleRequest, prov: dict, command: str) -> int:
    """Fly the asked condition's episodes, then calm air's (the retention reference), and print the
    table; 0, or 130 when interrupted (the table then holds the finished episodes)."""
    where, flight = request.conditions, request.flight
    formations, episodes, steps = request.formations, request.episodes, request.steps
    sitl = sitl_config(request.sitl, request.drop)
    base = condition_name(where.wind, where.deviation)
    # SITL-M flies the asked condition with one process per UAV; the calm reference stays one process.
    condition = base if sitl is None else ("SITL-M" if base == "SITL-S" else f"SITL-M+{base}")
    conditions = [(where.wind, where.deviation)] + ([(0.0, 0.0)] if condition != "SITL-S" else [])
    seeds = list(range(request.seed, request.seed + episodes))
    specs = [
        EpisodeSpec(
            formation=c,
            seed=seed,
            backend=where.backend,
            wind=wind,
            deviation=dev,
            steps=steps,
            policy=request.policy,
            airframe=flight.airframe,
            estimator=flight.estimator,
            offboard=flight.offboard,
            guard=flight.guard,
            wind_direction=where.wind_direction if wind else None,
            rotor_actuation=flight.rotor_actuation,
            accel_max=flight.accel_max,
            push_observer=flight.push_observer,
        )
        for wind, dev in conditions
        for c in formations
        for seed in seeds
    ]
    asked = list(range(len(formations) * len(seeds)))  # the first condition's episodes
    calm = list(range(len(asked), len(specs)))
    # (indices into specs, how they fly): the asked condition carries the deployment, the dropout and
    # the recording; without them both conditions fly as one batch, on one pool (started once)
    if sitl is None and request.drop is None and not request.recording:
        batches = [(asked + calm, {})]
    else:
        batches = [
            (
                asked,
                {
                    "sitl": sitl,
                    "drop": None if sitl is not None else request.drop,
                    "runners": deploy_runners(sitl is not None, request.drop is not None),
                },
            ),
            (calm, {}),
        ]
    wind = {"wind": where.wind, "wind_direction": where.wind_direction}
    vs = " vs calm air (SITL-S)" if condition != "SITL-S" else ""
    world = (
        f"mujoco ({flight.airframe} airframe{wind_direction_text(wind)}, rotors "
        f"{rotor_text(flight.rotor_actuation, formations)})"
        if where.backend == "mujoco"
        else where.backend
    )
    print(
        f"{PROG}: {condition}{vs}; policy {request.policy}; {world}; c = {', '.join(map(str, formations))}; "
        f"seeds {_seed_range(seeds)} ({episodes} per cell); {steps} steps per episode; {len(specs)} episodes"
        + (f" on {request.workers} workers" if request.workers > 1 else "")
    )
    finished: dict[int, dict] = {}
    recorded: list[Path] = []
    interrupted = False
    try:
        with tqdm(total=len(specs), desc="episodes", unit="ep", file=sys.stderr) as bar:
            for indices, how in batches:
                record = (lambda s: True) if request.recording and indices is asked else None
                for j, result in fly_episodes(
                    [specs[i] for i in indices], workers=request.workers, record=record, **how
                ):
                    i = indices[j]
                    if result.record is not None:
                        recorded += _emit_record(result.record, request, many=len(formations) * episodes > 1)
                    finished[i] = result.to_dict()
                    bar.update(1)
    except KeyboardInterrupt:
        interrupted = True
        print(
            f"\n{PROG}: interrupted after {len(finished)} of {len(specs)} episodes; the table below holds "
            "the finished ones",
            file=sys.stderr,
        )
    rows_by_cell: dict[str, dict[str, list]] = {str(c): {} for c in formations}
    for i in sorted(finished):
        row = finished[i]
        rows_by_cell[str(row["formation"])].setdefault(row["condition"], []).append(row)
    table: dict[str, dict] = {}
    for c, conds in rows_by_cell.items():
        table[c] = {cond: {**summarize(rows), "episodes_detail": rows} for cond, rows in conds.items()}
        for cond, cell in table[c].items():
            cell["retention"], cell["retention_note"] = retention(cell, table[c].get("SITL-S"))
            cell["paper"] = paper_cell(c, cond)
    summary = {
        "schema": "cefc-eval/single",
        "schema_version": 2,
        "protocol": "single",
        "command": command,
        "complete": not interrupted,
        "backend": where.backend,
        "policy": request.policy,
        "estimator": flight.estimator,
        "offboard": flight.offboard,
        "accel_max": flight.accel_max,
        "push_observer": flight.push_observer,
        "guard": flight.guard,
        "airframe": flight.airframe,
        "rotor_actuation": flight.rotor_actuation,
        "wind_direction": where.wind_direction if where.wind else None,
        "condition": condition,
        "wind": where.wind,
        "deviation": where.deviation,
        "steps": steps,
        "seeds": seeds,
        "comparable_to_paper": steps == PAPER_STEPS,
        "provenance": prov,
        "rows": table,
    }
    print(single_table(summary))
    for line in _sitl_and_dropout_lines(table, condition):
        print(line)
    record_if_test("single", request.seed, episodes, command, prov, (request.json,))
    write_outputs([(request.json, json.dumps(summary, indent=2) + "\n")] if request.json is not None else [])
    for path in recorded:
        print(f"wrote {path}" + (f"  (open with: rerun {path})" if path.suffix == ".rrd" else ""))
    if request.json is None:
        print("the table above is not saved: --json PATH writes it (and every episode's numbers) to a file")
    faulted = report_faults(fault_lines(table), "--drop" if request.drop is not None else None)
    return EXIT_INTERRUPTED if interrupted else faulted


# ---------------------------------------------------------------------------- the table
def single_table(summary: dict) -> str:
    """The single protocol's table: per c, our condition and calm rows, then the paper's rows, every
    column labelled; mean ± std over seeds; '-' with its reason where a value is undefined."""
    cond, steps = summary["condition"], summary["steps"]
    components = [n for n in cond.split("+") if n != "SITL-S"]
    lines = [
        "",
        f"Table VIII metrics, condition {cond}" + (" vs calm air (SITL-S)" if components else ""),
        (
            f"  F = decision steps in formation, N = decision steps with the swarm centre within 1 m of the anchor "
            f"(each out of {steps}),"
        ),
        "  C = % of agent-steps in collision, retention = (F+N) / (F+N of the calm row above it: same c, same seeds).",
        f"  ours: {summary['backend']}"
        + (
            f" ({summary.get('airframe', 'iris')} airframe, rotors {summary.get('rotor_actuation', 'auto')}"
            f"{wind_direction_text(summary)})"
            if summary["backend"] == "mujoco"
            else ""
        )
        + f", policy {summary['policy']}, "
        f"{summary.get('estimator', 'raw')} position estimate"
        + guard_text(summary)
        + (f", {summary.get('offboard', 'velocity')} offboard setpoints" if summary["backend"] == "mujoco" else "")
        + "; paper: its Table VIII (Gazebo + PX4 SITL, 1000 steps).",
        seeds_line(summary),
    ]
    if steps != PAPER_STEPS:
        lines.append(f"  NOTE: F, N over {steps} steps; the paper's are over {PAPER_STEPS}: not comparable.")
    header = ["c", "source", "condition", "F", "N", "F+N", "C (%)", "retention"]
    rows = [header]
    notes: list[str] = []

    def add(c, source, name, cell, ret, note):
        if ret is None and note:
            notes.append(f"c = {c} {source} {name}: retention - ({note})")
        rows.append(
            [
                c,
                source,
                name,
                format_mean_std(cell.get("F"), cell.get("F_std")),
                format_mean_std(cell.get("N"), cell.get("N_std")),
                format_mean_std(cell.get("FN", _fn(cell)), cell.get("FN_std")),
                format_mean_std(cell.get("C"), cell.get("C_std"), ".2f"),
                "-" if ret is None else f"{ret:.1%}",
            ]
        )

    for c, cells in summary["rows"].items():
        if not cells:
            rows.append([c, "ours", cond, "-", "-", "-", "-", "-"])
            notes.append(f"c = {c}: no finished episode")
            continue
        calm = cells.get("SITL-S")
        if components and cond in cells:
            cell = cells[cond]
            add(c, "ours", cond + cell_flag(cell), cell, cell["retention"], cell["retention_note"])
        if calm:
            ret, note = cells["SITL-S"]["retention"], cells["SITL-S"]["retention_note"]
            add(c, "ours", "SITL-S" + (" (calm reference)" if components else "") + cell_flag(calm), calm, ret, note)
        names = ["SITL-S"] + components
        found = False
        for name in names:
            p = paper_cell(c, name)
            if p is not None:
                found = True
                add(c, "paper", name, p, p["retention"], None)
        if not found:
            notes.append(f"c = {c}: the paper has no Table VIII row for this c")
    if len(components) > 1:
        notes.append(f"the paper has no combined {cond} condition: its {' and '.join(components)} rows are shown")
    lines += _render(rows, right={0, 3, 4, 5, 6, 7})
    lines += [f"  {n}" for n in dict.fromkeys(notes)]
    return "\n".join(lines)


def seeds_line(summary: dict) -> str:
    """The line saying how many seeds stand behind each of our cells: the mean ± sample std over K
    seeds, or, for one seed, that it is one layout and not a measurement; cells an interruption left
    with fewer are named."""
    seeds = summary["seeds"]
    k = len(seeds)
    if k == 1:
        return (
            f"  seeds: our cells are ONE seed ({seeds[0]}), one layout of obstacles and anchors: NOT A "
            f"MEASUREMENT of the policy (layouts differ widely); --episodes {SINGLE_EPISODES} or more gives "
            "mean ± std."
        )
    short = [
        f"c = {c} {cond} has {cell['episodes']}"
        for c, cells in summary["rows"].items()
        for cond, cell in cells.items()
        if cell["episodes"] < k
    ]
    return (
        f"  seeds: each of our cells is the mean ± sample std over {k} seeds ({_seed_range(seeds)}"
        + (f"; interrupted: {', '.join(short)}" if short else "")
        + "), the same layouts in every one of our rows."
    )


def _fn(cell: dict) -> float | None:
    return None if cell.get("F") is None else cell["F"] + cell["N"]


def _render(rows: list[list[str]], right: set[int]) -> list[str]:
    """Rows of cells as aligned text columns (columns in `right` right-aligned)."""
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    return [
        "  ".join(
            cell.rjust(w) if i in right else cell.ljust(w) for i, (cell, w) in enumerate(zip(row, widths))
        ).rstrip()
        for row in rows
    ]


def _sitl_and_dropout_lines(table: dict, condition: str) -> list[str]:
    """Below the single table: SITL-M timing (p50/p99 over every agent's decisions) and, with --drop,
    F/N/C before and after the agents left (mean over seeds)."""
    lines = []
    for c, cells in table.items():
        rows = cells.get(condition, {}).get("episodes_detail", [])
        sitl = [r["sitl"] for r in rows if r.get("sitl")]
        if sitl:

            def pct(name, q, sitl=sitl):
                return max((s[name]["all"][q] or 0.0) for s in sitl)

            rtf = np.mean([s["real_time_factor"] for s in sitl])
            events = sum(len(s["events"]) for s in sitl)
            lines.append(
                f"  c = {c} SITL-M: decision latency p50 {pct('decision_latency_ms', 'p50'):.2f} ms, round "
                f"trip p50 {pct('round_trip_ms', 'p50'):.2f} / p99 {pct('round_trip_ms', 'p99'):.2f} ms, "
                f"command age p99 {pct('command_age_ms', 'p99'):.1f} ms (worst seed); {rtf:.1f}x real "
                f"time; {events} fault event(s)"
            )
        drops = [r["dropout"] for r in rows if r.get("dropout")]
        if drops:
            phase = {
                ph: {m: np.mean([d["phases"][ph][m] for d in drops]) for m in ("F", "N", "C", "steps", "group_size")}
                for ph in ("before", "after")
            }
            b, a = phase["before"], phase["after"]
            lines.append(
                f"  c = {c} dropout at step {drops[0]['step']}: before ({b['group_size']:.0f} UAVs, "
                f"{b['steps']:.0f} steps) F {b['F']:.1f} N {b['N']:.1f} C {b['C']:.2f} %; after "
                f"({a['group_size']:.0f} UAVs, {a['steps']:.0f} steps) F {a['F']:.1f} N {a['N']:.1f} "
                f"C {a['C']:.2f} %"
            )
    return lines


def _seed_range(seeds: list[int]) -> str:
    return str(seeds[0]) if len(seeds) == 1 else f"{seeds[0]}..{seeds[-1]}"


# ---------------------------------------------------------------------------- recording
def _emit_record(record, request: SingleRequest, many: bool) -> list[Path]:
    """Send one episode to Rerun (a recording per episode: `--rrd run.rrd` becomes run_c5_s0.rrd etc.
    when several episodes are recorded) and/or draw its top-down PNG. Returns the files written."""
    written: list[Path] = []
    tag = f"c{record.formation}_s{record.seed}"
    if request.rrd is not None or request.spawn:
        from cefc_mj.viz.rerun_log import close_recording, log_episode, open_recording  # imports rerun

        rrd = request.rrd
        if rrd is not None:
            if many:
                rrd = rrd.with_name(f"{rrd.stem}_{tag}{rrd.suffix or '.rrd'}")
            rrd.parent.mkdir(parents=True, exist_ok=True)  # checked before the run; created when first written
        recording = open_recording(rrd_path=rrd, spawn=request.spawn, recording_id=f"{record.condition}_{tag}")
        try:
            log_episode(record, recording)
        finally:
            close_recording(recording)
        if rrd is not None:
            written.append(rrd)
    if request.png is not None:
        from cefc_mj.viz.plots import plot_episode  # imports matplotlib

        request.png.mkdir(parents=True, exist_ok=True)
        written.append(plot_episode(record, request.png / f"episode_{record.condition}_{tag}.png"))
    return written
