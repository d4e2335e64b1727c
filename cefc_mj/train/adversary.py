"""The PPO adversary (the paper's predator, Sec. V-A): single-agent PPO against a population of UAV teams.

Before PPO the actor imitates a rule (`imitation_rule`, by DAgger), then `critic_warmup` iterations fit
the critic alone. One iteration, CleanRL-style:

1. **Collect** one 400-step episode in each of `ppo.n_envs` envs of the CEFC game
   (`HierarchicalCEFCEnv` with adversary='learned'), split into `teams_per_iteration` games. Each
   game's UAVs are a team drawn from the population `teams` (every method's trained high levels
   and the rule-driven teams of `cefc_mj.rule_teams`) over a trained low level (default the
   distilled student), every decision the mode of their policies, as in the evaluation; the
   adversary samples its acceleration every low-level step from its Gaussian
   (`nn.adversary_policy`). It reads what the paper gives it (its own state, the agents' and the
   obstacles'), not the point the rule would chase (`observes_goal`).
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
from tqdm import tqdm

from cefc_mj.errors import CheckpointError, ConfigError
from cefc_mj.fileio import write_atomic
from cefc_mj.game_protocol import game_task, play_highlevel
from cefc_mj.hierarchy import DECISION_INTERVAL, HierarchicalCEFCEnv, LowLevel, load_low_level, recorded_low_level
from cefc_mj.nn.adversary_policy import (
    ADVERSARY_ACTIONS,
    AdversaryNetConfig,
    AdversaryPolicy,
    network_input,
    save_adversary_policy,
)
from cefc_mj.nn.atm import Critic
from cefc_mj.nn.highlevel_policy import HighLevelPolicy, highlevel_policy_path, load_highlevel_policy
from cefc_mj.nn.policy_io import atomic_torch_save
from cefc_mj.nn.registry import HIERARCHY_LOWLEVEL
from cefc_mj.provenance import file_sha256
from cefc_mj.rule_teams import RULE_TEAMS, RuleTeam
from cefc_mj.seeds import GAME_VALIDATION_SEED
from cefc_mj.task.adversary import ADVERSARY_OBS_DIM, InterceptRule, adversary_goal, adversary_reward
from cefc_mj.task.config import ADVERSARY_RULES, LEARNED_ADVERSARY, TaskConfig
from cefc_mj.train import run_state
from cefc_mj.train.config import MAX_DENSITY, MAX_SEED, Budget, BudgetPPODict, PPOConfig, config_from_flags
from cefc_mj.train.logger import RunLogger
from cefc_mj.train.mappo import iteration_seed
from cefc_mj.train.model_card import display_path, display_paths, write_model_card
from cefc_mj.train.ppo import ValueNorm, advantages_and_targets, learner_state, load_learner_state, ppo_epochs
from cefc_mj.train.run_state import STATE_FILE

STATE_FORMAT = "cefc-mj/adversary-state"
TEAM_DRAW_STREAM = 7
"""Extra SeedSequence entry of the team draws (apart from every other stream of a run)."""
IMITATION_STREAM = 1000
"""`iteration_seed` stream of the imitation episodes (the PPO games use streams 0..teams_per_iteration-1)."""
IMITATION_RULES = tuple(rule for rule in ADVERSARY_RULES if rule != "none")
"""The rules an adversary can imitate before PPO."""
PROGRESS_KEYS = ("episode_return", "team/E", "collision_share", "approx_kl")


def _adversary_ppo() -> PPOConfig:
    return PPOConfig(gamma=0.95, update_threads=1)


def _fail(name: str, value: object, why: str) -> None:
    raise ConfigError(f"{name}={value!r}: {why}")


_FIVE, _THREE = ("", "_seed1", "_seed2", "_seed3", "_seed4"), ("", "_seed1", "_seed2")
DEFAULT_POPULATION = (
    *(f"cihrl_consmac_a{s}" for s in _FIVE),
    *(f"cihrl_consmac_a{s}_wo_ft" for s in _FIVE),
    *(f"cihrl_mappo{s}" for s in _FIVE),
    *(f"{stem}{s}" for stem in ("cihrl_tarmac", "cihrl_consmac_a_dt", "cihrl_consmac_o") for s in _THREE),
    *RULE_TEAMS,
)
"""The population `adversary_ppo_nearest_group_member` (the previous generation's adversary) was
trained against: the methods of Table V's first rows over their training seeds (each over the shipped
student), and the rule-driven teams."""
EVERY_ROW_POPULATION = (
    *DEFAULT_POPULATION,
    *(
        f"{stem}{s}"
        for stem in (
            "cihrl_masia",
            "cihrl_nvif",
            "cihrl_consmac_a_clm",
            "benchmarl_mappo",
            "benchmarl_masac",
            *(f"cihrl_consmac_a_{a}" for a in ("wo_com", "wo_mem", "wo_de", "wt_rl", "consmac_g")),
        )
        for s in _THREE
    ),
    *(f"cihrl_consmac_a_clm{s}_wo_ft" for s in _THREE),
)
"""Every shipped Table V row over its training seeds, and the rule teams (`--teams every-row`): each
learned team flies over the low level its file records (the CL-M rows over `clm-per-group`)."""


@dataclass(frozen=True)
class AdversaryConfig(BudgetPPODict):
    """One PPO adversary training run; saved next to the run and in the model card."""

    budget: Budget
    """Iterations (each: one episode in each of ppo.n_envs envs, then the update) and/or wall-clock."""
    seed: int = 0
    """Seeds network init, action sampling, minibatches, every iteration's episodes and team draws."""
    teams: tuple[str, ...] = DEFAULT_POPULATION
    """The population of UAV teams, each drawn with equal chance for each game of an iteration: a
    trained high level's policy name (in the shipped folder) or file, or a rule team (RULE_TEAMS)."""
    teams_per_iteration: int = 4
    """Games per iteration, each with its own team and ppo.n_envs / teams_per_iteration envs."""
    low_level: str = HIERARCHY_LOWLEVEL
    """The UAV teams' low level: a policy name or file, or 'per-group'."""
    observes_goal: bool = False
    """Whether the adversary reads the rule's goal point (the centre of the nearest group of >= 3)
    as input; False (the paper's adversary) leaves it to find the group from the agents it sees."""
    action: str = "heading"
    """What the actor's outputs mean (AdversaryNetConfig.action): "heading", the direction it flies at top
    speed (as every rule does), "velocity", the direction and speed it wants, or "acceleration", the
    setpoint itself."""
    imitation_rule: str = "nearest_group_strike"
    """The rule the actor imitates before PPO (steering round obstacles, as the game's rules do): by
    default the nearest group of >= 3, or the nearest UAV once one is within 3 m; an imitation of the
    plain nearest-group rule chased at 0.7-1.0 of that rule's E (docs/research/high_level.md)."""
    imitation_episodes: int = 200
    """Before PPO, the actor imitates `imitation_rule` on this many episodes of the population's games
    (its observations, the rule's wishes); 0 starts PPO from random weights. PPO alone stayed at 0.4-0.8
    of the nearest-group rule's E (docs/research/high_level.md)."""
    imitation_steps: int = 8000
    """Adam steps (batch 1024, rate 1e-3) of that imitation, split over the rounds."""
    imitation_rounds: int = 8
    """DAgger rounds: the first flies the rule; each later one flies the actor as it stands and adds
    the rule's wish at the states the actor itself reaches (imitation of the rule's own states alone
    chased at 0.35-0.97 of the rule's E: small errors lead it where the rule never goes)."""
    obstacle_density: float = 0.03
    """Obstacles per m^2 (the game of Tables V and VI)."""
    distance_weight: float = 0.1
    """Reward per metre of distance to the nearest group of >= 3 (subtracted every step)."""
    alert_weight: float = 1.0
    """Reward for the share of UAVs within the alert distance (2 m), every step."""
    collision_weight: float = 30.0
    """Penalty for a step inside an obstacle (within obstacle + body radius of its centre); 30 kept
    the chase of 10 with half the time inside obstacles (docs/research/high_level.md)."""
    progress_weight: float = 10.0
    """Weight of the approach d_before - d_after (m) of each step; without it the distance term
    alone taught the chase about 3x slower (docs/research/high_level.md)."""
    critic_warmup: int = 20
    """Iterations at the start of PPO in which only the critic learns (the actor's rate is 0): an
    imitated actor is not pushed about by the advantages of a critic that has not yet fitted it. The
    shipped adversary is the imitation after these 20 (PPO beyond them lowered its E on validation)."""
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
        if isinstance(self.teams, list):  # read back from JSON
            object.__setattr__(self, "teams", tuple(self.teams))
        self.validate()

    @property
    def name(self) -> str:
        """Run folder and policy file stem: adversary_ppo, then _<rule> when it imitates another rule
        than nearest_group_strike (adversary_ppo_nearest_group_member, ...), then _seed<k> for seeds
        other than 0, so that no candidate overwrites another."""
        rule = "" if self.imitation_rule == "nearest_group_strike" else f"_{self.imitation_rule}"
        return "adversary_ppo" + rule + (f"_seed{self.seed}" if self.seed else "")

    def task(self) -> TaskConfig:
        return adversary_task(self.obstacle_density)

    def validate(self) -> None:
        validate_population_game(self)
        if not isinstance(self.init_log_std, (int, float)) or not -5 <= self.init_log_std <= 2:
            _fail("init_log_std", self.init_log_std, "must be a number in [-5, 2]")
        if self.imitation_rule not in IMITATION_RULES:
            _fail("imitation_rule", self.imitation_rule, f"must be one of {', '.join(IMITATION_RULES)}")
        _check_ints(
            self,
            (
                ("imitation_episodes", 0, 100_000),
                ("imitation_steps", 0, 10_000_000),
                ("imitation_rounds", 1, 100),
                ("critic_warmup", 0, 1_000_000),
            ),
        )
        if not isinstance(self.ppo, PPOConfig):
            _fail("ppo", self.ppo, "must be a PPOConfig")
        self.ppo.validate()
        if self.ppo.n_envs % self.teams_per_iteration:
            _fail("teams_per_iteration", self.teams_per_iteration, f"must divide the {self.ppo.n_envs} envs")
        self.task()


