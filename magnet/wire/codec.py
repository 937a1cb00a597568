"""msgpack framing shared by every message: versions, size limits, the one bounded ``unpack``, and the checks of
single fields.

Two versions of the sample messages (raw, heading) are read; v 2 is written:

- v 1: every array is msgpack lists of numbers (``"mag_ut": [[21.3, -4.1, 44.0], ...]``);
- v 2: every array is one binary array map ``{"dtype", "shape", "data"}`` (see ``magnet.wire.arrays``, which checks
  the arrays of both versions).

The records (calibration, history, progress, status, calibrate replies) carry no sample arrays and are the same in
both versions (``RECORD_VERSION`` 1, also their JSON form in files and the store); readers accept either number.
"""

from __future__ import annotations

import io
import math
import threading
from collections.abc import Mapping
from typing import Any, NamedTuple

import msgpack
import numpy as np

from magnet.wire.errors import WireError

#: sample messages (raw, heading) whose arrays are msgpack lists of numbers (still read; written by ``edge --wire 1``)
LISTS_VERSION = 1
#: sample messages whose arrays are binary (``Bin``): what the services write
BINARY_ARRAYS_VERSION = 2
#: the records (calibration, history, progress, status, replies): no sample arrays, one version
RECORD_VERSION = 1
VERSIONS = (LISTS_VERSION, BINARY_ARRAYS_VERSION)
#: Larger payloads are refused before they are unpacked.
MAX_PAYLOAD_BYTES = 4 * 1024 * 1024
#: Most samples in one raw or heading batch.
MAX_BATCH_SAMPLES = 10_000

Payload = bytes | bytearray | memoryview


def pack(message: Mapping[str, Any]) -> bytes:
    """msgpack bytes of a map (with ``v`` added when missing)."""
    if "v" not in message:
        message = {"v": RECORD_VERSION, **message}
    return msgpack.packb(message, use_bin_type=True)


class Limits(NamedTuple):
    """What one message of a kind may hold, enforced while msgpack builds it (see docs/front-door.md, "Decoding
    limits"): the payload's bytes, the entries of one array or map, the bytes of one string or bin, the entries of
    all arrays and maps together (``items``) and the number of arrays and maps (``containers``; None: as ``items``).
    A payload beyond any of them is refused (cause ``oversized``) before more than about ``items`` entries and
    ``containers`` containers exist, whatever its bytes hold."""

    payload_bytes: int
    array: int
    map: int
    text: int
    binary: int
    items: int
    containers: int | None = None


#: the bounds of a message of no particular kind (replies to the command line and the dashboard: a history of
#: MAX_HISTORY records, a fleet of 100,000 devices)
ANY_LIMITS = Limits(MAX_PAYLOAD_BYTES, 200_000, 200_000, 64 * 1024, MAX_PAYLOAD_BYTES, 2_000_000)


class _TooManyItemsError(Exception):
    """Raised inside msgpack's hooks when the entries of a message's arrays and maps exceed ``Limits.items``."""


def _counter(limits: Limits) -> Any:
    """A msgpack ``list_hook`` / ``object_hook`` that counts every array and map built and their entries, and stops
    the unpacking (``_TooManyItemsError``) past ``limits.items`` entries or ``limits.containers`` containers (an
    empty container is the cheapest bomb: one byte, some 70 once built)."""
    left = [limits.items, limits.items if limits.containers is None else limits.containers]

    def hook(value: Any) -> Any:
        left[0] -= len(value)
        left[1] -= 1
        if left[0] < 0 or left[1] < 0:
            raise _TooManyItemsError
        return value

    return hook


#: msgpack nests at most this many containers (its parser's stack); deeper is an error
MSGPACK_DEPTH = 1024
#: what msgpack may set aside for arrays it has opened but not filled, at most, before a payload is known whole
PREALLOCATION_BYTES = 2 * 1024 * 1024
#: the walk reads a larger payload this much at a time (it holds about this much, not a copy of the payload)
SKIP_READ_BYTES = 64 * 1024


