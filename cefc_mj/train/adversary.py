"""The PPO adversary (the paper's predator, Sec. V-A): single-agent PPO against a trained UAV team.

One iteration, CleanRL-style:

1. **Collect** one 400-step episode in each of `ppo.n_envs` envs of the CEFC game
   (`HierarchicalCEFCEnv` with adversary='learned'): the UAVs fly a trained high level (default
   CI-HRL, `cihrl_consmac_a`) over a trained low level (default the distilled student), every
   decision the mode of their policies, as in the evaluation; the adversary samples its
   acceleration every low-level step from its Gaussian (`nn.adversary_policy`).
2. **Reward** after each step (`task.adversary.adversary_reward`): -0.1 x the distance (m) to the
   centre of the nearest group of >= 3 UAVs (the nearest UAV when there is none; the rule
   adversary's goal), + the share of UAVs within the 2 m alert distance, - 10 inside an obstacle
   (obstacle radius + body radius of its centre): chase the nearest group, avoid obstacles. Plus
   10 x (d_before - d_after), the metres the step approached the goal: it credits each step with
   its own approach (shaping with gamma < 1, d_before - gamma d_after, pays (1 - gamma) d for
   standing still and taught an adversary to wait far away).
3. **Update**: PPO epochs with the low level's pieces (`train.ppo`: GAE with the time-limit
   bootstrap, clipped surrogate, value normalisation); the critic V(o_adv) has 3 layers of 128.

    run folder   <out>/<name>/   config.json, progress.csv, tb/, state.pt (resumable)
    policy file  <policies_dir>/<name>.pt  + <name>.json model card      name = adversary_ppo[_seed<k>]

Every iteration's episodes are seeded from (seed, iteration); `state.pt` holds the networks,
optimizers, value normalisation, the torch RNG and the counters, so `--resume` continues a run as if
it had not stopped.
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from cefc_mj.errors import CheckpointError, ConfigError
from cefc_mj.eval.highlevel import game_task, highlevel_policy_path, play_highlevel
from cefc_mj.fileio import write_atomic
from cefc_mj.hierarchy import DECISION_INTERVAL, HierarchicalCEFCEnv, LowLevel, load_low_level
from cefc_mj.nn.adversary_policy import AdversaryNetConfig, AdversaryPolicy, save_adversary_policy
from cefc_mj.nn.atm import Critic
from cefc_mj.nn.highlevel_policy import HighLevelPolicy, load_highlevel_policy
from cefc_mj.nn.policy_io import atomic_torch_save
from cefc_mj.task.adversary import adversary_goal, adversary_reward
from cefc_mj.task.config import LEARNED_ADVERSARY, TaskConfig
from cefc_mj.train import run_state
from cefc_mj.train.config import MAX_DENSITY, MAX_SEED, Budget, BudgetPPODict, PPOConfig, config_from_flags
from cefc_mj.train.logger import RunLogger
from cefc_mj.train.mappo import iteration_seed
from cefc_mj.provenance import file_sha256
from cefc_mj.train.model_card import display_path, display_paths, write_model_card
from cefc_mj.train.ppo import ValueNorm, advantages_and_targets, learner_state, load_learner_state, ppo_epochs
from cefc_mj.train.run_state import STATE_FILE

STATE_FORMAT = "cefc-mj/adversary-state"
PROGRESS_KEYS = ("episode_return", "team/E", "collision_share", "approx_kl")


def _adversary_ppo() -> PPOConfig:
    return PPOConfig(gamma=0.95, update_threads=1)


def _fail(name: str, value: object, why: str) -> None:
    raise ConfigError(f"{name}={value!r}: {why}")


@dataclass(frozen=True)
class AdversaryConfig(BudgetPPODict):
    """One PPO adversary training run; saved next to the run and in the model card."""

    budget: Budget
    """Iterations (each: one episode in each of ppo.n_envs envs, then the update) and/or wall-clock."""
    seed: int = 0
    """Seeds network init, action sampling, minibatches and every iteration's episodes."""
    high_level: str = "cihrl_consmac_a"
    """The UAV team's high level: a policy name (in the shipped folder) or file."""
    low_level: str = "atm_student"
    """The UAV team's low level: a policy name or file, or 'per-group'."""
    obstacle_density: float = 0.03
    """Obstacles per m^2 (the game of Tables V and VI)."""
    distance_weight: float = 0.1
    """Reward per metre of distance to the nearest group of >= 3 (subtracted every step)."""
    alert_weight: float = 1.0
    """Reward for the share of UAVs within the alert distance (2 m), every step."""
    collision_weight: float = 30.0
    """Penalty for a step inside an obstacle (within obstacle + body radius of its centre); 30 kept
    the chase of 10 with half the time inside obstacles (docs/high_level.md)."""
    progress_weight: float = 10.0
    """Weight of the approach d_before - d_after (m) of each step; without it the distance term
    alone taught the chase about 3x slower (docs/high_level.md)."""
    hidden: int = 128
    """Hidden width of actor and critic (the low level's 128)."""
    init_log_std: float = -0.5
    """Initial log-std of the action Gaussian (-0.5: std 0.61 m/s^2, under a third of the bound)."""
    ppo: PPOConfig = field(default_factory=_adversary_ppo)
    """PPO hyperparameters: the low level's defaults (5 epochs, Adam 3e-4, clip 0.2, lambda 0.95), 20
    envs, and gamma 0.95 per 0.1 s step (a 2 s horizon: a chase outlasts the low level's 0.8)."""
    checkpoint_every: int = 5
    """Write the resumable state every this many iterations (and always at the end)."""
    eval_episodes: int = 20
    """Episodes of the final (deterministic) adversary reported in the model card; 0 skips."""

    def __post_init__(self) -> None:
        self.validate()

    @property
    def name(self) -> str:
        """Run folder and policy file stem: adversary_ppo, then _seed<k> for seeds other than 0."""
        return "adversary_ppo" + (f"_seed{self.seed}" if self.seed else "")

    def task(self) -> TaskConfig:
        return dataclasses.replace(game_task(), adversary=LEARNED_ADVERSARY, obstacle_density=self.obstacle_density)

    def validate(self) -> None:
        if not isinstance(self.budget, Budget):
            _fail("budget", self.budget, "must be a Budget")
        if not isinstance(self.seed, int) or isinstance(self.seed, bool) or not 0 <= self.seed <= MAX_SEED:
            _fail("seed", self.seed, f"must be an integer in [0, {MAX_SEED}]")
        for name in ("high_level", "low_level"):
            if not isinstance(getattr(self, name), str) or not getattr(self, name):
                _fail(name, getattr(self, name), "must name a policy (a name or a file)")
        if not isinstance(self.obstacle_density, (int, float)) or not 0 <= self.obstacle_density <= MAX_DENSITY:
            _fail("obstacle_density", self.obstacle_density, f"must be in [0, {MAX_DENSITY}] per m^2")
        if not isinstance(self.init_log_std, (int, float)) or not -5 <= self.init_log_std <= 2:
            _fail("init_log_std", self.init_log_std, "must be a number in [-5, 2]")
        for name in ("distance_weight", "alert_weight", "collision_weight", "progress_weight"):
            value = getattr(self, name)
            if not isinstance(value, (int, float)) or not math.isfinite(value) or value < 0:
                _fail(name, value, "must be a number >= 0")
        for name, least, most in (("hidden", 1, 4096), ("checkpoint_every", 1, 1_000_000),
                                  ("eval_episodes", 0, 1000)):
            value = getattr(self, name)
            if not isinstance(value, int) or isinstance(value, bool) or not least <= value <= most:
                _fail(name, value, f"must be an integer in [{least}, {most}]")
        if not isinstance(self.ppo, PPOConfig):
            _fail("ppo", self.ppo, "must be a PPOConfig")
        self.ppo.validate()
        self.task()


