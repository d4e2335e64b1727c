"""ConsMAC, the high level's consensus-inference module (paper Sec. IV-C2, eqs. (7)-(11)).

For agent i with local observation o_i^(t), its own previous message m_i0^(t) and the messages
m_ij^(t) of its k neighbours at distances d_j (received through `cefc_mj.task.messages`):

    (7)  mem     m'_i0       = F_psiM([m_i0^(t) || o_i^(t)])              GRU-like memory
    (8)  DE      Phi_d       = sqrt(1/D) [cos(w_1 d), ..., cos(w_D d)]    learnable distance code
                 E_mi = [m'_i0 || Phi_0],  E_m-i = [m_ij^(t) || Phi_dj]_j=1..k
    (9)  AL      m_i^(t+1)   = MHA_psiA(E_mi, E_m-i, E_m-i)               4 heads, width 64
    (10) GE      g_hat_i^(t) = F_psiE(m_i^(t+1))                          3-layer MLP
    (11) celoss  L_ConsMAC   = E_i,t ||g_hat_i^(t) - g_i^(t)||^2

Equation numbers count the paper's numbered equations in order (docs/research/high_level.md); the names are
the paper's own labels.

m_i^(t+1) is both the message agent i broadcasts next step and the consensus feature the anchor
selector reads (eq. (12), `cefc_mj.nn.selector`). ConsMAC is trained by supervised learning only:
the RL loss must never reach it (paper Sec. IV-C3), so the policy reads it through
`ConsMACOutput.detach_for_policy()` and the selector detaches its input again.

Decisions where the paper is silent (docs/research/high_level.md gives the reasons):
- the memory is a GRU cell with o_i as input and m_i0 as hidden state (its gates read [m || o]);
- o_i is the paper's 38-number local observation (targets, adversary, neighbours), scaled by
  `obs_scale`;
- the attention is masked to the received messages; with no neighbour it contributes exactly zero;
- by default (`residual=True`) the message is LayerNorm(m'_i0 + MHA(...)), the Transformer's
  attention sub-layer; `residual=False` is eq. (9) as printed, in which o_i reaches the message
  only through the attention weights (and not at all with fewer than two neighbours);
- the global-state labels order agents nearest first (`label_order`).

The paper's Fig. 7 ablations are one flag, `ConsMACConfig.ablation`, each changing only what it names:
- "wo-com": no message is received: the inbox is treated as empty (mask all False), so the attention
  contributes exactly zero and m_i^(t+1) = LayerNorm(m'_i0) (0 with `residual=False`);
- "wo-mem": no memory: the GRU's hidden input is zero at every decision instead of m_i0^(t), so
  m'_i0 = GRU(o_i, 0) is a feed-forward (gated) map of o_i alone; the parameters are unchanged;
- "wo-de": no distance encoder: Phi_d is replaced by zeros (for E_mi and E_m-i alike), so the
  attention cannot tell near senders from far ones; the shapes and parameters are unchanged;
- "wt-rl": the network is unchanged; the high level lets the RL loss flow into ConsMAC besides
  eq. (11) (`cefc_mj.nn.highlevel_policy`, `cefc_mj.train.highlevel`);
- "consmac-g": the estimate g_hat_i replaces m_i^(t+1) wherever the message is used: it is broadcast
  (so neighbour messages and the own message m_i0 have `global_dim` numbers), and it is the
  selector's consensus input. The memory's hidden state stays `message_dim` wide: the own message
  g_hat_i^(t-1) enters it zero-padded. Needs global_dim <= message_dim.

>>> from cefc_mj.task.config import TaskConfig
>>> net = ConsMAC(ConsMACConfig.from_task(TaskConfig(n_agents=8)), seed=0)
>>> obs = torch.zeros(2, 8, net.cfg.env_obs_dim)
>>> out = net(obs, net.initial_message(2, 8), torch.zeros(2, 8, 7, 64), torch.zeros(2, 8, 7, dtype=torch.bool),
...           torch.zeros(2, 8, 7))
>>> out.message.shape, out.estimate.shape
(torch.Size([2, 8, 64]), torch.Size([2, 8, 16]))
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from cefc_mj.errors import ConfigError
from cefc_mj.nn.layers import layer_init, mlp
from cefc_mj.task.messages import Inbox
from cefc_mj.task.observation import ObservationLayout, cefc_layout

LOCAL_PARTS = ("targets", "adversary", "neighbours")
"""The parts of the CEFC observation that form the paper's local observation o_i, in this order."""
VARIANTS = ("A", "O")
LABEL_ORDERS = ("nearest", "index")
ABLATIONS = ("none", "wo-com", "wo-mem", "wo-de", "wt-rl", "consmac-g")
"""The paper's Fig. 7 ablations of ConsMAC (module docstring); "none" is ConsMAC itself."""
MESSAGE_CONTENTS = ("learned", "observation", "latent+observation")
"""What an agent broadcasts (`ConsMACConfig.message_content`): "learned", ConsMAC's (and TarMAC's)
message m_i^(t+1) (this module); "observation", the raw local observation o_i (MASIA); and
"latent+observation", a variational latent and o_i (NVIF). The last two are `cefc_mj.nn.obs_comm`."""


