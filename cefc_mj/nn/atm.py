"""The AT-M low-level actor (paper eq. 8), the distilled student, and the centralized critic.

    mu_i, sigma_i = F_o( F_f(p_a, o_nei,i) + F_a(d_i) )

- F_f, the formation & navigation module, reads `[anchor, own_velocity, neighbours, neighbour_mask]`
  (39 numbers for K = 7 slots); F_a, the obstacle-avoidance module, reads the LiDAR ranges d_i;
  F_o, the output layer, maps the *sum* of their 128-wide features to the action mean. Each is a
  3-layer MLP (hidden 128 for the teachers, 256 for the student). sigma is a state-independent
  learned log-std (the action distribution is a diagonal Gaussian over [a_x, a_y] in m/s^2).
- F_a's output is centred on free space: the module contributes F_a(d) - F_a(d_free), where d_free
  is every beam at the LiDAR range. With nothing in sight the obstacle module adds exactly zero, so
  AT-M Step 3's merge [F_f, F_o from Step 1; F_a from Step 2] starts from Step 1's behaviour in
  free space and only the obstacle response differs (eq. 8 unchanged otherwise; our decision).
- AT-M-Safe is an input transform: every beam that sees something (range < lidar_range) is
  reported 0.2 m shorter, so the policy reacts earlier (paper Sec. V-B).

>>> from cefc_mj.task.config import TaskConfig
>>> actor = ATMActor(ATMConfig.from_task(TaskConfig(n_agents=6, mode="formation")))
>>> actor(torch.zeros(4, 6, 63)).shape
torch.Size([4, 6, 2])
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from cefc_mj.errors import CheckpointError
from cefc_mj.nn.inference import InferenceWeights
from cefc_mj.nn.layers import mlp
from cefc_mj.task.observation import ObservationLayout, low_level_layout

FORMATION_PARTS = ("anchor", "own_velocity", "neighbours", "neighbour_mask")
"""Observation parts that the formation & navigation module F_f reads, in this order."""
OBSTACLE_PART = "lidar"
"""The observation part that the obstacle-avoidance module F_a reads."""


@dataclass(frozen=True)
class ATMConfig:
    """Shape and input conventions of one AT-M actor; saved inside every policy file."""

    layout: tuple[tuple[str, int], ...]
    """The observation layout as (part name, size) pairs, in order (ObservationLayout.parts)."""
    lidar_range: float = 3.0
    """LiDAR range (m): a beam reading below it sees something (used by the Safe transform and for
    the free-space centring of F_a)."""
    accel_max: float = 2.0
    """Per-axis action bound (m/s^2); `Policy.act` clips the mean to it as the env does."""
    push_observer_s: float = 0.0
    """The agent's push observer the policy was trained with (TaskConfig.push_observer_s; 0: none, the
    paper's memoryless agent); evaluators fly the policy with it (`Policy.task_for`)."""
    hidden: int = 128
    """Hidden width of every module (128 for AT-M teachers, 256 for the distilled student)."""
    act_dim: int = 2
    """Action size: the horizontal acceleration setpoint [a_x, a_y]."""
    lidar_sees_agents: bool = True
    """Whether the LiDAR it was trained with also sees the other UAVs (TaskConfig.lidar_sees_agents);
    evaluators fly the policy with that LiDAR (`Policy.task_for`)."""
    safe: bool = False
    """AT-M-Safe: report beams that see something `safe_margin` shorter."""
    safe_margin: float = 0.2
    """How much shorter the Safe transform reports a beam that sees something (m)."""
    log_std_init: float = 0.0
    """Initial log standard deviation of the Gaussian head."""
    action: str = "velocity"
    """What the Gaussian head outputs. "acceleration": the acceleration setpoint itself (m/s^2).
    "velocity": a velocity setpoint v* (m/s) that a fixed proportional loop turns into the
    acceleration setpoint u = clip(velocity_gain (v* - v), +-accel_max) with v the own velocity
    from the observation (see `to_acceleration`)."""
    velocity_gain: float = 5.0
    """Gain of the velocity loop (1/s) when action == "velocity"."""

    def __post_init__(self) -> None:
        names = [name for name, _ in self.layout]
        missing = [p for p in (*FORMATION_PARTS, OBSTACLE_PART) if p not in names]
        if missing:
            raise CheckpointError(f"observation layout {names} lacks the AT-M input part(s) {missing}")
        if self.action not in ("acceleration", "velocity") or self.velocity_gain <= 0:
            raise CheckpointError(f"invalid AT-M action head: {self.action!r}, gain {self.velocity_gain}")
        if self.hidden < 1 or self.act_dim < 1 or self.lidar_range <= 0 or self.accel_max <= 0:
            raise CheckpointError(f"invalid AT-M shape: {self}")

    @property
    def obs_dim(self) -> int:
        return sum(size for _, size in self.layout)

    def part(self, name: str) -> slice:
        return ObservationLayout(self.layout)[name]

    @classmethod
    def from_task(cls, task_cfg, **overrides) -> "ATMConfig":
        """The actor shape for a low-level TaskConfig (its layout, LiDAR range and action bound)."""
        return cls(
            layout=low_level_layout(task_cfg).parts,
            lidar_range=task_cfg.lidar_range,
            lidar_sees_agents=task_cfg.lidar_sees_agents,
            accel_max=task_cfg.accel_max,
            push_observer_s=task_cfg.push_observer_s,
            **overrides,
        )

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["layout"] = [[name, size] for name, size in self.layout]
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "ATMConfig":
        known = {f.name for f in dataclasses.fields(cls)}
        if not isinstance(d, dict) or set(d) - known or "layout" not in d:
            raise CheckpointError(f"not an AT-M network description: {d!r:.200}")
        d = dict(d)
        d["layout"] = tuple((str(name), int(size)) for name, size in d["layout"])
        return cls(**d)