def adversary_task(obstacle_density: float) -> TaskConfig:
    """The game an adversary trains in: Tables V and VI's, with a learned adversary."""
    return dataclasses.replace(game_task(), adversary=LEARNED_ADVERSARY, obstacle_density=obstacle_density)


def _check_ints(cfg, bounds: tuple[tuple[str, int, int], ...]) -> None:
    for name, least, most in bounds:
        value = getattr(cfg, name)
        if not isinstance(value, int) or isinstance(value, bool) or not least <= value <= most:
            _fail(name, value, f"must be an integer in [{least}, {most}]")


def validate_population_game(cfg) -> None:
    """The checks of the fields every adversary trainer (PPO, DDPG) shares: budget, seed, low level,
    teams, observes_goal, action, obstacle density, reward weights, hidden, checkpoint_every,
    eval_episodes and teams_per_iteration."""
    if not isinstance(cfg.budget, Budget):
        _fail("budget", cfg.budget, "must be a Budget")
    if not isinstance(cfg.seed, int) or isinstance(cfg.seed, bool) or not 0 <= cfg.seed <= MAX_SEED:
        _fail("seed", cfg.seed, f"must be an integer in [0, {MAX_SEED}]")
    if not isinstance(cfg.low_level, str) or not cfg.low_level:
        _fail("low_level", cfg.low_level, "must name a policy (a name or a file)")
    if (
        not isinstance(cfg.teams, tuple)
        or not cfg.teams
        or not all(isinstance(t, str) and t for t in cfg.teams)
        or len(set(cfg.teams)) != len(cfg.teams)
    ):
        _fail(
            "teams",
            cfg.teams,
            f"must be a non-empty list of distinct team names (policy names, files or rules: {', '.join(RULE_TEAMS)})",
        )
    if not isinstance(cfg.observes_goal, bool):
        _fail("observes_goal", cfg.observes_goal, "must be True or False")
    if cfg.action not in ADVERSARY_ACTIONS:
        _fail("action", cfg.action, f"must be one of {', '.join(ADVERSARY_ACTIONS)}")
    if not isinstance(cfg.obstacle_density, (int, float)) or not 0 <= cfg.obstacle_density <= MAX_DENSITY:
        _fail("obstacle_density", cfg.obstacle_density, f"must be in [0, {MAX_DENSITY}] per m^2")
    for name in ("distance_weight", "alert_weight", "collision_weight", "progress_weight"):
        value = getattr(cfg, name)
        if not isinstance(value, (int, float)) or not math.isfinite(value) or value < 0:
            _fail(name, value, "must be a number >= 0")
    _check_ints(
        cfg,
        (
            ("hidden", 1, 4096),
            ("checkpoint_every", 1, 1_000_000),
            ("eval_episodes", 0, 1000),
            ("teams_per_iteration", 1, 1000),
        ),
    )