class _Sampler:
    """The adversary_policy of the training env: samples each step's action from the Gaussian and
    records (observation, action, log-probability, value); the reward of a step is read from the env
    at the next call (the state the step led to), the last one by `finish()`."""

    def __init__(self, trainer: "AdversaryTrainer"):
        self.trainer = trainer
        self.env = None  # the BatchedCEFCEnv, set once the game exists
        self.buf: dict[str, list] = {}
        self.terms: dict[str, list] = {}

    def start(self) -> None:
        self.buf = {k: [] for k in ("obs", "actions", "logp", "values", "rewards")}
        self.terms = {k: [] for k in ("distance", "alert", "collision", "progress")}
        self.distance = None  # -d of the state the last action was taken in

    def _reward(self) -> np.ndarray:
        """The terms of the state the env is in; with an action pending, its reward is recorded."""
        env, cfg = self.env, self.trainer.cfg
        world, task = env.world, env.config
        goal = adversary_goal("nearest_group", world.adversary_pos, world.agent_pos, env.group_size,
                              env.group_centre)
        previous = None if self.distance is None else -self.distance
        terms = adversary_reward(world.adversary_pos, goal, world.agent_pos, env.obstacles,
                                 task.rewards.evasion_alert_distance, task.obstacle_radius + task.uav_radius,
                                 cfg.distance_weight, cfg.alert_weight, cfg.collision_weight,
                                 previous_distance=previous, progress_weight=cfg.progress_weight)
        if len(self.buf["obs"]) > len(self.buf["rewards"]):
            self.buf["rewards"].append(torch.as_tensor(terms["reward"], dtype=torch.float32))
            for name in self.terms:
                self.terms[name].append(terms[name])
        self.distance = terms["distance"]
        return terms["distance"]

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        self._reward()
        t = self.trainer
        obs_t = torch.from_numpy(obs)
        mean = t.actor(obs_t)
        std = t.actor.log_std.exp().expand_as(mean)
        action = mean + std * torch.randn(mean.shape, generator=t.generator)
        logp = torch.distributions.Normal(mean, std).log_prob(action).sum(-1)
        for name, value in (("obs", obs_t), ("actions", action), ("logp", logp), ("values", t.critic(obs_t))):
            self.buf[name].append(value)
        return action.numpy().astype(np.float64)

    def finish(self) -> torch.Tensor:
        """The last step's reward, and V of the final observation [B] (the time-limit bootstrap)."""
        self._reward()
        return self.trainer.critic(torch.from_numpy(self.env.adversary_observation()))


