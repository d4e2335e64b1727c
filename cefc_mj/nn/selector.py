"""The high level's RL-based anchor selector (paper eq. (12)) and its critic.

    E_o,i      = F_thetaHO(o_i^(t))                         observation encoder, 2-layer MLP
    p_a,i^(t) ~ F_thetaHS(E_o,i, m_i^(t+1))                 selector: a categorical over the anchors

The action space is the paper's discrete grid {-8, 0, 8}^2 m: 9 anchors, index = 3 ix + iy with
x = values[ix], y = values[iy] (index 0 is (-8, -8), 4 the centre, 8 is (8, 8)). The consensus input
is what `ConsMACOutput.detach_for_policy(consensus)` returns: by default the message m_i^(t+1) as in
eq. (12), optionally ConsMAC's global estimate g_hat_i. The selector detaches it once more, so the RL
loss cannot reach ConsMAC even if a caller passes a live tensor (paper Sec. IV-C3).

The value function V_phiH is the project's centralized `Critic` (input LayerNorm, 3 layers of 128,
paper Sec. V-A), built by `build_critic`.

>>> from cefc_mj.task.config import TaskConfig
>>> selector = AnchorSelector(SelectorConfig.from_task(TaskConfig(n_agents=8)), seed=0)
>>> index, log_prob = selector.act(torch.zeros(2, 8, selector.cfg.env_obs_dim), torch.zeros(2, 8, 64))
>>> index.shape, anchor_coordinates(torch.tensor([0, 4, 8])).tolist()
(torch.Size([2, 8]), [[-8.0, -8.0], [0.0, 0.0], [8.0, 8.0]])
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from cefc_mj.errors import ConfigError
from cefc_mj.nn.atm import Critic
from cefc_mj.nn.consmac import LOCAL_PARTS, ConsMACConfig, LocalObservationSizes, local_index, seeded
from cefc_mj.nn.layers import mlp
from cefc_mj.task.observation import cefc_layout

ANCHOR_VALUES = (-8.0, 0.0, 8.0)
"""The paper's anchor coordinates per axis (m); the grid is their Cartesian square."""
CONSENSUS_KINDS = ("message", "estimate", "message+estimate")


@dataclass(frozen=True)
class SelectorConfig(LocalObservationSizes):
    """Shape and conventions of one anchor selector; meant to be saved beside its weights."""

    layout: tuple[tuple[str, int], ...]
    """The CEFC observation layout as (part name, size) pairs; the encoder reads LOCAL_PARTS (o_i)."""
    consensus_dim: int = 64
    """Size of the consensus input from ConsMAC (64: the message m_i^(t+1)); 0: no consensus input
    (plain MAPPO, no communication)."""
    hidden: int = 128
    """Hidden width of the encoder and the selector (2 layers each); the paper: 128."""
    anchor_values: tuple[float, ...] = ANCHOR_VALUES
    """Anchor coordinates per axis (m); the action space is their square grid."""
    obs_scale: float = 0.125
    """Multiplies o_i before the encoder (the same convention as ConsMACConfig.obs_scale)."""
    consensus_gradient: bool = False
    """False (ConsMAC, the paper): the selector detaches its consensus input, so the RL loss never
    reaches the module that made it. True: the RL gradient flows into that module (the TarMAC baseline,
    trained end to end, and ConsMAC's "wt-rl" ablation); never for ConsMAC itself."""

    def __post_init__(self) -> None:
        names = [name for name, _ in self.layout]
        missing = [p for p in LOCAL_PARTS if p not in names]
        if missing:
            raise ConfigError(f"layout {names} lacks the selector input part(s) {missing}; use the CEFC layout")
        for name, least in (("consensus_dim", 0), ("hidden", 1)):
            value = getattr(self, name)
            if not isinstance(value, int) or isinstance(value, bool) or value < least:
                raise ConfigError(f"{name}={value!r}: must be an integer >= {least}")
        if not isinstance(self.consensus_gradient, bool):
            raise ConfigError(f"consensus_gradient={self.consensus_gradient!r}: must be True or False")
        values = tuple(self.anchor_values)
        if not values or not all(math.isfinite(v) for v in values) or len(set(values)) != len(values):
            raise ConfigError(f"anchor_values={self.anchor_values!r}: need distinct finite coordinates")
        if not (math.isfinite(self.obs_scale) and self.obs_scale > 0):
            raise ConfigError(f"obs_scale={self.obs_scale!r}: must be a finite number > 0")

    @property
    def n_anchors(self) -> int:
        return len(self.anchor_values) ** 2

    @classmethod
    def from_task(cls, task_cfg, **overrides) -> "SelectorConfig":
        """The selector shape for a CEFC-mode TaskConfig."""
        if task_cfg.mode != "cefc":
            raise ConfigError(f"mode={task_cfg.mode!r}: the anchor selector reads the CEFC observation (mode='cefc')")
        return cls(layout=cefc_layout(task_cfg).parts, **overrides)

    @classmethod
    def from_consmac(cls, consmac_cfg: ConsMACConfig, consensus: str = "message", **overrides) -> "SelectorConfig":
        """A selector that reads `ConsMACOutput.detach_for_policy(consensus)` of this ConsMAC."""
        sizes = {
            "message": consmac_cfg.feature_dim,  # m_i^(t+1), g_hat_i for ConsMAC-G, MASIA's z_i, NVIF's mean
            "estimate": consmac_cfg.global_dim,
            "message+estimate": consmac_cfg.feature_dim + consmac_cfg.global_dim,
        }
        if consensus not in sizes:
            raise ConfigError(f"consensus={consensus!r}: must be one of {CONSENSUS_KINDS}")
        return cls(
            layout=consmac_cfg.layout, consensus_dim=sizes[consensus], obs_scale=consmac_cfg.obs_scale, **overrides
        )

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["layout"] = [[name, size] for name, size in self.layout]
        d["anchor_values"] = list(self.anchor_values)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "SelectorConfig":
        known = {f.name for f in dataclasses.fields(cls)}
        if not isinstance(d, dict) or set(d) - known or "layout" not in d:
            raise ConfigError(f"not an anchor-selector description: {d!r:.200}")
        d = dict(d)
        d["layout"] = tuple((str(name), int(size)) for name, size in d["layout"])
        if "anchor_values" in d:
            d["anchor_values"] = tuple(float(v) for v in d["anchor_values"])
        return cls(**d)


