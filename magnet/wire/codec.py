"""msgpack framing shared by every message: version, size limits, and the checks of single fields."""

from __future__ import annotations

import math
from typing import Any
from collections.abc import Mapping

import msgpack
import numpy as np

from magnet.wire.errors import WireError

WIRE_VERSION = 1
#: Larger payloads are refused before they are unpacked.
MAX_PAYLOAD_BYTES = 4 * 1024 * 1024
#: Most samples in one raw or heading batch.
MAX_BATCH_SAMPLES = 10_000

Payload = bytes | bytearray | memoryview


def pack(message: Mapping[str, Any]) -> bytes:
    """msgpack bytes of a map (with ``v`` added when missing)."""
    if "v" not in message:
        message = {"v": WIRE_VERSION, **message}
    return msgpack.packb(message, use_bin_type=True)


def unpack(payload: Payload) -> dict[str, Any]:
    """The map inside ``payload``; WireError when oversized, not msgpack, not a map or of another version."""
    if len(payload) > MAX_PAYLOAD_BYTES:
        raise WireError("oversized", f"payload of {len(payload)} bytes exceeds {MAX_PAYLOAD_BYTES}")
    try:
        message = msgpack.unpackb(payload, raw=False, strict_map_key=True)
    except Exception as exc:  # msgpack raises several unrelated types for garbage
        raise WireError("not-msgpack", f"payload is not msgpack: {type(exc).__name__}") from None
    if not isinstance(message, dict):
        raise WireError("not-a-map", f"payload is a msgpack {type(message).__name__}, not a map")
    check_version(message)
    return message


def check_version(message: Mapping[str, Any]) -> None:
    """WireError ``wrong-version`` unless ``message['v']`` is ``WIRE_VERSION``."""
    if message.get("v") != WIRE_VERSION:
        raise WireError("wrong-version", f"schema version {message.get('v')!r}, expected {WIRE_VERSION}")


def int_field(message: Mapping[str, Any], name: str, default: int | None = None) -> int:
    """An integer field (bool refused); WireError ``bad-field`` otherwise."""
    value = message.get(name, default)
    if isinstance(value, bool) or not isinstance(value, int):
        raise WireError("bad-field", f"{name} must be an integer, got {type(value).__name__}")
    return value


def number_field(message: Mapping[str, Any], name: str, default: float) -> float:
    """A finite number field; WireError ``bad-field`` otherwise."""
    value = message.get(name, default)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise WireError("bad-field", f"{name} must be a finite number")
    return float(value)


def float_array(value: Any, name: str, shape_tail: tuple[int, ...], limit: float | None) -> np.ndarray:
    """float64 array of shape (N, *shape_tail), N <= MAX_BATCH_SAMPLES, finite, |x| <= limit; else WireError."""
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise WireError("bad-shape", f"{name} is not an array of numbers") from None
    if arr.ndim != 1 + len(shape_tail) or arr.shape[1:] != shape_tail:
        raise WireError("bad-shape", f"{name} has shape {arr.shape}, expected (N, {', '.join(map(str, shape_tail))})")
    if arr.shape[0] > MAX_BATCH_SAMPLES:
        raise WireError("oversized", f"{name} holds {arr.shape[0]} samples, more than {MAX_BATCH_SAMPLES}")
    if not np.isfinite(arr).all():
        raise WireError("non-finite", f"{name} holds non-finite values")
    if limit is not None and arr.size and np.abs(arr).max() > limit:
        raise WireError("absurd-magnitude", f"{name} holds values beyond +-{limit:g}")
    return arr


def int_array(value: Any, name: str) -> np.ndarray:
    """int64 array (N,) from a list of integers, N <= MAX_BATCH_SAMPLES; else WireError."""
    try:
        arr = np.asarray(value)
    except (TypeError, ValueError, OverflowError):
        raise WireError("bad-shape", f"{name} is not an array of integers") from None
    if arr.ndim != 1 or (arr.size and arr.dtype.kind not in "iu"):
        raise WireError("bad-shape", f"{name} must be a list of integers, got shape {arr.shape} dtype {arr.dtype}")
    if arr.shape[0] > MAX_BATCH_SAMPLES:
        raise WireError("oversized", f"{name} holds {arr.shape[0]} samples, more than {MAX_BATCH_SAMPLES}")
    return arr.astype(np.int64)


def check_lengths(n: int, arrays: Mapping[str, np.ndarray]) -> None:
    """WireError ``bad-shape`` unless every array holds ``n`` samples."""
    for name, arr in arrays.items():
        if arr.shape[0] != n:
            raise WireError("bad-shape", f"{name} holds {arr.shape[0]} samples but t_ns holds {n}")