class _Sampler:
    """The adversary_policy of the training env: samples each step's action from the Gaussian and
    records (observation, action, log-probability, value); the reward of a step is read from the env
    at the next call (the state the step led to), the last one by `finish()`."""

    def __init__(self, trainer: "AdversaryTrainer"):
        self.trainer = trainer
        self.env = None  # the BatchedCEFCEnv, set once the game exists
        self.buf: dict[str, list] = {}
        self.terms: dict[str, list] = {}

    KEYS = ("obs", "actions", "logp", "values", "rewards")
    """What each step records (`buf`); "rewards" is filled by `_reward`."""

    def start(self) -> None:
        self.buf = {k: [] for k in self.KEYS}
        self.terms = {k: [] for k in ("distance", "alert", "collision", "progress")}
        self.distance = None  # -d of the state the last action was taken in

    def _reward(self) -> np.ndarray:
        """The terms of the state the env is in; with an action pending, its reward is recorded."""
        env, cfg = self.env, self.trainer.cfg
        world, task = env.world, env.config
        goal = adversary_goal("nearest_group", world.adversary_pos, world.agent_pos, env.group_size, env.group_centre)
        previous = None if self.distance is None else -self.distance
        terms = adversary_reward(
            world.adversary_pos,
            goal,
            world.agent_pos,
            env.obstacles,
            task.rewards.evasion_alert_distance,
            task.obstacle_radius + task.uav_radius,
            cfg.distance_weight,
            cfg.alert_weight,
            cfg.collision_weight,
            previous_distance=previous,
            progress_weight=cfg.progress_weight,
        )
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
        for name, value in (("obs", obs_t), ("actions", action), ("logp", logp), ("values", t.value(obs_t))):
            self.buf[name].append(value)
        return t.actor.to_acceleration(action.numpy(), obs)

    def finish(self) -> torch.Tensor:
        """The last step's reward, and V of the final observation [B] (the time-limit bootstrap)."""
        self._reward()
        return self.trainer.value(torch.from_numpy(self.env.adversary_observation()))


