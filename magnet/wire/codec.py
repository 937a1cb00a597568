"""msgpack framing shared by every message: versions, size limits, binary arrays (v 2), and the checks of single
fields.

Two versions of the sample messages (raw, heading) are read; v 2 is written:

- v 1: every array is msgpack lists of numbers (``"mag_ut": [[21.3, -4.1, 44.0], ...]``);
- v 2: every array is one map ``{"dtype": "<f4", "shape": [N, 3], "data": <bin: N*3*4 bytes, little-endian,
  row-major>}`` (``Bin``), turned into numpy with ``np.frombuffer``, no per-number work. ``dtype`` is a numpy
  little-endian type string: times ``<i8`` only; measured and computed values ``<f4`` (written) or ``<f8``; flags
  ``<u1 <u2 <u4 <i4 <i8`` (``<u2`` written). Anything else (another dtype, a shape that is not [N] or [N, k] as the
  field needs, a byte count that is not N*k*itemsize) is refused with a ``WireError`` like any malformed v 1 array.

The records (calibration, history, progress, status, calibrate replies) carry no sample arrays and are the same in
both versions (``RECORD_VERSION`` 1, also their JSON form in files and the store); readers accept either number.
"""

from __future__ import annotations

import io
import itertools
import math
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
PREALLOCATION_BYTES = 1024 * 1024
#: the walk reads the payload this much at a time (it holds about this much, not a copy of the payload)
SKIP_READ_BYTES = 64 * 1024


def _incomplete(payload: Payload, limits: Limits) -> bool:
    """Whether ``payload`` is not one whole msgpack object, found by walking it without building anything
    (``Unpacker.skip``, in C). msgpack sets aside an array's slots (8 bytes each, up to about 10,000) when it meets
    the array's header, before its entries: a few kB of nested headers that declare long arrays and are then cut
    short would make it set aside about 80 kB per level, up to MSGPACK_DEPTH levels (80 MB for 5 kB), only to fail.
    In a whole payload every declared entry takes a byte at least, so what is set aside is at most 8 bytes per byte
    of payload. Skipped (free) when even the worst cut-short payload of this size stays within
    PREALLOCATION_BYTES."""
    if min(len(payload), MSGPACK_DEPTH) * 8 * limits.array <= PREALLOCATION_BYTES:
        return False
    size = len(payload)
    unpacker = msgpack.Unpacker(io.BytesIO(payload), read_size=min(size, SKIP_READ_BYTES), max_buffer_size=size)
    try:
        unpacker.skip()
    except Exception:  # OutOfData (cut short), StackError (too deep), FormatError ...: msgpack's verdict follows
        return True
    return unpacker.tell() != size


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
            max_array_len=limits.array,
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


# ------------------------------------------------------------------------------------------- binary arrays (v 2)

#: the dtypes a v 2 array may carry, by kind of field (numpy little-endian type strings)
TIME_DTYPES: dict[str, np.dtype[Any]] = {"<i8": np.dtype("<i8")}
FLOAT_DTYPES: dict[str, np.dtype[Any]] = {"<f4": np.dtype("<f4"), "<f8": np.dtype("<f8")}
FLAG_DTYPES: dict[str, np.dtype[Any]] = {name: np.dtype(name) for name in ("<u1", "<u2", "<u4", "<i4", "<i8")}
#: what v 2 writes, by kind of field
TIME_DTYPE, FLOAT_DTYPE, FLAG_DTYPE = "<i8", "<f4", "<u2"


class Bin(NamedTuple):
    """A checked v 2 array: its dtype, its number of rows (shape[0]) and its bytes."""

    dtype: np.dtype
    rows: int
    data: bytes


def bin_array(values: Any, dtype: str) -> dict[str, Any]:
    """The v 2 map of an array: ``{"dtype", "shape", "data"}`` with the values cast to ``dtype``."""
    arr = np.ascontiguousarray(values, dtype=dtype)
    return {"dtype": dtype, "shape": list(arr.shape), "data": arr.tobytes()}


