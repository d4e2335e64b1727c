"""What cefc-eval's protocol runners share: the program's name and exit codes, the outputs written at
the end, the deployment layer's episode runners and SITL-M settings, and a few words of report text."""

from __future__ import annotations

import sys
from pathlib import Path

from cefc_mj import fileio
from cefc_mj.eval.requests import SitlM
from cefc_mj.eval.table8 import RowRunners

PROG = "cefc-eval"
EXIT_USAGE = 2
EXIT_OUTPUT = 1
EXIT_INTERRUPTED = 130
EXIT_NOT_A_RESULT = 3
"""An episode lost agents, failed safe or diverged without being asked to: the table is written, its
faulted cells marked, and the run is not a result."""


def report_faults(lines: list[str], requested: str | None = None) -> int:
    """Print one line per fault cause on stderr and a verdict; returns EXIT_NOT_A_RESULT when there
    are any, 0 otherwise. `requested`: what the user asked for that faults may come from (e.g. the
    --drop flag), named in the verdict."""
    for line in lines:
        print(f"{PROG}: fault: {line}", file=sys.stderr)
    if not lines:
        return 0
    print(
        f"{PROG}: error: {len(lines)} fault(s) above: the marked cells are not a measurement of the policy"
        + (f" (faults requested with {requested} are expected and not counted)" if requested else ""),
        file=sys.stderr,
    )
    return EXIT_NOT_A_RESULT


def write_outputs(writes: list[tuple[Path, object]]) -> list[Path]:
    """Write (path, bytes|str|callable(path)) pairs, creating their folders now; a failure (disk
    full, a folder removed meanwhile) is one line and exit code 1, after everything else was tried."""
    written, failed = [], []
    for path, data in writes:
        try:
            if callable(data):
                Path(path).parent.mkdir(parents=True, exist_ok=True)
                data(path)
            else:
                fileio.write_atomic(path, data)
            written.append(Path(path))
        except OSError as e:
            failed.append(f"{path}: {e.strerror or e}")
    for path in written:
        print(f"wrote {path}")
    if failed:
        print(f"{PROG}: error: could not write " + "; ".join(failed), file=sys.stderr)
        raise SystemExit(EXIT_OUTPUT)
    return written


def deploy_runners(sitl: bool, dropout: bool, game: bool = False) -> RowRunners:
    """`cefc_mj.deploy`'s episode runners for the rows asked for (SITL-M, dropout, the SITL-M game), as
    table8 and table5 take them; deploy (the agent-process layer) is imported only when one is."""
    sitl_runner = dropout_runner = game_runner = None
    if game:
        from cefc_mj.deploy.game import run_sitl_game

        game_runner = run_sitl_game
    if sitl:
        from cefc_mj.deploy.episode import run_sitl_episode

        sitl_runner = run_sitl_episode
    if dropout:
        from cefc_mj.deploy.dropout import run_dropout_episode

        dropout_runner = run_dropout_episode
    return RowRunners(sitl=sitl_runner, dropout=dropout_runner, game=game_runner)


def sitl_config(sitl: SitlM | None, drop: tuple[int, int] | None = None):
    """The deployment's `SitlConfig` of a request's SITL-M settings (None: one process)."""
    if sitl is None:
        return None
    from cefc_mj.deploy.episode import SitlConfig

    return SitlConfig(link_delay_ms=sitl.link_delay_ms, jitter_ms=sitl.jitter_ms, drop=drop)


def rotor_text(mode: str, formations) -> str:
    """ "auto: actuators" (the rotor path each size flies, as `resolve_rotor_actuation` picks it)."""
    from cefc_mj.sim.mujoco_world import resolve_rotor_actuation  # imports mujoco

    used = sorted({resolve_rotor_actuation(mode, c) for c in formations})
    return f"{mode}: {'/'.join(used)}" if mode == "auto" else mode


def wind_direction_text(summary: dict) -> str:
    """ ", wind towards 90°" or ", wind direction drawn per episode" where the run has wind; "" otherwise."""
    if not summary.get("wind"):
        return ""
    given = summary.get("wind_direction")
    return ", wind direction drawn per episode from the seed" if given is None else f", wind towards {given:g}° (ENU)"