class PopulationGames:
    """What every adversary trainer (PPO, DDPG) shares: the team of each game, drawn from the
    population, and the games themselves. Needs cfg (seed, teams), task and population."""

    def draw_teams(self, iteration: int, stream: int = TEAM_DRAW_STREAM) -> list[str]:
        """The team of each game of `iteration`: uniform draws from the population, a function of
        (seed, iteration, stream) alone, so a resumed run draws what the uninterrupted one would have."""
        names = list(self.cfg.teams)
        rng = np.random.default_rng([self.cfg.seed, iteration, stream])
        return [names[i] for i in rng.integers(len(names), size=len(self.games))]

    def team_for(self, name: str, game: HierarchicalCEFCEnv):
        """The team `name` set to play `game`: its high level (or rule), over its own low level."""
        game.low_level = self.team_low_levels.get(name, self.low_level)
        return RuleTeam(name, game) if self.population[name] is None else self.population[name]

    def evaluate_population(self, adversary, episodes: int) -> dict:
        """`evaluate_against_population` of `adversary` over this trainer's population, each team over
        its own low level, at the games' decision interval (the model card's evaluation)."""
        return evaluate_against_population(
            adversary,
            self.population,
            self.low_level,
            self.task,
            episodes,
            self.games[0].decision_interval,
            team_low_levels=self.team_low_levels,
        )

    def build_games(self, samplers: list, low_level: LowLevel, n_envs: int, decision_interval: int) -> None:
        """One game of n_envs / len(samplers) envs per sampler, the sampler flying its adversary and
        reading its env: sets self.samplers and self.games."""
        self.samplers = samplers
        self.games = [
            HierarchicalCEFCEnv(
                self.task,
                low_level,
                n_envs=n_envs // len(samplers),
                seed=self.cfg.seed,
                decision_interval=decision_interval,
                adversary_policy=sampler,
            )
            for sampler in samplers
        ]
        for sampler, game in zip(self.samplers, self.games):
            sampler.env = game.env