def anchor_grid(values: tuple[float, ...] = ANCHOR_VALUES) -> np.ndarray:
    """[len(values)^2, 2] anchor coordinates (m); row 3 ix + iy is (values[ix], values[iy])."""
    v = np.asarray(values, dtype=np.float64)
    return np.stack(np.meshgrid(v, v, indexing="ij"), axis=-1).reshape(-1, 2)


def anchor_coordinates(index, values: tuple[float, ...] = ANCHOR_VALUES):
    """Anchor coordinates [..., 2] (m) for anchor indices [...]; a torch tensor in gives a float32
    tensor out, anything else a float64 numpy array."""
    grid = anchor_grid(values)
    if isinstance(index, torch.Tensor):
        bad = (index < 0) | (index >= len(grid))
        if index.is_floating_point() or bool(bad.any()):
            raise ConfigError(f"anchor index: must be integers in [0, {len(grid) - 1}]")
        return torch.as_tensor(grid, dtype=torch.float32, device=index.device)[index]
    index = np.asarray(index)
    if not np.issubdtype(index.dtype, np.integer) or ((index < 0) | (index >= len(grid))).any():
        raise ConfigError(f"anchor index: must be integers in [0, {len(grid) - 1}]")
    return grid[index]


class AnchorSelector(nn.Module):
    """pi_H(p_a | o_i, consensus) = Categorical(logits = F_HS([F_HO(o_i) || consensus]))."""

    def __init__(self, cfg: SelectorConfig, seed: int | None = None):
        super().__init__()
        self.cfg = cfg
        with seeded(seed):
            h = cfg.hidden
            self.register_buffer("local_index", local_index(cfg.layout), persistent=False)
            self.encoder = mlp([cfg.obs_dim, h, h], activate_last=True)  # theta_HO
            # theta_HS; a small last layer starts the policy near uniform over the anchors (PPO convention)
            self.selector = mlp([h + cfg.consensus_dim, h, cfg.n_anchors], activate_last=False, last_gain=0.01)

    def forward(self, obs: torch.Tensor, consensus: torch.Tensor) -> torch.Tensor:
        """Logits [..., n_anchors] for observations [..., env_obs_dim] and consensus [..., consensus_dim]."""
        cfg = self.cfg
        if obs.shape[-1] != cfg.env_obs_dim or consensus.shape != (*obs.shape[:-1], cfg.consensus_dim):
            raise ConfigError(
                f"selector input: expected obs [..., {cfg.env_obs_dim}] and consensus [..., {cfg.consensus_dim}] with "
                f"the same leading shape, got {tuple(obs.shape)} and {tuple(consensus.shape)}"
            )
        encoded = self.encoder(obs.index_select(-1, self.local_index) * cfg.obs_scale)  # E_o,i
        # Stop-gradient: ConsMAC learns only from its supervised loss (consensus_gradient is for baselines).
        consensus = consensus if cfg.consensus_gradient else consensus.detach()
        return self.selector(torch.cat([encoded, consensus], dim=-1))

    def distribution(self, obs: torch.Tensor, consensus: torch.Tensor) -> torch.distributions.Categorical:
        return torch.distributions.Categorical(logits=self(obs, consensus))

    def act(
        self,
        obs: torch.Tensor,
        consensus: torch.Tensor,
        deterministic: bool = False,
        generator: torch.Generator | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """(anchor index [...] int64, its log-probability [...]); sampled, or the mode if deterministic.
        `generator` makes the sampling reproducible without touching torch's global RNG."""
        dist = self.distribution(obs, consensus)
        if deterministic:
            index = dist.probs.argmax(dim=-1)
        else:
            probs = dist.probs.reshape(-1, self.cfg.n_anchors)
            index = torch.multinomial(probs, 1, generator=generator).reshape(dist.probs.shape[:-1])
        return index, dist.log_prob(index)

    def evaluate(
        self, obs: torch.Tensor, consensus: torch.Tensor, index: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """(log-probability, entropy) of taken anchor indices, for the PPO update."""
        dist = self.distribution(obs, consensus)
        return dist.log_prob(index), dist.entropy()

    def anchors(self, index: torch.Tensor) -> torch.Tensor:
        """Anchor coordinates [..., 2] (m) of anchor indices [...] on this selector's grid."""
        return anchor_coordinates(index, self.cfg.anchor_values)


def build_critic(state_dim: int, hidden: int = 128) -> Critic:
    """V_phiH: the project's centralized critic (input LayerNorm, 3-layer MLP of width `hidden`)."""
    if not isinstance(state_dim, int) or state_dim < 1 or not isinstance(hidden, int) or hidden < 1:
        raise ConfigError(f"critic shape: state_dim={state_dim!r}, hidden={hidden!r} must be integers >= 1")
    return Critic(state_dim, hidden)
