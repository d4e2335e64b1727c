"""The hierarchical CEFC game (paper Sec. IV-C, Algorithm 2): anchors above, a low-level policy below.

One high-level step of `HierarchicalCEFCEnv` takes every agent's anchor choice, an index into the
paper's 9 anchors {-8, 0, 8}^2 m (absolute arena points, the same grid as `cefc_mj.nn.selector`:
index = 3 ix + iy, 0 is (-8, -8), 4 the centre, 8 is (8, 8)), then runs `decision_interval` (10)
low-level decision steps of the batched CEFC game in which a low-level policy flies every agent
toward its own anchor. It returns the CEFC observation at the next decision, the reward R_H = 10 R_t
+ 0.1 R_n + 100 R_e of the env summed over those steps, and `done` after the env's 400 steps (40
high-level steps). Targets, adversary rule, groups, rewards and metrics are the env's own
(`BatchedCEFCEnv` in `mode="cefc"`).

The low-level observation of agent i (`low_level_observation`) is what the formation-mode env would
give it if every agent flew to agent i's anchor: `build_low_level_observation` with per-agent anchors,
i.e. [its anchor minus its perceived position, its velocity, every agent within 3 m (perceived) as a
neighbour, nearest first, the neighbour mask, its LiDAR], 63 numbers for N <= 8. Neighbours are not
filtered by anchor: an agent whose neighbours chose another anchor still sees them (and keeps its
distance), and leaves them once the anchors pull the two sub-groups more than 3 m apart, the
secession the paper describes (docs/research/high_level.md).

Why this module is here and not in `task/`: it calls trained networks (the low-level policies of
`cefc_mj.nn`), and `task/` is physics- and torch-free. It sits beside `env.py`, one layer up.

>>> from cefc_mj.task.config import TaskConfig
>>> task = TaskConfig(n_agents=8, mode="cefc", episode_steps=20)
>>> env = HierarchicalCEFCEnv(task, NavigationOnly.for_task(task), n_envs=2, seed=0)
>>> obs = env.reset()
>>> obs, reward, done, info = env.step(np.full((2, 8), 8))     # everyone to (8, 8)
>>> obs.shape, reward.shape, done.tolist(), info["low_level_rewards"].shape
((2, 8, 69), (2,), [False, False], (10, 2))
"""

from __future__ import annotations

from pathlib import Path
from typing import Protocol

import numpy as np

from cefc_mj.env import BatchedCEFCEnv
from cefc_mj.errors import ConfigError
from cefc_mj.nn.policy_io import Policy, load_policy, resolve_policy_path
from cefc_mj.nn.registry import clm_name, lowlevel_name
from cefc_mj.nn.selector import ANCHOR_VALUES, anchor_grid
from cefc_mj.provenance import display_path, file_sha256
from cefc_mj.sim.world import World
from cefc_mj.task.config import TaskConfig
from cefc_mj.task.observation import ObservationLayout, build_low_level_observation, low_level_layout

DECISION_INTERVAL = 10
"""Low-level decision steps per high-level step (paper Sec. V-A: anchors every 10 steps)."""
PER_GROUP = "per-group"
"""`load_low_level` name of the per-group-size AT-M teachers (atm_c{c}_step3)."""
CLM_PER_GROUP = "clm-per-group"
"""`load_low_level` name of the per-group-size CL-M baselines (clm_c{c}: the paper's CI-HRL-w-CL-M)."""
PER_GROUP_FILES = {
    PER_GROUP: (lambda c: lowlevel_name(c, "step3"), "the AT-M teacher of each agent's group size"),
    CLM_PER_GROUP: (clm_name, "the CL-M policy of each agent's group size"),
}
"""Per-group low levels: name -> (the policy file of group size c, what it is)."""