class AdversaryTrainer:
    """The learner: actor, critic, their optimizers, the value normalizer and a torch RNG; one
    `iterate()` = collect one episode per env, then the PPO update."""

    def __init__(self, cfg: AdversaryConfig, team: HighLevelPolicy, team_meta: dict, low_level: LowLevel):
        self.cfg = cfg
        self.task = cfg.task()
        self.team, self.low_level = team, low_level
        net = AdversaryNetConfig(hidden=cfg.hidden, accel_max=self.task.accel_max, init_log_std=cfg.init_log_std)
        self.actor = AdversaryPolicy(net, seed=cfg.seed)
        torch.manual_seed(cfg.seed + 1)
        self.critic = Critic(net.obs_dim, cfg.hidden)
        self.value_norm = ValueNorm()
        self.actor_opt = torch.optim.Adam(self.actor.parameters(), lr=cfg.ppo.lr, eps=1e-5)
        self.critic_opt = torch.optim.Adam(self.critic.parameters(), lr=cfg.ppo.lr, eps=1e-5)
        self.generator = torch.Generator().manual_seed(cfg.seed)
        self.iteration, self.episodes, self.elapsed = 0, 0, 0.0
        self.sampler = _Sampler(self)
        self.game = HierarchicalCEFCEnv(self.task, low_level, n_envs=cfg.ppo.n_envs, seed=cfg.seed,
                                        decision_interval=int(team_meta.get("decision_interval", DECISION_INTERVAL)),
                                        adversary_policy=self.sampler)
        self.sampler.env = self.game.env

    @torch.no_grad()
    def collect(self) -> tuple[dict[str, torch.Tensor], dict[str, float]]:
        self.sampler.start()
        team = play_highlevel(self.team, self.game, seed=iteration_seed(self.cfg.seed, self.iteration))
        final_value = self.sampler.finish()
        buf = {k: torch.stack(v) for k, v in self.sampler.buf.items()}  # [T, B, ...]
        next_values = torch.cat([buf["values"][1:], final_value[None]])
        episode_end = torch.zeros_like(buf["rewards"], dtype=torch.bool)
        episode_end[-1] = True
        buf["advantages"], buf["targets"], ev = advantages_and_targets(
            buf["rewards"], buf["values"], next_values, episode_end, self.cfg.ppo, self.value_norm)
        terms = {k: np.stack(v) for k, v in self.sampler.terms.items()}
        stats = {"episode_return": float(buf["rewards"].sum(0).mean()), "explained_variance": ev,
                 "distance_m": float(-terms["distance"].mean()), "alert_share": float(terms["alert"].mean()),
                 "collision_share": float(-terms["collision"].mean()),
                 "team/E": float(team["E"].mean()), "team/R_t": float(team["R_t"].mean()),
                 "team/R_H": float(team["R_H"].mean()), "action_std": float(self.actor.log_std.exp().mean()),
                 "episodes": self.game.n_envs}
        return buf, stats

    def update(self, buf: dict[str, torch.Tensor]) -> dict[str, float]:
        flat = {k: v.reshape(-1, *v.shape[2:]) for k, v in buf.items()}

        def policy_terms(mb):
            dist = self.actor.distribution(flat["obs"][mb])
            return dist.log_prob(flat["actions"][mb]).sum(-1), dist.entropy().sum(-1).mean()

        return ppo_epochs(len(flat["obs"]), self.cfg.ppo, self.generator, policy_terms, flat["logp"],
                          flat["advantages"], self.actor_opt, list(self.actor.parameters()), self.critic,
                          flat["obs"], flat["targets"], self.critic_opt)

    def iterate(self) -> dict[str, float]:
        t0 = time.perf_counter()
        torch.set_num_threads(self.cfg.ppo.rollout_threads)
        buf, stats = self.collect()
        t1 = time.perf_counter()
        torch.set_num_threads(self.cfg.ppo.update_threads)
        update = self.update(buf)
        t2 = time.perf_counter()
        self.iteration += 1
        self.episodes += stats["episodes"]
        self.elapsed += t2 - t0
        return {"iteration": self.iteration, "episodes_total": self.episodes, "wall_s": self.elapsed,
                **stats, **update, "rollout_s": t1 - t0, "update_s": t2 - t1}

    def state_dict(self) -> dict:
        return {**learner_state(self),
                "counters": {"iteration": self.iteration, "episodes": self.episodes, "elapsed": self.elapsed}}

    def load_state_dict(self, state: dict) -> None:
        load_learner_state(self, state)
        c = state["counters"]
        self.iteration, self.episodes, self.elapsed = int(c["iteration"]), int(c["episodes"]), float(c["elapsed"])


