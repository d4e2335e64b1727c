"""The learned adversary (the paper's PPO predator): a single-agent Gaussian actor with the low
level's network shape, and its policy file format.

    mu, sigma = F_o(F_f(o_adv))

F_f and F_o are 3-layer tanh MLPs of width 128, as AT-M's formation module and output layer (the
adversary has no LiDAR, so no obstacle module: it reads its nearest obstacles' positions,
`task.adversary.adversary_observation`); sigma is a state-independent learned log-std and the
action is the adversary's horizontal acceleration setpoint (m/s^2). `act` maps an observation batch
[B, D] to the mean clipped to accel_max, the deployed (deterministic) action: a loaded policy's
`act` is what `BatchedCEFCEnv(adversary_policy=...)` takes.

Files are `cefc-mj/adversary-policy`: the config, the weights and their SHA-256, and meta.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn

from cefc_mj.errors import CheckpointError, ConfigError
from cefc_mj.nn.layers import mlp
from cefc_mj.nn.policy_io import (
    checkpoint_errors,
    policy_meta,
    read_policy_payload,
    resolve_policy_path,
    write_policy_payload,
)
from cefc_mj.provenance import file_sha256
from cefc_mj.task.adversary import (
    ADVERSARY_GOAL_COLUMNS,
    ADVERSARY_OBS_DIM,
    OWN_VELOCITY_COLUMNS,
    clip_speed,
    velocity_tracking_acceleration,
)
from cefc_mj.task.config import ADVERSARY_RULES, LEARNED_ADVERSARY

POLICY_FORMAT = "cefc-mj/adversary-policy"
POLICY_VERSION = 1


ADVERSARY_ACTIONS = ("acceleration", "velocity", "heading")


@dataclass(frozen=True)
class AdversaryNetConfig:
    """Shape of the adversary's actor; saved inside its policy file."""

    obs_dim: int = ADVERSARY_OBS_DIM
    """Observation size (task.adversary.ADVERSARY_OBS_DIM)."""
    hidden: int = 128
    """Width of every hidden layer (the low level's 128)."""
    accel_max: float = 2.0
    """Per-axis action bound (m/s^2); the deployed action is the mean clipped to it."""
    init_log_std: float = 0.0
    """Initial log-std of the Gaussian (std 1 m/s^2)."""
    action: str = "acceleration"
    """What the network's 2 outputs u mean: "acceleration" (u is the setpoint, m/s^2, clipped to
    accel_max; files written before the field) or "velocity" (u x speed_max is the velocity it wants,
    capped at speed_max, and the setpoint is the acceleration that reaches it in one step, clipped:
    a pursuit is then a direction to learn, not a bang-bang acceleration) or "heading" (as "velocity",
    but at top speed along u / |u|: the rule adversaries always fly at top speed, and a regression onto
    their unit wishes shrinks |u| where it is unsure, which slowed an imitating adversary)."""
    speed_max: float = 0.75
    """The adversary's speed limit (m/s), the scale of a "velocity" action."""
    dt: float = 0.1
    """The decision step (s) over which a "velocity" action's acceleration reaches the velocity."""
    observes_goal: bool = True
    """Whether the network reads the observation's goal columns (ADVERSARY_GOAL_COLUMNS, the point the
    rule would chase). False plays by what the paper gives its adversary: its own state, the agents'
    and the obstacles' (files written before this field existed read it, hence the default True)."""

    def __post_init__(self) -> None:
        for name in ("obs_dim", "hidden"):
            value = getattr(self, name)
            if not isinstance(value, int) or isinstance(value, bool) or value < 1:
                raise ConfigError(f"{name}={value!r}: must be an integer >= 1")
        if not isinstance(self.accel_max, (int, float)) or not self.accel_max > 0:
            raise ConfigError(f"accel_max={self.accel_max!r}: must be a positive number")
        if not isinstance(self.observes_goal, bool):
            raise ConfigError(f"observes_goal={self.observes_goal!r}: must be True or False")
        if self.action not in ADVERSARY_ACTIONS:
            raise ConfigError(f"action={self.action!r}: must be one of {', '.join(ADVERSARY_ACTIONS)}")
        for name in ("speed_max", "dt"):
            if not isinstance(getattr(self, name), (int, float)) or not getattr(self, name) > 0:
                raise ConfigError(f"{name}={getattr(self, name)!r}: must be a positive number")

    @property
    def input_dim(self) -> int:
        """The network's input width: the observation without the goal columns unless it reads them."""
        goal = ADVERSARY_GOAL_COLUMNS.stop - ADVERSARY_GOAL_COLUMNS.start
        return self.obs_dim if self.observes_goal else self.obs_dim - goal

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