def check_bin(
    value: Any, name: str, dtypes: Mapping[str, np.dtype], tail: tuple[int, ...], rows: int | None = None
) -> Bin:
    """Check a v 2 array map of shape (N, *tail) (tail () or (k,)), N <= MAX_BATCH_SAMPLES (and N == ``rows`` when
    given), one of ``dtypes``, with exactly N * prod(tail) * itemsize bytes; WireError (``bad-shape``, ``bad-dtype``,
    ``oversized``) otherwise. Values are not looked at (see ``from_bins``). The hot path of a busy consumer: a few
    type and size comparisons, nothing per number."""
    try:
        dtype = dtypes[value["dtype"]]
        shape, data = value["shape"], value["data"]
        n = shape[0]
        if (
            type(shape) is list
            and type(n) is int
            and len(shape) == 1 + len(tail)
            and tuple(shape[1:]) == tail
            and 0 <= n <= MAX_BATCH_SAMPLES
            and (rows is None or n == rows)
            and type(data) is bytes
            and len(data) == n * dtype.itemsize * (tail[0] if tail else 1)
        ):
            return Bin(dtype, n, data)
    except (TypeError, KeyError, IndexError):
        pass
    raise _bin_error(value, name, dtypes, tail, rows)


def _bin_error(
    value: Any, name: str, dtypes: Mapping[str, np.dtype], tail: tuple[int, ...], rows: int | None
) -> WireError:
    """Why ``check_bin`` refused ``value``."""
    if type(value) is not dict:
        return WireError("bad-shape", f"{name} must be a map {{dtype, shape, data}} in v {BINARY_ARRAYS_VERSION}")
    dtype_name, shape, data = value.get("dtype"), value.get("shape"), value.get("data")
    dtype = dtypes.get(dtype_name) if type(dtype_name) is str else None
    if dtype is None:
        return WireError("bad-dtype", f"{name} has dtype {dtype_name!r}, expected one of {', '.join(dtypes)}")
    if (
        type(shape) is not list
        or len(shape) != 1 + len(tail)
        or any(type(s) is not int for s in shape)
        or tuple(shape[1:]) != tail
        or shape[0] < 0
    ):
        return WireError("bad-shape", f"{name} has shape {shape!r}, expected [N{''.join(f', {t}' for t in tail)}]")
    if shape[0] > MAX_BATCH_SAMPLES:
        return WireError("oversized", f"{name} holds {shape[0]} samples, more than {MAX_BATCH_SAMPLES}")
    if rows is not None and shape[0] != rows:
        return WireError("bad-shape", f"{name} holds {shape[0]} samples but t_ns holds {rows}")
    size = len(data) if type(data) is bytes else type(data).__name__
    expected = shape[0] * math.prod(tail) * dtype.itemsize
    return WireError("bad-shape", f"{name} data holds {size} bytes; dtype and shape say {expected}")


def from_bins(bins: list[Bin], tail: tuple[int, ...], out: str) -> np.ndarray:
    """The rows of checked ``bins`` one after the other as one ``out`` array (S, *tail): their bytes joined and read
    with ``np.frombuffer`` (one join per run of the same dtype)."""
    parts, start = [], 0
    for i in range(1, len(bins) + 1):
        if i == len(bins) or bins[i].dtype != bins[start].dtype:
            joined = b"".join(b.data for b in bins[start:i]) if i - start > 1 else bins[start].data
            parts.append(np.frombuffer(joined, dtype=bins[start].dtype))
            start = i
    flat = parts[0] if len(parts) == 1 else np.concatenate(parts) if parts else np.empty(0)
    return flat.astype(out).reshape(-1, *tail)


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


# ------------------------------------------------------------------------- the array checks (both versions)

#: the Python types msgpack gives numbers as: a boolean is not a number here, nor a string (numpy would read true
#: as 1 and "1e3" as 1000)
NUMBER_TYPES = frozenset({int, float})
INTEGER_TYPES = frozenset({int})
#: the largest integer of an int64 array (t_ns, seq)
INT64_MAX = 2**63 - 1


def _shape_text(tail: tuple[int, ...]) -> str:
    return f"(N{''.join(f', {k}' for k in tail)})"


def _only(values: Any, name: str, rows: bool, types: frozenset[type], what: str) -> None:
    """WireError ``bad-shape`` unless every one of v 1 ``values`` (or of their rows' entries, ``rows``) is of
    ``types``. One pass in C (``map(type, ...)``), no per-number Python; call it once the values form an array."""
    found = set(map(type, itertools.chain.from_iterable(values) if rows else values))
    if not found <= types:
        odd = "true/false" if bool in found else ", ".join(sorted(t.__name__ for t in found - types))
        raise WireError("bad-shape", f"{name} holds {odd} where {what} belong")


def numbers(values: Any, name: str, tail: tuple[int, ...] = ()) -> np.ndarray:
    """The one conversion of a v 1 array of numbers: lists (N numbers, or N rows of ``tail[0]`` numbers) -> float64
    (N, *tail); WireError ``bad-shape`` when they are not of that shape or not all numbers. The raw decoder passes
    the rows of many messages at once."""
    try:
        arr = np.array(values, dtype=np.float64)
    except (TypeError, ValueError, OverflowError):
        raise WireError("bad-shape", f"{name} is not an array of numbers of shape {_shape_text(tail)}") from None
    if arr.ndim != 1 + len(tail) or arr.shape[1:] != tail:
        raise WireError("bad-shape", f"{name} has shape {arr.shape}, expected {_shape_text(tail)}")
    _only(values, name, bool(tail), NUMBER_TYPES, "numbers")
    return arr