class LocalObservationSizes:
    """The observation sizes of a high-level network config with a `layout` of (part, size) pairs."""

    layout: tuple

    @property
    def env_obs_dim(self) -> int:
        """Size of the full CEFC observation the network is fed."""
        return sum(size for _, size in self.layout)

    @property
    def obs_dim(self) -> int:
        """Size of o_i, the parts it reads (38 for N = 8 and two targets)."""
        sizes = dict(self.layout)
        return sum(sizes[p] for p in LOCAL_PARTS)


@dataclass(frozen=True)
class ConsMACConfig(LocalObservationSizes):
    """Shape and conventions of one ConsMAC module; meant to be saved beside its weights."""

    layout: tuple[tuple[str, int], ...]
    """The CEFC observation layout as (part name, size) pairs (ObservationLayout.parts); ConsMAC reads
    its LOCAL_PARTS."""
    n_agents: int
    """N, the number of agents; fixes the size of the global-state label."""
    variant: str = "A"
    """Which global state g_i is the label: "A" (ConsMAC-A) the anchors of all agents, 2N numbers;
    "O" (ConsMAC-O) every other agent's position and velocity relative to agent i, 4(N-1) numbers."""
    label_order: str = "nearest"
    """How agents are ordered inside the label. "nearest": by true distance from agent i, nearest first
    (ConsMAC-A puts agent i's own anchor first), the convention of the observation's neighbour slots;
    learnable without agent identities. "index": by agent index, so ConsMAC-A's label is the same for
    every agent (the paper's "unique" global state)."""
    message_dim: int = 64
    """Size of the message m (and of the memory's hidden state m'); the paper uses 64."""
    attention_dim: int = 64
    """Width of the attention's query/key/value projections, split across the heads; the paper: 64."""
    n_heads: int = 4
    """Attention heads; must divide attention_dim. The paper: 4."""
    distance_dim: int = 64
    """D, the size of the distance code Phi_d of eq. (8)."""
    hidden: int = 128
    """Hidden width of the global estimator (3 layers); the paper: 128."""
    residual: bool = True
    """True: m_i^(t+1) = LayerNorm(m'_i0 + MHA(...)) (Transformer attention sub-layer; our default).
    False: m_i^(t+1) = MHA(...), eq. (9) as printed (zero for an agent without neighbours)."""
    obs_scale: float = 0.125
    """Multiplies o_i before the memory, so that target offsets of up to 16 m become O(1)."""
    ablation: str = "none"
    """One of ABLATIONS (the paper's Fig. 7; see the module docstring); "none" for ConsMAC itself.
    Policy files written before this field existed load as "none"."""
    message_content: str = "learned"
    """One of MESSAGE_CONTENTS: "learned" is ConsMAC (this module); "observation" (MASIA) and
    "latent+observation" (NVIF) are `cefc_mj.nn.obs_comm.ObservationComm`, which shares this
    config, the distance code and the masked attention (docs/research/baselines.md). Policy files written
    before this field existed load as "learned"."""
    kl_weight: float = 0.01
    """NVIF only: the weight beta of the KL term KL(q(z | o, inbox) || N(0, I)) beside the
    reconstruction in its VAE loss (a beta-VAE; NVIF's paper gives no value we could use)."""

    def __post_init__(self) -> None:
        names = [name for name, _ in self.layout]
        missing = [p for p in LOCAL_PARTS if p not in names]
        if missing:
            raise ConfigError(f"layout {names} lacks the ConsMAC input part(s) {missing}; use the CEFC layout")
        if not isinstance(self.n_agents, int) or self.n_agents < 2:
            raise ConfigError(f"n_agents={self.n_agents!r}: ConsMAC needs at least 2 agents")
        if dict(self.layout)["neighbours"] % 4:
            raise ConfigError(
                f"layout: the neighbour block ({dict(self.layout)['neighbours']}) is not 4 numbers per slot"
            )
        if self.variant not in VARIANTS:
            raise ConfigError(f"variant={self.variant!r}: must be one of {VARIANTS}")
        if self.label_order not in LABEL_ORDERS:
            raise ConfigError(f"label_order={self.label_order!r}: must be one of {LABEL_ORDERS}")
        for name in ("message_dim", "attention_dim", "n_heads", "distance_dim", "hidden"):
            value = getattr(self, name)
            if not isinstance(value, int) or isinstance(value, bool) or value < 1:
                raise ConfigError(f"{name}={value!r}: must be an integer >= 1")
        if self.attention_dim % self.n_heads:
            raise ConfigError(f"n_heads={self.n_heads}: must divide attention_dim={self.attention_dim}")
        if not (math.isfinite(self.obs_scale) and self.obs_scale > 0):
            raise ConfigError(f"obs_scale={self.obs_scale!r}: must be a finite number > 0")
        if self.ablation not in ABLATIONS:
            raise ConfigError(f"ablation={self.ablation!r}: must be one of {', '.join(ABLATIONS)}")
        if self.message_content not in MESSAGE_CONTENTS:
            raise ConfigError(f"message_content={self.message_content!r}: must be one of {', '.join(MESSAGE_CONTENTS)}")
        if self.ablation != "none" and self.message_content != "learned":
            raise ConfigError(f"ablation={self.ablation!r}: ablates ConsMAC, whose message_content is 'learned'")
        if not (isinstance(self.kl_weight, (int, float)) and math.isfinite(self.kl_weight) and self.kl_weight >= 0):
            raise ConfigError(f"kl_weight={self.kl_weight!r}: must be a finite number >= 0")
        if self.ablation == "consmac-g" and self.global_dim > self.message_dim:
            raise ConfigError(
                f"ablation='consmac-g': the estimate ({self.global_dim} numbers) must fit the memory "
                f"(message_dim={self.message_dim})"
            )

    @property
    def sent_dim(self) -> int:
        """Size of what an agent broadcasts (and gets back as its own message m_i0): message_dim,
        or global_dim for ConsMAC-G, which sends its estimate g_hat_i; obs_dim for MASIA (o_i),
        message_dim + obs_dim for NVIF ([z_i || o_i])."""
        if self.message_content == "observation":
            return self.obs_dim
        if self.message_content == "latent+observation":
            return self.message_dim + self.obs_dim
        return self.global_dim if self.ablation == "consmac-g" else self.message_dim

    @property
    def feature_dim(self) -> int:
        """Size of the selector's consensus input: the message itself for ConsMAC (sent_dim),
        message_dim for MASIA (z_i) and NVIF (the latent mean), which send something else."""
        return self.sent_dim if self.message_content == "learned" else self.message_dim

    @property
    def label_dim(self) -> int:
        """Size of the supervised label the replay stores: global_dim, or 0 for NVIF, whose VAE
        reconstructs observations that its inputs already hold."""
        return 0 if self.message_content == "latent+observation" else self.global_dim

    @property
    def global_dim(self) -> int:
        """Size of the global-state label g_i and of the estimate g_hat_i."""
        return 2 * self.n_agents if self.variant == "A" else 4 * (self.n_agents - 1)

    @classmethod
    def from_task(cls, task_cfg, **overrides) -> "ConsMACConfig":
        """The module shape for a CEFC-mode TaskConfig."""
        if task_cfg.mode != "cefc":
            raise ConfigError(f"mode={task_cfg.mode!r}: ConsMAC reads the CEFC observation (mode='cefc')")
        return cls(layout=cefc_layout(task_cfg).parts, n_agents=task_cfg.n_agents, **overrides)

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["layout"] = [[name, size] for name, size in self.layout]
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "ConsMACConfig":
        known = {f.name for f in dataclasses.fields(cls)}
        if not isinstance(d, dict) or set(d) - known or "layout" not in d:
            raise ConfigError(f"not a ConsMAC description: {d!r:.200}")
        d = dict(d)
        d["layout"] = tuple((str(name), int(size)) for name, size in d["layout"])
        return cls(**d)


