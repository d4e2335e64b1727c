"""Model cards: a JSON file beside each exported policy (`atm_c6_step3.pt` -> `atm_c6_step3.json`)
saying how it was made and how it scores: config, seed, git commit, wall-clock, samples, and its
Table III-protocol figures (particle world, density 0.05, 50 episodes x 100 steps)."""

from __future__ import annotations

import datetime as _dt
import json
import os
import platform
import subprocess
from pathlib import Path

import torch

from cefc_mj import paths
from cefc_mj.eval.table3 import PAPER_TABLE3, TABLE3_DENSITY, TABLE3_EPISODES, TABLE3_STEPS, evaluate_lowlevel
from cefc_mj.nn.policy_io import load_policy


def git_commit() -> str | None:
    """The project's HEAD commit (read-only query), or None outside a repository / before the first commit."""
    try:
        out = subprocess.run(["git", "rev-parse", "HEAD"], cwd=paths.PROJECT_ROOT, capture_output=True, text=True,
                             timeout=10)
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.strip() if out.returncode == 0 else None


def table3_figures(policy_path: Path, formation: int, method: str | None, seed: int = 0) -> dict:
    """The policy's Table III-protocol row for formation c, with the paper's row beside it."""
    row = evaluate_lowlevel(load_policy(policy_path), formation, seed=seed)
    return {
        "protocol": {"backend": "particle", "density": TABLE3_DENSITY, "episodes": TABLE3_EPISODES,
                     "steps": TABLE3_STEPS, "seed": seed, "formation": formation},
        "ours": row,
        "paper": PAPER_TABLE3.get(str(formation), {}).get(method) if method else None,
    }


def write_model_card(policy_path: Path, card: dict) -> Path:
    """Write `card` (plus provenance: commit, time, versions) as JSON beside the policy file."""
    policy_path = Path(policy_path)
    full = {
        "policy_file": policy_path.name,
        **card,
        "git_commit": git_commit(),
        "created_utc": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        "torch": torch.__version__,
        "python": platform.python_version(),
        "machine": f"{platform.machine()}, {os.cpu_count()} CPUs",
    }
    path = policy_path.with_suffix(".json")
    path.write_text(json.dumps(full, indent=2) + "\n")
    return path