class ATMActor(nn.Module):
    """pi(u | z) = Normal(F_o(F_f(anchor, o_nei) + F_a(d) - F_a(d_free)), exp(log_std))."""

    def __init__(self, cfg: ATMConfig):
        super().__init__()
        self.cfg = cfg
        h = cfg.hidden
        formation_index = torch.cat([torch.arange(cfg.obs_dim)[cfg.part(p)] for p in FORMATION_PARTS])
        lidar = cfg.part(OBSTACLE_PART)
        self.register_buffer("formation_index", formation_index, persistent=False)
        self.register_buffer(
            "free_lidar", torch.full((lidar.stop - lidar.start,), float(cfg.lidar_range)), persistent=False
        )
        self.lidar_slice = lidar
        self.velocity_slice = cfg.part("own_velocity")
        self.formation = mlp([len(formation_index), h, h, h], activate_last=True)
        self.obstacle = mlp([lidar.stop - lidar.start, h, h, h], activate_last=True)
        self.output = mlp([h, h, h, cfg.act_dim], activate_last=False, last_gain=0.01)
        self.log_std = nn.Parameter(torch.full((cfg.act_dim,), float(cfg.log_std_init)))

    def lidar_input(self, obs: torch.Tensor) -> torch.Tensor:
        """The LiDAR ranges as the obstacle module sees them (Safe transform applied if enabled)."""
        d = obs[..., self.lidar_slice]
        if self.cfg.safe:
            d = torch.where(d < self.cfg.lidar_range - 1e-6, d - self.cfg.safe_margin, d)
        return d

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        """Action mean [..., act_dim] for observations [..., obs_dim]."""
        f = self.formation(obs.index_select(-1, self.formation_index))
        a = self.obstacle(self.lidar_input(obs)) - self.free_features()
        return self.output(f + a)

    def free_features(self) -> torch.Tensor:
        """F_a(d_free), the obstacle module's output with every beam at the LiDAR range.

        With gradients on (training) it is computed afresh, since it depends on the weights being
        trained, and so it is while a TorchScript trace records the forward. Otherwise it is a
        constant of the weights: computed once by the same call and kept, so the forward gives the
        same bits while skipping a quarter of its work. The cache is keyed on the weight tensors
        themselves, their storage and their in-place version counters, so an optimizer step or a
        load_state_dict (assign or copy) recomputes it."""
        if torch.is_grad_enabled() or torch.jit.is_tracing():  # a TorchScript trace records the computation
            return self.obstacle(self.free_lidar)
        tensors = [self.free_lidar] + [
            t for layer in self.obstacle if isinstance(layer, nn.Linear) for t in (layer.weight, layer.bias)
        ]
        key = [(t, t.data_ptr(), t._version) for t in tensors]
        cached = self.__dict__.get("_free_cache")
        if cached is None or any(t is not c or p != cp or v != cv for (t, p, v), (c, cp, cv) in zip(key, cached[0])):
            with torch.inference_mode(False), torch.no_grad():  # a plain tensor, even when called in inference mode
                cached = (key, self.obstacle(self.free_lidar))
            self.__dict__["_free_cache"] = cached
        return cached[1]

    def deterministic_actions(self, obs: np.ndarray) -> np.ndarray:
        """float32 acceleration setpoints [..., act_dim] for float observations [..., obs_dim]: the
        action mean `to_acceleration(self(obs), obs)` computed by one compiled kernel
        (`cefc_mj.nn.inference`), in a fixed summation order that does not depend on the CPU or on
        the batch (a row gets the same bits alone or among others); within float32 rounding of the
        torch forward. What every evaluator flies (`Policy.act`, run_episode, the hierarchy's low
        level, SITL-M agents)."""
        return self.inference_weights().actions(obs)

    def inference_weights(self) -> InferenceWeights:
        """The kernel's float32 copies of the current weights (`.actions(obs)` = deterministic_actions),
        rebuilt when a parameter changes (in place, replaced or given new storage; see
        `_InferencePlan`). A loop that flies fixed weights takes them once and skips the check."""
        plan = self.__dict__.get("_inference_plan")
        if plan is None or not plan.current():
            plan = _InferencePlan(self)
            self.__dict__["_inference_plan"] = plan
        return plan.weights

    def distribution(self, obs: torch.Tensor) -> torch.distributions.Normal:
        mean = self(obs)
        return torch.distributions.Normal(mean, self.log_std.exp().expand_as(mean))

    def to_acceleration(self, command: torch.Tensor, obs: torch.Tensor) -> torch.Tensor:
        """The acceleration setpoint (m/s^2, clipped per axis) for a head output `command`."""
        limit = self.cfg.accel_max
        if self.cfg.action == "velocity":
            command = self.cfg.velocity_gain * (command - obs[..., self.velocity_slice])
        return command.clamp(-limit, limit)


