"""pi_H, the high level's policy: the communication module (ConsMAC, MASIA's or NVIF's, or none)
and the anchor selector, with its own policy file format (docs/research/high_level.md).

`HighLevelPolicy.decide(obs, inbox)` gives each agent's anchor index and the message it sends;
`save_highlevel_policy` / `load_highlevel_policy` write and read `cefc-mj/highlevel-policy` files
(configs, weights and their SHA-256)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from torch import nn

from cefc_mj.errors import CheckpointError, ConfigError
from cefc_mj.nn.consmac import ABLATIONS, ConsMAC, ConsMACConfig, inbox_tensors
from cefc_mj.nn.obs_comm import ObservationComm, build_comm
from cefc_mj.nn.policy_io import (
    checkpoint_errors,
    policy_meta,
    read_policy_payload,
    resolve_policy_path,
    write_policy_payload,
)
from cefc_mj.nn.selector import AnchorSelector, SelectorConfig
from cefc_mj.task.config import TaskConfig
from cefc_mj.task.messages import Inbox

VARIANTS = ("consmac-a", "consmac-o", "mappo", "tarmac", "masia", "nvif")
CONSMAC_VARIANTS = ("consmac-a", "consmac-o")
"""The variants whose communication module learns from eq. (11): the ones ConsMAC's ablations apply to."""
SUPERVISED_VARIANTS = (*CONSMAC_VARIANTS, "masia", "nvif")
"""The variants whose communication module learns from its own supervised loss on the replay
(ConsMAC's eq. (11), MASIA's global-state reconstruction, NVIF's VAE), never from the RL loss
(except ConsMAC's wt-rl ablation)."""
MESSAGE_CONTENT = {"masia": "observation", "nvif": "latent+observation"}
"""`ConsMACConfig.message_content` of the baselines that send their local observation (Table IV)."""
POLICY_FORMAT = "cefc-mj/highlevel-policy"
POLICY_VERSION = 1