def integers(values: Any, name: str) -> np.ndarray:
    """The one conversion of a v 1 array of integers: a list -> int64 (N,); WireError ``out-of-range`` for integers
    beyond int64 (they would wrap), ``bad-shape`` for anything else that is not a list of integers."""
    try:
        arr = np.array(values)
    except (TypeError, ValueError, OverflowError):
        raise WireError("bad-shape", f"{name} is not an array of integers") from None
    kind = arr.dtype.kind
    if arr.ndim == 1 and (not arr.size or kind == "i" or (kind == "u" and arr.max() <= INT64_MAX)):
        _only(values, name, False, INTEGER_TYPES, "integers")
        return arr.astype(np.int64)
    if arr.ndim == 1 and all(type(x) is int for x in values):
        raise WireError("out-of-range", f"{name} holds values beyond {INT64_MAX}")
    raise WireError("bad-shape", f"{name} must be a list of integers, got shape {arr.shape} dtype {arr.dtype}")


def value_faults(
    arr: np.ndarray, name: str, limit: float | None, absent_rows: bool = False
) -> list[tuple[np.ndarray, str, str]]:
    """The one check of the values of a float array (N,) or (N, k), per sample: (bad (N,) bool, cause, text) for
    non-finite values, then (when ``limit``) for values beyond +-limit. ``absent_rows``: a row that is all NaN is a
    value not known at that sample (raw ``vel_ned_ms``, absent fields), not a fault."""
    finite = np.isfinite(arr) if arr.ndim == 1 else np.isfinite(arr).all(axis=1)
    if absent_rows:
        finite |= np.isnan(arr) if arr.ndim == 1 else np.isnan(arr).all(axis=1)
    faults = [(~finite, "non-finite", f"{name} holds non-finite values")]
    if limit is not None:
        with np.errstate(invalid="ignore"):
            beyond = np.abs(arr) > limit
        faults.append(
            (
                beyond if arr.ndim == 1 else beyond.any(axis=1),
                "absurd-magnitude",
                f"{name} holds values beyond +-{limit:g}",
            )
        )
    return faults


def check_floats(arr: np.ndarray, name: str, limit: float | None) -> np.ndarray:
    """``arr`` if every value is finite and within +-limit (``value_faults``); WireError with the first fault."""
    for bad, cause, text in value_faults(arr, name, limit):
        if bad.any():
            raise WireError(cause, text)
    return arr


def _at_most_a_batch(arr: np.ndarray, name: str) -> np.ndarray:
    if arr.shape[0] > MAX_BATCH_SAMPLES:
        raise WireError("oversized", f"{name} holds {arr.shape[0]} samples, more than {MAX_BATCH_SAMPLES}")
    return arr


def float_array(
    value: Any, name: str, shape_tail: tuple[int, ...], limit: float | None, binary: bool = False
) -> np.ndarray:
    """One message's float64 array of shape (N, *shape_tail), N <= MAX_BATCH_SAMPLES, finite, |x| <= limit; else
    WireError. ``value``: lists (v 1, ``numbers``) or, ``binary``, a v 2 array map (``check_bin``)."""
    if binary:
        arr = from_bins([check_bin(value, name, FLOAT_DTYPES, shape_tail)], shape_tail, "f8")
    else:
        arr = _at_most_a_batch(numbers(value, name, shape_tail), name)
    return check_floats(arr, name, limit)


def int_array(value: Any, name: str, binary: bool = False, dtypes: Mapping[str, np.dtype] = TIME_DTYPES) -> np.ndarray:
    """One message's int64 array (N,) from a list of integers (v 1, ``integers``) or, ``binary``, a v 2 array map
    of one of ``dtypes``, N <= MAX_BATCH_SAMPLES; else WireError."""
    if binary:
        return from_bins([check_bin(value, name, dtypes, ())], (), "i8")
    return _at_most_a_batch(integers(value, name), name)


def check_lengths(n: int, arrays: Mapping[str, np.ndarray]) -> None:
    """WireError ``bad-shape`` unless every array holds ``n`` samples."""
    for name, arr in arrays.items():
        if arr.shape[0] != n:
            raise WireError("bad-shape", f"{name} holds {arr.shape[0]} samples but t_ns holds {n}")