# ---------------------------------------------------------------------------- evaluation
@torch.no_grad()
def evaluate_adversary(adversary, team: HighLevelPolicy, low_level: LowLevel, task: TaskConfig, episodes: int,
                       seed: int = 0, decision_interval: int = DECISION_INTERVAL, world=None) -> dict[str, float]:
    """The UAV team's per-episode means (R_H and its parts, E, F, C: `play_highlevel`) against an
    adversary, and the share of steps it spent inside an obstacle ("adversary_collision_share").
    adversary: a callable of observations (e.g. `AdversaryPolicy.act`) for a task with
    adversary='learned', or a rule's name (flown exactly as the env flies `task.adversary`)."""
    inside: list[np.ndarray] = []
    keep_out = task.obstacle_radius + task.uav_radius

    def flown(obs: np.ndarray) -> np.ndarray:
        env = game.env
        if env.obstacles.shape[1]:
            gap = np.linalg.norm(env.obstacles - env.world.adversary_pos[:, None, :], axis=-1)
            inside.append((gap < keep_out).any(axis=-1))
        return env.rule_adversary_acceleration(adversary) if isinstance(adversary, str) else adversary(obs)

    task = dataclasses.replace(task, adversary=LEARNED_ADVERSARY)
    game = HierarchicalCEFCEnv(task, low_level, n_envs=episodes, seed=seed, decision_interval=decision_interval,
                               world=world, adversary_policy=flown)
    per_episode = play_highlevel(team, game, seed)
    out = {name: float(values.mean()) for name, values in per_episode.items()}
    out["adversary_collision_share"] = float(np.mean(inside)) if inside else 0.0
    return out


