"""Model cards: a JSON file beside each exported policy (`atm_c6_step3.pt` -> `atm_c6_step3.json`)
saying how it was made and how it scores: config, seed, where its weights started, git commit, code
digest and library versions, wall-clock, samples, and its Table III-protocol figures (particle
world, density 0.05, 50 episodes x 100 steps)."""

from __future__ import annotations

import datetime as _dt
import json
from pathlib import Path

from cefc_mj.eval.table3 import PAPER_TABLE3, evaluate_lowlevel
from cefc_mj.fileio import write_atomic
from cefc_mj.nn.policy_io import load_policy
from cefc_mj.provenance import display_path, git_commit, library_versions
from cefc_mj.table3_protocol import TABLE3_DENSITY, TABLE3_EPISODES, TABLE3_STEPS


def table3_figures(
    policy_path: Path, formation: int, method: str | None, seed: int = 0, episodes: int = TABLE3_EPISODES
) -> dict:
    """The policy's Table III-protocol row for formation c, with the paper's row beside it."""
    row = evaluate_lowlevel(load_policy(policy_path), formation, episodes=episodes, seed=seed)
    return {
        "protocol": {
            "backend": "particle",
            "density": TABLE3_DENSITY,
            "episodes": episodes,
            "steps": TABLE3_STEPS,
            "seed": seed,
            "formation": formation,
        },
        "ours": row,
        "paper": PAPER_TABLE3.get(str(formation), {}).get(method) if method else None,
    }


def display_paths(record):
    """A record (e.g. a low level's description) with every "path" entry written by `display_path`."""
    if isinstance(record, dict):
        return {k: (display_path(Path(v)) if k == "path" else display_paths(v)) for k, v in record.items()}
    return record


def card_path(policy_path: Path) -> Path:
    """The model card of a policy file: same folder, same stem, `.json`."""
    return Path(policy_path).with_suffix(".json")


def write_model_card(policy_path: Path, card: dict) -> Path:
    """Write `card` plus provenance (git commit, UTC time, code digest, library versions and CPU
    from cefc_mj.provenance) as JSON beside the policy file, atomically."""
    policy_path = Path(policy_path)
    full = {
        "policy_file": policy_path.name,
        **card,
        "git_commit": git_commit(),
        "created_utc": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        "versions": library_versions(),
    }
    path = card_path(policy_path)
    write_atomic(path, json.dumps(full, indent=2) + "\n")
    return path


def install_policy(policy_path: Path, dest_dir: Path, load=load_policy) -> Path:
    """Copy a policy file and its model card into `dest_dir` (atomically, file by file; the policy
    is loaded first with `load`, e.g. `load_highlevel_policy` for a high level, so a broken export
    is never installed). Returns the installed policy path."""
    policy_path, dest_dir = Path(policy_path), Path(dest_dir)
    load(policy_path)  # raises CheckpointError on a broken file
    target = dest_dir / policy_path.name
    if target.resolve() == policy_path.resolve():
        return target  # exported there already
    card = card_path(policy_path)
    write_atomic(target, policy_path.read_bytes())
    write_atomic(card_path(target), card.read_bytes())
    return target
