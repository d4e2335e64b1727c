"""One AT-M training stage end to end (Algorithm 1 of the paper, one step for one formation c).

    run folder   <out>/<name>/   config.json, progress.csv, tb/, state.pt (resumable)
    policy file  <policies_dir>/<name>.pt   + <name>.json model card

with name = atm_c{c}_step{1,2,3} or atm_c{c}_safe. Initialisation per step:

- Step 1: random init, obstacle density 0.
- Step 2: random init, density 0.03.
- Step 3: formation & output modules (and log-std) from Step 1's final actor, obstacle module from
  Step 2's, critic and value-norm statistics from Step 2 (phi_{L,2}); density 0.03. Reads
  <out>/atm_c{c}_step1/state.pt and <out>/atm_c{c}_step2/state.pt.
- Safe: Step 3's final actor, critic and value norm, trained further with the Safe LiDAR transform.

`state.pt` holds networks, optimizers, value-norm statistics, the torch RNG, counters and the
config; `train_lowlevel(..., resume=True)` continues it exactly (see MAPPO).
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

import torch

from cefc_mj.env import BatchedCEFCEnv
from cefc_mj.errors import CheckpointError, ConfigError
from cefc_mj.nn.atm import ATMActor, ATMConfig, Critic, merge_step3
from cefc_mj.nn.policy_io import atomic_torch_save, safe_torch_load, save_policy
from cefc_mj.task.config import TaskConfig
from cefc_mj.train.config import LowLevelConfig
from cefc_mj.train.logger import RunLogger
from cefc_mj.train.mappo import MAPPO
from cefc_mj.train.model_card import table3_figures, write_model_card
from cefc_mj.train.ppo import ValueNorm

STATE_FORMAT = "cefc-mj/train-state"
STATE_FILE = "state.pt"
PROGRESS_KEYS = ("reward_per_step", "metric/F", "metric/N", "metric/C", "approx_kl")


def task_config_for(cfg: LowLevelConfig) -> TaskConfig:
    """The low-level game of a stage: one group of c agents, an anchor, the step's obstacle density."""
    return TaskConfig(n_agents=cfg.formation, mode="formation", obstacle_density=cfg.density, deviation=cfg.deviation,
                      deviation_sampling=cfg.deviation_sampling, response_time=cfg.response_time,
                      velocity_noise=cfg.velocity_noise)


def stage_name(formation: int, step: int, safe: bool = False) -> str:
    return f"atm_c{formation}_safe" if safe else f"atm_c{formation}_step{step}"


def read_state(path: Path) -> dict:
    """A training state written by `train_lowlevel`, checked for its format."""
    payload = safe_torch_load(path)
    if payload.get("format") != STATE_FORMAT or "trainer" not in payload or "config" not in payload:
        raise CheckpointError(f"{path}: not a cefc-mj training state")
    return payload


def _fresh_networks(cfg: LowLevelConfig, task: TaskConfig) -> tuple[ATMActor, Critic]:
    torch.manual_seed(cfg.seed)
    actor = ATMActor(ATMConfig.from_task(task, hidden=cfg.hidden, safe=cfg.safe, log_std_init=cfg.log_std_init))
    env = BatchedCEFCEnv(task, n_envs=1)
    critic = Critic(env.state_size + env.layout.size, hidden=cfg.critic_hidden)
    return actor, critic


def _source_state(out: Path, name: str, for_stage: str) -> tuple[dict, ATMActor]:
    path = out / name / STATE_FILE
    if not path.is_file():
        raise ConfigError(f"{for_stage} starts from {name}: no training state at {path}; train that stage first")
    payload = read_state(path)
    src_cfg = LowLevelConfig.from_dict(payload["config"])
    src_task = task_config_for(src_cfg)
    actor = ATMActor(ATMConfig.from_task(src_task, hidden=src_cfg.hidden, safe=src_cfg.safe))
    try:
        actor.load_state_dict(payload["trainer"]["actor"])
    except RuntimeError as e:
        raise CheckpointError(f"{path}: actor does not fit ({str(e).splitlines()[0][:160]})") from None
    return payload, actor


def initial_networks(cfg: LowLevelConfig, task: TaskConfig, out: Path) -> tuple[ATMActor, Critic, ValueNorm, dict]:
    """Actor, critic and value norm a stage starts from, and where they came from (for the model card)."""
    actor, critic = _fresh_networks(cfg, task)
    value_norm = ValueNorm()
    if cfg.step != 3:
        return actor, critic, value_norm, {"actor": "random", "critic": "random"}
    if cfg.fine_tune:
        src, src_actor = _source_state(out, stage_name(cfg.formation, 3), cfg.name)
        actor.load_state_dict(src_actor.state_dict())
        origin = {"actor": stage_name(cfg.formation, 3), "critic": stage_name(cfg.formation, 3)}
    else:
        _, step1 = _source_state(out, stage_name(cfg.formation, 1), cfg.name)
        src, step2 = _source_state(out, stage_name(cfg.formation, 2), cfg.name)
        actor.load_state_dict(merge_step3(step1, step2).state_dict())
        origin = {"actor": "formation & output modules, log-std: atm_c{c}_step1; obstacle module: atm_c{c}_step2"
                  .format(c=cfg.formation), "critic": stage_name(cfg.formation, 2)}
    critic.load_state_dict(src["trainer"]["critic"])
    value_norm.load_state_dict(src["trainer"]["value_norm"])
    origin["source_iterations"] = int(src["trainer"]["counters"]["iteration"])
    return actor, critic, value_norm, origin


