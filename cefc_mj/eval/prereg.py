"""The pre-registered Table V's plan (docs/research/preregistration.md): every training run it asks for, by the
policy file the run writes, and the check that the test flight waits for all of them.

`examples/prereg_table5.py` trains the runs in this order; `cefc-eval --preregistered-flight` refuses
to fly the pre-registered test batch until every file is in its --policies-dir.
"""

from __future__ import annotations

from pathlib import Path

PRIMARY_SEEDS = range(100, 120)
"""Training seeds of CI-HRL and MAPPO+AT-M, the primary pair (20 each)."""
OTHER_SEEDS = range(100, 105)
"""Training seeds of every other row (5 each)."""


def _stem(base: str, seed: int) -> str:
    return f"{base}_seed{seed}"


def planned_runs() -> list[tuple[str, list[str]]]:
    """(policy file stem, `cefc-train` arguments without the common ones) of every run, the primary
    pair's seeds first, interleaved."""
    runs = []
    for k in PRIMARY_SEEDS:
        runs.append((_stem("cihrl_consmac_a", k), ["highlevel", "--variant", "consmac-a"]))
        runs.append((_stem("cihrl_mappo", k), ["highlevel", "--variant", "mappo"]))
    for k in OTHER_SEEDS:
        runs.append((_stem("cihrl_consmac_a_dt", k), ["highlevel", "--variant", "consmac-a", "--pretrain-share", "0"]))
        for variant in ("tarmac", "consmac-o", "masia", "nvif"):
            runs.append((_stem(f"cihrl_{variant.replace('-', '_')}", k), ["highlevel", "--variant", variant]))
        for ablation in ("wo-com", "wo-mem", "wo-de", "wt-rl", "consmac-g"):
            stem = _stem(f"cihrl_consmac_a_{ablation.replace('-', '_')}", k)
            runs.append((stem, ["highlevel", "--variant", "consmac-a", "--ablation", ablation]))
        clm = ["highlevel", "--variant", "consmac-a", "--low-level", "clm-per-group"]
        runs.append((_stem("cihrl_consmac_a_clm", k), clm))
        for algorithm in ("mappo", "masac"):
            benchmarl = ["highlevel-benchmarl", "--algorithm", algorithm, "--budget", "1500ep"]
            runs.append((_stem(f"benchmarl_{algorithm}", k), benchmarl))
    return [(stem, [*args, "--seed", stem.rsplit("_seed", 1)[1]]) for stem, args in runs]


def missing_runs(policies_dir: Path) -> list[str]:
    """The planned runs whose policy file is not in `policies_dir`."""
    return [stem for stem, _ in planned_runs() if not (Path(policies_dir) / f"{stem}.pt").is_file()]
