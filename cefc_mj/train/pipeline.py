"""The whole low-level pipeline (`cefc-train lowlevel-all`): AT-M Steps 1-3 and Safe for every c,
then distillation of one student from the Step 3 teachers.

One total budget is split over the stages by weight (below). The evaluated formations (c = 6, 7,
8, then 5) come first and get full weight; c = 3, 4 get half (the paper, too, reports only c > 5).
With `workers` > 1 the formations are dealt round-robin to that many processes (one torch thread
each) that train side by side, and each worker's stages share the whole budget; distillation runs
afterwards in the main process. A stage's budget is fixed by the plan, so `--resume` after a kill
re-enters the interrupted stage where its last checkpoint left it and re-exports finished ones
(cheap) without training them again.
"""

from __future__ import annotations

import multiprocessing
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path

from cefc_mj.errors import ConfigError
from cefc_mj.train.config import Budget, DistillConfig, LowLevelConfig, PPOConfig
from cefc_mj.train.distill import train_student
from cefc_mj.train.lowlevel import STATE_FILE, train_lowlevel

PIPELINE_ORDER = (6, 7, 8, 5, 4, 3)
"""Formation order: the evaluated sizes first, so a cut-short pipeline still has them."""
STAGE_WEIGHTS = {"step1": 1.0, "step2": 0.8, "step3": 1.0, "safe": 0.35}
"""Relative training time of the stages of one formation."""
SMALL_FORMATION_WEIGHT = 0.5
"""Weight multiplier of c = 3, 4."""
DISTILL_SHARE = 0.06
"""Share of the total budget spent on the student's gradient steps."""


@dataclass(frozen=True)
class Stage:
    kind: str  # "lowlevel" or "distill"
    budget: Budget
    lowlevel: LowLevelConfig | None = None
    distill: DistillConfig | None = None

    @property
    def name(self) -> str:
        return self.lowlevel.name if self.lowlevel is not None else "atm_student"


def plan(
    budget: Budget,
    formations=PIPELINE_ORDER,
    seed: int = 0,
    ppo: PPOConfig | None = None,
    tuples_per_formation: int = 60_000,
    workers: int = 1,
) -> list[Stage]:
    """The ordered stages with their budgets (shares of `budget`; with `workers` processes training
    side by side, the shares of one worker's stages add up to the whole budget)."""
    ppo = ppo or PPOConfig()
    formations = [c for c in PIPELINE_ORDER if c in set(formations)]
    weights = []
    for c in formations:
        scale = SMALL_FORMATION_WEIGHT if c < 5 else 1.0
        for key, step, safe in (("step1", 1, False), ("step2", 2, False), ("step3", 3, False), ("safe", 3, True)):
            weights.append((c, step, safe, STAGE_WEIGHTS[key] * scale))
    total = sum(w for *_, w in weights) / min(workers, len(formations))
    stages = []
    for c, step, safe, w in weights:
        b = budget.scaled((1 - DISTILL_SHARE) * w / total)
        cfg = LowLevelConfig(formation=c, step=step, safe=safe, budget=b, seed=seed, ppo=ppo)
        stages.append(Stage("lowlevel", b, lowlevel=cfg))
    b = _distill_budget(budget)
    stages.append(
        Stage(
            "distill",
            b,
            distill=DistillConfig(
                budget=b, formations=tuple(sorted(formations)), seed=seed, tuples_per_formation=tuples_per_formation
            ),
        )
    )
    return stages


def _distill_budget(budget: Budget) -> Budget:
    """Distillation steps are ~100x cheaper than PPO iterations: an iteration budget maps to
    gradient steps at 100 per PPO iteration."""
    scaled = budget.scaled(DISTILL_SHARE)
    return replace(scaled, iterations=None if budget.iterations is None else max(1, 100 * scaled.iterations))