class AdversaryTrainer(PopulationGames):
    """The learner: actor, critic, their optimizers, the value normalizer and a torch RNG; one
    `iterate()` = collect one episode per env (teams_per_iteration games, a team drawn for each), then
    the PPO update."""

    def __init__(
        self,
        cfg: AdversaryConfig,
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
            init_log_std=cfg.init_log_std,
            observes_goal=cfg.observes_goal,
            action=cfg.action,
            speed_max=self.task.adversary_speed_max,
            dt=self.task.dt,
        )
        self.actor = AdversaryPolicy(net, seed=cfg.seed)
        torch.manual_seed(cfg.seed + 1)
        self.critic = Critic(net.input_dim, cfg.hidden)
        self.value_norm = ValueNorm()
        self.actor_opt = torch.optim.Adam(self.actor.parameters(), lr=cfg.ppo.lr, eps=1e-5)
        self.critic_opt = torch.optim.Adam(self.critic.parameters(), lr=cfg.ppo.lr, eps=1e-5)
        self.generator = torch.Generator().manual_seed(cfg.seed)
        self.iteration, self.episodes, self.elapsed = 0, 0, 0.0
        self.build_games(
            [_Sampler(self) for _ in range(cfg.teams_per_iteration)], low_level, cfg.ppo.n_envs, decision_interval
        )

    @torch.no_grad()
    def demonstrations(self, round_: int) -> tuple[torch.Tensor, torch.Tensor]:
        """(observations [S, D], what the actor should output there: the imitated rule's wish [S, 2])
        over cfg.imitation_episodes episodes: batches of ppo.n_envs / teams_per_iteration games, a team
        drawn for each; round 0 the rule flies the adversary, later rounds the actor's mean (DAgger).
        Seeded from the run seed and the round (an imitation stream apart from the iterations')."""
        obs_rows, act_rows = [], []
        per_game = self.games[0].n_envs
        batches = math.ceil(self.cfg.imitation_episodes / per_game)
        for batch in range(round_ * batches, (round_ + 1) * batches):
            name = self.draw_teams(batch, stream=IMITATION_STREAM)[0]

            def rule(obs):  # called while `game` below plays
                env = game.env
                action = env.rule_adversary_acceleration(self.cfg.imitation_rule)
                target = (
                    env.rule_adversary_velocity(self.cfg.imitation_rule) / self.task.adversary_speed_max
                    if self.cfg.action != "acceleration"
                    else action
                )  # what the actor outputs
                obs_rows.append(torch.from_numpy(obs.copy()))
                act_rows.append(torch.as_tensor(target, dtype=torch.float32))
                return action if round_ == 0 else self.actor.act(obs)

            game = HierarchicalCEFCEnv(
                self.task,
                self.low_level,
                n_envs=per_game,
                seed=self.cfg.seed,
                decision_interval=self.games[0].decision_interval,
                adversary_policy=rule,
            )
            play_highlevel(
                self.team_for(name, game), game, seed=iteration_seed(self.cfg.seed, batch, stream=IMITATION_STREAM)
            )
        return torch.cat(obs_rows), torch.cat(act_rows)

    def imitate(self, progress=None) -> dict[str, float]:
        """Fit the actor's mean to the rule's wish (MSE) over cfg.imitation_rounds DAgger rounds, the
        data of every round kept; returns the fit of each round on the states of all rounds.
        `progress` (a tqdm bar) counts the fitting steps, the round named beside it."""
        cfg = self.cfg
        optimizer = torch.optim.Adam(self.actor.parameters(), lr=1e-3)
        obs, target = torch.zeros(0, ADVERSARY_OBS_DIM), torch.zeros(0, 2)
        per_round = []
        for round_ in range(cfg.imitation_rounds):
            if progress is not None:
                progress.set_postfix_str(f"round {round_ + 1}/{cfg.imitation_rounds}: flying the demonstrations")
            new_obs, new_target = self.demonstrations(round_)
            if progress is not None:
                progress.set_postfix_str(f"round {round_ + 1}/{cfg.imitation_rounds}: fitting")
            obs, target = torch.cat([obs, new_obs]), torch.cat([target, new_target])
            with torch.no_grad():  # how far the actor is from the rule where it flew itself (before fitting)
                on_policy = float((self.actor(new_obs) - new_target).pow(2).sum(-1).mean())
            for _ in range(cfg.imitation_steps // cfg.imitation_rounds):
                idx = torch.randint(len(obs), (1024,), generator=self.generator)
                loss = (self.actor(obs[idx]) - target[idx]).pow(2).sum(-1).mean()
                optimizer.zero_grad()
                loss.backward()
                optimizer.step()
                if progress is not None:
                    progress.update(1)
            with torch.no_grad():
                fit = float((self.actor(obs) - target).pow(2).sum(-1).mean())
            per_round.append({"samples": len(obs), "mse_on_new_states_before": on_policy, "mse_after": fit})
        return {"rounds": per_round, "steps": cfg.imitation_steps, "mse_of_the_mean_action": float(target.var(0).sum())}

    def value(self, obs: torch.Tensor) -> torch.Tensor:
        """V of adversary observations: the critic reads what the actor reads."""
        return self.critic(network_input(obs, self.cfg.observes_goal))

    @torch.no_grad()
    def collect(self) -> tuple[dict[str, torch.Tensor], dict[str, float]]:
        parts, team_stats = [], []
        for g, (name, game, sampler) in enumerate(zip(self.draw_teams(self.iteration), self.games, self.samplers)):
            sampler.start()
            team_stats.append(
                play_highlevel(
                    self.team_for(name, game), game, seed=iteration_seed(self.cfg.seed, self.iteration, stream=g)
                )
            )
            final_value = sampler.finish()
            buf = {k: torch.stack(v) for k, v in sampler.buf.items()}  # [T, B/k, ...]
            buf["next_values"] = torch.cat([buf["values"][1:], final_value[None]])
            parts.append((buf, {k: np.stack(v) for k, v in sampler.terms.items()}))
        buf = {k: torch.cat([p[0][k] for p in parts], dim=1) for k in parts[0][0]}  # [T, B, ...]
        terms = {k: np.concatenate([p[1][k] for p in parts], axis=1) for k in parts[0][1]}
        episode_end = torch.zeros_like(buf["rewards"], dtype=torch.bool)
        episode_end[-1] = True
        buf["advantages"], buf["targets"], ev = advantages_and_targets(
            buf["rewards"], buf["values"], buf.pop("next_values"), episode_end, self.cfg.ppo, self.value_norm
        )
        team = {k: np.concatenate([s[k] for s in team_stats]) for k in ("E", "R_t", "R_H")}
        stats = {
            "episode_return": float(buf["rewards"].sum(0).mean()),
            "explained_variance": ev,
            "distance_m": float(-terms["distance"].mean()),
            "alert_share": float(terms["alert"].mean()),
            "collision_share": float(-terms["collision"].mean()),
            "team/E": float(team["E"].mean()),
            "team/R_t": float(team["R_t"].mean()),
            "team/R_H": float(team["R_H"].mean()),
            "action_std": float(self.actor.log_std.exp().mean()),
            "episodes": self.cfg.ppo.n_envs,
        }
        return buf, stats

    def update(self, buf: dict[str, torch.Tensor]) -> dict[str, float]:
        flat = {k: v.reshape(-1, *v.shape[2:]) for k, v in buf.items()}

        def policy_terms(mb):
            dist = self.actor.distribution(flat["obs"][mb])
            return dist.log_prob(flat["actions"][mb]).sum(-1), dist.entropy().sum(-1).mean()

        critic_obs = network_input(flat["obs"], self.cfg.observes_goal)
        return ppo_epochs(
            len(flat["obs"]),
            self.cfg.ppo,
            self.generator,
            policy_terms,
            flat["logp"],
            flat["advantages"],
            self.actor_opt,
            list(self.actor.parameters()),
            self.critic,
            critic_obs,
            flat["targets"],
            self.critic_opt,
        )

    def iterate(self) -> dict[str, float]:
        t0 = time.perf_counter()
        torch.set_num_threads(self.cfg.ppo.rollout_threads)
        buf, stats = self.collect()
        t1 = time.perf_counter()
        torch.set_num_threads(self.cfg.ppo.update_threads)
        for group in self.actor_opt.param_groups:
            group["lr"] = 0.0 if self.iteration < self.cfg.critic_warmup else self.cfg.ppo.lr
        update = self.update(buf)
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
            "rollout_s": t1 - t0,
            "update_s": t2 - t1,
        }

    def state_dict(self) -> dict:
        return {
            **learner_state(self),
            "counters": {"iteration": self.iteration, "episodes": self.episodes, "elapsed": self.elapsed},
        }

    def load_state_dict(self, state: dict) -> None:
        load_learner_state(self, state)
        c = state["counters"]
        self.iteration, self.episodes, self.elapsed = int(c["iteration"]), int(c["episodes"]), float(c["elapsed"])