# ---------------------------------------------------------------------------- the run
def read_state(path: Path) -> dict:
    return run_state.read_state(path, STATE_FORMAT, "adversary training state")


def load_team(cfg: AdversaryConfig, policies_dir: Path | None = None) -> tuple[HighLevelPolicy, dict, LowLevel]:
    """The UAV team the adversary trains against; CheckpointError naming the flag when a file is missing."""
    try:
        team, meta = load_highlevel_policy(highlevel_policy_path(cfg.high_level, policies_dir))
    except CheckpointError as e:
        raise CheckpointError(f"--high-level: {e}") from None
    try:
        low_level = load_low_level(cfg.low_level, cfg.task(), policies_dir)
    except CheckpointError as e:
        raise CheckpointError(f"--low-level: {e}") from None
    return team, meta, low_level


def train_adversary(cfg: AdversaryConfig, out: Path, policies_dir: Path, resume: bool = False,
                    show_progress: bool = True, command: str | None = None) -> dict:
    """Train under the budget, export the adversary and its model card to `policies_dir`; returns
    the card. Everything the run needs is loaded and checked before the run folder is made."""
    out, policies_dir = Path(out), Path(policies_dir)
    run_dir = out / cfg.name
    state_path = run_dir / STATE_FILE
    team, team_meta, low_level = load_team(cfg)
    team_path = highlevel_policy_path(cfg.high_level)
    team_record = {"high_level": display_path(team_path), "high_level_sha256": file_sha256(team_path),
                   "low_level": display_paths(low_level.describe())}
    saved = None
    if run_state.run_state_path(run_dir, resume) is not None:
        saved = read_state(state_path)
        run_state.check_same_run(saved["config"], cfg, state_path, free=("budget", "checkpoint_every", "eval_episodes"))
    trainer = AdversaryTrainer(cfg, team, team_meta, low_level)
    if saved is not None:
        trainer.load_state_dict(saved["trainer"])
    write_atomic(run_dir / "config.json", json.dumps(
        {"adversary": cfg.to_dict(), "task": trainer.task.to_dict(), "team": team_record, "command": command},
        indent=2, default=str) + "\n")

    def checkpoint() -> None:
        atomic_torch_save({"format": STATE_FORMAT, "config": cfg.to_dict(), "trainer": trainer.state_dict()},
                          state_path)

    if saved is None:
        checkpoint()
    logger = RunLogger(run_dir, trainer.iteration, cfg.budget.iterations, desc=cfg.name, show_progress=show_progress)
    last_row = run_state.train_under_budget(trainer, cfg.budget, cfg.checkpoint_every, logger, PROGRESS_KEYS,
                                            checkpoint)

    policy_path = save_adversary_policy(trainer.actor, policies_dir / f"{cfg.name}.pt", meta={
        "name": cfg.name, "seed": cfg.seed, "iterations": trainer.iteration})
    card = {
        "name": cfg.name,
        "method": "PPO adversary (single-agent PPO, the low level's network shape), trained against "
                  f"{cfg.high_level} over {low_level.name}",
        "seed": cfg.seed,
        "config": cfg.to_dict(),
        "task": trainer.task.to_dict(),
        "network": trainer.actor.cfg.to_dict(),
        "team": team_record,
        "iterations": trainer.iteration,
        "episodes": trainer.episodes,
        "steps": trainer.episodes * trainer.task.steps,
        "train_wall_clock_s": round(trainer.elapsed, 1),
        "run_dir": display_path(run_dir),
        "command": command,
        "last_iteration": {k: v for k, v in last_row.items() if isinstance(v, (int, float))},
    }
    if cfg.eval_episodes:
        interval = int(team_meta.get("decision_interval", DECISION_INTERVAL))
        card["evaluation"] = {
            "protocol": {"episodes": cfg.eval_episodes, "seed": 0, "backend": "particle",
                         "team": cfg.high_level, "adversary": "the mean action",
                         "figures": "the team's per-episode sums (R_t, R_n, R_e weighted, summing to R_H; "
                                    "E in steps) and the adversary's share of steps inside an obstacle"},
            "ours": evaluate_adversary(trainer.actor.act, team, low_level, trainer.task, cfg.eval_episodes,
                                       decision_interval=interval),
            "rule_nearest_group": evaluate_adversary("nearest_group", team, low_level, trainer.task,
                                                     cfg.eval_episodes, decision_interval=interval),
        }
    write_model_card(policy_path, card)
    return card


