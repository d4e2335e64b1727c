"""Small building blocks shared by the networks: orthogonally initialised MLPs."""

from __future__ import annotations

import hashlib
import math

import torch
from torch import nn


def layer_init(layer: nn.Linear, gain: float = math.sqrt(2.0)) -> nn.Linear:
    """Orthogonal weights with `gain`, zero bias (the PPO/MAPPO convention)."""
    nn.init.orthogonal_(layer.weight, gain)
    nn.init.zeros_(layer.bias)
    return layer


def mlp(sizes: list[int], activate_last: bool, last_gain: float = math.sqrt(2.0)) -> nn.Sequential:
    """Linear layers between consecutive `sizes` with tanh between them.

    `mlp([39, 128, 128, 128], activate_last=True)` is a 3-layer feature extractor whose output is
    tanh-bounded; `mlp([128, 128, 128, 2], activate_last=False, last_gain=0.01)` a 3-layer head whose
    last layer is linear with a small initial output (the PPO convention for the action mean).
    """
    layers: list[nn.Module] = []
    for i, (n_in, n_out) in enumerate(zip(sizes[:-1], sizes[1:])):
        last = i == len(sizes) - 2
        layers.append(layer_init(nn.Linear(n_in, n_out), last_gain if last else math.sqrt(2.0)))
        if not last or activate_last:
            layers.append(nn.Tanh())
    return nn.Sequential(*layers)


def state_digest(state: dict[str, torch.Tensor]) -> str:
    """SHA-256 over a state dict's names, dtypes, shapes and bytes: a tampered weight changes it."""
    h = hashlib.sha256()
    for name in sorted(state):
        t = state[name].detach().cpu().contiguous()
        h.update(f"{name}|{t.dtype}|{tuple(t.shape)}|".encode())
        h.update(t.numpy().tobytes())
    return h.hexdigest()
