"""Multi-seed sweeps of one low-level stage (`cefc-train lowlevel ... --seeds 0,1,2`).

Seed k trains the same stage as a single run would with `--seed k`, in its own run folder and
under its own policy name, so no two seeds share a file:

    run folder   <out>/seed<k>/<stage>/       (config, logs, resumable state)
    policy file  <policies_dir>/<stage>_s<k>.pt  + its model card

A Step 3 stage of seed k starts from the Step 1 and 2 runs of the same seed (<out>/seed<k>/...),
so a sweep of Steps 1, 2, 3 run one after the other keeps every seed's lineage apart. The seeds
run on an executor (`cefc_mj.executors`): "local" trains them one after another in this process,
"ray" trains each as a Ray task, on a cluster or on a Ray instance started here. `--resume`
continues every seed that has a run and starts those that have none; each seed resumes its own
folder. On a cluster of several machines <out> and the policies folder must be on a filesystem that
every node shares (docs/scaling.md).
"""

from __future__ import annotations

import os
from contextlib import closing
from dataclasses import dataclass, replace
from pathlib import Path

from cefc_mj.errors import ConfigError
from cefc_mj.executors import ExecutorConfig, map_unordered
from cefc_mj.train.config import MAX_SEED, LowLevelConfig

# cefc_mj.train.lowlevel (torch) is imported where a sweep starts, so that parse_seeds stays cheap

MAX_SEEDS = 1000
"""Most seeds in one sweep."""


def parse_seeds(text: str) -> tuple[int, ...]:
    """'0,1,2' -> (0, 1, 2): distinct integers in [0, 2^32 - 1], in the given order; ConfigError otherwise."""
    parts = [p.strip() for p in str(text).split(",")]
    try:
        seeds = tuple(int(p) for p in parts)
    except ValueError:
        raise ConfigError(f"--seeds {text}: expected comma-separated seeds, e.g. 0,1,2") from None
    if any(not 0 <= s <= MAX_SEED for s in seeds):
        raise ConfigError(f"--seeds {text}: seeds must be in 0..{MAX_SEED}")
    if len(set(seeds)) != len(seeds):
        raise ConfigError(f"--seeds {text}: a seed is listed twice")
    if len(seeds) > MAX_SEEDS:
        raise ConfigError(f"--seeds {text}: at most {MAX_SEEDS} seeds in one sweep")
    return seeds


def seed_folder(out: Path, seed: int) -> Path:
    """The folder seed `seed` of a sweep trains in (it holds the stage's run folder)."""
    return Path(out) / f"seed{seed}"


def seed_policy_name(cfg: LowLevelConfig) -> str:
    """The exported policy's name for a seed of a sweep: the stage name with _s<seed>, e.g. atm_c6_step3_s1."""
    return f"{cfg.name}_s{cfg.seed}"


@dataclass(frozen=True)
class SeedRun:
    """One seed of a sweep: everything `train_seed` needs, picklable for a pool or Ray worker."""

    cfg: LowLevelConfig
    """The stage, with this seed."""
    out: Path
    """The seed's folder <out>/seed<k> (absolute: a Ray worker's working folder is its own)."""
    policies_dir: Path
    """Where the policy and its card are exported (absolute)."""
    resume: bool
    """Continue the run in the seed's folder (it has one) rather than start it."""
    init_from: str | None = None
    """A policy file or shipped name the Step 3 actor starts from (train_lowlevel's init_from)."""
    command: str | None = None
    """The command line, recorded in the run's config.json and the card."""
    show_progress: bool = False
    """A progress bar (only where the seed trains in this process)."""


def _has_run(folder: Path, name: str) -> bool:
    from cefc_mj.train.lowlevel import STATE_FILE

    return (folder / name / STATE_FILE).is_file()


