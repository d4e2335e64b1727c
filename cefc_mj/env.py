"""The batched CEFC environment: the task core on top of a physics world.

`BatchedCEFCEnv` is what training uses (B envs x N agents, numpy, one process); the PettingZoo
wrapper (`cefc_mj.pettingzoo_env`) exposes one env of it. Both backends run through this class, so
observations, rewards and metrics are the same code for particles and quadrotors.

The game's pieces, in the order a step uses them (read this file top to bottom, then each module):

| piece | where | in this class |
|---|---|---|
| task parameters | `task/config.py` (`TaskConfig`, `RewardConfig`) | `__init__` |
| scenario: starts, obstacles, targets, anchors, adversary start | `task/scenario.py` | `reset` |
| world: particles or MuJoCo quadrotors | `sim/particle.py`, `sim/mujoco_world.py` (`sim/backends.py`) | `step` |
| adversary: rules and the learned one's observation | `task/adversary.py` | `step`, `rule_adversary_*` |
| groups and formation error | `task/formation.py` | `_groups` |
| sensing: deviation, position estimate, LiDAR | `task/deviation.py`, `estimator.py`, `lidar.py` | `_observe` |
| observation | `task/observation.py` | `_observe` |
| reward terms R_f, R_n, R_t, R_e, R_c | `task/rewards.py` | `_rewards` |
| metrics F, N, C, E, E_agents | here | `_accumulate_metrics`, `episode_metrics` |

>>> from cefc_mj.env import BatchedCEFCEnv
>>> from cefc_mj.task.config import TaskConfig
>>> env = BatchedCEFCEnv(TaskConfig(n_agents=5, mode="formation"), n_envs=4, seed=0)
>>> obs = env.reset()
>>> obs.shape
(4, 5, 63)
>>> obs, reward, done, info = env.step(np.zeros((4, 5, 2)))
>>> reward.shape, done.any(), sorted(info["reward_terms"])
((4,), np.False_, ['R_c', 'R_f', 'R_n'])
"""

from __future__ import annotations

import numpy as np

from cefc_mj.errors import ConfigError
from cefc_mj.sim.particle import ParticleWorld
from cefc_mj.sim.world import World
from cefc_mj.task import rewards as R
from cefc_mj.task.adversary import (
    InterceptRule,
    adversary_goal,
    adversary_observation,
    pursuit_velocity,
    velocity_tracking_acceleration,
)
from cefc_mj.task.config import LEARNED_ADVERSARY, TaskConfig
from cefc_mj.task.deviation import sample_deviation
from cefc_mj.task.estimator import FusedPositionEstimate
from cefc_mj.task.formation import agent_group_error, connected_groups, group_formation_error
from cefc_mj.task.observation import build_cefc_observation, build_low_level_observation, layout_for
from cefc_mj.task.push_observer import PushObserver
from cefc_mj.task.scenario import Scenario, check_scenario, sample_anchor, sample_scenario

METRIC_NAMES = ("F", "N", "C", "E", "E_agents")