class HighLevelPolicy(nn.Module):
    """pi_H: the communication module (ConsMAC, MASIA's or NVIF's `ObservationComm`, or None for the
    mappo variant) and the anchor selector."""

    def __init__(self, selector: AnchorSelector, comm: ConsMAC | ObservationComm | None, variant: str):
        super().__init__()
        self.selector, self.comm, self.variant = selector, comm, variant

    @classmethod
    def build(
        cls, variant: str, task: TaskConfig, seed: int = 0, hidden: int = 128, ablation: str = "none"
    ) -> "HighLevelPolicy":
        """Fresh networks of a variant: consmac-a / consmac-o (ConsMAC with either label), tarmac (the
        same module, its output left attached so the RL loss trains it end to end), masia / nvif
        (`cefc_mj.nn.obs_comm`: raw local observations sent, a supervised module, detached) or mappo
        (no communication). ablation: one of the paper's Fig. 7 ablations of ConsMAC
        (`cefc_mj.nn.consmac.ABLATIONS`), for the ConsMAC variants only; "wt-rl" leaves the
        selector's consensus input attached, so the RL loss reaches ConsMAC too."""
        if variant not in VARIANTS:
            raise ConfigError(f"variant={variant!r}: must be one of {', '.join(VARIANTS)}")
        if ablation not in ABLATIONS:
            raise ConfigError(f"ablation={ablation!r}: must be one of {', '.join(ABLATIONS)}")
        if ablation != "none" and variant not in CONSMAC_VARIANTS:
            raise ConfigError(
                f"ablation={ablation!r}: ablates ConsMAC, so it needs variant consmac-a or consmac-o, not {variant!r}"
            )
        comm = None
        if variant != "mappo":
            label = "O" if variant in ("consmac-o", "masia", "nvif") else "A"
            content = MESSAGE_CONTENT.get(variant, "learned")
            cfg = ConsMACConfig.from_task(task, variant=label, ablation=ablation, message_content=content)
            comm = build_comm(cfg, seed=seed)
            live = variant == "tarmac" or ablation == "wt-rl"
            s_cfg = SelectorConfig.from_consmac(comm.cfg, hidden=hidden, consensus_gradient=live)
        else:
            s_cfg = SelectorConfig.from_task(task, consensus_dim=0, hidden=hidden)
        return cls(AnchorSelector(s_cfg, seed=seed + 1), comm, variant)

    @property
    def message_dim(self) -> int:
        """Numbers each agent sends per decision (0 without communication; global_dim for ConsMAC-G,
        38 for MASIA, 102 for NVIF: the paper's Table IV)."""
        return self.comm.cfg.sent_dim if self.comm is not None else 0

    @property
    def ablation(self) -> str:
        """ConsMAC's ablation ("none" for the paper's ConsMAC and for the other variants)."""
        return self.comm.cfg.ablation if self.comm is not None else "none"

    def comm_inputs(self, obs: torch.Tensor, inbox: Inbox | None) -> tuple[torch.Tensor, ...]:
        """(obs, own, messages, mask, distance) as ConsMAC takes them; () without communication."""
        return (obs, *inbox_tensors(inbox)) if self.comm is not None else ()

    def consensus(self, comm_inputs: tuple[torch.Tensor, ...], lead: tuple[int, ...]):
        """(the selector's consensus input, the module's output or None). The input is detached
        unless the variant trains the communication module by RL (tarmac, wt-rl). It is the
        message for ConsMAC and TarMAC, the aggregated feature for MASIA and NVIF (`out.consensus`);
        `out.message` is what is sent."""
        if self.comm is None:
            return torch.zeros(*lead, 0), None
        out = self.comm(*comm_inputs)
        live = self.selector.cfg.consensus_gradient
        return (out.consensus if live else out.detach_for_policy("message")), out

    @torch.no_grad()
    def decide(
        self, obs: np.ndarray, inbox: Inbox | None, deterministic: bool = True, generator: torch.Generator | None = None
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """(anchor index [B, N], message to send [B, N, message_dim] or None) for CEFC observations
        [B, N, D] and the channel's inbox of this decision."""
        obs_t = torch.as_tensor(obs, dtype=torch.float32)
        if self.comm is None:
            consensus, message = torch.zeros(*obs_t.shape[:-1], 0), None
        else:  # the selector reads the message (eq. 12; MASIA/NVIF: their feature), not the estimate
            out = self.comm(*self.comm_inputs(obs_t, inbox), with_estimate=False)
            consensus, message = out.consensus, out.message.numpy()
        if deterministic:  # the mode: the largest logit (no distribution object on the deployed path)
            return self.selector(obs_t, consensus).argmax(dim=-1).numpy(), message
        index, _ = self.selector.act(obs_t, consensus, deterministic=False, generator=generator)
        return index.numpy(), message

    def agent_decider(self):
        """One agent's deployed decision: `decide(obs, inbox)` for a batch of one ([1, 1, ...]
        arrays, the inbox of that agent), the mode of its distribution. The networks run as a
        TorchScript trace, made on first use for each neighbour-slot count K: the same operations
        as `decide` (equal bit for bit), without the per-module Python overhead that dominates
        these small networks at batch one. Falls back to `decide` if tracing fails."""
        import warnings

        policy = self
        traced: dict[int, object] = {}

        class _Step(nn.Module):
            def __init__(self):
                super().__init__()
                self.policy = policy

            def forward(self, obs, *inbox):
                if not inbox:
                    return self.policy.selector(obs, obs.new_zeros(*obs.shape[:-1], 0)).argmax(dim=-1)
                out = self.policy.comm(obs, *inbox, with_estimate=False)
                return self.policy.selector(obs, out.consensus).argmax(dim=-1), out.message

        def decide_one(obs: np.ndarray, inbox: Inbox | None) -> tuple[np.ndarray, np.ndarray | None]:
            if np.shape(obs)[:2] != (1, 1):
                raise ConfigError(f"agent_decider: expects one agent's observation [1, 1, D], got {np.shape(obs)}")
            inputs = (
                torch.as_tensor(obs, dtype=torch.float32),
                *(inbox_tensors(inbox) if policy.comm is not None else ()),
            )
            k = inputs[2].shape[-2] if policy.comm is not None else 0
            if k not in traced:
                try:
                    with warnings.catch_warnings(), torch.no_grad():
                        warnings.simplefilter("ignore")  # the shape checks become constants of this K
                        traced[k] = torch.jit.trace(_Step().eval(), inputs, check_trace=False)
                except Exception:  # a network that does not trace: the eager path is always right
                    traced[k] = None
            if traced[k] is None:
                return policy.decide(obs, inbox)
            with torch.inference_mode():
                out = traced[k](*inputs)
            if policy.comm is None:
                return out.numpy(), None
            return out[0].numpy(), out[1].numpy()

        return decide_one


def save_highlevel_policy(policy: HighLevelPolicy, path: Path, meta: dict | None = None) -> Path:
    """Write pi_H (communication module and selector, with their configs) as one policy file."""
    return write_policy_payload(
        path,
        POLICY_FORMAT,
        POLICY_VERSION,
        policy,
        meta,
        variant=policy.variant,
        comm=None if policy.comm is None else policy.comm.cfg.to_dict(),
        selector=policy.selector.cfg.to_dict(),
    )


def load_highlevel_policy(path: Path) -> tuple[HighLevelPolicy, dict]:
    """(policy, meta) from a file written by `save_highlevel_policy`; CheckpointError with one line
    for a missing, foreign, tampered or mismatched file."""
    path = Path(path)
    payload = read_policy_payload(path, POLICY_FORMAT, POLICY_VERSION, "a high-level policy")
    state = payload["state_dict"]
    with checkpoint_errors(path, "weights do not fit the described networks"):
        comm = None if payload.get("comm") is None else build_comm(ConsMACConfig.from_dict(payload["comm"]))
        selector = AnchorSelector(SelectorConfig.from_dict(payload["selector"]))
        policy = HighLevelPolicy(selector, comm, str(payload.get("variant")))
        policy.load_state_dict(state)
    policy.eval()
    return policy, policy_meta(path, payload)


def highlevel_policy_path(policy: str, policies_dir: Path | None = None) -> Path:
    """The file of a high-level policy given by name (in policies_dir, default the shipped folder) or
    path (`resolve_policy_path`); CheckpointError (one line) when there is none."""
    try:
        return resolve_policy_path(policy, policies_dir)
    except CheckpointError as e:
        raise CheckpointError(
            f"--policy {policy}: no high-level policy file ({e}); train it with cefc-train highlevel"
        ) from None