# ---------------------------------------------------------------------------- evaluation
@torch.no_grad()
def evaluate_adversary(
    adversary,
    team: HighLevelPolicy | str,
    low_level: LowLevel,
    task: TaskConfig,
    episodes: int,
    seed: int = 0,
    decision_interval: int = DECISION_INTERVAL,
    world=None,
) -> dict[str, float]:
    """The UAV team's per-episode means (R_H and its parts, E, F, C: `play_highlevel`) against an
    adversary, and the share of steps it spent inside an obstacle ("adversary_collision_share").
    adversary: a callable of observations (e.g. `AdversaryPolicy.act`) for a task with
    adversary='learned', or a rule (its name or an `InterceptRule`, flown exactly as the env flies
    `task.adversary`). team: a trained high level or a rule team's name (RULE_TEAMS)."""
    inside: list[np.ndarray] = []
    keep_out = task.obstacle_radius + task.uav_radius

    def flown(obs: np.ndarray) -> np.ndarray:
        env = game.env
        if env.obstacles.shape[1]:
            gap = np.linalg.norm(env.obstacles - env.world.adversary_pos[:, None, :], axis=-1)
            inside.append((gap < keep_out).any(axis=-1))
        if isinstance(adversary, (str, InterceptRule)):
            return env.rule_adversary_acceleration(adversary)
        return adversary(obs)

    task = dataclasses.replace(task, adversary=LEARNED_ADVERSARY)
    game = HierarchicalCEFCEnv(
        task,
        low_level,
        n_envs=episodes,
        seed=seed,
        decision_interval=decision_interval,
        world=world,
        adversary_policy=flown,
    )
    per_episode = play_highlevel(RuleTeam(team, game) if isinstance(team, str) else team, game, seed)
    out = {name: float(values.mean()) for name, values in per_episode.items()}
    out["adversary_collision_share"] = float(np.mean(inside)) if inside else 0.0
    return out


# ---------------------------------------------------------------------------- the run
def read_state(path: Path) -> dict:
    return run_state.read_state(path, STATE_FORMAT, "adversary training state")