def summary_lines(card: dict, policies_dir: Path) -> list[str]:
    """What `cefc-train adversary` prints when a run ends."""
    lines = [f"{card['name']}: {card['iterations']} iterations, {card['episodes']} episodes, "
             f"{card['train_wall_clock_s']} s -> {policies_dir / (card['name'] + '.pt')} (run {card['run_dir']})"]
    if "evaluation" in card:
        e = card["evaluation"]
        for label, row in (("PPO adversary", e["ours"]), ("rule nearest_group", e["rule_nearest_group"])):
            lines.append(f"{label} vs {e['protocol']['team']} ({e['protocol']['episodes']} episodes): team E "
                         f"{row['E']:.1f} steps, R_t {row['R_t']:.1f}, R_e {row['R_e']:.1f}; adversary inside an "
                         f"obstacle {100 * row['adversary_collision_share']:.1f} % of steps")
    return lines


# ---------------------------------------------------------------------------- command line
_FLAG_OF_FIELD = {"seed": "--seed", "high_level": "--high-level", "low_level": "--low-level",
                  "obstacle_density": "--density", "eval_episodes": "--eval-episodes", "n_envs": "--envs",
                  "collision_weight": "--collision-weight",
                  "epochs": "--epochs", "lr": "--lr", "update_threads": "--threads"}
"""Config fields set by `cefc-train adversary` flags: their errors name the flag the user typed."""
CLI_FIELDS = ("seed", "high_level", "low_level", "obstacle_density", "collision_weight", "eval_episodes")
CLI_PPO_FIELDS = ("n_envs", "epochs", "lr", "update_threads")


def config_from_args(args, budget: Budget) -> AdversaryConfig:
    """The AdversaryConfig of `cefc-train adversary` arguments (flags left out keep the defaults);
    a bad value raises ConfigError naming the flag."""
    return config_from_flags(AdversaryConfig, args, budget, CLI_FIELDS, CLI_PPO_FIELDS, _adversary_ppo(),
                             _FLAG_OF_FIELD)