def plan_seeds(
    cfg: LowLevelConfig,
    seeds,
    out: Path,
    policies_dir: Path,
    resume: bool = False,
    init_from: str | None = None,
    command: str | None = None,
    show_progress: bool = False,
) -> list[SeedRun]:
    """The seed runs of a sweep, checked before any of them starts (ConfigError, one line).

    Without `resume` no seed may have a run of this stage yet; with it at least one must, and the
    seeds without one start fresh. A Step 3 stage that starts from earlier stages (no `init_from`)
    needs their runs in every starting seed's folder; an `init_from` policy is loaded and checked here."""
    from cefc_mj.train.lowlevel import load_init_policy

    if init_from is not None:
        load_init_policy(init_from, cfg)
    out, policies_dir = Path(out).absolute(), Path(policies_dir).absolute()
    started = [s for s in seeds if _has_run(seed_folder(out, s), cfg.name)]
    if resume and not started:
        raise ConfigError(
            f"--resume: no run to continue in {out}/seed<k>/{cfg.name} for seeds "
            f"{','.join(map(str, seeds))}; drop --resume to start them"
        )
    if not resume and started:
        raise ConfigError(
            f"{seed_folder(out, started[0]) / cfg.name} already holds a run; pass --resume to continue "
            "the sweep, or choose another --out"
        )
    if cfg.step == 3 and init_from is None:
        sources = cfg.source_stages
        for s in seeds:
            missing = [n for n in sources if s not in started and not _has_run(seed_folder(out, s), n)]
            if missing:
                raise ConfigError(
                    f"{cfg.name} of seed {s} starts from {missing[0]}: no training state in "
                    f"{seed_folder(out, s) / missing[0]}; run that stage with the same --seeds and "
                    f"--out first, or start from a trained policy with --init-from"
                )
    return [
        SeedRun(
            cfg=replace(cfg, seed=s),
            out=seed_folder(out, s),
            policies_dir=policies_dir,
            resume=s in started,
            init_from=init_from,
            command=command,
            show_progress=show_progress,
        )
        for s in seeds
    ]


def train_seed(run: SeedRun) -> dict:
    """Train one seed of a sweep (in this process, a pool worker or a Ray worker); returns its model card."""
    from cefc_mj.train.lowlevel import train_lowlevel

    return train_lowlevel(
        run.cfg,
        run.out,
        run.policies_dir,
        resume=run.resume,
        show_progress=run.show_progress,
        init_from=run.init_from,
        command=run.command,
        policy_name=seed_policy_name(run.cfg),
    )


def sweep_executor(runs: list[SeedRun], executor: ExecutorConfig | None = None) -> tuple[ExecutorConfig, dict | None]:
    """The executor a sweep runs on and the Ray options of its tasks. A Ray task asks for as many CPUs
    as the stage's PPO update uses threads and is not retried (a retry would find the run it had
    started and refuse it: resume it with --resume); a Ray instance started here gets the machine's
    CPUs. The local executor trains the seeds one after another in this process."""
    executor = executor or ExecutorConfig()
    if executor.kind != "ray":
        return replace(executor, workers=1), None
    threads = max(run.cfg.ppo.update_threads for run in runs)
    if executor.address is None:  # never fewer CPUs than one task asks for, or it would wait forever
        executor = replace(executor, workers=max(os.cpu_count() or 1, threads))
    return executor, {"num_cpus": threads, "max_retries": 0}


def train_seeds(runs: list[SeedRun], executor: ExecutorConfig | None = None, on_done=None) -> list[dict]:
    """Train every seed run on `executor` (see sweep_executor; default: one after another here);
    returns the model cards in the order of `runs`. `on_done(card)` is called as each seed finishes."""
    executor, options = sweep_executor(runs, executor)
    if executor.kind == "ray":
        runs = [replace(run, show_progress=False) for run in runs]  # bars of remote processes would interleave
    cards = {}
    with closing(map_unordered(train_seed, runs, executor, ray_options=options)) as done:
        for run, card in done:
            cards[run.cfg.seed] = card
            if on_done is not None:
                on_done(card)
    return [cards[run.cfg.seed] for run in runs]
