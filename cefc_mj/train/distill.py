"""Policy distillation (paper Sec. IV-B3, Algorithm 1 lines 13-19): one student for every c.

1. Replay: each teacher pi_L^c (the Step 3 policy of formation c) flies its own group of c agents
   at the training obstacle density; every agent-step gives one tuple (z, u): the observation (which
   holds the anchor vector p_a) and the teacher's deterministic head output (see collect_replay).
   All formations share one observation shape (K = 7 zero-padded neighbour slots), so the tuples
   need no further padding. The episodes of the last few envs are held out.
2. Student: an AT-M-shaped network with hidden 256, trained by MSE (eq. 9) with Adam 1e-4; each
   batch of 600 draws the same number of tuples from every teacher.

Run folder <out>/atm_student/: config.json, replay.pt, progress.csv, tb/, state.pt; the policy goes
to <policies_dir>/atm_student.pt with its model card.
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from cefc_mj.env import BatchedCEFCEnv
from cefc_mj.errors import CheckpointError, ConfigError
from cefc_mj.fileio import write_atomic
from cefc_mj.nn import registry
from cefc_mj.nn.atm import ATMActor, ATMConfig
from cefc_mj.nn.policy_io import (
    Policy,
    atomic_torch_save,
    checkpoint_errors,
    load_policy,
    resolve_policy_path,
    safe_torch_load,
    save_policy,
)
from cefc_mj.provenance import file_sha256
from cefc_mj.task.config import TaskConfig
from cefc_mj.train.config import DistillConfig
from cefc_mj.train.logger import RunLogger
from cefc_mj.train.mappo import iteration_seed
from cefc_mj.train.model_card import display_path, table3_figures, write_model_card
from cefc_mj.train.run_state import STATE_FILE, run_state_path

STUDENT_NAME = registry.STUDENT
STATE_FORMAT = "cefc-mj/distill-state"
COLLECT_ENVS = 40
LOG_EVERY = 200


@torch.no_grad()
def collect_replay(
    teacher: Policy,
    formation: int,
    tuples: int,
    density: float,
    seed: int,
    held_out: float,
    n_envs: int = COLLECT_ENVS,
    progress=None,
) -> dict[str, torch.Tensor]:
    """Fly `teacher` with `formation` agents until `tuples` training tuples are stored (`progress`, a
    tqdm bar, counts them).

    The stored action is the teacher's deterministic head output (for the velocity head: the
    velocity setpoint, which the shared fixed loop turns into the acceleration the env applies).
    Returns {"obs", "actions"} (training) and {"held_obs", "held_actions"} (from the last
    ceil(held_out * n_envs) envs, never trained on). Observations [n, D] float32, actions [n, 2].
    """
    env = BatchedCEFCEnv(TaskConfig(n_agents=formation, mode="formation", obstacle_density=density), n_envs, seed)
    held_envs = max(1, math.ceil(held_out * n_envs))
    train_obs, train_act, held_obs, held_act = [], [], [], []
    stored, episode = 0, 0
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        while stored < tuples:
            obs = env.reset(seed=iteration_seed(seed, episode))
            done = np.zeros(n_envs, dtype=bool)
            while not done.all() and stored < tuples:
                obs_t = torch.from_numpy(obs.copy())
                command = teacher.actor(obs_t)  # the head output the student learns to reproduce
                train_obs.append(obs_t[:-held_envs].reshape(-1, obs.shape[-1]))
                train_act.append(command[:-held_envs].reshape(-1, 2))
                held_obs.append(obs_t[-held_envs:].reshape(-1, obs.shape[-1]))
                held_act.append(command[-held_envs:].reshape(-1, 2))
                added = min(train_obs[-1].shape[0], tuples - stored)
                stored += train_obs[-1].shape[0]
                if progress is not None:
                    progress.update(added)
                obs, _, done, _ = env.step(teacher.actor.to_acceleration(command, obs_t).numpy())
            episode += 1
    finally:
        torch.set_num_threads(threads)
    return {
        "obs": torch.cat(train_obs)[:tuples].clone(),
        "actions": torch.cat(train_act)[:tuples].clone(),
        "held_obs": torch.cat(held_obs),
        "held_actions": torch.cat(held_act),
    }


def teacher_name(formation: int, teacher: str = registry.DISTILL_TEACHER) -> str:
    """The policy name of c's teacher (DistillConfig.teacher: "step3" or "nav")."""
    return registry.lowlevel_name(formation, teacher)