def _incomplete(payload: Payload, limits: Limits) -> bool:
    """Whether ``payload`` is not one whole msgpack object, found by walking it without building anything
    (``Unpacker.skip``, in C). msgpack sets aside an array's slots (8 bytes each, up to about 10,000) when it meets
    the array's header, before its entries: a few kB of nested headers that declare long arrays and are then cut
    short would make it set aside about 80 kB per level, up to MSGPACK_DEPTH levels (80 MB for 5 kB), only to fail.
    In a whole payload every declared entry takes a byte at least, so what is set aside is at most 8 bytes per byte
    of payload. The walk is skipped (free) where even a payload cut short cannot make msgpack set aside more than
    PREALLOCATION_BYTES: no array may declare more entries than the payload has bytes (``_unpackb``), and a header
    declaring more than 15 takes 3 bytes, so at most size/3 levels of ``min(array, size)`` slots (fixed arrays of
    up to 15 add at most 120 kB): the common small message (under about 880 bytes at the raw limits) pays nothing."""
    size = len(payload)
    if min(size // 3, MSGPACK_DEPTH) * 8 * min(limits.array, size) <= PREALLOCATION_BYTES:
        return False
    if size <= SKIP_READ_BYTES:  # a copy of a small payload costs less than a file to read it from
        return _walk_small(payload, size)
    unpacker = msgpack.Unpacker(io.BytesIO(payload), read_size=SKIP_READ_BYTES, max_buffer_size=size)
    try:
        unpacker.skip()
    except Exception:  # OutOfData (cut short), StackError (too deep), FormatError ...: msgpack's verdict follows
        return True
    return unpacker.tell() != size


class _Walker(threading.local):
    """Each thread's ``msgpack.Unpacker`` for the walks of payloads up to SKIP_READ_BYTES, kept while its buffer is
    left empty: making one costs about 1.3 us (it zeroes its 40 kB parser stack), more than the walk of a raw batch
    of 100 samples. Its limits are SKIP_READ_BYTES, not the payload's size: a whole payload cannot declare more
    entries or bytes than it holds, so a declaration over its size fails as cut short instead, the same verdict."""

    unpacker: msgpack.Unpacker | None = None


_WALKER = _Walker()


def _walk_small(payload: Payload, size: int) -> bool:
    """``_incomplete`` of a payload of at most SKIP_READ_BYTES, on the thread's kept Unpacker (dropped whenever a
    walk leaves anything in its buffer: cut short, trailing data, an error)."""
    unpacker = _WALKER.unpacker
    if unpacker is None:
        unpacker = msgpack.Unpacker(max_buffer_size=SKIP_READ_BYTES)
    _WALKER.unpacker = None
    start = unpacker.tell()
    try:
        unpacker.feed(payload)
        unpacker.skip()
    except Exception:  # OutOfData (cut short), StackError (too deep), FormatError ...: msgpack's verdict follows
        return True
    whole = unpacker.tell() - start == size
    if whole:  # nothing left in its buffer: kept for the next walk
        _WALKER.unpacker = unpacker
    return not whole


def _unpackb(payload: Payload, limits: Limits) -> tuple[Any, tuple[str, str] | None]:
    """(object, None) or (None, (cause, text)): the refusal is returned, not raised, so that no exception of
    msgpack's (and no frame holding the payload) is chained to the caller's WireError. A payload that is not one
    whole msgpack object is refused before anything is built (``_incomplete``). Entries and containers are counted
    only in payloads larger than their limits: a smaller one cannot hold more (each takes a byte at least), and the
    common small message pays nothing for the count."""
    if _incomplete(payload, limits):
        return None, ("not-msgpack", "payload is not one whole msgpack object (cut short, too deep or trailing data)")
    small = len(payload) <= min(limits.items, limits.containers or limits.items)
    hooks = {} if small else dict.fromkeys(("list_hook", "object_hook"), _counter(limits))
    try:
        value = msgpack.unpackb(
            payload,
            raw=False,
            strict_map_key=True,
            max_str_len=limits.text,
            max_bin_len=limits.binary,
            max_array_len=min(limits.array, len(payload)),  # a whole payload has a byte per entry at least
            max_map_len=limits.map,
            max_ext_len=0,
            **hooks,
        )
    except _TooManyItemsError:
        most = f"{limits.items} entries or {limits.containers or limits.items} arrays and maps"
        return None, ("oversized", f"payload holds more than {most}")
    except ValueError as exc:
        text = str(exc)
        if " exceeds max_" in text:  # msgpack's own limits: "N exceeds max_array_len(M)"
            return None, ("oversized", f"payload holds a string, bin, array or map too long for its kind: {text}")
        return None, ("not-msgpack", f"payload is not msgpack: {type(exc).__name__}")
    except Exception as exc:  # msgpack raises several unrelated types for garbage
        return None, ("not-msgpack", f"payload is not msgpack: {type(exc).__name__}")
    return value, None


def unpack(payload: Payload, limits: Limits = ANY_LIMITS) -> dict[str, Any]:
    """The map inside ``payload``, unpacked within ``limits`` (the kind's, ``ANY_LIMITS`` when unsaid); WireError
    when oversized, not msgpack, not a map or of another version. The error holds no reference to the payload or
    to what was unpacked (no traceback, no chained exception): a refused bomb is freed at once."""
    size = len(payload)
    if size > limits.payload_bytes:
        raise WireError("oversized", f"payload of {size} bytes exceeds {limits.payload_bytes}")
    message, problem = _unpackb(payload, limits)
    if problem is not None:
        raise WireError(*problem)
    if type(message) is not dict:
        kind = type(message).__name__
        del message
        raise WireError("not-a-map", f"payload is a msgpack {kind}, not a map")
    check_version(message)
    return message


def detached(exc: WireError) -> WireError:
    """``exc`` without traceback or chained exception: safe to keep (in a list of refusals, a counter) without
    keeping the frames, payloads and unpacked objects of the decoding alive (nor a reference cycle through them)."""
    exc.__context__ = exc.__cause__ = None
    return exc.with_traceback(None)


def check_version(message: Mapping[str, Any]) -> int:
    """The message's version: WireError ``wrong-version`` unless ``message['v']`` is one of ``VERSIONS``."""
    version = message.get("v")
    if type(version) is not int or version not in VERSIONS:
        raise WireError("wrong-version", f"schema version {version!r}, expected one of {VERSIONS}")
    return version


def binary_message(message: Mapping[str, Any]) -> bool:
    """Whether an unpacked (version-checked) message is v 2."""
    return message["v"] == BINARY_ARRAYS_VERSION


def plain(value: Any) -> Any:
    """``value`` with every v 2 array map replaced by its values as lists (for JSON printing); unusable array maps
    are left as they are."""
    if isinstance(value, dict):
        if set(value) == {"dtype", "shape", "data"}:
            try:
                shape = value["shape"]
                arr = np.frombuffer(value["data"], dtype=np.dtype(value["dtype"])).reshape(shape)
                return arr.tolist()
            except (TypeError, ValueError):
                return value
        return {k: plain(v) for k, v in value.items()}
    if isinstance(value, list):
        return [plain(v) for v in value]
    return value


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