def load_population(
    cfg: AdversaryConfig, policies_dir: Path | None = None
) -> tuple[dict[str, HighLevelPolicy | None], dict[str, dict], LowLevel, int, dict[str, LowLevel]]:
    """(team name -> high level or None for a rule team, team name -> its record for the card, the low
    level, the teams' decision interval, team name -> its own low level for the learned teams whose
    file records a per-group low level (`PER_GROUP_FILES`) other than cfg.low_level, e.g. the CL-M rows'
    `clm-per-group`: a team flies over the low level it was fine-tuned with, as Table V flies it; any
    other recorded low level is flown as cfg.low_level); CheckpointError naming the flag when a file
    is missing."""
    population, records, intervals, wanted = {}, {}, set(), {}
    for name in cfg.teams:
        if name in RULE_TEAMS:
            population[name], records[name] = None, {"kind": "rule", "rule": name}
            continue
        try:
            path = highlevel_policy_path(name, policies_dir)
            population[name], meta = load_highlevel_policy(path)
        except CheckpointError as e:
            raise CheckpointError(f"--teams: {e}") from None
        records[name] = {"kind": "learned", "path": display_path(path), "sha256": file_sha256(path)}
        intervals.add(int(meta.get("decision_interval", DECISION_INTERVAL)))
        wanted[name] = recorded_low_level(meta, None)  # None: cfg.low_level
    if len(intervals) > 1:
        raise ConfigError(f"--teams: the teams decide at different intervals ({sorted(intervals)} steps)")
    try:
        low_level = load_low_level(cfg.low_level, cfg.task(), policies_dir)
    except CheckpointError as e:
        raise CheckpointError(f"--low-level: {e}") from None
    own: dict[str, LowLevel] = {}
    for spec in {spec for spec in wanted.values() if spec is not None and spec != low_level.name}:
        try:
            own[spec] = load_low_level(spec, cfg.task(), policies_dir)
        except CheckpointError as e:
            raise CheckpointError(f"--teams: the low level of a team: {e}") from None
    team_low_levels = {name: own[spec] for name, spec in wanted.items() if spec in own}
    for name in team_low_levels:
        records[name]["low_level"] = wanted[name]
    return population, records, low_level, intervals.pop() if intervals else DECISION_INTERVAL, team_low_levels


def train_adversary(
    cfg: AdversaryConfig,
    out: Path,
    policies_dir: Path,
    resume: bool = False,
    show_progress: bool = True,
    command: str | None = None,
) -> dict:
    """Train under the budget, export the adversary and its model card to `policies_dir`; returns
    the card. Everything the run needs is loaded and checked before the run folder is made."""
    out, policies_dir = Path(out), Path(policies_dir)
    run_dir = out / cfg.name
    state_path = run_dir / STATE_FILE
    population, team_records, low_level, interval, team_low_levels = load_population(cfg)
    team_record = {"population": team_records, "low_level": display_paths(low_level.describe())}
    saved = None
    if run_state.run_state_path(run_dir, resume) is not None:
        saved = read_state(state_path)
        run_state.check_same_run(saved["config"], cfg, state_path, free=("budget", "checkpoint_every", "eval_episodes"))
    trainer = AdversaryTrainer(cfg, population, low_level, interval, team_low_levels)
    imitation = None
    if saved is not None:
        run_state.restore_trainer(trainer, saved, state_path)
        imitation = saved.get("imitation")
    elif cfg.imitation_episodes and cfg.imitation_steps:
        if show_progress:
            print(
                f"{cfg.name}: imitating the {cfg.imitation_rule} rule ({cfg.imitation_episodes} episodes, "
                f"{cfg.imitation_steps} steps)",
                flush=True,
            )
        start = time.perf_counter()
        fitting_steps = cfg.imitation_steps // cfg.imitation_rounds * cfg.imitation_rounds
        with tqdm(
            total=fitting_steps, desc="imitation", unit="step", disable=not show_progress, mininterval=2.0
        ) as bar:
            imitation = {**trainer.imitate(progress=bar), "wall_s": round(time.perf_counter() - start, 1)}
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
            {"format": STATE_FORMAT, "config": cfg.to_dict(), "trainer": trainer.state_dict(), "imitation": imitation},
            state_path,
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
        meta={"name": cfg.name, "seed": cfg.seed, "iterations": trainer.iteration},
    )
    card = {
        "name": cfg.name,
        "method": "PPO adversary (single-agent PPO, the low level's network shape), trained against a population "
        f"of {len(cfg.teams)} teams over {low_level.name}",
        "seed": cfg.seed,
        "config": cfg.to_dict(),
        "task": trainer.task.to_dict(),
        "network": trainer.actor.cfg.to_dict(),
        "team": team_record,
        "imitation": imitation,
        "iterations": trainer.iteration,
        "episodes": trainer.episodes,
        "steps": trainer.episodes * trainer.task.steps,
        "train_wall_clock_s": round(trainer.elapsed, 1),
        "run_dir": display_path(run_dir),
        "command": command,
        "last_iteration": {k: v for k, v in last_row.items() if isinstance(v, (int, float))},
    }
    if cfg.eval_episodes:
        card["evaluation"] = trainer.evaluate_population(trainer.actor.act, cfg.eval_episodes)
    write_model_card(policy_path, card)
    return card


