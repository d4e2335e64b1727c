"""The SITL-M wire format, version 2: one message per ZeroMQ frame, each with a version field.

Every message is a dict `{"v": 2, "type": ..., ...}`. The two that cross the link at every decision,
`sensor` and `action`, travel as a fixed binary layout (a 12-byte header, then little-endian
float64s; `encode` picks it); the rest (hello, welcome, ready, error, ping, stop, reject) as one
UTF-8 JSON object. `decode` reads both (a binary frame starts with the two bytes CE FC, which no
JSON text does) and returns the same dict either way; sensor and action are also accepted as JSON.
Floats cross the wire bit for bit (float64, or Python's shortest round-trip repr in JSON); NaN and
infinities are refused in both directions. In JSON, receivers ignore fields they do not know (a new
optional field keeps the version; a changed or new required field bumps it). docs/sitl_m.md has
the table of messages and fields and the binary layouts.

`decode` validates a frame completely (size, encoding, version, type, every field's type, length
and finiteness) and raises `WireError` with a short reason; the receiver drops and counts the
message. `check_sensor` adds the checks that need the game's sizes (LiDAR beams, UAV ids).

>>> frame = encode({"v": 2, "type": "action", "uav": 2, "seq": 7, "accel": [0.5, -1.0], "latency_ms": 0.4})
>>> len(frame), decode(frame, AGENT_TO_SIM)["accel"]
(36, [0.5, -1.0])
>>> try:
...     decode(b'{"v": 2, "type": "action", "uav": 2}', AGENT_TO_SIM)
... except WireError as e:
...     print(e)
seq: missing
"""

from __future__ import annotations

import json
import math
import struct

WIRE_VERSION = 2
"""The version every message carries in its "v" field."""
MAX_FRAME_BYTES = 65536
"""Frames longer than this are refused unread (a binary sensor packet with 7 neighbours and 24 beams is 540 bytes)."""


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
        "seq": _int,
        "t": _float,
        "pos": lambda v, n: _vector(v, n, 2),
        "vel": lambda v, n: _vector(v, n, 2),
        "anchor": lambda v, n: _vector(v, n, 2),
        "lidar": lambda v, n: _vector(v, n, None),
        "neighbours": _neighbours,
    },
    "ping": {"t": _float},
    "stop": {"reason": _text},
}
"""Messages the simulator sends, with their required fields."""


# ------------------------------------------------------------------- binary sensor / action frames
BINARY_MAGIC = b"\xce\xfc"
"""The first two bytes of a binary frame (not valid UTF-8, so never the start of a JSON frame)."""
_HEADER = struct.Struct("<2sBBIHH")
"""magic, version (u8), kind (u8: 1 sensor, 2 action), seq (u32), then sensor: LiDAR beams (u16),
neighbours (u16); action: uav (u16), 0 (u16)."""
_SENSOR, _ACTION = 1, 2
_SENSOR_FIXED = 7  # t, pos[2], vel[2], anchor[2]
_MAX_SEQ = 2**32 - 1


def _encode_binary(message: dict) -> bytes:
    if message["type"] == "sensor":
        rows = message["neighbours"]
        head = _HEADER.pack(BINARY_MAGIC, WIRE_VERSION, _SENSOR, message["seq"], len(message["lidar"]), len(rows))
        numbers = [message["t"], *message["pos"], *message["vel"], *message["anchor"], *message["lidar"]]
        for row in rows:
            numbers.extend(row)
    else:
        head = _HEADER.pack(BINARY_MAGIC, WIRE_VERSION, _ACTION, message["seq"], message["uav"], 0)
        numbers = [*message["accel"], message["latency_ms"]]
    if not all(map(math.isfinite, numbers)):
        raise ValueError("NaN or infinity in a message")
    return head + struct.pack(f"<{len(numbers)}d", *numbers)


def _decode_binary(frame: bytes, schema: dict[str, dict]) -> dict:
    if len(frame) < _HEADER.size:
        raise WireError("truncated binary frame")
    _, version, kind, seq, a, b = _HEADER.unpack_from(frame)
    if version != WIRE_VERSION:
        raise WireError("wrong wire version")
    kind_name = {_SENSOR: "sensor", _ACTION: "action"}.get(kind)
    if kind_name not in schema:
        raise WireError("unknown message type")
    expected = _SENSOR_FIXED + a + 5 * b if kind == _SENSOR else 3
    if len(frame) != _HEADER.size + 8 * expected or (kind == _ACTION and b != 0):
        raise WireError("binary frame: wrong length")
    values = list(struct.unpack_from(f"<{expected}d", frame, _HEADER.size))
    if not all(map(math.isfinite, values)):
        raise WireError("not a finite number")
    if kind == _ACTION:
        return {"v": version, "type": "action", "uav": a, "seq": seq, "accel": values[:2], "latency_ms": values[2]}
    lidar_end = _SENSOR_FIXED + a
    rows = [values[k : k + 5] for k in range(lidar_end, len(values), 5)]
    for row in rows:
        uav = row[0]
        if not (uav.is_integer() and 0 <= uav < 65536):
            raise WireError("neighbours id: not an integer")
        row[0] = int(uav)
    return {
        "v": version,
        "type": "sensor",
        "seq": seq,
        "t": values[0],
        "pos": values[1:3],
        "vel": values[3:5],
        "anchor": values[5:7],
        "lidar": values[7:lidar_end],
        "neighbours": rows,
    }


def _refuse_constant(name: str):
    raise WireError("NaN or infinity in JSON")


def encode(message: dict) -> bytes:
    """One frame for `message` (a dict of JSON-ready values; numpy arrays must be `.tolist()`-ed):
    binary for sensor and action, JSON otherwise. ValueError for NaN or infinities."""
    if message.get("type") in ("sensor", "action"):
        return _encode_binary(message)
    return json.dumps(message, separators=(",", ":"), allow_nan=False).encode("utf-8")


def decode(frame: bytes, schema: dict[str, dict]) -> dict:
    """The validated message in `frame` for one direction's schema (AGENT_TO_SIM or SIM_TO_AGENT);
    WireError with the reason otherwise."""
    if not isinstance(frame, (bytes, bytearray, memoryview)):
        raise WireError("not bytes")
    if len(frame) > MAX_FRAME_BYTES:
        raise WireError("frame too long")
    if bytes(frame[:2]) == BINARY_MAGIC:
        return _decode_binary(bytes(frame), schema)
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