class _InferencePlan:
    """The kernel's float32 weight copies for an actor, and what says whether they still describe it:
    every parameter and buffer the same object, with the same storage and in-place version counter
    (an optimizer step, load_state_dict with or without assign, or `param.data = ...` rebuilds it)."""

    def __init__(self, actor: ATMActor):
        self.tensors = [
            (owner, name, tensor, tensor.data_ptr(), tensor._version)
            for module in actor.modules()
            for owner in (module._parameters, module._buffers)
            for name, tensor in owner.items()
            if tensor is not None
        ]
        self.weights = InferenceWeights.from_actor(actor)

    def current(self) -> bool:
        return all(
            owner[name] is tensor and tensor.data_ptr() == ptr and tensor._version == version
            for owner, name, tensor, ptr, version in self.tensors
        )


def merge_step3(step1: ATMActor, step2: ATMActor) -> ATMActor:
    """AT-M Step 3's initial actor: formation & output modules (and log-std) from Step 1, the
    obstacle module from Step 2 (Algorithm 1, line 11)."""
    if step1.cfg.layout != step2.cfg.layout or step1.cfg.hidden != step2.cfg.hidden:
        raise CheckpointError("AT-M Step 3: the Step 1 and Step 2 actors have different shapes")
    merged = ATMActor(step1.cfg)
    merged.load_state_dict(step1.state_dict())
    merged.obstacle.load_state_dict(step2.obstacle.state_dict())
    return merged


class Critic(nn.Module):
    """Centralized value function: input LayerNorm, then a 3-layer MLP with hidden 128 (paper
    Sec. V-A). The trainer feeds it the env's global state concatenated with one agent's
    observation (MAPPO's agent-specific global state) and it predicts that agent's *normalized*
    return (see ValueNorm and cefc_mj.train.mappo)."""

    def __init__(self, state_dim: int, hidden: int = 128):
        super().__init__()
        self.state_dim = state_dim
        self.norm = nn.LayerNorm(state_dim)
        self.net = mlp([state_dim, hidden, hidden, 1], activate_last=False, last_gain=1.0)

    def forward(self, state: torch.Tensor) -> torch.Tensor:
        return self.net(self.norm(state)).squeeze(-1)
