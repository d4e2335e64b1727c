"""The MASIA and NVIF baselines of the paper's Table IV: communication modules whose messages carry
the sender's raw local observation o_i (docs/research/baselines.md, "MASIA and NVIF").

Both share ConsMAC's config (`ConsMACConfig.message_content`), channel, distance code and masked
attention, and are trained, like ConsMAC, by a supervised loss on the trainer's replay only: the
selector reads their output detached, so the RL loss never reaches them.

- **MASIA** (Guan et al., NeurIPS 2022; message_content "observation"): agent i broadcasts o_i, the
  38 numbers of the env as they are (unscaled; the receiver scales them by `obs_scale`). The receiver
  aggregates its own o_i^(t) and the observations o_j^(t-1) its neighbours sent (one decision late,
  within 3 m) by one layer of self-attention over that set, read at the agent's own token:

      e_j  = [s o_j || Phi_dj]   (own token: [s o_i || Phi_0]),   s = obs_scale
      z_i  = LayerNorm(W s o_i + MHA(e_i, {e_i, e_j}, {e_i, e_j}))     aggregated representation
      g_hat_i = F_E(z_i),   L = ||g_hat_i - g_i||^2                    the global state, ConsMAC-O's label

  The selector reads z_i (64 numbers). MASIA's latent future-prediction loss is left out (it needs
  the next decision's inputs in the replay and a momentum target encoder; docs/research/baselines.md).

- **NVIF** (Chai et al., IEEE TNNLS 2024; message_content "latent+observation"): agent i's
  variational encoder reads its own o_i and its neighbours' messages [z_j || o_j] (attention, as
  MASIA's) and gives q(z_i | o_i, inbox) = N(mu_i, diag(exp(log_var_i))); the agent broadcasts
  [mu_i || o_i] (64 + 38 = 102 numbers, o_i unscaled). Its own token also carries its previous
  latent mu_i^(t-1) (its own previous message), so information flows over hops and decisions:

      e_j  = [mu_j || s o_j || Phi_dj]   (own token: [mu_i^(t-1) || s o_i^(t) || Phi_0])
      h_i  = LayerNorm(W e_i + MHA(e_i, {e_i, e_j}, {e_i, e_j})),   mu_i, log_var_i = linear maps of h_i
      L    = sum over o in {o_i, o_j received} ||D([z_i || Phi_d]) - s o||^2 / (1 + k)
             + kl_weight KL(q || N(0, I)),  z_i = mu_i + sigma_i eps   (the reparameterised sample)

  The decoder D reconstructs the agent's own observation (d = 0) and each received one (at its
  sender's distance): local observations, not the global state (the CI-HRL paper's m ~ F^-1(o)).
  The selector reads mu_i; acting and deployment use mu_i, never a sample.

>>> from cefc_mj.task.config import TaskConfig
>>> cfg = ConsMACConfig.from_task(TaskConfig(n_agents=8), variant="O", message_content="observation")
>>> net = build_comm(cfg, seed=0)
>>> obs = torch.zeros(2, 8, net.cfg.env_obs_dim)
>>> out = net(obs, net.initial_message(2, 8), torch.zeros(2, 8, 7, 38), torch.zeros(2, 8, 7, dtype=torch.bool),
...           torch.zeros(2, 8, 7))
>>> out.message.shape, out.consensus.shape, out.estimate.shape
(torch.Size([2, 8, 38]), torch.Size([2, 8, 64]), torch.Size([2, 8, 28]))
"""

from __future__ import annotations

import math

import torch
from torch import nn

from cefc_mj.errors import ConfigError
from cefc_mj.nn.consmac import (
    ConsMAC,
    ConsMACConfig,
    ConsMACOutput,
    DistanceEncoder,
    MaskedMultiHeadAttention,
    consmac_loss,
    local_index,
    seeded,
)
from cefc_mj.nn.layers import layer_init, mlp

OBSERVATION_CONTENTS = ("observation", "latent+observation")
"""The `ConsMACConfig.message_content` values this module implements: MASIA's and NVIF's."""
LOG_VAR_RANGE = (-10.0, 10.0)
"""NVIF's log-variance is clamped to this range, so exp() stays finite."""


