"""The DDPG adversary (the paper's second RL predator, Table VI; Lillicrap et al. 2016), CleanRL-style.

The game, the population of UAV teams and the reward are the PPO adversary's (`train.adversary`):
one iteration plays one 400-step episode in each of `n_envs` envs, split into `teams_per_iteration`
games, each against a team drawn from `teams`. What differs is the learner:

1. **Act**: the actor is the PPO adversary's network (`AdversaryPolicy`, the paper's "same network
   structure"); its mean mu(o) is the deterministic action, and training flies mu(o) + N(0, noise^2).
   Until `learning_starts` transitions are in the replay, whole iterations fly uniform random actions
   (CleanRL's warm-up). Actions are bounded as the env reads them (`effective_action`): "velocity" onto
   the unit disc, "heading" onto the unit circle, "acceleration" into [-accel_max, accel_max]^2.
2. **Store** every step's (o, a, r, o') in a ring replay of `replay_capacity`. An episode ends only at
   the 400-step time limit, which is no terminal state: every target bootstraps, y = r + gamma Q'(o', mu'(o')).
3. **Update** `updates_per_iteration` times on batches drawn uniformly from the replay: the critic
   Q(o, a) (an MLP on [network_input(o), a]) regresses y (MSE), the actor ascends Q(o, mu(o)), and
   both target networks follow by Polyak averaging, theta' <- (1 - tau) theta' + tau theta.

No imitation: DDPG learns from scratch.

    run folder   <out>/<name>/   config.json, progress.csv, tb/, state.pt (resumable)
    policy file  <policies_dir>/<name>.pt  + <name>.json model card      name = adversary_ddpg[_seed<k>]

`state.pt` holds the networks, target networks, optimizers, replay, torch RNG and counters; the
episodes and team draws are functions of (seed, iteration), so `--resume` continues a run exactly.
"""

from __future__ import annotations

import copy
import dataclasses
import json
import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn

from cefc_mj.errors import ConfigError
from cefc_mj.fileio import write_atomic
from cefc_mj.game_protocol import play_highlevel
from cefc_mj.hierarchy import DECISION_INTERVAL, LowLevel
from cefc_mj.nn.adversary_policy import (
    AdversaryNetConfig,
    AdversaryPolicy,
    network_input,
    save_adversary_policy,
)
from cefc_mj.nn.highlevel_policy import HighLevelPolicy
from cefc_mj.nn.layers import mlp
from cefc_mj.nn.policy_io import atomic_torch_save
from cefc_mj.task.config import TaskConfig
from cefc_mj.train import run_state
from cefc_mj.train.adversary import (
    AdversaryConfig,
    PopulationGames,
    _check_ints,
    _fail,
    _Sampler,
    adversary_task,
    load_population,
    summary_lines as _summary_lines,
    validate_population_game,
)
from cefc_mj.train.config import MAX_ENVS, MAX_LR, MAX_THREADS, Budget, flag_error
from cefc_mj.train.logger import RunLogger
from cefc_mj.train.mappo import iteration_seed
from cefc_mj.train.model_card import display_path, display_paths, write_model_card
from cefc_mj.train.run_state import STATE_FILE

STATE_FORMAT = "cefc-mj/adversary-ddpg-state"
PROGRESS_KEYS = ("episode_return", "team/E", "collision_share", "critic_loss")
MAX_REPLAY = 2_000_000
"""Largest replay (about 1.3 GB of float32 transitions)."""

_PPO = {f.name: f.default for f in dataclasses.fields(AdversaryConfig) if f.default is not dataclasses.MISSING}
"""The PPO adversary's defaults: one source for the game, population and reward both adversaries play."""


