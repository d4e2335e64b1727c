"""Policy files and the loading API for evaluators.

A policy file (`*.pt`) holds only what inference needs, readable with `torch.load(weights_only=True)`:

    {"format": "cefc-mj/atm-policy", "version": 1, "net": ATMConfig as a dict,
     "state_dict": {name: tensor}, "sha256": digest of the state dict, "meta": {...}}

The digest makes an edited weight fail loudly; a file made for another observation shape, a
truncated file or a foreign pickle all raise `CheckpointError` with one line. A model card
(`*.json`, same stem) sits beside each shipped file (see `cefc_mj.train.model_card`).

Loading builds the network without running its initialisers (the file's weights replace them
anyway; orthogonal init's QR factorisations used to be most of a load's time), so a loaded policy
acts exactly as one built the slow way.

Example (the name is resolved in POLICIES_DIR):

>>> policy = load_policy("atm_c6_step3")   # doctest: +SKIP
>>> actions = policy.act(obs)              # doctest: +SKIP   [B, N, 63] -> [B, N, 2], or [N, 63] -> [N, 2]
>>> actions = policy.act(observations)     # doctest: +SKIP   PettingZoo {agent: obs} -> {agent: action}
"""

from __future__ import annotations

import copy
import dataclasses
import pickle
import zipfile
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import torch
from torch.overrides import TorchFunctionMode

from cefc_mj import paths
from cefc_mj.errors import CheckpointError, ConfigError
from cefc_mj.fileio import atomic_write
from cefc_mj.nn.atm import ATMActor, ATMConfig
from cefc_mj.nn.layers import state_digest

POLICY_FORMAT = "cefc-mj/atm-policy"
POLICY_VERSION = 1


def atomic_torch_save(payload: dict, path: Path) -> None:
    """torch.save to a temporary file, then rename: a kill mid-write never leaves a torn file."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(path, lambda fh: torch.save(payload, fh))


def safe_torch_load(path: Path) -> dict:
    """torch.load(weights_only=True) with every failure turned into one-line CheckpointError."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"{path}: no such checkpoint file")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except (pickle.UnpicklingError, RuntimeError, EOFError, zipfile.BadZipFile, ValueError, OSError, KeyError) as e:
        first = str(e).strip().splitlines()[0] if str(e).strip() else ""
        raise CheckpointError(f"{path}: not a readable checkpoint ({type(e).__name__}: {first[:160]})") from None
    if not isinstance(payload, dict):
        raise CheckpointError(f"{path}: not a cefc-mj checkpoint (top level is {type(payload).__name__})")
    return payload


def write_policy_payload(
    path: Path, file_format: str, version: int, module: torch.nn.Module, meta: dict | None = None, **configs
) -> Path:
    """Write `module`'s weights (copied to the CPU, with their SHA-256) as a policy file of
    `file_format` and `version`, with its `configs` and `meta`, atomically: what
    `read_policy_payload` reads back."""
    state = {k: v.detach().cpu().clone() for k, v in module.state_dict().items()}
    atomic_torch_save(
        {
            "format": file_format,
            "version": version,
            **configs,
            "state_dict": state,
            "sha256": state_digest(state),
            "meta": meta or {},
        },
        Path(path),
    )
    return Path(path)


def save_policy(actor: ATMActor, path: Path, meta: dict | None = None) -> Path:
    """Write `actor` as a policy file; `meta` (JSON-like: str/int/float/bool/list/dict) rides along."""
    return write_policy_payload(path, POLICY_FORMAT, POLICY_VERSION, actor, meta, net=actor.cfg.to_dict())


def read_policy_payload(path: Path, file_format: str, version: int, what: str) -> dict:
    """A policy file's payload, checked: readable, of `file_format` (`what` names it in the error,
    e.g. "an AT-M policy") and `version`, with a tensor state_dict that matches its SHA-256."""
    payload = safe_torch_load(path)
    if payload.get("format") != file_format:
        raise CheckpointError(f"{path}: not {what} file (format {payload.get('format')!r})")
    if payload.get("version") != version:
        raise CheckpointError(f"{path}: {what} file version {payload.get('version')!r}, this code reads {version}")
    state = payload.get("state_dict")
    if not isinstance(state, dict) or not all(isinstance(v, torch.Tensor) for v in state.values()):
        raise CheckpointError(f"{path}: {what} file without a tensor state_dict")
    if state_digest(state) != payload.get("sha256"):
        raise CheckpointError(f"{path}: weights do not match the stored SHA-256 (file modified or corrupted)")
    return payload


