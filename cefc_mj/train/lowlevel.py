"""One AT-M training stage end to end (Algorithm 1 of the paper, one step for one formation c).

    run folder   <out>/<name>/   config.json, progress.csv, tb/, state.pt (resumable)
    policy file  <policies_dir>/<name>.pt   + <name>.json model card

with name = atm_c{c}_step{1,2,3}, atm_c{c}_safe, atm_c{c}_robust, atm_c{c}_quad or clm_c{c}. Initialisation:

- Step 1: random init, obstacle density 0.
- Step 2: random init, density 0.03.
- Step 3: formation & output modules (and log-std) from Step 1's final actor, obstacle module from
  Step 2's, critic and value-norm statistics from Step 2 (phi_{L,2}); density 0.03. Reads
  <out>/atm_c{c}_step1/state.pt and <out>/atm_c{c}_step2/state.pt.
- Safe, Robust, Quad: Step 3's final actor, critic and value norm (<out>/atm_c{c}_step3/state.pt),
  trained further with the Safe LiDAR transform, sensing deviation or quadrotor-like dynamics.
- Any Step 3 stage with `init_from` (a policy file, e.g. the shipped policies/atm_c6_step3.pt):
  the actor from that file, the critic and value normalisation fresh, because a policy file holds
  only the actor. This needs no earlier run folders.
- CL-M (a config with a `curriculum`): random init like Step 1, then one MAPPO run whose obstacle
  density rises through the curriculum's phases, each an equal share of the budget. Every iteration
  logs its `curriculum_phase` and `obstacle_density`; the state records the iterations trained in
  each phase, so `--resume` re-enters the phase the run had reached (and never goes back to an
  easier one, even when a larger budget moves the phase boundaries).

`state.pt` holds networks, optimizers, value-norm statistics, the torch RNG, counters and the
config; `train_lowlevel(..., resume=True)` continues it exactly (see MAPPO).
"""

from __future__ import annotations

import csv
import dataclasses
import functools
import json
from pathlib import Path

import numpy as np
import torch

from cefc_mj.env import BatchedCEFCEnv
from cefc_mj.errors import CheckpointError, ConfigError
from cefc_mj.fileio import write_atomic
from cefc_mj.nn.atm import ATMActor, ATMConfig, Critic, merge_step3
from cefc_mj.nn.policy_io import atomic_torch_save, checkpoint_errors, load_actor, resolve_policy_path, save_policy
from cefc_mj.nn.registry import lowlevel_name
from cefc_mj.provenance import file_sha256
from cefc_mj.sim.mujoco_world import MujocoWorldConfig, make_mujoco_world
from cefc_mj.sim.wind import WindConfig
from cefc_mj.task.config import FORMATION_EPISODE_STEPS, RewardConfig, TaskConfig
from cefc_mj.train import run_state
from cefc_mj.train.config import LowLevelConfig, MujocoTraining
from cefc_mj.train.logger import RunLogger
from cefc_mj.train.mappo import MAPPO, particle_env
from cefc_mj.train.model_card import display_path, table3_figures, write_model_card
from cefc_mj.train.ppo import ValueNorm
from cefc_mj.train.run_state import STATE_FILE

STATE_FORMAT = "cefc-mj/train-state"
PROGRESS_KEYS = ("reward_per_step", "metric/F", "metric/N", "metric/C", "approx_kl")


def task_config_for(cfg: LowLevelConfig, density: float | None = None) -> TaskConfig:
    """The low-level game of a stage: one group of c agents, an anchor, the step's obstacle density
    (or `density`, a curriculum phase's)."""
    density = cfg.density if density is None else density
    rewards = RewardConfig()
    if cfg.collision_margin:
        rewards = dataclasses.replace(
            rewards,
            safety_distance=rewards.safety_distance + cfg.collision_margin,
            collision_alert_distance=rewards.collision_alert_distance + cfg.collision_margin,
        )
    if cfg.navigation_weight is not None:
        rewards = dataclasses.replace(rewards, navigation_weight_low=float(cfg.navigation_weight))
    return TaskConfig(
        n_agents=cfg.formation,
        mode="formation",
        obstacle_density=density,
        deviation=cfg.deviation,
        deviation_sampling=cfg.deviation_sampling,
        response_time=cfg.response_time,
        velocity_noise=cfg.velocity_noise,
        accel_max=float(cfg.accel_max),
        push_observer_s=float(cfg.push_observer_s),
        rewards=rewards,
        lidar_sees_agents=cfg.lidar_sees_uavs,
        straggler_fraction=float(cfg.straggler_fraction),
        **_anchor_periods(cfg.anchor_periods),
    )


