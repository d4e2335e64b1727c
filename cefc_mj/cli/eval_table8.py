"""cefc-eval --protocol table8: the paper's Table VIII grid (7 conditions, and SITL-M when asked) on a
local pool or a Ray cluster, each finished episode kept in a resumable cell file; the report (markdown,
CSV, JSON, PNG) written into the report folder at the end."""

from __future__ import annotations

import shlex
import sys
from pathlib import Path

from tqdm import tqdm

from cefc_mj import paths
from cefc_mj.cli.eval_common import (
    EXIT_INTERRUPTED,
    PROG,
    deploy_runners,
    report_faults,
    rotor_text,
    sitl_config,
    write_outputs,
)
from cefc_mj.eval import table8
from cefc_mj.eval.ledger import check_before_flight, record_if_test
from cefc_mj.eval.requests import Table8Request
from cefc_mj.eval.runner import fault_lines, provenance


def is_shipped_reports(path: Path) -> bool:
    """Whether `path` is the shipped eval/reports folder or inside it."""
    shipped = (paths.EVAL_DIR / "reports").resolve()
    resolved = Path(path).resolve()
    return resolved == shipped or shipped in resolved.parents


def check(request: Table8Request) -> dict:
    """Before anything flies: the policy file of every c, resolved, hashed and loaded (a missing or
    misfit checkpoint fails here). Returns the run's provenance."""
    prov = provenance(request.policy, request.formations)
    for c in request.formations:
        table8.cached_policy(request.policy, c)
    check_before_flight("table8", request.seed, request.episodes)  # a damaged test ledger: refused here
    return prov


def run(request: Table8Request, prov: dict, command: str) -> int:
    """Fly the cells the cell file lacks, then write the report; 0, or 130 when interrupted (the
    finished cells are kept, and the line printed says how to resume)."""
    out, flight, formations = request.report_dir, request.flight, request.formations
    specs = table8.table8_specs(
        formations,
        request.episodes,
        request.seed,
        request.steps,
        request.backend,
        request.policy,
        flight.airframe,
        flight.estimator,
        flight.offboard,
        flight.guard,
        request.wind_direction,
        flight.rotor_actuation,
        flight.accel_max,
        flight.push_observer,
    )
    policy_sha256 = {c: prov["policies"][str(c)]["sha256"] for c in formations}
    cells = table8.plan_cells(specs, policy_sha256, prov["code_version"])
    sitl = sitl_config(request.sitl)
    if sitl is not None:  # the SITL-M row: the calm specs again, one process per UAV
        cells += table8.plan_cells(
            [s for s in specs if s.condition == "SITL-S"], policy_sha256, prov["code_version"], sitl=sitl
        )
    cell_file = out / f"table8_cells_{request.backend}.jsonl"
    known = {} if request.fresh else table8.load_cells(cell_file)
    reused = sum(cell.key in known for cell in cells)
    rows_desc = "7 conditions" + (" + SITL-M" if sitl is not None else "")
    direction = request.wind_direction
    wind_towards = "drawn per episode" if direction is None else f"towards {direction:g}° (ENU)"
    rotors = rotor_text(flight.rotor_actuation, formations)
    print(
        f"{PROG} table8: {len(cells)} episodes ({len(formations)} c x {rows_desc} x {request.episodes} seeds, "
        f"{request.steps} steps), {flight.airframe} airframe, rotors {rotors}, Wind rows' direction {wind_towards}, "
        f"policy {request.policy}, {flight.estimator} position estimate, "
        f"{'separation guard' if flight.guard else 'no separation guard'}, {request.executor.describe()}"
        + ("; SITL-M episodes fly one at a time" if sitl is not None else "")
    )
    print(
        f"reports go to {out}"
        + ("  (the shipped reports folder, as --report-dir asks)" if is_shipped_reports(out) else "")
    )
    if request.fresh and cell_file.exists():
        print(f"--fresh: {cell_file} is moved aside; every episode is flown anew")
    else:
        stale = len(known) - reused
        print(
            f"{reused} of {len(cells)} cells reused from {cell_file}"
            + (
                f" ({stale} rows there are for other code, policy files or conditions and are not used)"
                if stale > 0
                else ""
            )
        )
    resume = command if "--report-dir" in command else f"{command} --report-dir {shlex.quote(str(out))}"
    try:
        with tqdm(total=len(cells), desc="episodes", unit="ep", file=sys.stderr) as bar:
            rows = table8.run_grid(
                cells,
                cell_file,
                progress=bar,
                fresh=request.fresh,
                executor=request.executor,
                runners=deploy_runners(sitl is not None, False),
            )
    except KeyboardInterrupt:
        print(
            f"\n{PROG}: interrupted; finished episodes are kept in {cell_file}; resume with:\n  {resume}",
            file=sys.stderr,
        )
        return EXIT_INTERRUPTED
    table = table8.aggregate(rows)
    meta = {
        "command": command,
        "backend": request.backend,
        "policy": request.policy,
        "estimator": flight.estimator,
        "offboard": flight.offboard,
        "accel_max": flight.accel_max,
        "push_observer": flight.push_observer,
        "guard": flight.guard,
        "airframe": flight.airframe,
        "wind_direction": request.wind_direction,
        "episodes": request.episodes,
        "seed": request.seed,
        "steps": request.steps,
        "report_dir": str(out),
        "cell_file": str(cell_file),
        "cells_reused": reused,
        "cells_total": len(cells),
        "provenance": prov,
    }
    markdown = table8.report_markdown(table, meta)
    data = table8.report_json(table, meta)
    print(markdown)
    record_if_test("table8", request.seed, request.episodes, command, prov, (out / "table8.json", request.json))
    writes = [
        (out / "table8.md", markdown),
        (out / "table8.csv", table8.report_csv(table)),
        (out / "table8.json", data),
        (out / "table8.png", lambda path: table8.report_plot(table, path, meta)),
    ]
    if sitl is not None:
        writes.append((out / "table8_sitl.png", lambda path: table8.report_sitl_histograms(table, path)))
    if request.json is not None:
        writes.append((request.json, data))
    write_outputs(writes)
    return report_faults(fault_lines(table))