def local_index(layout: tuple[tuple[str, int], ...]) -> torch.Tensor:
    """Indices of o_i (LOCAL_PARTS, in order) inside a flat observation with this layout."""
    full = ObservationLayout(layout)
    total = full.size
    return torch.cat([torch.arange(total)[full[p]] for p in LOCAL_PARTS])


@dataclass
class ConsMACOutput:
    """One ConsMAC step for every agent; leading shape [B, N]."""

    message: torch.Tensor
    """m_i^(t+1) [B, N, message_dim]: broadcast next step, and the selector's consensus input, eq. (12).
    ConsMAC-G: the estimate g_hat_i [B, N, global_dim] in its place."""
    estimate: torch.Tensor | None
    """g_hat_i^(t) [B, N, global_dim], eq. (10): the supervised output."""
    memory: torch.Tensor
    """m'_i0 [B, N, message_dim], eq. (7)."""
    attention: torch.Tensor
    """[B, N, n_heads, K] attention weights over the neighbour slots; zero on empty slots
    (MASIA/NVIF: K + 1, the agent's own token first)."""
    feature: torch.Tensor | None = None
    """The selector's consensus input where it is not the message (MASIA's z_i, NVIF's latent mean),
    [B, N, message_dim]; None: the message is the consensus input (ConsMAC, TarMAC)."""

    @property
    def consensus(self) -> torch.Tensor:
        """What the selector reads, eq. (12): `feature`, or the message where there is none."""
        return self.message if self.feature is None else self.feature

    def detach_for_policy(self, consensus: str = "message") -> torch.Tensor:
        """The policy's view of this step, cut from ConsMAC's graph (the RL loss never reaches ConsMAC).

        consensus: "message" (m_i^(t+1), eq. (12); MASIA/NVIF: their `feature`), "estimate" (g_hat_i)
        or "message+estimate".
        """
        parts = {
            "message": [self.consensus],
            "estimate": [self.estimate],
            "message+estimate": [self.consensus, self.estimate],
        }
        if consensus not in parts:
            raise ConfigError(f"consensus={consensus!r}: must be one of {sorted(parts)}")
        return torch.cat(parts[consensus], dim=-1).detach()