def training_wind(training: MujocoTraining, episode_seconds: float) -> WindConfig:
    """The wind of a MuJoCo fine-tune: each episode's mean speed uniform in [0, wind_max], its
    direction uniform, and a gust at a uniformly drawn time that ends before the episode does."""
    gust = training.gust_speed > 0 and training.gust_duration > 0
    return WindConfig(
        mean_speed=0.0,
        mean_speed_max=float(training.wind_max),
        gust_mean_speed=float(training.gust_speed) if gust else 0.0,
        gust_duration=float(training.gust_duration) if gust else 0.0,
        gust_start=0.0,
        gust_start_max=max(0.0, episode_seconds - training.gust_duration) if gust else None,
    )


PRIVILEGED_STATE = 5
"""Entries the MuJoCo training critic sees beyond the global state (WindAwareCriticEnv)."""


class WindAwareCriticEnv(BatchedCEFCEnv):
    """The MuJoCo training env, whose centralized critic also sees what no agent senses: the wind
    vector now, the episode's mean wind (speed along its direction) and the episode's sensing
    deviation. The agents' observations are unchanged (an asymmetric actor-critic): without these the
    critic cannot tell a calm episode from an 8 m/s one, and the wind's share of each return would be
    noise in every advantage."""

    def global_state(self) -> np.ndarray:
        wind = self.world.wind
        privileged = np.column_stack(
            [
                wind.vector[:, :2],
                wind.mean_speed * np.cos(wind.mean_direction),
                wind.mean_speed * np.sin(wind.mean_direction),
                self.env_deviation,
            ]
        ).astype(np.float32)
        return np.concatenate([super().global_state(), privileged], axis=-1)

    @property
    def state_size(self) -> int:
        return super().state_size + PRIVILEGED_STATE


def critic_input_size(cfg: LowLevelConfig, task: TaskConfig) -> int:
    """The centralized critic's input width of a stage: its env's global state and one observation."""
    probe = BatchedCEFCEnv(task, n_envs=1)
    return probe.state_size + probe.layout.size + (PRIVILEGED_STATE if cfg.mujoco is not None else 0)


def mujoco_training_env(task: TaskConfig, n_envs: int, seed: int, training: MujocoTraining) -> BatchedCEFCEnv:
    """`n_envs` episodes of the stage's game on MuJoCo quadrotors, through `training`'s offboard
    interface and wind (a rollout worker builds its share with this too)."""
    world_cfg = MujocoWorldConfig(offboard=training.offboard)
    wind = training_wind(training, task.steps * world_cfg.decision_dt)
    world = make_mujoco_world(task, n_envs=n_envs, wind=wind, seed=seed, config=world_cfg)
    return WindAwareCriticEnv(task, n_envs=n_envs, seed=seed, world=world)


def _anchor_periods(periods: int) -> dict:
    """TaskConfig fields of training episodes of `periods` anchor periods (none for the paper's one)."""
    if periods == 1:
        return {}
    return {"episode_steps": periods * FORMATION_EPISODE_STEPS, "anchor_redraw_steps": FORMATION_EPISODE_STEPS}


def stage_name(formation: int, step: int, safe: bool = False) -> str:
    return lowlevel_name(formation, "safe" if safe else f"step{step}")


def read_state(path: Path) -> dict:
    """A training state written by `train_lowlevel`, checked for its format."""
    return run_state.read_state(path, STATE_FORMAT, "training state")


