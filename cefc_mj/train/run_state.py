"""The resumable-run rules every trainer shares: is there a run in the folder, may it be resumed,
is its saved state what it claims, and was it made with the same settings."""

from __future__ import annotations

from pathlib import Path

from cefc_mj.errors import CheckpointError, ConfigError
from cefc_mj.nn.policy_io import checkpoint_errors, safe_torch_load

STATE_FILE = "state.pt"


def run_state_path(run_dir: Path, resume: bool) -> Path | None:
    """The state file of the run in `run_dir` when resuming it, None for a new run; ConfigError when
    a new run would overwrite one, or when there is nothing to resume."""
    state_path = run_dir / STATE_FILE
    if state_path.exists() and not resume:
        raise ConfigError(f"{run_dir} already holds a run; pass --resume to continue it, or choose another --out")
    if resume and not state_path.exists():
        raise ConfigError(f"--resume: no run to continue in {run_dir} (no {STATE_FILE}); drop --resume to start one")
    return state_path if resume else None


def read_state(path: Path, state_format: str, what: str) -> dict:
    """A saved training state, checked for its format (`what` names it in the error)."""
    payload = safe_torch_load(path)
    if payload.get("format") != state_format or "trainer" not in payload or "config" not in payload:
        raise CheckpointError(f"{path}: not a cefc-mj {what}")
    if not isinstance(payload["trainer"], dict) or not isinstance(payload["config"], dict):
        raise CheckpointError(f"{path}: a {what} without its trainer state and config")
    return payload


def restore_trainer(trainer, saved: dict, path: Path) -> None:
    """`trainer.load_state_dict(saved["trainer"])`, a state that does not fit the trainer (another
    network, a damaged entry) raising CheckpointError with one line naming `path`."""
    with checkpoint_errors(path, "the saved training state does not fit this run"):
        trainer.load_state_dict(saved["trainer"])


def train_under_budget(
    trainer, budget, checkpoint_every: int, logger, progress_keys: tuple[str, ...], checkpoint, iterate=None
) -> dict:
    """Iterate until `budget` is spent (counted by trainer.iteration and trainer.elapsed, so across
    resumes), logging every row and calling `checkpoint()` every `checkpoint_every` iterations and
    at the end; the logger is closed even on an error. iterate: one iteration returning its row
    (default trainer.iterate). Returns the last row, {} when the budget was already spent."""
    iterate = iterate or trainer.iterate
    last_row: dict = {}
    try:
        while not budget.exhausted(trainer.iteration, trainer.elapsed):
            last_row = iterate()
            logger.log(last_row, progress_keys)
            if trainer.iteration % checkpoint_every == 0:
                checkpoint()
    finally:
        logger.close()
    checkpoint()
    return last_row


def check_same_run(saved: dict, cfg, path: Path, free: tuple[str, ...]) -> None:
    """A resumed run keeps the settings of its config `cfg` (a dataclass with to_dict / from_dict;
    fields added later load as defaults) except the `free` fields and the PPO thread counts."""

    def comparable(config) -> dict:
        d = config.to_dict()
        for key in free:
            del d[key]
        if "ppo" in d:
            d["ppo"] = {k: v for k, v in d["ppo"].items() if k not in ("rollout_threads", "update_threads")}
        return d

    mine = comparable(cfg)
    with checkpoint_errors(path, "the saved run's settings cannot be read"):
        theirs = comparable(type(cfg).from_dict(saved))
    diffs = [k for k in mine if theirs.get(k) != mine[k]]
    if diffs:
        raise ConfigError(f"--resume: {path} was made with different settings ({', '.join(diffs)}); use another --out")