class DistanceEncoder(nn.Module):
    """Phi_d = sqrt(1/D) [cos(w_1 d), ..., cos(w_D d)] (eq. (8)); psi_D = w is one bias-free linear
    layer 1 -> D. The frequencies start log-spaced from 0.1 to 10 rad/m, so the code resolves
    distances from centimetres to the whole arena."""

    def __init__(self, dim: int):
        super().__init__()
        self.dim = dim
        self.frequency = nn.Linear(1, dim, bias=False)
        with torch.no_grad():
            self.frequency.weight.copy_(torch.logspace(-1.0, 1.0, dim).unsqueeze(-1))

    def forward(self, distance: torch.Tensor) -> torch.Tensor:
        """distance [...] (m) -> [..., D]."""
        return torch.cos(self.frequency(distance.unsqueeze(-1))) / math.sqrt(self.dim)


class MaskedMultiHeadAttention(nn.Module):
    """Scaled dot-product attention of one query over K masked keys (Vaswani et al.), with its own
    query/key/value/output projections (psi_A). Empty slots get weight exactly 0 and their inputs are
    never read, so whatever they hold changes nothing; with no key at all the output is exactly 0.

    Two orders of the same products: `fast=False` (acting, evaluation, deployment: bit for bit what
    the shipped policies were trained and measured with) projects every key and value; `fast=True`
    (ConsMAC's supervised update) moves the key projection onto the single query,
    q_h . (W_K,h e_j + b_K,h) = (W_K,h^T q_h) . e_j + q_h . b_K,h, and the value projection after the
    weighted sum, sum_j w_hj (W_V,h e_j + b_V,h) = W_V,h (sum_j w_hj e_j) + b_V,h sum_j w_hj, which
    with one query per row needs about a fifth of the multiplications. Equal to float rounding
    (tests/test_ablations.py); the parameters are the same."""

    def __init__(self, query_dim: int, key_dim: int, attention_dim: int, out_dim: int, n_heads: int):
        super().__init__()
        self.n_heads, self.head_dim = n_heads, attention_dim // n_heads
        self.query = layer_init(nn.Linear(query_dim, attention_dim), 1.0)
        self.key = layer_init(nn.Linear(key_dim, attention_dim), 1.0)
        self.value = layer_init(nn.Linear(key_dim, attention_dim), 1.0)
        self.out = layer_init(nn.Linear(attention_dim, out_dim), 1.0)

    def forward(
        self, query: torch.Tensor, keys: torch.Tensor, mask: torch.Tensor, fast: bool = False
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """query [L, Eq], keys [L, K, Ek], mask [L, K] bool -> (out [L, out_dim], weights [L, H, K])."""
        n_rows, k = keys.shape[:2]
        h, hd = self.n_heads, self.head_dim
        keys = keys.masked_fill(~mask.unsqueeze(-1), 0.0)  # never read empty slots
        has_neighbour = mask.any(dim=-1, keepdim=True)
        open_slot = mask.unsqueeze(1)
        if fast:
            q = self.query(query).view(n_rows, h, hd)
            key_dim = keys.shape[-1]
            w_key = self.key.weight.view(h, hd, key_dim)
            q_key = (q.transpose(0, 1) @ w_key).transpose(0, 1)  # [L, H, Ek]: W_K,h^T q_h
            scores = (q_key @ keys.transpose(1, 2) + (q * self.key.bias.view(h, hd)).sum(-1, keepdim=True)) / math.sqrt(
                hd
            )  # [L, H, K]
        else:
            q = self.query(query).view(n_rows, h, 1, hd)
            key = self.key(keys).view(n_rows, k, h, hd).transpose(1, 2)  # [L, H, K, hd]
            scores = (q @ key.transpose(-1, -2)).squeeze(-2) / math.sqrt(hd)  # [L, H, K]
        scores = scores.masked_fill(~open_slot, torch.finfo(scores.dtype).min)
        # A row without any open slot would spread its weight uniformly over padding: zero it instead.
        weights = torch.softmax(scores, dim=-1) * open_slot
        if fast:
            w_value = self.value.weight.view(h, hd, -1).transpose(1, 2)  # [H, Ek, hd]
            pooled = weights @ keys  # [L, H, Ek]: sum_j w_hj e_j
            heads = (pooled.transpose(0, 1) @ w_value).transpose(0, 1)  # [L, H, hd]
            heads = (heads + weights.sum(-1, keepdim=True) * self.value.bias.view(h, hd)).reshape(n_rows, h * hd)
        else:
            value = self.value(keys).view(n_rows, k, h, hd).transpose(1, 2)
            heads = (weights.unsqueeze(-2) @ value).reshape(n_rows, h * hd)  # [L, H*hd]; zeros when K = 0
        return self.out(heads) * has_neighbour, weights


class ConsMAC(nn.Module):
    """The parameters Psi = [psi_D, psi_M, psi_A, psi_E] of eqs. (7)-(10); see the module docstring."""

    def __init__(self, cfg: ConsMACConfig, seed: int | None = None):
        super().__init__()
        if cfg.message_content != "learned":
            raise ConfigError(
                f"message_content={cfg.message_content!r}: not ConsMAC's; build it with cefc_mj.nn.obs_comm.build_comm"
            )
        self.cfg = cfg
        with seeded(seed):
            d, e = cfg.message_dim, cfg.distance_dim
            self.register_buffer("local_index", local_index(cfg.layout), persistent=False)
            self.memory = nn.GRUCell(cfg.obs_dim, d)  # psi_M
            for name, p in self.memory.named_parameters():  # the MAPPO convention for recurrent layers
                if name.startswith("weight"):
                    nn.init.orthogonal_(p)
                else:
                    nn.init.zeros_(p)
            self.distance_encoder = DistanceEncoder(e)  # psi_D
            # psi_A; the keys are what neighbours sent (g_hat for ConsMAC-G) with their distance code
            self.attention = MaskedMultiHeadAttention(d + e, cfg.sent_dim + e, cfg.attention_dim, d, cfg.n_heads)
            self.norm = nn.LayerNorm(d) if cfg.residual else nn.Identity()
            # psi_E: the global estimator, 3 layers
            self.estimator = mlp([d, cfg.hidden, cfg.hidden, cfg.global_dim], activate_last=False, last_gain=1.0)

    def initial_message(self, *lead: int) -> torch.Tensor:
        """Zeros [*lead, sent_dim]: the own message m_i0^(0) before anything was sent."""
        return torch.zeros(*lead, self.cfg.sent_dim)

    def local_observation(self, obs: torch.Tensor) -> torch.Tensor:
        """o_i [..., obs_dim] from the full CEFC observation [..., env_obs_dim] (unscaled)."""
        return obs.index_select(-1, self.local_index)

    def forward(
        self,
        obs: torch.Tensor,
        own_message: torch.Tensor,
        messages: torch.Tensor,
        mask: torch.Tensor,
        distance: torch.Tensor,
        with_estimate: bool = True,
        fast: bool = False,
    ) -> ConsMACOutput:
        """One step for every agent (`with_estimate=False`: skip the global estimator, whose output
        only the supervised loss reads, the output's estimate is then None, except for ConsMAC-G,
        which sends it; `fast=True`: the attention's reassociated products, for training,
        `MaskedMultiHeadAttention`).

        obs [B, N, env_obs_dim] (the env's CEFC observation), own_message [B, N, sent_dim] (m_i0^(t)),
        messages [B, N, K, sent_dim], mask [B, N, K] (bool or 0/1), distance [B, N, K] (m): the
        inbox of `cefc_mj.task.messages` (any K >= 0; K = N - 1 there). Any leading shape works.
        sent_dim is message_dim except for ConsMAC-G (global_dim).
        """
        cfg = self.cfg
        lead = obs.shape[:-1]
        k = messages.shape[-2] if messages.dim() >= 2 else -1
        expected = {
            "obs": (obs, (*lead, cfg.env_obs_dim)),
            "own_message": (own_message, (*lead, cfg.sent_dim)),
            "messages": (messages, (*lead, k, cfg.sent_dim)),
            "mask": (mask, (*lead, k)),
            "distance": (distance, (*lead, k)),
        }
        for name, (tensor, shape) in expected.items():
            if tuple(tensor.shape) != tuple(shape):
                raise ConfigError(f"{name}: expected shape {tuple(shape)}, got {tuple(tensor.shape)}")
        rows = math.prod(lead)
        dtype = self.distance_encoder.frequency.weight.dtype
        obs, own_message, messages, distance = (t.to(dtype) for t in (obs, own_message, messages, distance))
        mask = mask.to(torch.bool)
        ablation = cfg.ablation
        if ablation == "wo-com":  # nothing is received
            mask = torch.zeros_like(mask)

        o = self.local_observation(obs) * cfg.obs_scale
        hidden = own_message.reshape(rows, cfg.sent_dim)
        if ablation == "wo-mem":  # no memory: the GRU starts from zero at every decision
            hidden = torch.zeros(rows, cfg.message_dim, dtype=dtype)
        elif cfg.sent_dim < cfg.message_dim:  # ConsMAC-G: the own estimate, zero-padded to the memory's width
            hidden = F.pad(hidden, (0, cfg.message_dim - cfg.sent_dim))
        memory = self.memory(o.reshape(rows, cfg.obs_dim), hidden)  # eq. (7)
        query_code = self.distance_encoder(memory.new_zeros(rows))
        key_code = self.distance_encoder(distance.reshape(rows, k))
        if ablation == "wo-de":  # no distance encoder: the codes are zeros
            query_code, key_code = torch.zeros_like(query_code), torch.zeros_like(key_code)
        query = torch.cat([memory, query_code], dim=-1)  # E_mi, d_0 = 0
        keys = torch.cat([messages.reshape(rows, k, cfg.sent_dim), key_code], dim=-1)  # E_m-i, eq. (8)
        attended, weights = self.attention(query, keys, mask.reshape(rows, k), fast=fast)  # eq. (9)
        message = self.norm(memory + attended) if cfg.residual else attended
        estimate = None
        if with_estimate or ablation == "consmac-g":
            estimate = self.estimator(message).reshape(*lead, cfg.global_dim)  # eq. (10)
        return ConsMACOutput(
            message=estimate if ablation == "consmac-g" else message.reshape(*lead, cfg.message_dim),
            estimate=estimate,
            memory=memory.reshape(*lead, cfg.message_dim),
            attention=weights.reshape(*lead, cfg.n_heads, k),
        )

    def supervised_loss(self, batch: dict[str, torch.Tensor], generator: torch.Generator | None = None) -> torch.Tensor:
        """Eq. (11) on a replay batch (`obs`, `own`, `messages`, `mask`, `distance`, `label`, each
        [L, ...]), with the fast attention; generator: unused (ConsMAC draws nothing)."""
        out = self(batch["obs"], batch["own"], batch["messages"], batch["mask"], batch["distance"], fast=True)
        return consmac_loss(out.estimate, batch["label"])


def inbox_tensors(inbox: Inbox) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """(own_message, messages, mask, distance) as float32/bool tensors from a channel Inbox, in the
    order `ConsMAC.forward` takes them after the observation."""
    return (
        torch.as_tensor(inbox.own, dtype=torch.float32),
        torch.as_tensor(inbox.messages, dtype=torch.float32),
        torch.as_tensor(inbox.mask, dtype=torch.bool),
        torch.as_tensor(inbox.distance, dtype=torch.float32),
    )


def consmac_loss(estimate: torch.Tensor, label: torch.Tensor, weight: torch.Tensor | None = None) -> torch.Tensor:
    """Eq. (11): the mean over agents and steps of ||g_hat - g||^2 (summed over the label's numbers).

    estimate, label [..., G]; weight [...] (optional, e.g. 0 for padding) weights each agent-step.
    """
    if estimate.shape != label.shape:
        raise ConfigError(f"label: expected shape {tuple(estimate.shape)}, got {tuple(label.shape)}")
    squared = ((estimate - label) ** 2).sum(dim=-1)
    if weight is None:
        return squared.mean()
    weight = weight.to(squared.dtype)
    return (squared * weight).sum() / weight.sum().clamp_min(1e-8)


def global_labels(
    cfg: ConsMACConfig,
    agent_pos: np.ndarray,
    agent_vel: np.ndarray | None = None,
    anchors: np.ndarray | None = None,
) -> np.ndarray:
    """The label g_i^(t) of every agent from the true state, [B, N, global_dim] float32.

    agent_pos, agent_vel [B, N, 2]: true positions and velocities (the env's `world`); anchors [B, N, 2]:
    each agent's current anchor (needed for ConsMAC-A). See ConsMACConfig.variant and .label_order.
    """
    pos = np.asarray(agent_pos, dtype=np.float64)
    b, n = pos.shape[:2]
    if pos.shape != (b, n, 2) or n != cfg.n_agents:
        raise ConfigError(f"agent_pos: expected shape (B, {cfg.n_agents}, 2), got {pos.shape}")
    dist = np.linalg.norm(pos[:, None, :, :] - pos[:, :, None, :], axis=-1)  # [B, i, j]
    dist[:, np.arange(n), np.arange(n)] = -1.0  # agent i itself sorts first
    if cfg.label_order == "nearest":
        order = np.argsort(dist, axis=-1, kind="stable")  # [B, N, N], column 0 is i itself
    else:
        order = np.broadcast_to(np.arange(n), (b, n, n))
    env = np.arange(b)[:, None, None]
    if cfg.variant == "A":
        if anchors is None or np.shape(anchors) != (b, n, 2):
            raise ConfigError(f"anchors: ConsMAC-A needs every agent's anchor, shape ({b}, {n}, 2)")
        label = np.asarray(anchors, dtype=np.float64)[env, order]  # [B, N, N, 2]
    else:
        if agent_vel is None or np.shape(agent_vel) != (b, n, 2):
            raise ConfigError(f"agent_vel: ConsMAC-O needs every agent's velocity, shape ({b}, {n}, 2)")
        vel = np.asarray(agent_vel, dtype=np.float64)
        others = order[..., 1:] if cfg.label_order == "nearest" else _others_by_index(b, n)
        rel_pos = pos[env, others] - pos[:, :, None, :]
        rel_vel = vel[env, others] - vel[:, :, None, :]
        label = np.concatenate([rel_pos, rel_vel], axis=-1)  # [B, N, N-1, 4]
    return label.reshape(b, n, -1).astype(np.float32)


def _others_by_index(b: int, n: int) -> np.ndarray:
    """[B, N, N-1]: for each agent i, the indices j != i in increasing order."""
    j = np.arange(n - 1)
    others = j[None, :] + (j[None, :] >= np.arange(n)[:, None])
    return np.broadcast_to(others, (b, n, n - 1))


@contextmanager
def seeded(seed: int | None) -> Iterator[None]:
    """Run a block (a network's construction) with torch's global RNG seeded by `seed`, restoring the
    caller's RNG state afterwards; `None` runs it on the caller's RNG unchanged."""
    if seed is None:
        yield
        return
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(int(seed))
        yield