@dataclass(frozen=True)
class DDPGAdversaryConfig:
    """One DDPG adversary training run; saved next to the run and in the model card. The game, population
    and reward fields are the PPO adversary's (AdversaryConfig), with its defaults and checks."""

    budget: Budget
    """Iterations (each: one episode in each of n_envs envs, then the updates) and/or wall-clock."""
    seed: int = 0
    """Seeds network init, exploration noise, replay batches, every iteration's episodes and team draws."""
    teams: tuple[str, ...] = _PPO["teams"]
    """The population of UAV teams, one drawn per game (AdversaryConfig.teams)."""
    teams_per_iteration: int = _PPO["teams_per_iteration"]
    """Games per iteration, each with its own team and n_envs / teams_per_iteration envs."""
    low_level: str = _PPO["low_level"]
    """The UAV teams' low level: a policy name or file, or 'per-group'."""
    observes_goal: bool = _PPO["observes_goal"]
    """Whether the networks read the rule's goal point (False: the paper's adversary, as the PPO one)."""
    action: str = _PPO["action"]
    """What the actor's outputs mean (AdversaryNetConfig.action): "velocity", "heading" or "acceleration"."""
    obstacle_density: float = _PPO["obstacle_density"]
    """Obstacles per m^2 (the game of Tables V and VI)."""
    distance_weight: float = _PPO["distance_weight"]
    """Reward per metre of distance to the nearest group of >= 3 (AdversaryConfig)."""
    alert_weight: float = _PPO["alert_weight"]
    """Reward for the share of UAVs within the alert distance (2 m), every step."""
    collision_weight: float = _PPO["collision_weight"]
    """Penalty for a step inside an obstacle."""
    progress_weight: float = _PPO["progress_weight"]
    """Weight of each step's approach to the nearest group (m)."""
    hidden: int = _PPO["hidden"]
    """Hidden width of actor and critic (the PPO adversary's 128)."""
    n_envs: int = 20
    """Parallel envs per iteration (the PPO adversary's 20): 20 x 400 = 8000 transitions an iteration."""
    replay_capacity: int = 100_000
    """Transitions the ring replay holds (12.5 iterations of 20 envs): data from an actor and teams long
    gone is forgotten; about 67 MB in memory and in state.pt."""
    batch_size: int = 256
    """Transitions per gradient step (CleanRL's 256)."""
    learning_starts: int = 8_000
    """Transitions in the replay before the updates start; until then whole iterations fly uniform random
    actions (CleanRL's warm-up; 8000: the first iteration at 20 envs)."""
    updates_per_iteration: int = 1_000
    """Gradient steps (critic, actor, targets) after each iteration: one per 8 new transitions at 20 envs."""
    actor_lr: float = 1e-4
    """Adam learning rate of the actor (Lillicrap et al.: 1e-4, slower than the critic it follows)."""
    critic_lr: float = 1e-3
    """Adam learning rate of the critic (Lillicrap et al.: 1e-3)."""
    tau: float = 0.005
    """Polyak rate of the target networks per gradient step (CleanRL's 0.005)."""
    gamma: float = 0.95
    """Discount per 0.1 s step (the PPO adversary's: a 2 s horizon)."""
    exploration_noise: float = 0.2
    """Std of the Gaussian added to the actor's output while training, in its units (velocity: a fifth of
    top speed); saved as the policy's log_std."""
    threads: int = 1
    """torch threads of the updates (collection uses 1)."""
    checkpoint_every: int = 5
    """Write the resumable state every this many iterations (and always at the end)."""
    eval_episodes: int = 20
    """Episodes of the final (deterministic) adversary reported in the model card; 0 skips."""

    def __post_init__(self) -> None:
        if isinstance(self.teams, list):  # read back from JSON
            object.__setattr__(self, "teams", tuple(self.teams))
        self.validate()

    @property
    def name(self) -> str:
        """Run folder and policy file stem: adversary_ddpg, then _seed<k> for seeds other than 0."""
        return "adversary_ddpg" + (f"_seed{self.seed}" if self.seed else "")

    def task(self) -> TaskConfig:
        return adversary_task(self.obstacle_density)

    def validate(self) -> None:
        validate_population_game(self)
        _check_ints(
            self,
            (
                ("n_envs", 1, MAX_ENVS),
                ("replay_capacity", 1, MAX_REPLAY),
                ("batch_size", 1, 65_536),
                ("learning_starts", 0, MAX_REPLAY),
                ("updates_per_iteration", 0, 1_000_000),
                ("threads", 1, MAX_THREADS),
            ),
        )
        for name, least, most, open_low in (
            ("actor_lr", 0, MAX_LR, True),
            ("critic_lr", 0, MAX_LR, True),
            ("tau", 0, 1, True),
            ("gamma", 0, 1, False),
            ("exploration_noise", 0, 5, True),
        ):
            value = getattr(self, name)
            if (
                not isinstance(value, (int, float))
                or isinstance(value, bool)
                or not math.isfinite(value)
                or not least <= value <= most
                or (open_low and value == least)
            ):
                _fail(name, value, f"must be a number in {'(' if open_low else '['}{least}, {most}]")
        if self.n_envs % self.teams_per_iteration:
            _fail("teams_per_iteration", self.teams_per_iteration, f"must divide the {self.n_envs} envs")
        if self.learning_starts > self.replay_capacity:
            _fail("learning_starts", self.learning_starts, f"must be at most the replay's {self.replay_capacity}")
        self.task()

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> DDPGAdversaryConfig:
        d = dict(d)
        d["budget"] = Budget(**d["budget"])
        return cls(**d)