def _fresh_networks(cfg: LowLevelConfig, task: TaskConfig) -> tuple[ATMActor, Critic]:
    torch.manual_seed(cfg.seed)
    actor = ATMActor(ATMConfig.from_task(task, hidden=cfg.hidden, safe=cfg.safe, log_std_init=cfg.log_std_init))
    critic = Critic(critic_input_size(cfg, task), hidden=cfg.critic_hidden)
    return actor, critic


def _source_state(out: Path, name: str, cfg: LowLevelConfig) -> tuple[dict, ATMActor]:
    path = out / name / STATE_FILE
    if not path.is_file():
        raise ConfigError(
            f"{cfg.name} starts from {name}: no training state at {path}; train that stage first, "
            f"or start from a trained policy with --init-from {stage_name(cfg.formation, 3)}"
        )
    payload = read_state(path)
    with checkpoint_errors(path, "actor does not fit"):
        src_cfg = LowLevelConfig.from_dict(payload["config"])
        src_task = task_config_for(src_cfg)
        actor = ATMActor(ATMConfig.from_task(src_task, hidden=src_cfg.hidden, safe=src_cfg.safe))
        actor.load_state_dict(payload["trainer"]["actor"])
    return payload, actor


# The actor-shape fields a policy file must share with the stage it initialises (safe, log_std_init and
# accel_max may differ: the Safe transform is an input transform, the log-std is a loaded weight, and
# the action bound clips the network's output, whose weights mean the same under either bound).
_INIT_SHAPE_FIELDS = ("layout", "lidar_range", "hidden", "act_dim", "action", "velocity_gain")


def load_init_policy(path_or_name: str | Path, cfg: LowLevelConfig) -> tuple[ATMActor, dict]:
    """The actor of a trained policy file that `cfg` (a Step 3 stage) starts from, and the origin
    record for its model card. `path_or_name` is a file or a name in the shipped policies folder.
    The file holds only the actor: the critic and value normalisation start fresh."""
    if cfg.step != 3:
        raise ConfigError(
            f"--init-from: {cfg.name} (AT-M Step {cfg.step}) starts from random weights; --init-from "
            "is for Step 3 stages (Step 3 itself, --safe, --deviation, --response-time/--velocity-noise)"
        )
    expected = ATMConfig.from_task(
        task_config_for(cfg), hidden=cfg.hidden, safe=cfg.safe, log_std_init=cfg.log_std_init
    )
    try:
        path = resolve_policy_path(path_or_name)
        actor, meta = load_actor(path, obs_dim=expected.obs_dim)
    except CheckpointError as e:
        raise CheckpointError(f"--init-from: {e}") from None
    differ = [f for f in _INIT_SHAPE_FIELDS if getattr(actor.cfg, f) != getattr(expected, f)]
    if differ:
        shown = ", ".join(
            f if f == "layout" else f"{f} {getattr(actor.cfg, f)!r} (this stage: {getattr(expected, f)!r})"
            for f in differ
        )
        raise CheckpointError(f"--init-from {path}: made for another network: {shown}")
    origin = {
        "actor": f"policy file {display_path(path)}",
        "critic": "fresh (random), value normalisation fresh: a policy file holds only the actor",
        "init_from": {
            "path": display_path(path),
            "sha256": file_sha256(path.resolve()),
            "name": meta.get("name"),
            "iterations": meta.get("iterations"),
        },
    }
    return actor, origin


def initial_networks(
    cfg: LowLevelConfig, task: TaskConfig, out: Path, init_from: tuple[ATMActor, dict] | None = None
) -> tuple[ATMActor, Critic, ValueNorm, dict]:
    """Actor, critic and value norm a stage starts from, and where they came from (for the model card).
    `init_from`: the (actor, origin) of `load_init_policy`, used instead of earlier stages' states."""
    actor, critic = _fresh_networks(cfg, task)
    value_norm = ValueNorm()
    if init_from is not None:
        src_actor, origin = init_from
        actor.load_state_dict(src_actor.state_dict())
        return actor, critic, value_norm, dict(origin)
    if cfg.step != 3:
        return actor, critic, value_norm, {"actor": "random", "critic": "random"}
    if cfg.fine_tune:
        (step3,) = cfg.source_stages
        src, src_actor = _source_state(out, step3, cfg)
        actor.load_state_dict(src_actor.state_dict())
        origin = {"actor": step3, "critic": step3}
    else:
        step1, step2 = cfg.source_stages
        _, step1_actor = _source_state(out, step1, cfg)
        src, step2_actor = _source_state(out, step2, cfg)
        actor.load_state_dict(merge_step3(step1_actor, step2_actor).state_dict())
        origin = {"actor": f"formation & output modules, log-std: {step1}; obstacle module: {step2}", "critic": step2}
    critic.load_state_dict(src["trainer"]["critic"])
    value_norm.load_state_dict(src["trainer"]["value_norm"])
    origin["source_iterations"] = int(src["trainer"]["counters"]["iteration"])
    return actor, critic, value_norm, origin


