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
import struct
import warnings
import zipfile
from collections.abc import Mapping
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import torch
from torch.overrides import TorchFunctionMode

from cefc_mj import paths
from cefc_mj.errors import CefcError, CheckpointError, ConfigError
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


def _one_line(error: BaseException) -> str:
    """`Type: first line of the message` (at most 160 characters of it), for a one-line error."""
    text = str(error).strip()
    first = text.splitlines()[0][:160] if text else ""
    return f"{type(error).__name__}: {first}" if first else type(error).__name__


@contextmanager
def checkpoint_errors(path: Path, reason: str):
    """Inside it, any exception but a CheckpointError that names `path` (a file's content that fails
    to build, fit or restore a network: KeyError, TypeError, RuntimeError, a ConfigError of a config
    read from the file, ...) becomes CheckpointError `<path>: <reason> (<Type>: <its first line>)`:
    everything a loader does with a file's content is a question about that file."""
    try:
        yield
    except CheckpointError as e:
        if str(path) in str(e):
            raise
        raise CheckpointError(f"{path}: {reason} ({_one_line(e)})") from None
    except Exception as e:  # noqa: BLE001 (any failure here is the file's)
        raise CheckpointError(f"{path}: {reason} ({_one_line(e)})") from None


_LOCAL_HEADER = struct.Struct("<4sHHHHHIIIHH")
_DATA_DESCRIPTOR = b"PK\x07\x08"
_TORCH_PADDING_FIELD = 0x4246  # "FB": torch.save's alignment padding, filled with b"Z"
_ZIP64_FIELD = 0x0001
_END = struct.Struct("<4sHHHHIIH")  # end of central directory (no comment: torch.save writes none)
_ZIP64_END = struct.Struct("<4sQHHIIQQQQ")
_ZIP64_LOCATOR = struct.Struct("<4sIQI")


def _check_archive_end(path: Path, raw, size: int, start_dir: int, entries: int) -> None:
    """The end records (classic and zip64) agree with each other and with the directory zipfile read."""
    raw.seek(size - _END.size)
    sig, disk, cd_disk, here, total, cd_size, cd_offset, comment = _END.unpack(raw.read(_END.size))
    end_at = size - _END.size
    if sig != b"PK\x05\x06" or comment or disk or cd_disk:
        raise CheckpointError(f"{path}: corrupted (the zip end record)")
    real = (entries, entries, end_at - start_dir, start_dir)
    if size >= _END.size + _ZIP64_LOCATOR.size:
        raw.seek(end_at - _ZIP64_LOCATOR.size)
        loc_sig, loc_disk, record_at, disks = _ZIP64_LOCATOR.unpack(raw.read(_ZIP64_LOCATOR.size))
        if loc_sig == b"PK\x06\x07":
            raw.seek(record_at)
            record = raw.read(_ZIP64_END.size)
            fields = _ZIP64_END.unpack(record) if len(record) == _ZIP64_END.size else (None,) * 10
            rec_sig, rec_size, _, _, rec_disk, rec_cd_disk, *counts = fields
            real = (entries, entries, record_at - start_dir, start_dir)
            if (
                rec_sig != b"PK\x06\x06"
                or (loc_disk, disks, rec_disk, rec_cd_disk) != (0, 1, 0, 0)
                or rec_size != end_at - _ZIP64_LOCATOR.size - record_at - 12
                or tuple(counts) != real
            ):
                raise CheckpointError(f"{path}: corrupted (the zip64 end record)")
    for value, expected, marker in zip((here, total, cd_size, cd_offset), real, (0xFFFF, 0xFFFF, 2**32 - 1, 2**32 - 1)):
        if value not in (expected, marker):
            raise CheckpointError(f"{path}: corrupted (the zip end record)")