@torch.no_grad()
def held_out_error(student: ATMActor, replay: dict[int, dict[str, torch.Tensor]]) -> dict[str, float]:
    """Per formation: MSE of the student's mean against the teacher's actions on held-out tuples, and
    the same relative to the teacher actions' variance (0 = exact, 1 = no better than their mean)."""
    out = {}
    for c, r in replay.items():
        pred = student(r["held_obs"])
        mse = (pred - r["held_actions"]).pow(2).sum(-1).mean().item()
        var = r["held_actions"].var(0).sum().item()
        out[f"held_mse/c{c}"] = mse
        out[f"held_rel/c{c}"] = mse / max(var, 1e-12)
    return out


def train_student(
    cfg: DistillConfig,
    policies_dir: Path,
    out: Path,
    resume: bool = False,
    show_progress: bool = True,
    evaluate: bool = True,
    teachers_dir: Path | None = None,
    command: str | None = None,
) -> dict:
    """Collect (or reload) the replay, train the student under cfg.budget, export it with a card.

    Teachers are `<teachers_dir>/atm_c{c}_<cfg.teacher>.pt` (teachers_dir defaults to policies_dir).
    resume: continue the run in <out>/atm_student/ (ConfigError if there is none). command: the
    command line, recorded in config.json and the card. The inputs (run folder, teachers) are
    checked before the run folder is made."""
    policies_dir, out = Path(policies_dir), Path(out)
    teachers_dir = Path(teachers_dir) if teachers_dir is not None else policies_dir
    run_dir = out / STUDENT_NAME
    state_path, replay_path = run_dir / STATE_FILE, run_dir / "replay.pt"
    run_state_path(run_dir, resume)
    teacher_paths = {c: resolve_policy_path(teacher_name(c, cfg.teacher), teachers_dir) for c in cfg.formations}
    teachers = {c: load_policy(path) for c, path in teacher_paths.items()}
    heads = {(t.actor.cfg.layout, t.actor.cfg.action, t.actor.cfg.velocity_gain) for t in teachers.values()}
    if len(heads) != 1:
        raise CheckpointError("distillation: the teachers differ in observation layout or action head")
    teacher_cfg = next(iter(teachers.values())).actor.cfg
    run_dir.mkdir(parents=True, exist_ok=True)

    if replay_path.exists():
        saved = safe_torch_load(replay_path)
        with checkpoint_errors(replay_path, "not a distillation replay"):
            replay = {int(c): r for c, r in saved["replay"].items()}
        if saved.get("config") != cfg.to_dict() or sorted(replay) != sorted(cfg.formations):
            raise ConfigError(f"{replay_path} was collected with other settings; use another --out")
    else:
        replay = {}
        total = cfg.tuples_per_formation * len(teachers)
        with tqdm(
            total=total, desc="collecting replay", unit="tuple", disable=not show_progress, mininterval=2.0
        ) as bar:
            for c, teacher in teachers.items():
                bar.set_postfix_str(f"teacher c = {c}")
                replay[c] = collect_replay(
                    teacher,
                    c,
                    cfg.tuples_per_formation,
                    cfg.collect_density,
                    iteration_seed(cfg.seed, 1000 + c),
                    cfg.held_out,
                    progress=bar,
                )
        atomic_torch_save({"config": cfg.to_dict(), "replay": {str(c): r for c, r in replay.items()}}, replay_path)
    teacher_files = {
        str(c): {"path": display_path(path), "sha256": file_sha256(path.resolve())} for c, path in teacher_paths.items()
    }
    write_atomic(
        run_dir / "config.json",
        json.dumps({"distill": cfg.to_dict(), "teachers": teacher_files, "command": command}, indent=2) + "\n",
    )

    torch.set_num_threads(cfg.threads)
    torch.manual_seed(cfg.seed)
    student = ATMActor(
        ATMConfig(
            layout=teacher_cfg.layout,
            lidar_range=teacher_cfg.lidar_range,
            accel_max=teacher_cfg.accel_max,
            hidden=cfg.hidden,
            action=teacher_cfg.action,
            velocity_gain=teacher_cfg.velocity_gain,
        )
    )
    optimizer = torch.optim.Adam(student.parameters(), lr=cfg.lr)
    generator = torch.Generator().manual_seed(cfg.seed)
    step, elapsed = 0, 0.0
    if state_path.exists():
        state = safe_torch_load(state_path)
        with checkpoint_errors(state_path, "not a distillation state of this run"):
            if state.get("format") != STATE_FORMAT or state.get("config", {}).get("formations") != list(cfg.formations):
                raise CheckpointError(f"{state_path}: not a distillation state of this run")
            student.load_state_dict(state["student"])
            optimizer.load_state_dict(state["optimizer"])
            generator.set_state(state["generator"])
            step, elapsed = int(state["step"]), float(state["elapsed"])

    def checkpoint() -> None:
        atomic_torch_save(
            {
                "format": STATE_FORMAT,
                "config": {**cfg.to_dict(), "formations": list(cfg.formations)},
                "student": student.state_dict(),
                "optimizer": optimizer.state_dict(),
                "generator": generator.get_state(),
                "step": step,
                "elapsed": elapsed,
            },
            state_path,
        )

    if step == 0:
        checkpoint()  # step 0: a run killed before its first periodic checkpoint can still --resume
    per_teacher = max(1, cfg.batch_size // len(replay))
    total_logs = None if cfg.budget.iterations is None else cfg.budget.iterations
    logger = RunLogger(run_dir, step, total_logs, desc=STUDENT_NAME, show_progress=show_progress)
    running = 0.0
    try:
        while not cfg.budget.exhausted(step, elapsed):
            t0 = time.perf_counter()
            obs, target = [], []
            for r in replay.values():
                idx = torch.randint(r["obs"].shape[0], (per_teacher,), generator=generator)
                obs.append(r["obs"][idx])
                target.append(r["actions"][idx])
            pred = student(torch.cat(obs))
            loss = (pred - torch.cat(target)).pow(2).sum(-1).mean()
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
            step += 1
            elapsed += time.perf_counter() - t0
            running += loss.item()
            if step % LOG_EVERY == 0 or cfg.budget.exhausted(step, elapsed):
                n = step % LOG_EVERY or LOG_EVERY
                row = {"iteration": step, "wall_s": elapsed, "loss": running / n, **held_out_error(student, replay)}
                logger.log(row, ("loss",), advance=n)
                running = 0.0
            if step % cfg.checkpoint_every == 0:
                checkpoint()
    finally:
        logger.close()
    checkpoint()

    errors = held_out_error(student, replay)
    policy_path = save_policy(
        student,
        policies_dir / f"{STUDENT_NAME}.pt",
        meta={
            "name": STUDENT_NAME,
            "method": "Student",
            "formations": list(cfg.formations),
            "seed": cfg.seed,
            "steps": step,
        },
    )
    card = {
        "name": STUDENT_NAME,
        "method": "Student",
        "formations": list(cfg.formations),
        "seed": cfg.seed,
        "config": cfg.to_dict(),
        "network": student.cfg.to_dict(),
        "teachers": teacher_files,
        "replay_tuples": {str(c): int(r["obs"].shape[0]) for c, r in replay.items()},
        "held_out_tuples": {str(c): int(r["held_obs"].shape[0]) for c, r in replay.items()},
        "gradient_steps": step,
        "samples": step * per_teacher * len(replay),
        "train_wall_clock_s": round(elapsed, 1),
        "held_out_error": errors,
        "run_dir": display_path(run_dir),
        "command": command,  # with config and teachers: the run's config.json
    }
    if evaluate:
        card["table3"] = {str(c): table3_figures(policy_path, c, None, seed=0) for c in cfg.formations}
    write_model_card(policy_path, card)
    return card