def load_actor(path: Path, obs_dim: int | None = None) -> tuple[ATMActor, dict]:
    """(actor, meta) from a policy file. obs_dim, if given, must match the file's input size."""
    payload = read_policy_payload(path, POLICY_FORMAT, POLICY_VERSION, "an AT-M policy")
    state = payload["state_dict"]
    cfg = ATMConfig.from_dict(payload.get("net"))
    if obs_dim is not None and cfg.obs_dim != obs_dim:
        raise CheckpointError(f"{path}: made for observations of size {cfg.obs_dim}, this env gives {obs_dim}")
    with _ParametersOnMeta():
        actor = ATMActor(cfg)
    expected = actor.state_dict()
    # assign=True puts the file's tensors in place of the meta ones; cast as copying into them would
    state = {k: v.to(expected[k].dtype).contiguous() if k in expected else v for k, v in state.items()}
    try:
        actor.load_state_dict(state, assign=True)
    except RuntimeError as e:
        raise CheckpointError(
            f"{path}: weights do not fit the described network ({str(e).splitlines()[0][:160]})"
        ) from None
    actor.eval()
    return actor, dict(payload.get("meta") or {})


class _ParametersOnMeta(TorchFunctionMode):
    """Inside it, `torch.empty` allocates on the meta device: nn.Linear allocates its weight and bias
    with it, so the layers' initialisers (orthogonal_, zeros_) have nothing to compute, and
    `load_state_dict(assign=True)` then puts the file's tensors in their place. What a constructor
    computes with other factories (the actor's index and free-space buffers, its log-std) stays real.
    If a torch release allocated Linear weights another way, loading would only get slower again."""

    def __torch_function__(self, func, types, args=(), kwargs=None):
        kwargs = dict(kwargs or {})
        if func is torch.empty:
            kwargs["device"] = "meta"
        return func(*args, **kwargs)


def resolve_policy_path(path_or_name: str | Path, policies_dir: Path | None = None) -> Path:
    """A path to an existing file, or a bare name looked up as `<policies_dir>/<name>.pt`
    (policies_dir defaults to `cefc_mj.paths.POLICIES_DIR`). A path with a folder part that is not
    a file is an error, never replaced by a shipped policy of the same file name."""
    candidate = Path(path_or_name)
    if candidate.is_file():
        return candidate
    if len(candidate.parts) > 1:
        raise CheckpointError(f"no policy file {str(path_or_name)!r}")
    base = Path(policies_dir) if policies_dir is not None else paths.POLICIES_DIR
    for name in (candidate.name, candidate.name + ".pt"):
        if (base / name).is_file():
            return base / name
    raise CheckpointError(
        f"no policy {str(path_or_name)!r}: not a file, and not found as {base / (candidate.name + '.pt')}"
    )