def recorded_low_level(meta: dict, default: str | None) -> str | None:
    """The low level a high level flies over: the per-group low level its file's meta records
    (`PER_GROUP_FILES`, e.g. the CI-HRL-w-CL-M rows' `clm-per-group`, what they were fine-tuned with),
    else `default` (any other recorded low level is flown as the caller's)."""
    name = (meta.get("low_level") or {}).get("name")
    return name if name in PER_GROUP_FILES else default


NAVIGATION = "navigation"
"""`load_low_level` name of the navigation-only low level (Algorithm 2's pre-training)."""
GROUP_SIZES = (3, 4, 5, 6, 7, 8)


class LowLevel(Protocol):
    """What flies the agents between two high-level decisions."""

    name: str
    """Short name, recorded in model cards."""

    def act(self, obs: np.ndarray, group_size: np.ndarray) -> np.ndarray:
        """Acceleration setpoints [B, N, 2] (m/s^2) for low-level observations [B, N, D] and each
        agent's group size [B, N] (connected components under 3 m, true positions)."""
        ...

    def describe(self) -> dict:
        """A JSON-ready record of what this low level is (policy files and their SHA-256)."""
        ...


class NavigationOnly:
    """A deterministic navigation-only low level without formation (Algorithm 2's pre-training):
    each agent flies straight at its anchor at top speed, slowing down within `slow_radius`.

        v* = speed_max * r / max(|r|, slow_radius),  r = anchor - perceived position
        u  = clip(gain (v* - v), +-accel_max)

    It reads only the observation's `anchor` and `own_velocity` parts, so it ignores neighbours and
    obstacles (the particle world stops it at obstacle surfaces). The gain is the AT-M velocity
    head's (5 1/s)."""

    name = NAVIGATION

    def __init__(
        self,
        layout_parts: tuple[tuple[str, int], ...],
        speed_max: float = 1.0,
        accel_max: float = 2.0,
        gain: float = 5.0,
        slow_radius: float = 1.0,
    ):
        sizes = dict(layout_parts)
        if "anchor" not in sizes or "own_velocity" not in sizes:
            raise ConfigError("NavigationOnly: needs the low-level observation layout (anchor, own_velocity)")
        for name, value in (
            ("speed_max", speed_max),
            ("accel_max", accel_max),
            ("gain", gain),
            ("slow_radius", slow_radius),
        ):
            if not np.isfinite(value) or value <= 0:
                raise ConfigError(f"{name}={value!r}: must be a finite number > 0")
        layout = ObservationLayout(layout_parts)
        self.obs_dim = layout.size
        self.anchor_slice, self.velocity_slice = layout["anchor"], layout["own_velocity"]
        self.speed_max, self.accel_max, self.gain, self.slow_radius = speed_max, accel_max, gain, slow_radius

    @classmethod
    def for_task(cls, task: TaskConfig) -> "NavigationOnly":
        return cls(low_level_layout(task).parts, speed_max=task.speed_max, accel_max=task.accel_max)

    def act(self, obs: np.ndarray, group_size: np.ndarray) -> np.ndarray:
        obs = np.asarray(obs, dtype=np.float64)
        offset, velocity = obs[..., self.anchor_slice], obs[..., self.velocity_slice]
        dist = np.linalg.norm(offset, axis=-1, keepdims=True)
        desired = self.speed_max * offset / np.maximum(dist, self.slow_radius)
        return np.clip(self.gain * (desired - velocity), -self.accel_max, self.accel_max)

    def describe(self) -> dict:
        return {
            "name": self.name,
            "kind": "rule: fly at the anchor at top speed (no formation, no obstacles)",
            "speed_max": self.speed_max,
            "gain": self.gain,
            "slow_radius": self.slow_radius,
        }


class SharedPolicy:
    """One trained low-level policy for every agent (the distilled student `atm_student`, which
    serves every group size c = 3..8). Deterministic: the Gaussian mean, as evaluators fly it."""

    def __init__(self, policy: Policy, path: Path):
        self.policy, self.path = policy, Path(path)
        self.name = policy.name
        self.obs_dim = policy.obs_dim

    def act(self, obs: np.ndarray, group_size: np.ndarray) -> np.ndarray:
        return self.policy.actor.deterministic_actions(obs).astype(np.float64)

    def describe(self) -> dict:
        return {"name": self.name, "kind": "one policy for every agent", "file": _file_record(self.path)}