# ---------------------------------------------------------------------------- the pieces
def effective_action(u: torch.Tensor, net: AdversaryNetConfig) -> torch.Tensor:
    """Actor outputs [B, 2] bounded as `AdversaryPolicy.to_acceleration` reads them (so both give the same
    setpoint): "velocity" onto the unit disc, "heading" onto the unit circle, "acceleration" per axis into
    [-accel_max, accel_max]. The critic sees these, never a part of the output the env ignores."""
    if net.action == "acceleration":
        return u.clamp(-net.accel_max, net.accel_max)
    norm = u.norm(dim=-1, keepdim=True)
    return u / (norm.clamp(min=1e-9) if net.action == "heading" else norm.clamp(min=1.0))


class QCritic(nn.Module):
    """Q(o, a): a tanh MLP with two hidden layers of width `hidden` (the PPO adversary's critic shape) on
    [network_input(o), a]."""

    def __init__(self, net: AdversaryNetConfig, hidden: int):
        super().__init__()
        self.observes_goal = net.observes_goal
        self.net = mlp([net.input_dim + 2, hidden, hidden, 1], activate_last=False, last_gain=1.0)

    def forward(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        return self.net(torch.cat([network_input(obs, self.observes_goal), action], dim=-1)).squeeze(-1)


@torch.no_grad()
def soft_update(target: nn.Module, online: nn.Module, tau: float) -> None:
    """Polyak averaging: theta' <- (1 - tau) theta' + tau theta, parameter by parameter."""
    for t, p in zip(target.parameters(), online.parameters()):
        t.lerp_(p, tau)


class ReplayBuffer:
    """A ring of `capacity` transitions (o, a, r, o'), batch-first float32 tensors; the newest overwrite
    the oldest. No terminal flags: the game's episodes end only at the time limit."""

    FIELDS = ("obs", "actions", "rewards", "next_obs")

    def __init__(self, capacity: int, obs_dim: int, action_dim: int = 2):
        self.capacity = capacity
        self.obs = torch.zeros(capacity, obs_dim)
        self.actions = torch.zeros(capacity, action_dim)
        self.rewards = torch.zeros(capacity)
        self.next_obs = torch.zeros(capacity, obs_dim)
        self.pos = self.size = 0

    def add(self, obs: torch.Tensor, actions: torch.Tensor, rewards: torch.Tensor, next_obs: torch.Tensor) -> None:
        """Append n transitions ([n, ...] each); of more than the capacity only the last ones stay."""
        data = [t[-self.capacity :] for t in (obs, actions, rewards, next_obs)]
        n = len(data[0])
        index = (self.pos + torch.arange(n)) % self.capacity
        for name, value in zip(self.FIELDS, data):
            getattr(self, name)[index] = value
        self.pos = (self.pos + n) % self.capacity
        self.size = min(self.size + n, self.capacity)

    def sample(self, batch_size: int, generator: torch.Generator) -> tuple[torch.Tensor, ...]:
        """A batch drawn uniformly (with replacement) from what the ring holds: (o, a, r, o')."""
        index = torch.randint(self.size, (batch_size,), generator=generator)
        return tuple(getattr(self, name)[index] for name in self.FIELDS)

    def state_dict(self) -> dict:
        return {
            **{name: getattr(self, name)[: self.size].clone() for name in self.FIELDS},
            "pos": self.pos,
            "size": self.size,
        }

    def load_state_dict(self, state: dict) -> None:
        size = int(state["size"])
        if size > self.capacity:
            raise ConfigError(f"replay of {size} transitions does not fit a capacity of {self.capacity}")
        for name in self.FIELDS:
            getattr(self, name)[:size] = state[name]
        self.pos, self.size = int(state["pos"]), size


class _NoisySampler(_Sampler):
    """The training env's adversary_policy: mu(o) plus Gaussian noise (uniform random actions while the
    replay warms up), recording (o, a) each step; the rewards are the PPO adversary's (`_Sampler._reward`)."""

    KEYS = ("obs", "actions", "rewards")

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        self._reward()
        t = self.trainer
        obs_t = torch.from_numpy(obs)
        shape = (len(obs), 2)
        if t.warming_up:
            u = (2 * torch.rand(shape, generator=t.generator) - 1) * t.action_scale
        else:
            u = t.actor(obs_t) + t.cfg.exploration_noise * torch.randn(shape, generator=t.generator)
        action = effective_action(u, t.actor.cfg)
        self.buf["obs"].append(obs_t)
        self.buf["actions"].append(action)
        return t.actor.to_acceleration(action.numpy(), obs)

    def finish(self) -> torch.Tensor:
        """The last step's reward, and the final observation [B, D] (o' of the last step)."""
        self._reward()
        return torch.from_numpy(self.env.adversary_observation())


# ---------------------------------------------------------------------------- the learner
class DDPGAdversaryTrainer(PopulationGames):
    """Actor, critic, their targets and optimizers, the replay and a torch RNG; one `iterate()` = collect
    one episode per env (teams_per_iteration games, a team drawn for each) into the replay, then the updates."""

    PARTS = ("actor", "critic", "actor_target", "critic_target", "actor_opt", "critic_opt", "replay")
    """What `state_dict` saves (with the RNG and the counters)."""

    def __init__(
        self,
        cfg: DDPGAdversaryConfig,
        population: dict[str, HighLevelPolicy | None],
        low_level: LowLevel,
        decision_interval: int = DECISION_INTERVAL,
        team_low_levels: dict[str, LowLevel] | None = None,
    ):
        """population: team name -> its high level, None for a rule team (RULE_TEAMS); low_level: the
        teams' low level, except those of team_low_levels (`load_population`)."""
        self.cfg = cfg
        self.task = cfg.task()
        self.population, self.low_level, self.team_low_levels = population, low_level, team_low_levels or {}
        net = AdversaryNetConfig(
            hidden=cfg.hidden,
            accel_max=self.task.accel_max,
            init_log_std=math.log(cfg.exploration_noise),
            observes_goal=cfg.observes_goal,
            action=cfg.action,
            speed_max=self.task.adversary_speed_max,
            dt=self.task.dt,
        )
        self.actor = AdversaryPolicy(net, seed=cfg.seed)
        torch.manual_seed(cfg.seed + 1)
        self.critic = QCritic(net, cfg.hidden)
        self.actor_target = copy.deepcopy(self.actor).requires_grad_(False)
        self.critic_target = copy.deepcopy(self.critic).requires_grad_(False)
        self.actor_opt = torch.optim.Adam(self.actor.parameters(), lr=cfg.actor_lr)
        self.critic_opt = torch.optim.Adam(self.critic.parameters(), lr=cfg.critic_lr)
        self.replay = ReplayBuffer(cfg.replay_capacity, net.obs_dim)
        self.action_scale = net.accel_max if net.action == "acceleration" else 1.0
        self.generator = torch.Generator().manual_seed(cfg.seed)
        self.iteration, self.episodes, self.updates, self.elapsed = 0, 0, 0, 0.0
        self.build_games(
            [_NoisySampler(self) for _ in range(cfg.teams_per_iteration)], low_level, cfg.n_envs, decision_interval
        )

    @property
    def warming_up(self) -> bool:
        """Whether the replay still holds fewer than learning_starts transitions (fly random actions)."""
        return self.replay.size < self.cfg.learning_starts

    @torch.no_grad()
    def collect(self) -> dict[str, float]:
        """Play this iteration's games, add their transitions to the replay; returns the episodes' figures."""
        exploring = self.warming_up
        returns, terms, team_stats = [], [], []
        for g, (name, game, sampler) in enumerate(zip(self.draw_teams(self.iteration), self.games, self.samplers)):
            sampler.start()
            team_stats.append(
                play_highlevel(
                    self.team_for(name, game), game, seed=iteration_seed(self.cfg.seed, self.iteration, stream=g)
                )
            )
            final_obs = sampler.finish()
            obs, actions, rewards = (torch.stack(sampler.buf[k], dim=1) for k in ("obs", "actions", "rewards"))
            next_obs = torch.cat([obs[:, 1:], final_obs[:, None]], dim=1)  # [b, T, D]: o' of every step
            self.replay.add(obs.flatten(0, 1), actions.flatten(0, 1), rewards.flatten(0, 1), next_obs.flatten(0, 1))
            returns.append(rewards.sum(1))
            terms.append({k: np.stack(v, axis=1) for k, v in sampler.terms.items()})
        terms = {k: np.concatenate([t[k] for t in terms]) for k in terms[0]}
        team = {k: np.concatenate([s[k] for s in team_stats]) for k in ("E", "R_t", "R_H")}
        return {
            "episode_return": float(torch.cat(returns).mean()),
            "distance_m": float(-terms["distance"].mean()),
            "alert_share": float(terms["alert"].mean()),
            "collision_share": float(-terms["collision"].mean()),
            "team/E": float(team["E"].mean()),
            "team/R_t": float(team["R_t"].mean()),
            "team/R_H": float(team["R_H"].mean()),
            "random_actions": int(exploring),
            "replay_size": self.replay.size,
            "episodes": self.cfg.n_envs,
        }

    def update_step(
        self, obs: torch.Tensor, actions: torch.Tensor, rewards: torch.Tensor, next_obs: torch.Tensor
    ) -> dict[str, float]:
        """One DDPG step on a batch: the critic towards r + gamma Q'(o', mu'(o')), the actor up Q(o, mu(o)),
        then the targets by tau."""
        net = self.actor.cfg
        with torch.no_grad():
            target = rewards + self.cfg.gamma * self.critic_target(
                next_obs, effective_action(self.actor_target(next_obs), net)
            )
        q = self.critic(obs, actions)
        critic_loss = (q - target).pow(2).mean()
        self.critic_opt.zero_grad()
        critic_loss.backward()
        self.critic_opt.step()
        actor_loss = -self.critic(obs, effective_action(self.actor(obs), net)).mean()
        self.actor_opt.zero_grad()
        actor_loss.backward()
        self.actor_opt.step()
        soft_update(self.actor_target, self.actor, self.cfg.tau)
        soft_update(self.critic_target, self.critic, self.cfg.tau)
        self.updates += 1
        return {"critic_loss": critic_loss.item(), "actor_loss": actor_loss.item(), "q": q.detach().mean().item()}

    def update(self) -> dict[str, float]:
        """updates_per_iteration steps on uniform replay batches (none while warming up); their mean losses."""
        rows = []
        if not self.warming_up:
            for _ in range(self.cfg.updates_per_iteration):
                rows.append(self.update_step(*self.replay.sample(self.cfg.batch_size, self.generator)))
        return {
            k: float(np.mean([r[k] for r in rows])) if rows else math.nan for k in ("critic_loss", "actor_loss", "q")
        }

    def iterate(self) -> dict[str, float]:
        t0 = time.perf_counter()
        torch.set_num_threads(1)
        stats = self.collect()
        t1 = time.perf_counter()
        torch.set_num_threads(self.cfg.threads)
        update = self.update()
        t2 = time.perf_counter()
        self.iteration += 1
        self.episodes += stats["episodes"]
        self.elapsed += t2 - t0
        return {
            "iteration": self.iteration,
            "episodes_total": self.episodes,
            "wall_s": self.elapsed,
            **stats,
            **update,
            "updates_total": self.updates,
            "rollout_s": t1 - t0,
            "update_s": t2 - t1,
        }

    def state_dict(self) -> dict:
        return {
            **{name: getattr(self, name).state_dict() for name in self.PARTS},
            "generator": self.generator.get_state(),
            "counters": {
                "iteration": self.iteration,
                "episodes": self.episodes,
                "updates": self.updates,
                "elapsed": self.elapsed,
            },
        }

    def load_state_dict(self, state: dict) -> None:
        for name in self.PARTS:
            getattr(self, name).load_state_dict(state[name])
        self.generator.set_state(state["generator"])
        c = state["counters"]
        self.iteration, self.episodes, self.updates = int(c["iteration"]), int(c["episodes"]), int(c["updates"])
        self.elapsed = float(c["elapsed"])


# ---------------------------------------------------------------------------- the run
def train_ddpg_adversary(
    cfg: DDPGAdversaryConfig,
    out: Path,
    policies_dir: Path,
    resume: bool = False,
    show_progress: bool = True,
    command: str | None = None,
) -> dict:
    """Train under the budget, export the adversary and its model card to `policies_dir`; returns the
    card. Everything the run needs is loaded and checked before the run folder is made."""
    out, policies_dir = Path(out), Path(policies_dir)
    run_dir = out / cfg.name
    state_path = run_dir / STATE_FILE
    population, team_records, low_level, interval, team_low_levels = load_population(cfg)
    team_record = {"population": team_records, "low_level": display_paths(low_level.describe())}
    saved = None
    if run_state.run_state_path(run_dir, resume) is not None:
        saved = run_state.read_state(state_path, STATE_FORMAT, "DDPG adversary training state")
        run_state.check_same_run(
            saved["config"], cfg, state_path, free=("budget", "checkpoint_every", "eval_episodes", "threads")
        )
    trainer = DDPGAdversaryTrainer(cfg, population, low_level, interval, team_low_levels)
    if saved is not None:
        run_state.restore_trainer(trainer, saved, state_path)
    write_atomic(
        run_dir / "config.json",
        json.dumps(
            {"adversary": cfg.to_dict(), "task": trainer.task.to_dict(), "team": team_record, "command": command},
            indent=2,
            default=str,
        )
        + "\n",
    )

    def checkpoint() -> None:
        atomic_torch_save(
            {"format": STATE_FORMAT, "config": cfg.to_dict(), "trainer": trainer.state_dict()}, state_path
        )

    if saved is None:
        checkpoint()
    logger = RunLogger(run_dir, trainer.iteration, cfg.budget.iterations, desc=cfg.name, show_progress=show_progress)
    last_row = run_state.train_under_budget(
        trainer, cfg.budget, cfg.checkpoint_every, logger, PROGRESS_KEYS, checkpoint
    )

    policy_path = save_adversary_policy(
        trainer.actor,
        policies_dir / f"{cfg.name}.pt",
        meta={"name": cfg.name, "algorithm": "ddpg", "seed": cfg.seed, "iterations": trainer.iteration},
    )
    card = {
        "name": cfg.name,
        "method": "DDPG adversary (Lillicrap et al. 2016: the PPO adversary's actor network, a Q critic, target "
        f"networks, replay), trained from scratch against a population of {len(cfg.teams)} teams over "
        f"{low_level.name}",
        "seed": cfg.seed,
        "config": cfg.to_dict(),
        "task": trainer.task.to_dict(),
        "network": trainer.actor.cfg.to_dict(),
        "team": team_record,
        "iterations": trainer.iteration,
        "episodes": trainer.episodes,
        "steps": trainer.episodes * trainer.task.steps,
        "gradient_steps": trainer.updates,
        "train_wall_clock_s": round(trainer.elapsed, 1),
        "run_dir": display_path(run_dir),
        "command": command,
        "last_iteration": {k: v for k, v in last_row.items() if isinstance(v, (int, float)) and math.isfinite(v)},
    }
    if cfg.eval_episodes:
        card["evaluation"] = trainer.evaluate_population(trainer.actor.act, cfg.eval_episodes)
    write_model_card(policy_path, card)
    return card


def summary_lines(card: dict, policies_dir: Path) -> list[str]:
    """What `cefc-train adversary-ddpg` prints when a run ends."""
    return _summary_lines(card, policies_dir, algorithm="DDPG")


# ---------------------------------------------------------------------------- command line
FLAG_OF_FIELD = {
    "seed": "--seed",
    "teams": "--teams",
    "teams_per_iteration": "--teams-per-iteration",
    "low_level": "--low-level",
    "action": "--action",
    "alert_weight": "--alert-weight",
    "progress_weight": "--progress-weight",
    "collision_weight": "--collision-weight",
    "obstacle_density": "--density",
    "eval_episodes": "--eval-episodes",
    "n_envs": "--envs",
    "threads": "--threads",
    "replay_capacity": "--replay",
    "batch_size": "--batch-size",
    "actor_lr": "--actor-lr",
    "critic_lr": "--critic-lr",
    "tau": "--tau",
    "gamma": "--gamma",
    "exploration_noise": "--noise",
    "learning_starts": "--learning-starts",
    "updates_per_iteration": "--updates",
}
"""Config fields set by `cefc-train adversary-ddpg` flags (argparse dest = field): errors name the flag."""


def config_from_args(args, budget: Budget) -> DDPGAdversaryConfig:
    """The DDPGAdversaryConfig of `cefc-train adversary-ddpg` arguments (flags left out keep the
    defaults); a bad value raises ConfigError naming the flag."""
    given = {name: getattr(args, name) for name in FLAG_OF_FIELD if getattr(args, name, None) is not None}
    try:
        return DDPGAdversaryConfig(budget=budget, **given)
    except ConfigError as e:
        raise flag_error(e, FLAG_OF_FIELD) from None