class BatchedCEFCEnv:
    """B independent CEFC episodes stepped together.

    Rewards are the paper's team rewards [B]: R_L = 15 R_f + 4 R_n + 100 R_c in formation mode,
    R_H = 10 R_t + 0.1 R_n + 100 R_e in cefc mode; `info["reward_terms"]` holds each unweighted term.
    Episodes of all envs end together after `config.steps` steps; `reset(mask)` restarts some.
    """

    def __init__(
        self,
        config: TaskConfig,
        n_envs: int = 1,
        seed: int | None = 0,
        world: World | None = None,
        adversary_policy=None,
    ):
        """adversary_policy: with config.adversary = "learned", a callable mapping the adversary's
        observation [B, D] (`adversary_observation`) to its acceleration setpoint [B, 2] (m/s^2),
        called at every step (e.g. a loaded `nn.adversary_policy.AdversaryPolicy`)."""
        if not isinstance(n_envs, int) or n_envs < 1:
            raise ConfigError(f"n_envs={n_envs!r}: must be an integer >= 1")
        learned = config.mode == "cefc" and config.adversary == LEARNED_ADVERSARY
        if learned and adversary_policy is None:
            raise ConfigError("adversary='learned': give the env an adversary_policy (a trained adversary)")
        if adversary_policy is not None and not learned:
            raise ConfigError(
                f"adversary_policy: flies only the 'learned' adversary of cefc mode (this task: "
                f"mode={config.mode!r}, adversary={config.adversary!r})"
            )
        self.adversary_policy = adversary_policy
        if config.mode == "formation" and config.n_agents < 3:
            raise ConfigError(f"n_agents={config.n_agents}: formation mode needs a group of at least 3 agents")
        self.config = config
        self.n_envs = n_envs
        self.n_agents = config.n_agents
        self.layout = layout_for(config)
        self.world = world if world is not None else ParticleWorld(config, n_envs, seed=seed)
        self.rng = np.random.default_rng(seed)
        b, n, j = n_envs, config.n_agents, config.n_targets if config.mode == "cefc" else 0
        self.t = np.zeros(b, dtype=int)
        self.anchor = np.zeros((b, 2))
        self.targets = np.zeros((b, j, 2))
        self.urgency = np.ones((b, j))
        self.obstacles = np.zeros((b, config.n_obstacles, 2))
        self.prev_formation_reward = np.zeros(b)
        self.metric_sums = {name: np.zeros(b) for name in METRIC_NAMES}
        self.perceived_pos = np.zeros((b, n, 2))
        """The position each agent acts on: its fix, or its fused estimate (config.position_estimator)."""
        self.estimate = FusedPositionEstimate(b, n) if config.position_estimator == "fused" else None
        self._last_true_pos = np.zeros((b, n, 2))
        self.push_observer = (
            PushObserver(b, n, config.push_observer_s, config.dt, config.accel_max)
            if config.push_observer_s > 0
            else None
        )
        """The agents' push observers (config.push_observer_s > 0), None for the paper's memoryless agent."""
        self.env_deviation = np.full(b, config.deviation)
        """Each env's sensing deviation d (m) this episode (drawn at reset with deviation_sampling='uniform')."""
        self.lidar = np.full((b, n, config.n_lidar_rays), config.lidar_range)
        self.true_lidar = self.lidar
        """LiDAR cast from the true positions (the collision reward's input; `lidar` is what agents see)."""
        self.agent_collision_penalty = np.zeros((b, n))
        """CR_i of the last step (eq. 17) from the true clearances, [B, N]; R_c = -its sum."""
        self.labels = np.zeros((b, n), dtype=int)
        self.agent_error = np.full((b, n), np.nan)
        self.group_size = np.zeros((b, n), dtype=np.int64)
        self.group_centre = np.zeros((b, n, 2))
        self._obs = np.zeros((b, n, self.layout.size), dtype=np.float32)

    # ------------------------------------------------------------------ reset
    @property
    def observation(self) -> np.ndarray:
        """The current observation [B, N, D] (what the last reset or step returned)."""
        return self._obs

    def reset(
        self, mask: np.ndarray | None = None, seed: int | None = None, scenario: Scenario | None = None
    ) -> np.ndarray:
        """Start new episodes in the masked envs (all by default); returns obs [B, N, D] of all envs.
        `scenario` (one layout per masked env) replaces the sampled one, e.g. a hand-built situation."""
        if seed is not None:
            self.rng = np.random.default_rng(seed)
            if isinstance(self.world, ParticleWorld):  # its velocity noise belongs to the episode too
                self.world.rng = np.random.default_rng((seed, 1))
        mask = np.ones(self.n_envs, dtype=bool) if mask is None else np.asarray(mask, dtype=bool)
        if mask.shape != (self.n_envs,):
            raise ConfigError(f"mask: expected shape ({self.n_envs},), got {mask.shape}")
        count = int(mask.sum())
        if count == 0:
            return self._obs
        if scenario is None:
            scenario = sample_scenario(self.config, self.rng, count)
        else:
            check_scenario(self.config, scenario, count)
        full = lambda arr, like: _scatter(mask, arr, like)  # noqa: E731 - expand masked rows to [B, ...]
        self.world.reset(
            mask,
            full(scenario.agent_pos, self.world.agent_pos),
            full(scenario.adversary_pos, self.world.adversary_pos),
            full(scenario.obstacles, self.obstacles),
        )
        self.obstacles[mask] = scenario.obstacles
        if self.push_observer is not None:
            self.push_observer.reset(mask, self.world.agent_vel)
        if self.config.deviation_sampling == "uniform":
            self.env_deviation[mask] = self.rng.uniform(0.0, self.config.deviation, count)
        self.anchor[mask] = scenario.anchor
        self.targets[mask] = scenario.targets
        self.urgency[mask] = 1.0
        self.t[mask] = 0
        self.prev_formation_reward[mask] = 0.0
        for total in self.metric_sums.values():
            total[mask] = 0.0
        self._groups(self.world.agent_pos)
        self._observe(mask, first=True)
        return self._obs

    # ------------------------------------------------------------------ step
    def step(self, actions: np.ndarray):
        """Apply acceleration setpoints [B, N, 2] (m/s^2) for one decision step.

        Returns (obs [B,N,D] float32, reward [B], done [B] bool, info); the obs array is the env's own
        buffer, overwritten by the next step or reset (copy it to keep it). info["reward_terms"] maps each
        unweighted reward term to [B]; at episode end info["metrics"] maps F, N, C, E to [B].
        """
        cfg = self.config
        actions = np.asarray(actions, dtype=np.float64)
        if actions.shape != (self.n_envs, self.n_agents, 2):
            raise ConfigError(f"actions: expected shape ({self.n_envs}, {self.n_agents}, 2), got {actions.shape}")
        if not np.isfinite(actions).all():
            raise ConfigError("actions: contain NaN or inf")
        if (self.t >= cfg.steps).any():
            raise ConfigError("step() called on a finished episode; call reset(mask=done) first")
        actions = np.clip(actions, -cfg.accel_max, cfg.accel_max)
        if self.push_observer is not None:  # the agents' own setpoints: the command less the push they feel
            actions = self.push_observer.setpoint(actions)

        if self.adversary_policy is not None:
            adversary_accel = np.asarray(self.adversary_policy(self.adversary_observation()), dtype=np.float64)
            if adversary_accel.shape != (self.n_envs, 2) or not np.isfinite(adversary_accel).all():
                raise ConfigError(f"adversary_policy: must return finite accelerations of shape ({self.n_envs}, 2)")
            adversary_accel = np.clip(adversary_accel, -cfg.accel_max, cfg.accel_max)
        elif cfg.mode == "cefc" and cfg.adversary != "none":
            adversary_accel = self.rule_adversary_acceleration(cfg.adversary)
        else:
            adversary_accel = np.zeros((self.n_envs, 2))
        self.world.step(actions, adversary_accel)
        if self.push_observer is not None:
            self.push_observer.update(self.world.agent_vel)
        self.t += 1
        if cfg.anchor_redraw_steps is not None:
            redraw = (self.t % cfg.anchor_redraw_steps == 0) & (self.t < cfg.steps)
            if redraw.any():
                self.anchor[redraw] = sample_anchor(cfg, self.rng, self.obstacles[redraw], int(redraw.sum()))

        pos = self.world.agent_pos
        group_error, group_size, group_centre = self._groups(pos)
        self._observe(np.ones(self.n_envs, dtype=bool))
        # the swarm centre's distance to the anchor: the low level's R_n is minus it, the metric N counts it
        centre_distance = -R.anchor_navigation_reward(pos, self.anchor)
        terms, reward = self._rewards(pos, group_error, group_size, group_centre, centre_distance)
        self._accumulate_metrics(pos, centre_distance)
        done = self.t >= cfg.steps
        info = {"reward_terms": terms, "t": self.t.copy()}
        if done.any():
            info["metrics"] = self.episode_metrics()
        return self._obs, reward, done, info

    # ------------------------------------------------------------------ pieces
    def _groups(self, pos):
        """Group labels, per-group HD error [B,G], sizes [B,G] and centres [B,G,2] from true positions."""
        formation = self.config.mode == "formation"
        if formation:
            self.labels = np.zeros((self.n_envs, self.n_agents), dtype=np.int64)
        else:
            self.labels = connected_groups(pos, self.config.observation_distance)
        error, size, centre = group_formation_error(pos, self.labels, self.config.formation_spacing)
        # formation mode: every agent is in group 0 (the gather, without its cost)
        if formation:
            self.agent_error = np.repeat(error[:, :1], self.n_agents, axis=1)
        else:
            self.agent_error = agent_group_error(error, self.labels)
        self.group_size, self.group_centre = size, centre
        return error, size, centre

    def _observe(self, mask: np.ndarray, first: bool = False) -> None:
        """Observations of the masked envs; `first`: the masked envs have just been reset."""
        cfg, world = self.config, self.world
        true_pos = world.agent_pos
        fix = true_pos + sample_deviation(self.rng, self.env_deviation, true_pos.shape[:2])
        if self.estimate is None:
            self.perceived_pos = fix
        else:
            exact = self.env_deviation == 0
            if first:
                self.estimate.reset(mask, fix)
            elif not exact.all():  # an exact env's estimate is never read until its next reset
                self.estimate.update(fix, true_pos - self._last_true_pos)
            self._last_true_pos = true_pos.copy()
            # Exact fixes leave the filter at the fix up to rounding: use the fix itself there, so a
            # noise-free episode is bit-identical to the raw agent's.
            self.perceived_pos = fix if exact.all() else np.where(exact[:, None, None], fix, self.estimate.position)
        self.lidar = world.lidar(self.perceived_pos)
        # The collision reward scores true clearances (like the metrics), not what the noisy LiDAR shows.
        self.true_lidar = world.lidar(true_pos) if cfg.deviation > 0 else self.lidar
        if cfg.mode == "formation":
            obs = build_low_level_observation(cfg, self.perceived_pos, world.agent_vel, self.anchor, self.lidar)
        else:
            obs = build_cefc_observation(
                cfg,
                self.perceived_pos,
                world.agent_vel,
                self.targets,
                self.urgency,
                world.adversary_pos,
                world.adversary_vel,
                self.lidar,
            )
        self._obs[mask] = obs[mask]

    def rule_adversary_goal(self, rule: str | InterceptRule) -> np.ndarray:
        """The point [B, 2] a rule adversary (task/adversary.py: a rule's name or an InterceptRule)
        chases at this step."""
        w = self.world
        return adversary_goal(
            rule,
            w.adversary_pos,
            w.agent_pos,
            self.group_size,
            self.group_centre,
            self.labels,
            w.agent_vel,
            self.config.adversary_speed_max,
        )

    def rule_adversary_velocity(self, rule: str | InterceptRule) -> np.ndarray:
        """The velocity [B, 2] a rule adversary (task/adversary.py) wants at this step."""
        cfg = self.config
        return pursuit_velocity(
            self.rule_adversary_goal(rule),
            self.world.adversary_pos,
            cfg.adversary_speed_max,
            obstacles=self.obstacles if cfg.adversary_avoids_obstacles else None,
            keep_out=cfg.obstacle_radius + cfg.uav_radius,
        )

    def rule_adversary_acceleration(self, rule: str | InterceptRule) -> np.ndarray:
        """The acceleration [B, 2] a rule adversary (task/adversary.py) commands at this step."""
        cfg = self.config
        return velocity_tracking_acceleration(
            self.rule_adversary_velocity(rule), self.world.adversary_vel, cfg.accel_max, cfg.dt
        )

    def adversary_observation(self) -> np.ndarray:
        """The learned adversary's observation [B, D] of the current step (task/adversary.py)."""
        world, cfg = self.world, self.config
        goal = adversary_goal("nearest_group", world.adversary_pos, world.agent_pos, self.group_size, self.group_centre)
        return adversary_observation(
            world.adversary_pos,
            world.adversary_vel,
            goal,
            world.agent_pos,
            world.agent_vel,
            np.take_along_axis(self.group_size, self.labels, axis=1),
            self.obstacles,
            cfg.arena_half_size,
            cfg.adversary_speed_max,
            cfg.obstacle_radius + cfg.uav_radius,
            self.group_centre,
            self.group_size,
        )

    def _rewards(self, pos, group_error, group_size, group_centre, centre_distance):
        cfg, w = self.config, self.config.rewards
        hd_sum = np.nansum(group_error, axis=-1)
        r_f = R.formation_reward(hd_sum, self.prev_formation_reward, w.formation_lag)
        self.prev_formation_reward = r_f
        self.agent_collision_penalty = R.collision_penalty(self.true_lidar.min(axis=-1), w)
        r_c = -self.agent_collision_penalty.sum(axis=-1)  # R_c = -sum_i CR_i (eq. 16)
        if cfg.mode == "formation":
            r_n = -centre_distance  # R.anchor_navigation_reward
            terms = {"R_f": r_f, "R_n": r_n, "R_c": r_c}
            reward = w.formation_weight * r_f + w.navigation_weight_low * r_n + w.collision_weight * r_c
            return terms, reward
        coverage = R.target_coverage(
            group_error, group_size, group_centre, self.targets, cfg.formation_tolerance, cfg.target_radius
        )
        r_n = R.target_navigation_reward(pos, self.targets, self.urgency)
        r_t = R.task_reward(coverage, self.urgency)
        r_e = R.evasion_reward(pos, self.world.adversary_pos, w.evasion_alert_distance)
        self.urgency = R.update_urgency(self.urgency, coverage, w.urgency_decay)
        terms = {"R_f": r_f, "R_n": r_n, "R_t": r_t, "R_e": r_e, "R_c": r_c}
        reward = w.task_weight * r_t + w.navigation_weight_high * r_n + w.evasion_weight * r_e
        return terms, reward

    def _accumulate_metrics(self, pos, centre_distance) -> None:
        cfg = self.config
        in_formation = self.agent_error < cfg.formation_tolerance  # NaN (no formation group) compares False
        self.metric_sums["F"] += in_formation.mean(axis=-1)
        self.metric_sums["N"] += centre_distance < cfg.navigation_tolerance
        self.metric_sums["C"] += self.world.collisions().sum(axis=-1)
        if cfg.mode == "cefc" and cfg.adversary != "none":
            adv_dist = np.linalg.norm(pos - self.world.adversary_pos[:, None, :], axis=-1)
            in_danger = adv_dist < cfg.rewards.evasion_alert_distance
            self.metric_sums["E"] += in_danger.any(axis=-1)
            self.metric_sums["E_agents"] += in_danger.sum(axis=-1)

    def episode_metrics(self) -> dict[str, np.ndarray]:
        """F, N (steps), C (% of agent-steps in collision), E (steps with any agent within the alert
        distance of the adversary) and E_agents (agent-steps within it) so far, each [B]."""
        steps = np.maximum(self.t, 1)
        return {
            "F": self.metric_sums["F"].copy(),
            "N": self.metric_sums["N"].copy(),
            "C": 100.0 * self.metric_sums["C"] / (steps * self.n_agents),
            "E": self.metric_sums["E"].copy(),
            "E_agents": self.metric_sums["E_agents"].copy(),
        }

    def global_state(self) -> np.ndarray:
        """Centralized-critic input [B, S] float32: per agent (true position relative to the anchor
        in formation mode, else absolute), velocity and LiDAR; in cefc mode also the adversary's
        position and velocity and the targets with their urgency."""
        world = self.world
        pos = world.agent_pos
        ref = self.anchor[:, None, :] if self.config.mode == "formation" else 0.0
        parts = [np.concatenate([pos - ref, world.agent_vel, self.lidar], axis=-1).reshape(self.n_envs, -1)]
        if self.config.mode == "cefc":
            parts += [world.adversary_pos, world.adversary_vel, self.targets.reshape(self.n_envs, -1), self.urgency]
        return np.concatenate(parts, axis=-1).astype(np.float32)

    @property
    def state_size(self) -> int:
        n, m = self.n_agents, self.config.n_lidar_rays
        extra = 0 if self.config.mode == "formation" else 4 + 3 * self.config.n_targets
        return n * (4 + m) + extra


def _scatter(mask: np.ndarray, rows: np.ndarray, like: np.ndarray) -> np.ndarray:
    """An array shaped like `like` with `rows` in the masked positions (others copied from like)."""
    out = np.array(like, dtype=np.float64, copy=True)
    out[mask] = rows
    return out