def run_pipeline(
    budget: Budget,
    out: Path,
    policies_dir: Path,
    seed: int = 0,
    resume: bool = False,
    formations=PIPELINE_ORDER,
    ppo: PPOConfig | None = None,
    show_progress: bool = True,
    tuples_per_formation: int = 60_000,
    workers: int = 1,
    command: str | None = None,
) -> list[dict]:
    """Run every stage of `plan(...)`; returns the model cards (AT-M stages, then the student).

    resume: continue the pipeline whose stage runs are under `out` (stages not started yet start
    fresh); ConfigError if `out` holds none. Without it, `out` must hold no stage run. Both are
    checked, like every stage config, before any stage starts."""
    out = Path(out)
    ppo = ppo or PPOConfig()
    if workers > 1:
        ppo = replace(ppo, rollout_threads=1, update_threads=1)
    stages = plan(budget, formations, seed, ppo, tuples_per_formation, workers)
    started = [s.name for s in stages if _started(out, s.name)]
    if resume and not started:
        raise ConfigError(
            f"--resume: no run to continue in {out} (no stage folder with {STATE_FILE}); drop --resume to start one"
        )
    if not resume and started:
        shown = ", ".join(started[:3]) + (", ..." if len(started) > 3 else "")
        raise ConfigError(
            f"{out} already holds runs of a pipeline ({shown}); pass --resume to continue it, or choose another --out"
        )
    lowlevel, distill = stages[:-1], stages[-1]
    start = time.perf_counter()
    order = [c for c in PIPELINE_ORDER if c in set(formations)]
    groups = [[s for s in lowlevel if order.index(s.lowlevel.formation) % workers == w] for w in range(workers)]
    groups = [g for g in groups if g]
    if len(groups) == 1:
        cards = _run_stages(groups[0], out, policies_dir, resume, show_progress, "", command)
    else:
        _log(
            f"[lowlevel-all] {len(groups)} workers: "
            + "; ".join(
                "w{}: c = {}".format(i, ", ".join(str(c) for c in dict.fromkeys(s.lowlevel.formation for s in g)))
                for i, g in enumerate(groups)
            )
        )
        with ProcessPoolExecutor(len(groups), mp_context=multiprocessing.get_context("spawn")) as pool:
            futures = [
                pool.submit(_run_stages, g, out, policies_dir, resume, False, f"w{i} ", command)
                for i, g in enumerate(groups)
            ]
            cards = [card for f in futures for card in f.result()]
    _log(
        f"[lowlevel-all] stage {distill.name}: budget {distill.budget} "
        f"(pipeline wall-clock so far {time.perf_counter() - start:.0f} s)"
    )
    card = train_student(
        distill.distill,
        policies_dir,
        out,
        resume=resume and _started(out, distill.name),
        show_progress=show_progress,
        command=command,
    )
    _log(f"[lowlevel-all] {distill.name} done: {_summary(card)}")
    _log(f"[lowlevel-all] finished in {time.perf_counter() - start:.0f} s")
    return cards + [card]


def _started(out: Path, stage_name: str) -> bool:
    """The stage has a run folder with resumable state (a resumed pipeline continues it)."""
    return (Path(out) / stage_name / STATE_FILE).exists()


def _run_stages(
    stages: list[Stage],
    out: Path,
    policies_dir: Path,
    resume: bool,
    show_progress: bool,
    prefix: str,
    command: str | None = None,
) -> list[dict]:
    """Train AT-M stages in order (one worker's share of the pipeline)."""
    cards = []
    start = time.perf_counter()
    for stage in stages:
        _log(
            f"[lowlevel-all] {prefix}{stage.name}: budget {stage.budget} (worker wall-clock "
            f"{time.perf_counter() - start:.0f} s)"
        )
        card = train_lowlevel(
            stage.lowlevel,
            out,
            policies_dir,
            resume=resume and _started(out, stage.name),
            show_progress=show_progress,
            command=command,
        )
        cards.append(card)
        _log(f"[lowlevel-all] {prefix}{stage.name} done after {card['iterations']} it: {_summary(card)}")
    return cards


def _summary(card: dict) -> str:
    t3 = card.get("table3")
    if t3 and "ours" in t3:
        o = t3["ours"]
        return f"Table III protocol R_L {o['R_L']:.1f} F {o['F']:.1f} N {o['N']:.1f} C {o['C']:.2f}%"
    if t3:
        return "; ".join(
            f"c={c}: F {v['ours']['F']:.1f} N {v['ours']['N']:.1f} C {v['ours']['C']:.2f}%" for c, v in t3.items()
        )
    return "exported"


def _log(message: str) -> None:
    print(message, flush=True)
