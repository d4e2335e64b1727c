"""The SITL-M wire format: one UTF-8 JSON object per ZeroMQ frame, with a version field.

Every message is `{"v": 1, "type": ..., ...}`. Floats are JSON numbers written with Python's
shortest round-trip repr, so a float64 crosses the wire bit for bit; NaN and infinities are refused
in both directions. Receivers ignore fields they do not know (a new optional field keeps v = 1; a
changed or new required field bumps it). docs/sitl_m.md has the table of messages and fields.

`decode` validates a frame completely (size, encoding, JSON, version, type, every field's type,
length and finiteness) and raises `WireError` with a short reason; the receiver drops and counts
the message. `check_sensor` adds the checks that need the game's sizes (LiDAR beams, UAV ids).

>>> frame = encode({"v": 1, "type": "action", "uav": 2, "seq": 7, "accel": [0.5, -1.0], "latency_ms": 0.4})
>>> decode(frame, AGENT_TO_SIM)["accel"]
[0.5, -1.0]
>>> try:
...     decode(b'{"v": 1, "type": "action", "uav": 2}', AGENT_TO_SIM)
... except WireError as e:
...     print(e)
seq: missing
"""

from __future__ import annotations

import json
import math

WIRE_VERSION = 1
"""The version every message carries in its "v" field."""
MAX_FRAME_BYTES = 65536
"""Frames longer than this are refused unread (a sensor packet with 7 neighbours is about 1.2 kB)."""


class WireError(ValueError):
    """A received frame is not a valid message; the text is the reason (a short, fixed phrase)."""


# -------------------------------------------------------------------- field validators
def _int(value, name: str, low: int = 0, high: int | None = None) -> int:
    if not isinstance(value, int) or isinstance(value, bool):
        raise WireError(f"{name}: not an integer")
    if value < low or (high is not None and value > high):
        raise WireError(f"{name}: out of range")
    return value


def _float(value, name: str) -> float:
    if not isinstance(value, (int, float)) or isinstance(value, bool) or not math.isfinite(value):
        raise WireError(f"{name}: not a finite number")
    return float(value)


def _vector(value, name: str, length: int | None) -> list[float]:
    if not isinstance(value, list) or (length is not None and len(value) != length):
        raise WireError(f"{name}: not a list of {length} numbers")
    for x in value:
        _float(x, name)
    return value


def _text(value, name: str, max_len: int = 512) -> str:
    if not isinstance(value, str) or len(value) > max_len:
        raise WireError(f"{name}: not a string")
    return value


def _object(value, name: str) -> dict:
    if not isinstance(value, dict):
        raise WireError(f"{name}: not an object")
    return value


def _neighbours(value, name: str) -> list:
    if not isinstance(value, list):
        raise WireError(f"{name}: not a list")
    for row in value:
        if not isinstance(row, list) or len(row) != 5:
            raise WireError(f"{name}: rows must be [id, px, py, vx, vy]")
        _int(row[0], f"{name} id")
        for x in row[1:]:
            _float(x, name)
    return value


# message type -> {field: validator}; "v" and "type" are checked for every message
AGENT_TO_SIM: dict[str, dict] = {
    "hello": {"uav": _int, "policy": _text, "pid": _int, "host": _text},
    "ready": {"uav": _int},
    "action": {"uav": _int, "seq": _int, "accel": lambda v, n: _vector(v, n, 2), "latency_ms": _float},
    "error": {"uav": _int, "reason": _text},
}
"""Messages an agent sends, with their required fields."""

SIM_TO_AGENT: dict[str, dict] = {
    "welcome": {"uav": _int, "formation": _int, "task": _object, "heartbeat_timeout_s": _float},
    "reject": {"reason": _text},
    "sensor": {
        "seq": _int, "t": _float, "pos": lambda v, n: _vector(v, n, 2), "vel": lambda v, n: _vector(v, n, 2),
        "anchor": lambda v, n: _vector(v, n, 2), "lidar": lambda v, n: _vector(v, n, None), "neighbours": _neighbours,
    },
    "ping": {"t": _float},
    "stop": {"reason": _text},
}
"""Messages the simulator sends, with their required fields."""


def _refuse_constant(name: str):
    raise WireError("NaN or infinity in JSON")


def encode(message: dict) -> bytes:
    """One frame for `message` (a dict of JSON-ready values; numpy arrays must be `.tolist()`-ed)."""
    return json.dumps(message, separators=(",", ":"), allow_nan=False).encode("utf-8")


def decode(frame: bytes, schema: dict[str, dict]) -> dict:
    """The validated message in `frame` for one direction's schema (AGENT_TO_SIM or SIM_TO_AGENT);
    WireError with the reason otherwise."""
    if not isinstance(frame, (bytes, bytearray, memoryview)):
        raise WireError("not bytes")
    if len(frame) > MAX_FRAME_BYTES:
        raise WireError("frame too long")
    try:
        text = bytes(frame).decode("utf-8")
    except UnicodeDecodeError:
        raise WireError("not UTF-8") from None
    try:
        message = json.loads(text, parse_constant=_refuse_constant)
    except WireError:
        raise
    except (ValueError, RecursionError):
        raise WireError("not JSON") from None
    if not isinstance(message, dict):
        raise WireError("not a JSON object")
    if message.get("v") != WIRE_VERSION or isinstance(message.get("v"), bool):
        raise WireError("wrong wire version")
    fields = schema.get(message.get("type")) if isinstance(message.get("type"), str) else None
    if fields is None:
        raise WireError("unknown message type")
    for name, check in fields.items():
        if name not in message:
            raise WireError(f"{name}: missing")
        check(message[name], name)
    return message


def check_sensor(message: dict, n_lidar_rays: int, n_agents: int, own_uav: int) -> None:
    """The sensor-packet checks that need the game's sizes (raises WireError)."""
    if len(message["lidar"]) != n_lidar_rays:
        raise WireError("lidar: wrong number of beams")
    ids = [row[0] for row in message["neighbours"]]
    if len(ids) > n_agents - 1 or len(set(ids)) != len(ids) or any(j >= n_agents or j == own_uav for j in ids):
        raise WireError("neighbours: bad UAV ids")