def evaluate_against_population(
    adversary,
    population: dict[str, HighLevelPolicy | None],
    low_level: LowLevel,
    task: TaskConfig,
    episodes: int,
    decision_interval: int = DECISION_INTERVAL,
    seed: int = GAME_VALIDATION_SEED,
    team_low_levels: dict[str, LowLevel] | None = None,
) -> dict:
    """Each team against the adversary (its mean action) and against the nearest-group rule, flown under
    the same obstacle rule (task.adversary_avoids_obstacles), on `episodes` validation games, each team
    over its own low level where team_low_levels has one; with the ratio of E (PPO / rule) per team."""
    per_team = {}
    for name, policy in population.items():
        team = name if policy is None else policy
        own = (team_low_levels or {}).get(name, low_level)
        ours = evaluate_adversary(adversary, team, own, task, episodes, seed=seed, decision_interval=decision_interval)
        rule = evaluate_adversary(
            "nearest_group", team, own, task, episodes, seed=seed, decision_interval=decision_interval
        )
        per_team[name] = {
            "ours": ours,
            "rule_nearest_group": rule,
            "E_ratio": ours["E"] / rule["E"] if rule["E"] else None,
        }
    return {
        "protocol": {
            "episodes": episodes,
            "seed": seed,
            "seed_block": "validation",
            "backend": "particle",
            "adversary": "the mean action",
            "rule_avoids_obstacles": task.adversary_avoids_obstacles,
            "figures": "the team's per-episode sums (R_t, R_n, R_e weighted, summing to R_H; E in "
            "steps) and the adversary's share of steps inside an obstacle",
        },
        "per_team": per_team,
    }


def summary_lines(card: dict, policies_dir: Path, algorithm: str = "PPO") -> list[str]:
    """What `cefc-train adversary` (and adversary-ddpg, algorithm "DDPG") prints when a run ends."""
    lines = [
        f"{card['name']}: {card['iterations']} iterations, {card['episodes']} episodes, "
        f"{card['train_wall_clock_s']} s -> {policies_dir / (card['name'] + '.pt')} (run {card['run_dir']})"
    ]
    if "evaluation" in card:
        e = card["evaluation"]
        lines.append(
            f"team E in steps against the {algorithm} adversary / the nearest-group rule "
            f"({e['protocol']['episodes']} validation episodes each):"
        )
        for name, row in e["per_team"].items():
            ratio = "-" if row["E_ratio"] is None else f"{row['E_ratio']:.2f}"
            lines.append(
                f"  {name:24s} {row['ours']['E']:6.1f} / {row['rule_nearest_group']['E']:6.1f}  "
                f"(ratio {ratio}); adversary inside an obstacle "
                f"{100 * row['ours']['adversary_collision_share']:.1f} %"
            )
    return lines


# ---------------------------------------------------------------------------- command line
_FLAG_OF_FIELD = {
    "seed": "--seed",
    "teams": "--teams",
    "teams_per_iteration": "--teams-per-iteration",
    "low_level": "--low-level",
    "imitation_episodes": "--imitation-episodes",
    "imitation_steps": "--imitation-steps",
    "imitation_rounds": "--imitation-rounds",
    "init_log_std": "--init-log-std",
    "critic_warmup": "--critic-warmup",
    "action": "--action",
    "imitation_rule": "--imitation-rule",
    "alert_weight": "--alert-weight",
    "progress_weight": "--progress-weight",
    "obstacle_density": "--density",
    "eval_episodes": "--eval-episodes",
    "n_envs": "--envs",
    "collision_weight": "--collision-weight",
    "epochs": "--epochs",
    "lr": "--lr",
    "update_threads": "--threads",
}
"""Config fields set by `cefc-train adversary` flags: their errors name the flag the user typed."""
CLI_FIELDS = (
    "seed",
    "teams",
    "teams_per_iteration",
    "low_level",
    "obstacle_density",
    "collision_weight",
    "eval_episodes",
    "imitation_episodes",
    "imitation_steps",
    "imitation_rounds",
    "init_log_std",
    "critic_warmup",
    "action",
    "alert_weight",
    "progress_weight",
    "imitation_rule",
)
CLI_PPO_FIELDS = ("n_envs", "epochs", "lr", "update_threads")


def config_from_args(args, budget: Budget) -> AdversaryConfig:
    """The AdversaryConfig of `cefc-train adversary` arguments (flags left out keep the defaults);
    a bad value raises ConfigError naming the flag."""
    return config_from_flags(
        AdversaryConfig, args, budget, CLI_FIELDS, CLI_PPO_FIELDS, _adversary_ppo(), _FLAG_OF_FIELD
    )