def network_input(obs: torch.Tensor, observes_goal: bool) -> torch.Tensor:
    """What the networks read of an observation [..., D]: all of it, or without the goal columns."""
    if observes_goal:
        return obs
    return torch.cat([obs[..., : ADVERSARY_GOAL_COLUMNS.start], obs[..., ADVERSARY_GOAL_COLUMNS.stop :]], dim=-1)


class AdversaryPolicy(nn.Module):
    """F_o(F_f(o)) -> the mean acceleration [.., 2]; `log_std` is the Gaussian's learned log-std."""

    def __init__(self, cfg: AdversaryNetConfig, seed: int | None = None):
        super().__init__()
        self.cfg = cfg
        if seed is not None:
            torch.manual_seed(seed)
        h = cfg.hidden
        self.features = mlp([cfg.input_dim, h, h, h], activate_last=True)
        self.head = mlp([h, h, h, 2], activate_last=False, last_gain=0.01)
        self.log_std = nn.Parameter(torch.full((2,), float(cfg.init_log_std)))

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return self.head(self.features(network_input(obs, self.cfg.observes_goal)))

    def distribution(self, obs: torch.Tensor) -> torch.distributions.Normal:
        mean = self(obs)
        return torch.distributions.Normal(mean, self.log_std.exp().expand_as(mean))

    def to_acceleration(self, u: np.ndarray, obs: np.ndarray) -> np.ndarray:
        """The acceleration setpoints [B, 2] (float64, m/s^2) of network outputs u [B, 2] at observations
        obs [B, D] (cfg.action says how; the own velocity is read from the observation)."""
        cfg = self.cfg
        u = np.asarray(u, dtype=np.float64)
        if cfg.action == "acceleration":
            return np.clip(u, -cfg.accel_max, cfg.accel_max)
        if cfg.action == "heading":
            u = u / np.maximum(np.sqrt((u * u).sum(-1, keepdims=True)), 1e-9)
        desired = clip_speed(cfg.speed_max * u, cfg.speed_max)
        velocity = np.asarray(obs, dtype=np.float64)[..., OWN_VELOCITY_COLUMNS] * cfg.speed_max
        return velocity_tracking_acceleration(desired, velocity, cfg.accel_max, cfg.dt)

    @torch.no_grad()
    def act(self, obs: np.ndarray) -> np.ndarray:
        """The deployed action [B, 2] (float64, m/s^2) of observations [B, D]: the mean, as a setpoint."""
        obs = np.asarray(obs)
        return self.to_acceleration(self(torch.as_tensor(obs, dtype=torch.float32)).numpy(), obs)


def save_adversary_policy(policy: AdversaryPolicy, path: Path, meta: dict | None = None) -> Path:
    return write_policy_payload(path, POLICY_FORMAT, POLICY_VERSION, policy, meta, net=policy.cfg.to_dict())


def load_adversary_policy(path: Path) -> tuple[AdversaryPolicy, dict]:
    """(policy, meta) of a file written by `save_adversary_policy`; CheckpointError with one line
    for a missing, foreign, tampered or mismatched file."""
    path = Path(path)
    payload = read_policy_payload(path, POLICY_FORMAT, POLICY_VERSION, "an adversary policy")
    state = payload["state_dict"]
    with checkpoint_errors(path, "weights do not fit the described network"):
        cfg = AdversaryNetConfig(**payload["net"])
        if cfg.obs_dim != ADVERSARY_OBS_DIM:
            raise ConfigError(f"observation size {cfg.obs_dim}, this code builds {ADVERSARY_OBS_DIM}")
        policy = AdversaryPolicy(cfg)
        policy.load_state_dict(state)
    policy.eval()
    return policy, policy_meta(path, payload)


def resolve_adversary(spec: str, policies_dir: Path | None = None) -> tuple[str, object, dict]:
    """(TaskConfig.adversary, the env's adversary_policy or None, a record for reports) of an
    adversary given as a rule name or as a trained adversary's policy name (in policies_dir, default
    the shipped folder) or file; CheckpointError (one line) for a missing or broken file."""
    if spec in ADVERSARY_RULES:
        return spec, None, {"rule": spec}
    try:
        path = resolve_policy_path(spec, policies_dir)
        policy, _ = load_adversary_policy(path)
    except CheckpointError as e:
        raise CheckpointError(
            f"adversary {spec}: {e} (a rule is one of {', '.join(ADVERSARY_RULES)}; a trained "
            "adversary comes from cefc-train adversary)"
        ) from None
    return LEARNED_ADVERSARY, policy.act, {"policy": path.name, "sha256": file_sha256(path)}
