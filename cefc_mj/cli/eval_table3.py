"""cefc-eval --protocol table3: the paper's Table III in the particle world (its MPE), every method or
one policy, beside the paper's rows; optional JSON."""

from __future__ import annotations

import json
import sys

from tqdm import tqdm

from cefc_mj.cli.eval_common import PROG, write_outputs
from cefc_mj.errors import ConfigError
from cefc_mj.eval.requests import Table3Request
from cefc_mj.eval.runner import provenance
from cefc_mj.eval.table3 import POLICY_CHOICES, format_table3, policy_file_for, run_table3
from cefc_mj.eval.table8 import cached_policy


def check(request: Table3Request) -> dict:
    """Before anything flies: ORCA-F's simulator where it is asked for (its absence is a note when every
    method is), and the asked policy's file of every c, loaded. Returns the run's provenance."""
    from cefc_mj.baselines.orca import PYRVO_MISSING, pyrvo_available  # imports scipy

    if request.policy == "orca" and not pyrvo_available():
        raise ConfigError(f"--policy orca: {PYRVO_MISSING}")
    if request.policy is None:  # every method: missing files are listed, not fatal (run_table3)
        if not pyrvo_available():
            print(f"note: ORCA-F skipped: {PYRVO_MISSING}", file=sys.stderr)
        return provenance("atm", [])
    for c in request.formations:
        name = (
            policy_file_for(POLICY_CHOICES[request.policy], c) if request.policy in POLICY_CHOICES else request.policy
        )
        if name is not None:  # ORCA-F has no policy file
            cached_policy(name, c)
    return provenance("atm", [])  # table3 records each row's file and sha256 itself


def run(request: Table3Request, prov: dict, command: str) -> int:
    """Fly every c's batch of episodes and print the table."""
    print(
        f"{PROG} table3: particle, c = {', '.join(map(str, request.formations))}, {request.episodes} episodes x "
        f"{request.steps} steps, seed {request.seed}, policy {request.policy or 'every Table III method'}"
    )
    with tqdm(total=None, desc="episodes", unit="ep", file=sys.stderr) as bar:
        result = run_table3(
            formations=request.formations,
            episodes=request.episodes,
            seed=request.seed,
            steps=request.steps,
            policy=request.policy,
            provenance={k: v for k, v in prov.items() if k != "policies"},
            progress=bar,
        )
    result["protocol"]["command"] = command
    print(format_table3(result))
    if request.json is not None:
        write_outputs([(request.json, json.dumps(result, indent=2) + "\n")])
    return 0