def curriculum_tasks(cfg: LowLevelConfig) -> list[TaskConfig] | None:
    """The training game of each curriculum phase (None without a curriculum); building them checks
    every phase's density against the arena before anything is written."""
    return None if cfg.curriculum is None else [task_config_for(cfg, d) for d in cfg.curriculum]


def enter_curriculum_phase(trainer: MAPPO, cfg: LowLevelConfig, tasks: list[TaskConfig], progress: dict) -> int:
    """Move `trainer` to the curriculum phase its iterations and time have reached and return it.
    `progress["phase"]` is the phase trained last; the phase never goes back (a resumed run with a
    larger budget stays in the phase it reached). Each iteration reseeds its episodes, so swapping
    the env between iterations keeps a resumed run identical to an uninterrupted one."""
    phase = max(progress["phase"], cfg.curriculum_phase(trainer.iteration, trainer.elapsed))
    progress["phase"] = phase
    if trainer.task_cfg != tasks[phase]:
        trainer.task_cfg = tasks[phase]
        trainer.env = BatchedCEFCEnv(tasks[phase], n_envs=cfg.ppo.n_envs, seed=cfg.seed)
    return phase


def _curriculum_card(cfg: LowLevelConfig, progress: dict) -> dict:
    """The curriculum as the model card records it: each phase's density and iterations trained."""
    return {
        "schedule": "equal shares of the budget, in order",
        "final_phase": progress["phase"],
        "phases": [{"density": d, "iterations": n} for d, n in zip(cfg.curriculum, progress["iterations"])],
    }


def _last_csv_row(run_dir: Path) -> dict:
    with (run_dir / "progress.csv").open(newline="") as f:
        rows = list(csv.DictReader(f))
    return rows[-1] if rows else {}