class PerGroupPolicies:
    """The policy of each agent's current group size (PER_GROUP_FILES): atm_c{c}_step3 ("per-group")
    or clm_c{c} ("clm-per-group") for a group of c = 3..8 agents; agents in groups of 1 or 2 (no
    formation of their own) fly the c = 3 policy."""

    def __init__(self, policies: dict[int, tuple[Policy, Path]], name: str = PER_GROUP):
        self.name = name
        missing = [c for c in GROUP_SIZES if c not in policies]
        if missing:
            raise ConfigError(f"{name} low level: no policy for group size(s) {missing}")
        self.policies = policies
        dims = {p.obs_dim for p, _ in policies.values()}
        if len(dims) != 1:
            raise ConfigError(f"{name} low level: the policies read different observation sizes {sorted(dims)}")
        self.obs_dim = dims.pop()

    def act(self, obs: np.ndarray, group_size: np.ndarray) -> np.ndarray:
        size = np.clip(np.asarray(group_size), GROUP_SIZES[0], GROUP_SIZES[-1])
        actions = np.zeros((*obs.shape[:-1], 2))
        for c in np.unique(size):
            rows = size == c
            actions[rows] = self.policies[int(c)][0].actor.deterministic_actions(obs[rows])
        return actions

    def describe(self) -> dict:
        return {
            "name": self.name,
            "kind": f"{PER_GROUP_FILES[self.name][1]} (c < 3: c = 3)",
            "files": {str(c): _file_record(path) for c, (_, path) in sorted(self.policies.items())},
        }


def _file_record(path: Path) -> dict:
    path = Path(path).resolve()
    return {"path": display_path(path), "sha256": file_sha256(path)}


def load_low_level(spec: str, task: TaskConfig, policies_dir: Path | None = None) -> LowLevel:
    """The low level named by `spec`: "navigation" (NavigationOnly), "per-group" (atm_c{c}_step3 for
    c = 3..8 from `policies_dir`, default the shipped policies), "clm-per-group" (clm_c{c}), or a
    policy file path or name (e.g. "atm_student"). Raises ConfigError / CheckpointError with one line."""
    if not isinstance(spec, str) or not spec:
        raise ConfigError(f"low level {spec!r}: give 'navigation', 'per-group' or a policy name or file")
    expected = low_level_layout(task).size
    if spec == NAVIGATION:
        return NavigationOnly.for_task(task)
    if spec in PER_GROUP_FILES:
        policies = {}
        for c in GROUP_SIZES:
            path = resolve_policy_path(PER_GROUP_FILES[spec][0](c), policies_dir)
            policies[c] = (load_policy(path, obs_dim=expected), path)
        return PerGroupPolicies(policies, spec)
    path = resolve_policy_path(spec, policies_dir)
    policy = load_policy(path, obs_dim=expected)
    if policy.push_observer_s > 0:
        raise ConfigError(
            f"low level {spec!r} was trained with the agent's push observer, which the high level's game "
            "does not fly; give a memoryless low level"
        )
    if policy.lidar_sees_agents != task.lidar_sees_agents:
        sees = "obstacles and UAVs" if policy.lidar_sees_agents else "obstacles only"
        raise ConfigError(
            f"low level {spec!r} was trained with a LiDAR that sees {sees}, unlike this game's "
            f"(TaskConfig.lidar_sees_agents={task.lidar_sees_agents})"
        )
    return SharedPolicy(policy, path)