class Policy:
    """A loaded low-level policy for evaluators: `act(obs) -> actions`, for a batch of envs
    `[B, N, D] -> [B, N, 2]`, one env `[N, D] -> [N, 2]` (float64, m/s^2), or a PettingZoo
    observation dict `{agent: [D]} -> {agent: [2]}` (float32, inside the env's action space).

    `act` is deterministic (the Gaussian mean, turned into an acceleration setpoint by the actor's
    action head and clipped per axis to accel_max as the env clips it) and runs without gradients.
    Each agent's action depends on its own observation only. Call `torch.set_num_threads(1)` in
    rollout loops: these networks are far too small for intra-op threading.
    """

    def __init__(self, actor: ATMActor, meta: dict, name: str):
        self.actor = actor
        self.meta = meta
        self.name = name

    @property
    def obs_dim(self) -> int:
        return self.actor.cfg.obs_dim

    @property
    def safe(self) -> bool:
        return self.actor.cfg.safe

    @property
    def lidar_sees_agents(self) -> bool:
        """Whether the LiDAR this policy was trained with also sees the other UAVs."""
        return self.actor.cfg.lidar_sees_agents

    @property
    def accel_max(self) -> float:
        """The action bound (m/s^2 per axis) the policy clips its actions to: the one it was trained at,
        unless `with_action_bound` set another."""
        return self.actor.cfg.accel_max

    def task_for(self, task):
        """`task` (a TaskConfig) with the LiDAR and the action bound this policy was trained with: every
        evaluator flies a policy with the sensing it learned on (an `_obstacle_lidar` stage's LiDAR sees
        obstacles only) and clips the env's actions where the policy clips its own."""
        sees, bound = self.lidar_sees_agents, self.accel_max
        if (task.lidar_sees_agents, task.accel_max) == (sees, bound):
            return task
        return dataclasses.replace(task, lidar_sees_agents=sees, accel_max=bound)

    def with_action_bound(self, accel_max: float) -> "Policy":
        """This policy flown at another action bound (m/s^2 per axis): the same weights, the network's
        output clipped to `accel_max` instead of the bound it was trained at."""
        if accel_max == self.accel_max:
            return self
        actor = copy.deepcopy(self.actor)
        actor.__dict__.pop("_inference_plan", None)  # the compiled kernel's copy names the old bound
        actor.cfg = dataclasses.replace(actor.cfg, accel_max=float(accel_max))
        return Policy(actor, self.meta, self.name)

    def act(self, obs: np.ndarray | Mapping[str, np.ndarray]) -> np.ndarray | dict[str, np.ndarray]:
        """Actions for `[B, N, D]` or `[N, D]` observations (same leading shape, last axis 2), or
        for a `{agent: [D]}` dict (a dict of float32 `[2]` actions, same keys). ConfigError for any
        other shape."""
        if isinstance(obs, Mapping):
            agents = list(obs)
            if not agents:
                return {}
            rows = [self._as_array(obs[a], f"obs[{a!r}]") for a in agents]
            bad = [(a, list(r.shape)) for a, r in zip(agents, rows) if r.shape != (self.obs_dim,)]
            if bad:
                raise ConfigError(f"obs[{bad[0][0]!r}]: expected shape [{self.obs_dim}], got {bad[0][1]}")
            actions = self._act(np.stack(rows))
            return {a: actions[i].copy() for i, a in enumerate(agents)}
        obs = self._as_array(obs, "obs")
        if obs.ndim not in (2, 3) or obs.shape[-1] != self.obs_dim:
            raise ConfigError(
                f"obs: expected shape [N, {self.obs_dim}] (one env), [B, N, {self.obs_dim}] or a dict "
                f"{{agent: [{self.obs_dim}]}}, got {list(obs.shape)}"
            )
        return self._act(obs).astype(np.float64)

    @torch.no_grad()
    def _act(self, obs: np.ndarray) -> np.ndarray:
        """float32 accelerations [..., 2] for observations [..., D] (the actor's fast inference path,
        bit-identical to to_acceleration(actor(obs)); tests/test_eval_speed_equivalence.py)."""
        return self.actor.deterministic_actions(obs)

    @staticmethod
    def _as_array(obs, name: str) -> np.ndarray:
        try:
            obs = np.asarray(obs)
        except ValueError:  # ragged nesting
            obs = None
        if obs is None or not (np.issubdtype(obs.dtype, np.floating) or np.issubdtype(obs.dtype, np.integer)):
            raise ConfigError(f"{name}: not an array of numbers")
        return obs


def load_policy(path_or_name: str | Path, policies_dir: Path | None = None, obs_dim: int | None = None) -> Policy:
    """Load a policy by file path or by name in the policies folder (see resolve_policy_path)."""
    path = resolve_policy_path(path_or_name, policies_dir)
    actor, meta = load_actor(path, obs_dim)
    return Policy(actor, meta, name=path.stem)