def train_lowlevel(
    cfg: LowLevelConfig,
    out: Path,
    policies_dir: Path,
    resume: bool = False,
    show_progress: bool = True,
    evaluate: bool = True,
    init_from: str | Path | None = None,
    command: str | None = None,
    policy_name: str | None = None,
) -> dict:
    """Train one stage under its budget; export the policy and its model card. Returns the card.
    policy_name: the exported policy's name and file stem (default the stage name; a seed sweep
    adds _s<seed>).

    resume: continue the run in <out>/<name>/ (ConfigError if there is none). init_from: a policy
    file or shipped policy name the actor of a Step 3 stage starts from (see load_init_policy).
    command: the command line, recorded in config.json and the card. Every check on the inputs
    runs before the run folder is made."""
    out, policies_dir = Path(out), Path(policies_dir)
    run_dir = out / cfg.name
    state_path = run_dir / STATE_FILE
    task = task_config_for(cfg)
    phase_tasks = curriculum_tasks(cfg)
    init = load_init_policy(init_from, cfg) if init_from is not None else None

    saved = None
    if run_state.run_state_path(run_dir, resume) is not None:
        saved = read_state(state_path)
        run_state.check_same_run(saved["config"], cfg, state_path, free=("budget", "checkpoint_every"))
        if init is not None and saved["origin"].get("init_from", {}).get("sha256") != init[1]["init_from"]["sha256"]:
            raise ConfigError(
                f"--init-from {init_from}: the run in {run_dir} started from {saved['origin']['actor']}; "
                "resume it without --init-from, or choose another --out"
            )
        actor, critic = _fresh_networks(cfg, task)
        value_norm, origin = ValueNorm(), saved["origin"]
    else:
        actor, critic, value_norm, origin = initial_networks(cfg, task, out, init)
    make_env = particle_env if cfg.mujoco is None else functools.partial(mujoco_training_env, training=cfg.mujoco)
    workers = 1 if cfg.mujoco is None else cfg.mujoco.rollout_workers
    trainer = MAPPO(
        task, cfg.ppo, actor, critic, seed=cfg.seed, value_norm=value_norm, make_env=make_env, rollout_workers=workers
    )
    if cfg.mujoco is not None:
        trainer.critic_warmup = cfg.mujoco.critic_warmup
    try:
        if saved is not None:
            run_state.restore_trainer(trainer, saved, state_path)
        # CL-M: the phase trained last and the iterations of each phase (restored on resume).
        curriculum = None
        if cfg.curriculum is not None:
            fresh = {"phase": 0, "iterations": [0] * len(cfg.curriculum)}
            curriculum = saved["curriculum"] if saved is not None else fresh

        run_config = {"stage": cfg.to_dict(), "task": task.to_dict(), "init": origin, "command": command}
        write_atomic(run_dir / "config.json", json.dumps(run_config, indent=2) + "\n")

        def checkpoint() -> None:
            atomic_torch_save(
                {
                    "format": STATE_FORMAT,
                    "config": cfg.to_dict(),
                    "origin": origin,
                    "trainer": trainer.state_dict(),
                    "curriculum": curriculum,
                },
                state_path,
            )

        if saved is None:
            checkpoint()  # iteration 0: a run killed before its first periodic checkpoint can still --resume

        def iterate() -> dict:
            if curriculum is None:
                return trainer.iterate()
            phase = enter_curriculum_phase(trainer, cfg, phase_tasks, curriculum)
            row = trainer.iterate()
            curriculum["iterations"][phase] += 1
            row.update(curriculum_phase=phase, obstacle_density=cfg.curriculum[phase])
            return row

        logger = RunLogger(
            run_dir, trainer.iteration, cfg.budget.iterations, desc=cfg.name, show_progress=show_progress
        )
        last_row = run_state.train_under_budget(
            trainer, cfg.budget, cfg.checkpoint_every, logger, PROGRESS_KEYS, checkpoint, iterate
        )
        if not last_row and trainer.iteration:  # a finished run re-exported: report its last logged iteration
            last_row = {k: float(v) for k, v in _last_csv_row(run_dir).items()}

        name = policy_name or cfg.name
        policy_path = save_policy(
            actor,
            policies_dir / f"{name}.pt",
            meta={
                "name": name,
                "method": cfg.method,
                "formation": cfg.formation,
                "seed": cfg.seed,
                "iterations": trainer.iteration,
                "agent_steps": trainer.agent_steps,
            },
        )
        card = {
            "name": name,
            "method": cfg.method,
            "formation": cfg.formation,
            "seed": cfg.seed,
            "differs_from_paper": cfg.paper_differences(),
            "config": cfg.to_dict(),
            "task": task.to_dict(),
            "network": actor.cfg.to_dict(),
            "init": origin,
            "init_from": origin.get("init_from"),
            **({"curriculum": _curriculum_card(cfg, curriculum)} if curriculum is not None else {}),
            "iterations": trainer.iteration,
            "agent_steps": trainer.agent_steps,
            "env_steps": trainer.agent_steps // cfg.formation,
            "train_wall_clock_s": round(trainer.elapsed, 1),
            "agent_steps_per_s": round(trainer.agent_steps / trainer.elapsed, 1) if trainer.elapsed else None,
            "last_iteration": {k: v for k, v in last_row.items() if isinstance(v, (int, float))},
            "run_dir": display_path(run_dir),
            "command": command,  # with config, task and init: the run's config.json
        }
        if evaluate:
            card["table3"] = table3_figures(policy_path, cfg.formation, cfg.method, seed=0)
        write_model_card(policy_path, card)
        return card
    finally:
        trainer.close()