def _last_csv_row(run_dir: Path) -> dict:
    with (run_dir / "progress.csv").open(newline="") as f:
        rows = list(csv.DictReader(f))
    return rows[-1] if rows else {}


def _check_same_run(saved: dict, cfg: LowLevelConfig, path: Path) -> None:
    """A resumed run must have the same config except its budget (which may be extended) and how
    many threads it uses."""
    def comparable(config: LowLevelConfig) -> dict:
        d = config.to_dict()
        for key in ("budget", "checkpoint_every"):
            del d[key]
        d["ppo"] = {k: v for k, v in d["ppo"].items() if k not in ("rollout_threads", "update_threads")}
        return d

    mine, theirs = comparable(cfg), comparable(LowLevelConfig.from_dict(saved))  # fields added later: defaults
    diffs = [k for k in mine if theirs.get(k) != mine[k]]
    if diffs:
        raise ConfigError(f"--resume: {path} was made with different settings ({', '.join(diffs)}); use another --out")


def train_lowlevel(cfg: LowLevelConfig, out: Path, policies_dir: Path, resume: bool = False,
                   show_progress: bool = True, evaluate: bool = True) -> dict:
    """Train one stage under its budget; export the policy and its model card. Returns the card."""
    out, policies_dir = Path(out), Path(policies_dir)
    run_dir = out / cfg.name
    state_path = run_dir / STATE_FILE
    task = task_config_for(cfg)

    saved = None
    if state_path.exists():
        if not resume:
            raise ConfigError(f"{run_dir} already holds a run; pass --resume to continue it, or choose another --out")
        saved = read_state(state_path)
        _check_same_run(saved["config"], cfg, state_path)
        actor, critic = _fresh_networks(cfg, task)
        value_norm, origin = ValueNorm(), saved["origin"]
    else:
        actor, critic, value_norm, origin = initial_networks(cfg, task, out)
    trainer = MAPPO(task, cfg.ppo, actor, critic, seed=cfg.seed, value_norm=value_norm)
    if saved is not None:
        trainer.load_state_dict(saved["trainer"])

    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "config.json").write_text(json.dumps({"stage": cfg.to_dict(), "task": task.to_dict(), "init": origin},
                                                    indent=2) + "\n")

    def checkpoint() -> None:
        atomic_torch_save({"format": STATE_FORMAT, "config": cfg.to_dict(), "origin": origin,
                           "trainer": trainer.state_dict()}, state_path)

    logger = RunLogger(run_dir, trainer.iteration, cfg.budget.iterations, desc=cfg.name, show_progress=show_progress)
    last_row: dict = {}
    try:
        while not cfg.budget.exhausted(trainer.iteration, trainer.elapsed):
            last_row = trainer.iterate()
            logger.log(last_row, PROGRESS_KEYS)
            if trainer.iteration % cfg.checkpoint_every == 0:
                checkpoint()
    finally:
        logger.close()
    checkpoint()
    if not last_row and trainer.iteration:  # a finished run re-exported: report its last logged iteration
        last_row = {k: float(v) for k, v in _last_csv_row(run_dir).items()}

    policy_path = save_policy(actor, policies_dir / f"{cfg.name}.pt", meta={
        "name": cfg.name, "method": cfg.method, "formation": cfg.formation, "seed": cfg.seed,
        "iterations": trainer.iteration, "agent_steps": trainer.agent_steps,
    })
    card = {
        "name": cfg.name,
        "method": cfg.method,
        "formation": cfg.formation,
        "seed": cfg.seed,
        "config": cfg.to_dict(),
        "task": task.to_dict(),
        "network": actor.cfg.to_dict(),
        "init": origin,
        "iterations": trainer.iteration,
        "agent_steps": trainer.agent_steps,
        "env_steps": trainer.agent_steps // cfg.formation,
        "train_wall_clock_s": round(trainer.elapsed, 1),
        "last_iteration": {k: v for k, v in last_row.items() if isinstance(v, (int, float))},
        "run_dir": str(run_dir),
    }
    if evaluate:
        card["table3"] = table3_figures(policy_path, cfg.formation, cfg.method, seed=0)
    write_model_card(policy_path, card)
    return card