class HierarchicalCEFCEnv:
    """B CEFC episodes in which every agent picks an anchor each high-level step (module docstring).

    Arrays are batch-first [B, N, ...]. All envs start and end together (the env's convention);
    after `done`, call `reset()` (or `reset(mask)`).
    """

    def __init__(
        self,
        task: TaskConfig,
        low_level: LowLevel,
        n_envs: int = 1,
        seed: int | None = 0,
        decision_interval: int = DECISION_INTERVAL,
        anchor_values: tuple[float, ...] = ANCHOR_VALUES,
        world: World | None = None,
        adversary_policy=None,
    ):
        """adversary_policy: the trained adversary of a task with adversary='learned' (BatchedCEFCEnv)."""
        if task.mode != "cefc":
            raise ConfigError(f"mode={task.mode!r}: the hierarchical game is the CEFC game (mode='cefc')")
        if not isinstance(decision_interval, int) or isinstance(decision_interval, bool) or decision_interval < 1:
            raise ConfigError(f"decision_interval={decision_interval!r}: must be an integer >= 1")
        if task.steps % decision_interval:
            raise ConfigError(
                f"episode_steps={task.steps}: must be a multiple of the decision interval {decision_interval}"
            )
        needed = low_level_layout(task).size
        if getattr(low_level, "obs_dim", needed) != needed:
            raise ConfigError(
                f"max_neighbours={task.neighbour_slots}: the low level {low_level.name!r} reads "
                f"{low_level.obs_dim} "
                f"numbers, this game's low-level observation has {needed} "
                f"({task.neighbour_slots} neighbour slots)"
            )
        self.task = task
        self.low_level = low_level
        self.decision_interval = decision_interval
        self.grid = anchor_grid(tuple(anchor_values))
        self.env = BatchedCEFCEnv(task, n_envs=n_envs, seed=seed, world=world, adversary_policy=adversary_policy)
        self.n_envs, self.n_agents = n_envs, task.n_agents
        self.layout = self.env.layout
        self.anchors = np.zeros((n_envs, task.n_agents, 2))
        """Each agent's current anchor (m) [B, N]; set by `step`."""

    # ------------------------------------------------------------------ properties
    @property
    def n_anchors(self) -> int:
        return len(self.grid)

    @property
    def decision_steps(self) -> int:
        """High-level steps per episode (40 for the paper's 400-step episodes)."""
        return self.task.steps // self.decision_interval

    @property
    def world(self) -> World:
        return self.env.world

    @property
    def state_size(self) -> int:
        return self.env.state_size

    def global_state(self) -> np.ndarray:
        """The env's centralized state [B, S] (the high-level critic's input)."""
        return self.env.global_state()

    def episode_metrics(self) -> dict[str, np.ndarray]:
        return self.env.episode_metrics()

    def agent_group_size(self) -> np.ndarray:
        """[B, N] size of each agent's group (connected components under delta_obs, true positions)."""
        return np.take_along_axis(self.env.group_size, self.env.labels, axis=1)

    def decode(self, anchor_index) -> np.ndarray:
        """Anchor coordinates [B, N, 2] (m) of anchor indices [B, N]; ConfigError for anything else."""
        index = np.asarray(anchor_index)
        if index.shape != (self.n_envs, self.n_agents):
            raise ConfigError(f"anchor_index: expected shape ({self.n_envs}, {self.n_agents}), got {index.shape}")
        if not np.issubdtype(index.dtype, np.integer) or ((index < 0) | (index >= self.n_anchors)).any():
            raise ConfigError(f"anchor_index: must be integers in [0, {self.n_anchors - 1}]")
        return self.grid[index]

    def low_level_observation(self) -> np.ndarray:
        """[B, N, 63] float32: each agent's formation-mode observation toward its own anchor (module
        docstring), from the env's perceived positions and LiDAR of the current step."""
        env = self.env
        return build_low_level_observation(self.task, env.perceived_pos, env.world.agent_vel, self.anchors, env.lidar)

    # ------------------------------------------------------------------ episode
    def reset(self, mask: np.ndarray | None = None, seed: int | None = None) -> np.ndarray:
        """Start new episodes in the masked envs (all by default); returns a copy of the CEFC
        observation [B, N, D] of all envs."""
        obs = self.env.reset(mask, seed=seed)
        rows = slice(None) if mask is None else np.asarray(mask, dtype=bool)
        self.anchors[rows] = 0.0
        return obs.copy()

    def step(self, anchor_index):
        """Fly every agent toward its chosen anchor for `decision_interval` low-level steps.

        anchor_index [B, N] ints in [0, 9). Returns (obs [B, N, D] float32 (a copy), reward [B],
        done [B] bool, info): reward is the env's R_H summed over the low-level steps; info has
        "low_level_rewards" [k, B] (each step's R_H), "reward_terms" (each unweighted term summed
        over the steps, [B]), "anchors" [B, N, 2], "low_level_steps" (k) and, at episode end,
        "metrics" (F, N, C, E of the episode, [B]).
        """
        anchors = self.decode(anchor_index)
        if (self.env.t >= self.task.steps).any():
            raise ConfigError("step() called on a finished episode; call reset() first")
        self.anchors = anchors.astype(np.float64)
        total = np.zeros(self.n_envs)
        step_rewards, term_sums = [], {}
        info: dict = {}
        done = np.zeros(self.n_envs, dtype=bool)
        for _ in range(self.decision_interval):
            accel = self.low_level.act(self.low_level_observation(), self.agent_group_size())
            obs, reward, done, info = self.env.step(accel)
            total += reward
            step_rewards.append(reward.copy())
            for name, value in info["reward_terms"].items():
                term_sums[name] = term_sums.get(name, 0.0) + value
        out = {
            "low_level_rewards": np.stack(step_rewards),
            "reward_terms": term_sums,
            "anchors": self.anchors.copy(),
            "low_level_steps": self.decision_interval,
        }
        if "metrics" in info:
            out["metrics"] = info["metrics"]
        return obs.copy(), total, done.copy(), out


