"""The SITL-M wire format, version 2: one message per ZeroMQ frame, each with a version field.

Every message is a dict `{"v": 2, "type": ..., ...}`. The two that cross the link at every decision,
`sensor` and `action`, travel as a fixed binary layout (a 12-byte header, then little-endian
float64s; `encode` picks it); the rest (hello, welcome, ready, error, ping, stop, reject) as one
UTF-8 JSON object. `decode` reads both (a binary frame starts with the two bytes CE FC, which no
JSON text does) and returns the same dict either way; sensor and action are also accepted as JSON.
Floats cross the wire bit for bit (float64, or Python's shortest round-trip repr in JSON); NaN and
infinities are refused in both directions. In JSON, receivers ignore fields they do not know (a new
optional field keeps the version; a changed or new required field bumps it). docs/research/sitl_m.md has
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
    "message": {},  # binary only (the game's ConsMAC message)
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
    "game_sensor": {},  # binary only (the game's sensor packet)
    "inbox": {},  # binary only (the neighbours' messages of one decision)
}
"""Messages the simulator sends, with their required fields."""


# ------------------------------------------------------------------- binary sensor / action frames
BINARY_MAGIC = b"\xce\xfc"
"""The first two bytes of a binary frame (not valid UTF-8, so never the start of a JSON frame)."""
_HEADER = struct.Struct("<2sBBIHH")
"""magic, version (u8), kind (u8: 1 sensor, 2 action), seq (u32), then sensor: LiDAR beams (u16),
neighbours (u16); action: uav (u16), 0 (u16)."""
_SENSOR, _ACTION = 1, 2
_GAME_SENSOR, _MESSAGE, _INBOX = 3, 5, 6
"""The game's frames (docs/research/sitl_m.md, "Frame layout"): a game sensor packet (kind 3, sim ->
agent), a ConsMAC message (kind 5, agent -> sim) and an inbox of neighbours' messages (kind 6, sim ->
agent)."""
_SENSOR_FIXED = 7  # t, pos[2], vel[2], anchor[2]
_GAME_FIXED = 9  # t, pos[2], vel[2], adversary_pos[2], adversary_vel[2]
_MESSAGE_FIXED = 2  # latency_ms, anchor (float64), then the message as float32
_INBOX_ROW_FIXED = 16  # sender (u16), 0 (u16), 0 (u32), distance (float64), then the message as float32
_MAX_SEQ = 2**32 - 1
MAX_MESSAGE_DIM = 1024
"""Message sizes above this are refused (ConsMAC's is 64)."""
BINARY_ONLY = frozenset({"game_sensor", "message", "inbox"})
"""Message types that travel only as binary frames (a JSON object of these types is refused)."""
_KIND_NAMES = {
    _SENSOR: "sensor",
    _ACTION: "action",
    _GAME_SENSOR: "game_sensor",
    _MESSAGE: "message",
    _INBOX: "inbox",
}


def _f32_block(values, dim: int) -> bytes:
    import numpy as np

    block = np.ascontiguousarray(values, dtype="<f4").reshape(-1)
    if block.size != dim:
        raise ValueError(f"a message of {block.size} numbers where {dim} are declared")
    if not np.isfinite(block).all():
        raise ValueError("NaN or infinity in a message")
    return block.tobytes()


def _encode_game_binary(message: dict) -> bytes:
    kind = message["type"]
    if kind == "message":
        body = message["message"]
        dim = len(body)
        head = _HEADER.pack(BINARY_MAGIC, WIRE_VERSION, _MESSAGE, message["seq"], message["uav"], dim)
        numbers = [message["latency_ms"], message["anchor"]]
        if not all(map(math.isfinite, numbers)):
            raise ValueError("NaN or infinity in a message")
        return head + struct.pack("<2d", *numbers) + _f32_block(body, dim)
    if kind == "inbox":
        rows = message["rows"]
        dim = message["dim"]
        head = _HEADER.pack(BINARY_MAGIC, WIRE_VERSION, _INBOX, message["seq"], dim, len(rows))
        parts = [head]
        for sender, distance, body in rows:
            if not math.isfinite(distance):
                raise ValueError("NaN or infinity in a message")
            parts.append(struct.pack("<HHId", sender, 0, 0, distance))
            parts.append(_f32_block(body, dim))
        return b"".join(parts)
    rows = message["neighbours"]  # game_sensor
    head = _HEADER.pack(BINARY_MAGIC, WIRE_VERSION, _GAME_SENSOR, message["seq"], len(message["lidar"]), len(rows))
    numbers = [
        message["t"],
        *message["pos"],
        *message["vel"],
        *message["adversary_pos"],
        *message["adversary_vel"],
    ]
    for target in message["targets"]:
        numbers.extend(target)
    numbers.extend(message["lidar"])
    for row in rows:
        numbers.extend(row)
    if not all(map(math.isfinite, numbers)):
        raise ValueError("NaN or infinity in a message")
    return head + struct.pack(f"<{len(numbers)}d", *numbers)


def _neighbour_rows(values: list[float], start: int) -> list[list]:
    """The (id, px, py, vx, vy) rows of a sensor packet's body from `start` on, the id checked and made
    an int; WireError for an id that is not an integer in 0..65535."""
    rows = [values[k : k + 5] for k in range(start, len(values), 5)]
    for row in rows:
        uav = row[0]
        if not (uav.is_integer() and 0 <= uav < 65536):
            raise WireError("neighbours id: not an integer")
        row[0] = int(uav)
    return rows


def _decode_game_binary(frame: bytes, kind: int, seq: int, a: int, b: int) -> dict:
    import numpy as np

    size = len(frame) - _HEADER.size
    if kind == _MESSAGE:
        if not 0 <= b <= MAX_MESSAGE_DIM or size != 8 * _MESSAGE_FIXED + 4 * b:
            raise WireError("binary frame: wrong length")
        latency_ms, anchor = struct.unpack_from("<2d", frame, _HEADER.size)
        body = np.frombuffer(frame, dtype="<f4", count=b, offset=_HEADER.size + 16).astype(np.float32)
        if not (math.isfinite(latency_ms) and math.isfinite(anchor) and np.isfinite(body).all()):
            raise WireError("not a finite number")
        if not (anchor.is_integer() and 0 <= anchor < 65536):
            raise WireError("anchor: not an integer")
        return {
            "v": WIRE_VERSION,
            "type": "message",
            "seq": seq,
            "uav": a,
            "latency_ms": latency_ms,
            "anchor": int(anchor),
            "message": body,
        }
    if kind == _INBOX:
        row_size = _INBOX_ROW_FIXED + 4 * a
        if not 1 <= a <= MAX_MESSAGE_DIM or size != b * row_size:
            raise WireError("binary frame: wrong length")
        dtype = np.dtype(
            [("sender", "<u2"), ("pad", "<u2"), ("pad2", "<u4"), ("distance", "<f8"), ("message", "<f4", (a,))]
        )
        rows = np.frombuffer(frame, dtype=dtype, count=b, offset=_HEADER.size)
        if (rows["pad"] != 0).any() or (rows["pad2"] != 0).any():
            raise WireError("inbox: nonzero padding")
        if not (np.isfinite(rows["distance"]).all() and np.isfinite(rows["message"]).all()):
            raise WireError("not a finite number")
        if (rows["distance"] < 0).any():
            raise WireError("inbox distance: negative")
        return {
            "v": WIRE_VERSION,
            "type": "inbox",
            "seq": seq,
            "dim": a,
            "sender": rows["sender"].astype(np.int64),
            "distance": rows["distance"].astype(np.float64),
            "messages": rows["message"].astype(np.float32).reshape(b, a),
        }
    # game sensor: J targets inferred from the length (3 numbers each)
    if size % 8:
        raise WireError("binary frame: wrong length")
    spare = size // 8 - _GAME_FIXED - a - 5 * b
    if spare < 0 or spare % 3:
        raise WireError("binary frame: wrong length")
    n = size // 8
    values = list(struct.unpack_from(f"<{n}d", frame, _HEADER.size))
    if not all(map(math.isfinite, values)):
        raise WireError("not a finite number")
    j_end = _GAME_FIXED + spare
    lidar_end = j_end + a
    rows = _neighbour_rows(values, lidar_end)
    return {
        "v": WIRE_VERSION,
        "type": "game_sensor",
        "seq": seq,
        "t": values[0],
        "pos": values[1:3],
        "vel": values[3:5],
        "adversary_pos": values[5:7],
        "adversary_vel": values[7:9],
        "targets": [values[k : k + 3] for k in range(_GAME_FIXED, j_end, 3)],
        "lidar": values[j_end:lidar_end],
        "neighbours": rows,
    }


def _encode_binary(message: dict) -> bytes:
    if message["type"] in BINARY_ONLY:
        return _encode_game_binary(message)
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
    kind_name = _KIND_NAMES.get(kind)
    if kind_name not in schema:
        raise WireError("unknown message type")
    if kind_name in BINARY_ONLY:
        return _decode_game_binary(frame, kind, seq, a, b)
    expected = _SENSOR_FIXED + a + 5 * b if kind == _SENSOR else 3
    if len(frame) != _HEADER.size + 8 * expected or (kind == _ACTION and b != 0):
        raise WireError("binary frame: wrong length")
    values = list(struct.unpack_from(f"<{expected}d", frame, _HEADER.size))
    if not all(map(math.isfinite, values)):
        raise WireError("not a finite number")
    if kind == _ACTION:
        return {"v": version, "type": "action", "uav": a, "seq": seq, "accel": values[:2], "latency_ms": values[2]}
    lidar_end = _SENSOR_FIXED + a
    rows = _neighbour_rows(values, lidar_end)
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
    if message.get("type") in ("sensor", "action") or message.get("type") in BINARY_ONLY:
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
    if message["type"] in BINARY_ONLY:
        raise WireError("binary-only message type as JSON")
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


def check_game_sensor(message: dict, n_lidar_rays: int, n_targets: int, n_agents: int, own_uav: int) -> None:
    """The game-sensor checks that need the game's sizes (raises WireError)."""
    if len(message["targets"]) != n_targets:
        raise WireError("targets: wrong number")
    check_sensor(message, n_lidar_rays, n_agents, own_uav)


def check_inbox(message: dict, message_dim: int, n_agents: int, own_uav: int, comm_range: float) -> None:
    """The inbox checks that need the game's sizes (raises WireError): the message size, at most
    N - 1 rows, senders in range, distinct and not the receiver, distances below the radio range."""
    if message["dim"] != message_dim:
        raise WireError("inbox: wrong message size")
    sender = message["sender"]
    if len(sender) > n_agents - 1:
        raise WireError("inbox: too many rows")
    if len(set(sender.tolist())) != len(sender) or ((sender >= n_agents) | (sender == own_uav)).any():
        raise WireError("inbox: bad sender ids")
    if (message["distance"] >= comm_range).any():
        raise WireError("inbox: sender out of radio range")


def check_message(message: dict, message_dim: int, n_anchors: int) -> None:
    """The message checks that need the game's sizes (raises WireError)."""
    if len(message["message"]) != message_dim:
        raise WireError("message: wrong size")
    if not 0 <= message["anchor"] < n_anchors:
        raise WireError("message: anchor out of range")
