"""High-level training runs that outlive a session through a tracked copy of their progress.

A session's checkout is laid anew and its `runs/` folder lost, so a plan of long runs (the budget
ladder, the paper-schedule pre-registration) keeps, in a tracked folder, every finished run's policy
files and logs, and every unfinished run's logs with its resumable state when that state leaves out
the ConsMAC replay's rows (about 3 MB instead of 125 MB: a state saved while the replay is refilled
before its next read, `HighLevelTrainer.replay_refilled_before_read`). A run whose newest state still
holds the rows keeps its earlier copy. `restore` copies back what the tracked copy holds beyond the
run's folder, so a fresh checkout continues where the copy stands; `claim` locks a run so that two
drivers never train it at once.

A run is any object with: `stem` and `label` (its names in messages), `run_dir` (the trainer's folder:
config.json, progress.csv, state.pt), `policy` (its policy file; the run is done when it exists),
`log`, `claim_dir`, `done()`, `policy_files(folder)` (its exported files in a policies folder),
`kept_dir(kept)` (its logs and state in the tracked copy) and `kept_policy_dir(kept)` (its policy
files there).
"""

from __future__ import annotations

import csv
import fcntl
import shlex
import subprocess
import sys
import time
from pathlib import Path

RUN_LOGS = ("config.json", "progress.csv")
"""The files of a run's folder that the tracked copy keeps beside its state."""


def saved_trainer(state: Path) -> dict | None:
    """The trainer part of a run's saved state, None when there is none."""
    if not state.is_file():
        return None
    from cefc_mj.train.highlevel import STATE_FORMAT  # torch: only when a state is read
    from cefc_mj.train.run_state import read_state

    return read_state(state, STATE_FORMAT, "high-level training state")["trainer"]


def saved_iteration(state: Path, trainer: dict | None = None) -> int:
    """The iteration a run's saved state stands at (-1 when there is none); `trainer`: its trainer part
    when already read."""
    trainer = saved_trainer(state) if trainer is None else trainer
    return -1 if trainer is None else int(trainer["counters"]["iteration"])


def without_rows(trainer: dict) -> bool:
    """Whether a saved trainer state holds no ConsMAC replay rows (MAPPO+AT-M has no replay)."""
    replay = trainer["replay"]
    return replay is None or int(replay["size"]) == 0


def copy_files(files: list[Path], folder: Path) -> None:
    from cefc_mj.fileio import write_atomic

    folder.mkdir(parents=True, exist_ok=True)
    for f in files:
        write_atomic(folder / f.name, f.read_bytes())


def exported_files(stem: str, folder: Path) -> list[Path]:
    """A high-level run's exported files in a policies folder: policy and card, and its wo-FT pair."""
    return sorted(p for name in (stem, f"{stem}_wo_ft") for p in folder.glob(f"{name}.*"))


def progress_state(run, iterations: int) -> str:
    """ "done", "<k>/<iterations> it" (the iterations its progress.csv holds) or "todo"."""
    if run.done():
        return "done"
    progress = run.run_dir / "progress.csv"
    if progress.is_file():
        with progress.open() as handle:
            rows = sum(1 for _ in csv.DictReader(handle))
        return f"{rows}/{iterations} it"
    return "todo"


def _logs(folder: Path) -> list[Path]:
    return [folder / n for n in RUN_LOGS if (folder / n).is_file()]


def keep(runs: list, kept: Path) -> list[str]:
    """Copy each run's progress into the tracked copy; the lines to print."""
    lines = []
    for run in runs:
        target = run.kept_dir(kept)
        if run.done():
            if run.kept_policy_dir(kept).resolve() != run.policy.parent.resolve():
                copy_files(run.policy_files(run.policy.parent), run.kept_policy_dir(kept))
            copy_files(_logs(run.run_dir), target)
            (target / "state.pt").unlink(missing_ok=True)  # done: the final state (with its rows) is not kept
            lines.append(f"kept {run.label}: done")
        elif (run.run_dir / "state.pt").is_file():
            state = run.run_dir / "state.pt"
            trainer = saved_trainer(state)  # read once: a state with its rows is 125 MB
            local, there = saved_iteration(state, trainer), saved_iteration(target / "state.pt")
            if local <= there:
                lines.append(f"kept {run.label}: unchanged at iteration {there}")
            elif without_rows(trainer):
                copy_files([state, *_logs(run.run_dir)], target)
                lines.append(f"kept {run.label}: iteration {local}")
            else:
                lines.append(
                    f"kept {run.label}: its state at iteration {local} holds the replay's rows; "
                    f"the copy stays at iteration {there} (run --keep again after the next checkpoint)"
                )
    return lines


def restore(runs: list, kept: Path) -> list[str]:
    """Copy back from the tracked copy what it holds beyond each run's folder; the lines to print."""
    lines = []
    for run in runs:
        if run.done() and (run.run_dir / "progress.csv").is_file():
            continue
        source = run.kept_dir(kept)
        files = run.policy_files(run.kept_policy_dir(kept))
        if any(f.name == run.policy.name for f in files):
            if not run.done():
                copy_files(files, run.policy.parent)
            copy_files(_logs(source), run.run_dir)
            lines.append(f"restored {run.label}: done")
        elif (there := saved_iteration(source / "state.pt")) > saved_iteration(run.run_dir / "state.pt"):
            copy_files([source / "state.pt", *_logs(source)], run.run_dir)  # there >= 0: the state is there
            lines.append(f"restored {run.label}: iteration {there}")
    return lines


def claim(run):
    """An open, exclusively locked claim file for the run, or None when another driver holds it."""
    run.claim_dir.mkdir(parents=True, exist_ok=True)
    handle = open(run.claim_dir / f"{run.stem}.lock", "w")  # noqa: SIM115 - held for the run's duration
    try:
        fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        handle.close()
        return None
    if run.done():  # finished by another driver between our check and the lock
        handle.close()
        return None
    return handle


def train(run, cmd: list[str], root: Path, prog: str) -> int:
    """Run `cmd` (a `cefc-train` command, from `root`) for one claimed run, its output appended to the
    run's log; its exit code, 0 when another driver holds the run."""
    handle = claim(run)
    if handle is None:
        return 0
    with handle:
        run.log.parent.mkdir(parents=True, exist_ok=True)
        print(f"{prog}: {shlex.join(cmd)}  > {run.log}", flush=True)
        start = time.monotonic()
        script = Path(sys.executable).with_name(cmd[0])  # this environment's, not another on PATH
        with run.log.open("a") as log:
            code = subprocess.run(
                [str(script) if script.is_file() else cmd[0], *cmd[1:]], cwd=root, stdout=log, stderr=subprocess.STDOUT
            ).returncode
        print(f"{prog}: {run.label} exited {code} after {time.monotonic() - start:.0f} s", flush=True)
        return code


def train_all(todo: list, planned: int, jobs: int, command_of, root: Path, prog: str) -> int:
    """Train the runs of `todo` (of `planned` in the plan), `jobs` at a time, each with
    `command_of(run)`; 0, or 1 after one line naming every run that failed."""
    from concurrent.futures import ThreadPoolExecutor

    print(f"{prog}: {len(todo)} of {planned} runs to train, {jobs} at a time", flush=True)
    with ThreadPoolExecutor(max_workers=jobs) as pool:
        codes = list(pool.map(lambda run: train(run, command_of(run), root, prog), todo))
    failed = [f"{run.label}: exit {code}" for run, code in zip(todo, codes) if code]
    if failed:
        print(f"{prog}: {len(failed)} runs failed: {'; '.join(failed)}", file=sys.stderr)
        return 1
    return 0