# ---------------------------------------------------------------------------- one agent's hierarchy
def agent_cefc_observation(
    task: TaskConfig,
    own: np.ndarray,
    neighbours: np.ndarray,
    targets: np.ndarray,
    adversary: np.ndarray,
    lidar: np.ndarray,
) -> np.ndarray:
    """One agent's CEFC observation [D] (float32) from what it senses itself: own [px, py, vx, vy]
    (perceived position, velocity), the neighbours it heard, neighbours [k, 5] = [id, px, py, vx, vy]
    in increasing id, targets [J, 3] = [x, y, urgency], adversary [px, py, vx, vy], its LiDAR [M].

    It is `build_cefc_observation`'s row of this agent, bit for bit, computed by the same function on
    a local swarm [itself, its neighbours] (the neighbour kernel breaks distance ties by index, and
    the local order keeps the UAV ids' order), as long as the same neighbours are within the
    observation distance (always with exact sensing). The SITL-M game's agents build their
    observation with it (docs/sitl_m.md, "The game over SITL-M")."""
    from cefc_mj.task.observation import build_cefc_observation

    rows = np.asarray(neighbours, dtype=np.float64).reshape(-1, 5)
    own = np.asarray(own, dtype=np.float64)
    pos = np.concatenate([own[None, :2], rows[:, 1:3]])[None]
    vel = np.concatenate([own[None, 2:4], rows[:, 3:5]])[None]
    lidar_rows = np.zeros((1, pos.shape[1], len(lidar)))
    lidar_rows[0, 0] = lidar
    targets = np.asarray(targets, dtype=np.float64).reshape(-1, 3)
    adversary = np.asarray(adversary, dtype=np.float64)
    obs = build_cefc_observation(
        task, pos, vel, targets[None, :, :2], targets[None, :, 2], adversary[None, :2], adversary[None, 2:4], lidar_rows
    )
    return obs[0, 0]