def _check_torch_archive(path: Path) -> None:
    """What torch.load leaves unchecked in a torch.save zip archive, checked: every member's CRC-32
    (torch reads the members without it, so a flipped bit in the pickle would load), each local
    header and data descriptor against the central directory, the alignment padding, and that the
    members agree on what the writer recorded about them. CheckpointError names what is wrong."""
    with zipfile.ZipFile(path) as archive, path.open("rb") as raw:
        infos = archive.infolist()
        if not infos or min(info.header_offset for info in infos) != 0:
            raise CheckpointError(f"{path}: not a checkpoint (a zip archive with data before its first member)")
        recorded = {
            (i.create_version, i.create_system, i.reserved, i.volume, i.internal_attr, i.external_attr) for i in infos
        }
        if len(recorded) != 1:
            raise CheckpointError(f"{path}: corrupted (the zip directory's entries disagree)")
        for info in infos:
            raw.seek(info.header_offset)
            head = raw.read(_LOCAL_HEADER.size)
            if len(head) != _LOCAL_HEADER.size:
                raise CheckpointError(f"{path}: truncated (member {info.filename})")
            _, version, flags, method, time, date, crc, csize, usize, n_name, n_extra = _LOCAL_HEADER.unpack(head)
            y, mo, d, h, mi, sec = info.date_time
            central = (
                info.extract_version | info.reserved << 8,
                info.flag_bits,
                info.compress_type,
                h << 11 | mi << 5 | sec // 2,
            )
            sizes = {(crc, csize, usize)} - {(0, 0, 0)} if flags & 0x08 else {(crc, csize, usize)}
            if (
                (version, flags, method, time) != central
                or date != ((y - 1980) << 9 | mo << 5 | d)
                or not sizes <= {(info.CRC, info.compress_size, info.file_size), (info.CRC, 0xFFFFFFFF, 0xFFFFFFFF)}
            ):
                raise CheckpointError(f"{path}: corrupted (member {info.filename}: header and directory disagree)")
            raw.seek(n_name, 1)
            extra = raw.read(n_extra)
            while extra:
                field_id, size = struct.unpack("<HH", extra[:4]) if len(extra) >= 4 else (None, len(extra))
                body = extra[4 : 4 + size]
                known = field_id == _ZIP64_FIELD or (field_id == _TORCH_PADDING_FIELD and not body.strip(b"Z"))
                if not known or len(body) != size:
                    raise CheckpointError(f"{path}: corrupted (member {info.filename}: bad extra field)")
                extra = extra[4 + size :]
            if flags & 0x08:
                raw.seek(info.compress_size, 1)
                tail = raw.read(24)
                tail = tail[4:] if tail.startswith(_DATA_DESCRIPTOR) else tail
                short, wide = struct.unpack("<III", tail[:12]), struct.unpack("<IQQ", tail[:20].ljust(20, b"\0"))
                expected = (info.CRC, info.compress_size, info.file_size)
                if expected not in (short, wide):
                    raise CheckpointError(f"{path}: corrupted (member {info.filename}: data descriptor disagrees)")
        _check_archive_end(path, raw, path.stat().st_size, archive.start_dir, len(infos))
        broken = archive.testzip()  # reads every member and checks its CRC-32
        if broken is not None:
            raise CheckpointError(f"{path}: corrupted (member {broken} fails its CRC-32 check)")


def safe_torch_load(path: Path) -> dict:
    """The one way the project reads a checkpoint (policy files of every level, training states):
    `torch.load(weights_only=True)` of a zip archive as torch.save writes it, after
    `_check_torch_archive`. Every way a file can be wrong (missing, a folder, empty, text, truncated,
    a flipped bit, a pickle with a global the weights-only unpickler refuses, a top level that is not
    a dict) raises CheckpointError with one line naming the file and the reason."""
    path = Path(path)
    if path.is_dir():
        raise CheckpointError(f"{path}: a folder, not a checkpoint file")
    if not path.is_file():
        raise CheckpointError(f"{path}: no such checkpoint file")
    try:
        if not zipfile.is_zipfile(path):
            size = path.stat().st_size
            what = "an empty file" if size == 0 else "not a zip archive as torch.save writes one"
            raise CheckpointError(f"{path}: not a readable checkpoint ({what})")
        _check_torch_archive(path)
        with warnings.catch_warnings():  # a damaged pickle may warn before it fails: the error says it
            warnings.simplefilter("ignore")
            payload = torch.load(path, map_location="cpu", weights_only=True)
    except CefcError:
        raise
    except Exception as e:  # noqa: BLE001 (the unpickler and the zip reader raise many types)
        raise CheckpointError(f"{path}: not a readable checkpoint ({_one_line(e)})") from None
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
    with checkpoint_errors(path, f"{what} file with unreadable weights"):
        digest = state_digest(state)
    if digest != payload.get("sha256"):
        raise CheckpointError(f"{path}: weights do not match the stored SHA-256 (file modified or corrupted)")
    return payload