def build_comm(cfg: ConsMACConfig, seed: int | None = None) -> nn.Module:
    """The communication module a config describes: ConsMAC, or MASIA / NVIF (`ObservationComm`)."""
    return ObservationComm(cfg, seed) if cfg.message_content in OBSERVATION_CONTENTS else ConsMAC(cfg, seed)


class ObservationComm(nn.Module):
    """MASIA (message_content "observation") or NVIF ("latent+observation"); see the module docstring.
    Same call as `ConsMAC.forward` and the same `ConsMACOutput`, whose `message` is what is sent and
    whose `feature` is what the selector reads."""

    def __init__(self, cfg: ConsMACConfig, seed: int | None = None):
        super().__init__()
        if cfg.message_content not in OBSERVATION_CONTENTS:
            raise ConfigError(f"message_content={cfg.message_content!r}: ObservationComm is MASIA or NVIF")
        self.cfg = cfg
        self.nvif = cfg.message_content == "latent+observation"
        with seeded(seed):
            d, e, token = cfg.message_dim, cfg.distance_dim, cfg.sent_dim  # a token holds what was sent
            self.register_buffer("local_index", local_index(cfg.layout), persistent=False)
            self.distance_encoder = DistanceEncoder(e)
            self.attention = MaskedMultiHeadAttention(token + e, token + e, cfg.attention_dim, d, cfg.n_heads)
            self.embed = layer_init(nn.Linear(token, d), 1.0)  # the own token's residual path
            self.norm = nn.LayerNorm(d) if cfg.residual else nn.Identity()
            if self.nvif:
                self.mean = layer_init(nn.Linear(d, d), 1.0)
                self.log_var = layer_init(nn.Linear(d, d), 0.01)
                self.decoder = mlp([d + e, cfg.hidden, cfg.hidden, cfg.obs_dim], activate_last=False, last_gain=1.0)
            else:  # MASIA's global-state decoder, ConsMAC's estimator
                self.estimator = mlp([d, cfg.hidden, cfg.hidden, cfg.global_dim], activate_last=False, last_gain=1.0)

    def initial_message(self, *lead: int) -> torch.Tensor:
        """Zeros [*lead, sent_dim]: the own message before anything was sent."""
        return torch.zeros(*lead, self.cfg.sent_dim)

    def local_observation(self, obs: torch.Tensor) -> torch.Tensor:
        """o_i [..., obs_dim] from the full CEFC observation [..., env_obs_dim] (unscaled)."""
        return obs.index_select(-1, self.local_index)

    def tokens(self, sent: torch.Tensor) -> torch.Tensor:
        """What was sent [..., sent_dim] as the attention reads it: its observation part (the last
        obs_dim numbers) scaled by obs_scale, a latent part as it is."""
        o = self.cfg.obs_dim
        return torch.cat([sent[..., :-o], sent[..., -o:] * self.cfg.obs_scale], dim=-1)

    def aggregate(
        self,
        obs: torch.Tensor,
        own_message: torch.Tensor,
        messages: torch.Tensor,
        mask: torch.Tensor,
        distance: torch.Tensor,
        fast: bool = False,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """(h [L, d] the aggregated representation, own token embedding [L, d], attention weights
        [L, H, K + 1], o_i [L, obs_dim] unscaled) for the inputs flattened to L rows."""
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
        o = self.local_observation(obs).reshape(rows, cfg.obs_dim)
        # the own token: o_i of this decision (NVIF: after its own previous latent mu_i^(t-1))
        own = own_message.reshape(rows, cfg.sent_dim)
        own = torch.cat([own[:, : cfg.sent_dim - cfg.obs_dim], o], dim=-1)
        own_token = self.tokens(own)
        own_code = self.distance_encoder(own.new_zeros(rows))
        query = torch.cat([own_token, own_code], dim=-1)
        received = self.tokens(messages.reshape(rows, k, cfg.sent_dim))
        keys = torch.cat([received, self.distance_encoder(distance.reshape(rows, k))], dim=-1)
        keys = torch.cat([query.unsqueeze(1), keys], dim=1)  # the own token first: self-attention over the set
        slots = torch.cat([torch.ones(rows, 1, dtype=torch.bool), mask.reshape(rows, k).to(torch.bool)], dim=1)
        attended, weights = self.attention(query, keys, slots, fast=fast)
        embedded = self.embed(own_token)
        h = self.norm(embedded + attended) if cfg.residual else attended
        return h, embedded, weights, o

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
        """One step for every agent, the inputs as `ConsMAC.forward` takes them (messages of
        sent_dim numbers: 38 for MASIA, 102 for NVIF). The output's message is what the agent sends
        (MASIA: o_i; NVIF: [mu_i || o_i], o_i unscaled), its feature what the selector reads (z_i;
        mu_i), its estimate MASIA's g_hat_i (None for NVIF, or with `with_estimate=False`)."""
        cfg = self.cfg
        lead = obs.shape[:-1]
        h, embedded, weights, o = self.aggregate(obs, own_message, messages, mask, distance, fast=fast)
        estimate = None
        if self.nvif:
            feature = self.mean(h)
            message = torch.cat([feature, o], dim=-1)
        else:
            feature, message = h, o
            if with_estimate:
                estimate = self.estimator(h).reshape(*lead, cfg.global_dim)
        return ConsMACOutput(
            message=message.reshape(*lead, cfg.sent_dim),
            estimate=estimate,
            memory=embedded.reshape(*lead, cfg.message_dim),
            attention=weights.reshape(*lead, cfg.n_heads, weights.shape[-1]),
            feature=feature.reshape(*lead, cfg.message_dim),
        )

    def supervised_loss(self, batch: dict[str, torch.Tensor], generator: torch.Generator | None = None) -> torch.Tensor:
        """The module's own loss on a replay batch (`obs`, `own`, `messages`, `mask`, `distance`,
        and MASIA's `label`, each [L, ...]). MASIA: ||g_hat_i - g_i||^2 (eq. (11) with ConsMAC-O's
        label). NVIF: the reconstruction of the own and the received observations from a
        reparameterised sample (noise from `generator`), plus kl_weight times the KL term."""
        inputs = (batch["obs"], batch["own"], batch["messages"], batch["mask"], batch["distance"])
        if not self.nvif:
            return consmac_loss(self(*inputs, fast=True).estimate, batch["label"])
        cfg = self.cfg
        h, _, _, o = self.aggregate(*inputs, fast=True)
        mean = self.mean(h)
        log_var = self.log_var(h).clamp(*LOG_VAR_RANGE)
        noise = torch.randn(mean.shape, generator=generator, dtype=mean.dtype)
        z = mean + torch.exp(0.5 * log_var) * noise  # [L, d]
        rows, k = batch["mask"].reshape(len(h), -1).shape
        mask = batch["mask"].reshape(rows, k).to(mean.dtype)
        distance = torch.cat([torch.zeros(rows, 1), batch["distance"].reshape(rows, k).to(mean.dtype)], dim=1)
        received = batch["messages"].reshape(rows, k, cfg.sent_dim)[..., -cfg.obs_dim :].to(mean.dtype)
        target = torch.cat([o.unsqueeze(1), received], dim=1) * cfg.obs_scale  # [L, 1 + K, obs_dim]
        code = self.distance_encoder(distance)  # [L, 1 + K, D]
        decoded = self.decoder(torch.cat([z.unsqueeze(1).expand(rows, k + 1, -1), code], dim=-1))
        weight = torch.cat([torch.ones(rows, 1), mask], dim=1)  # the own observation and the received ones
        squared = ((decoded - target) ** 2).sum(-1)
        reconstruction = ((squared * weight).sum(-1) / weight.sum(-1)).mean()
        kl = 0.5 * (mean**2 + log_var.exp() - 1.0 - log_var).sum(-1).mean()
        return reconstruction + cfg.kl_weight * kl