def agent_inbox(own_message: np.ndarray, sender, distance, messages, slots: int):
    """One agent's `Inbox` ([1, 1, ...] arrays, K = `slots`) from the messages it received, in the
    channel's order (nearest first): sender [k] ids, distance [k] (m), messages [k, D]; own_message
    [D] is its own previous message (the memory input). Empty slots as the channel pads them (zeros,
    mask False, sender -1), so an absent neighbour and a missing message read the same."""
    from cefc_mj.task.messages import Inbox

    own_message = np.asarray(own_message, dtype=np.float32)
    dim = own_message.shape[-1]
    sender = np.asarray(sender, dtype=np.int64).reshape(-1)[:slots]
    k = len(sender)
    box = np.zeros((1, 1, slots, dim), dtype=np.float32)
    box[0, 0, :k] = np.asarray(messages, dtype=np.float32).reshape(-1, dim)[:k]
    mask = np.zeros((1, 1, slots), dtype=bool)
    mask[0, 0, :k] = True
    dist = np.zeros((1, 1, slots))
    dist[0, 0, :k] = np.asarray(distance, dtype=np.float64).reshape(-1)[:k]
    senders = np.full((1, 1, slots), -1, dtype=np.int64)
    senders[0, 0, :k] = sender
    return Inbox(box, mask, dist, senders, np.array([[k]], dtype=np.int64), own_message.reshape(1, 1, dim))


class AgentHierarchy:
    """One UAV's whole CI-HRL hierarchy, deciding from its own observations only: what a SITL-M game
    agent runs (`cefc_mj.deploy.agent --game`).

    - `decide(cefc_obs, sender, distance, messages)`: ConsMAC and the anchor selector, every
      high-level decision, through `HighLevelPolicy.agent_decider` (the same anchor and message as
      `HighLevelPolicy.decide` on this agent's row, bit for bit); its memory (the GRU's hidden state,
      ConsMAC's m_i0) is the agent's own previous message, kept here. The anchor is decoded on the
      game's grid (`HierarchicalCEFCEnv.decode`).
    - `act(low_obs)`: the low level toward that anchor, every step (`LowLevel.act` on one row).

    Low levels that need the agent's group size (the per-group teachers) are refused: a lone agent
    does not know the swarm's connected components."""

    def __init__(self, policy, low_level: LowLevel, task: TaskConfig, anchor_values: tuple[float, ...] = ANCHOR_VALUES):
        if isinstance(low_level, PerGroupPolicies):
            raise ConfigError("the per-group low level needs each agent's group size, which one agent does not know")
        self.policy, self.low_level, self.task = policy, low_level, task
        self.grid = anchor_grid(tuple(anchor_values))
        self.decider = policy.agent_decider()
        self.message_dim = policy.message_dim
        self.slots = task.n_agents - 1
        self.own = np.zeros(self.message_dim, dtype=np.float32)
        self.anchor_index = None
        self.anchor = np.zeros(2)

    @property
    def communicates(self) -> bool:
        return self.message_dim > 0

    def decide(self, cefc_obs: np.ndarray, sender=(), distance=(), messages=()) -> tuple[int, np.ndarray | None]:
        """(anchor index, message [D] float32 or None) for this agent's CEFC observation [D_obs] and
        the messages it received for this decision; sets `anchor` and the memory."""
        inbox = None
        if self.communicates:
            inbox = agent_inbox(self.own, sender, distance, np.reshape(messages, (-1, self.message_dim)), self.slots)
        index, message = self.decider(np.asarray(cefc_obs, dtype=np.float32)[None, None], inbox)
        self.anchor_index = int(index[0, 0])
        self.anchor = self.grid[self.anchor_index].astype(np.float64)
        if message is None:
            return self.anchor_index, None
        self.own = np.asarray(message[0, 0], dtype=np.float32)
        return self.anchor_index, self.own

    def act(self, low_obs: np.ndarray) -> np.ndarray:
        """The acceleration setpoint [2] (m/s^2) for this agent's low-level observation [D_low]."""
        return np.asarray(self.low_level.act(np.asarray(low_obs)[None, None], np.ones((1, 1), dtype=np.int64))[0, 0])