def load_actor(path: Path, obs_dim: int | None = None) -> tuple[ATMActor, dict]:
    """(actor, meta) from a policy file. obs_dim, if given, must match the file's input size."""
    payload = read_policy_payload(path, POLICY_FORMAT, POLICY_VERSION, "an AT-M policy")
    state = payload["state_dict"]
    with checkpoint_errors(path, "an AT-M policy file whose network description is not valid"):
        cfg = ATMConfig.from_dict(payload.get("net"))
    if obs_dim is not None and cfg.obs_dim != obs_dim:
        raise CheckpointError(f"{path}: made for observations of size {cfg.obs_dim}, this env gives {obs_dim}")
    with checkpoint_errors(path, "weights do not fit the described network"):
        with _ParametersOnMeta():
            actor = ATMActor(cfg)
        expected = actor.state_dict()
        # assign=True puts the file's tensors in place of the meta ones; cast as copying into them would
        state = {k: v.to(expected[k].dtype).contiguous() if k in expected else v for k, v in state.items()}
        actor.load_state_dict(state, assign=True)
    actor.eval()
    return actor, policy_meta(path, payload)


def policy_meta(path: Path, payload: dict) -> dict:
    """A policy file's "meta" record (a dict; {} where it has none)."""
    meta = payload.get("meta") or {}
    if not isinstance(meta, dict):
        raise CheckpointError(f"{path}: a policy file whose meta is a {type(meta).__name__}, not a dict")
    return dict(meta)


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

    @property
    def push_observer_s(self) -> float:
        """The time constant of the agent's push observer the policy was trained with (0: none)."""
        return self.actor.cfg.push_observer_s

    def task_for(self, task):
        """`task` (a TaskConfig) with the LiDAR, the action bound and the push observer this policy was
        trained with: every evaluator flies a policy with the sensing it learned on (an
        `_obstacle_lidar` stage's LiDAR sees obstacles only), clips the env's actions where the policy
        clips its own, and gives the agent the push observer it learned with."""
        own = {
            "lidar_sees_agents": self.lidar_sees_agents,
            "accel_max": self.accel_max,
            "push_observer_s": self.push_observer_s,
        }
        if all(getattr(task, name) == value for name, value in own.items()):
            return task
        return dataclasses.replace(task, **own)

    def with_action_bound(self, accel_max: float) -> "Policy":
        """This policy flown at another action bound (m/s^2 per axis): the same weights, the network's
        output clipped to `accel_max` instead of the bound it was trained at."""
        return self._with_actor_settings(accel_max=float(accel_max))

    def with_push_observer(self, time_constant: float) -> "Policy":
        """This policy flown by an agent with the push observer of `time_constant` s (0: none) instead of
        the one it was trained with; the same weights."""
        return self._with_actor_settings(push_observer_s=float(time_constant))

    def _with_actor_settings(self, **changes) -> "Policy":
        """This policy with its actor's config fields `changes` replaced (self where they are already so)."""
        if all(getattr(self.actor.cfg, name) == value for name, value in changes.items()):
            return self
        actor = copy.deepcopy(self.actor)
        actor.__dict__.pop("_inference_plan", None)  # the compiled kernel's copy names the old settings
        actor.cfg = dataclasses.replace(actor.cfg, **changes)
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
