"""The one set of array checks of the wire, both versions: v 2 binary array maps (``check_bin``, ``from_bins``)
and v 1 lists (``numbers``, ``integers``), then the values of any float array (``value_faults``, ``check_floats``).
The raw decoder applies them to the rows of many messages at once, the heading decoder to one message
(``float_array``, ``int_array``); both give the same causes (``bad-shape``, ``bad-dtype``, ``oversized``,
``out-of-range``, ``non-finite``, ``absurd-magnitude``).

v 2 arrays: every array is one map ``{"dtype": "<f4", "shape": [N, 3], "data": <bin: N*3*4 bytes, little-endian,
row-major>}`` (``Bin``), turned into numpy with ``np.frombuffer``, no per-number work. ``dtype`` is a numpy
little-endian type string: times ``<i8`` only; measured and computed values ``<f4`` (written) or ``<f8``; flags
``<u1 <u2 <u4 <i4 <i8`` (``<u2`` written).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Mapping
from typing import Any, NamedTuple

import numpy as np

from magnet import _kernels
from magnet.wire.codec import BINARY_ARRAYS_VERSION, MAX_BATCH_SAMPLES
from magnet.wire.errors import WireError

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
    if len({b.dtype for b in bins}) == 1:  # one dtype throughout (the usual case): one join
        joined = b"".join([b.data for b in bins]) if len(bins) > 1 else bins[0].data
        return np.frombuffer(joined, dtype=bins[0].dtype).astype(out).reshape(-1, *tail)
    parts, start = [], 0
    for i in range(1, len(bins) + 1):
        if i == len(bins) or bins[i].dtype != bins[start].dtype:
            joined = b"".join(b.data for b in bins[start:i]) if i - start > 1 else bins[start].data
            parts.append(np.frombuffer(joined, dtype=bins[start].dtype))
            start = i
    flat = parts[0] if len(parts) == 1 else np.concatenate(parts) if parts else np.empty(0)
    return flat.astype(out).reshape(-1, *tail)


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
    values = np.asarray(arr, dtype=float)
    rows = values.reshape(-1, 1) if values.ndim == 1 else values.reshape(len(values), -1)
    nonfinite, beyond = np.empty(len(rows), dtype=bool), np.empty(len(rows), dtype=bool)
    _kernels.row_faults(rows, math.inf if limit is None else float(limit), absent_rows, nonfinite, beyond)  # one pass
    faults = [(nonfinite, "non-finite", f"{name} holds non-finite values")]
    if limit is not None:
        faults.append((beyond, "absurd-magnitude", f"{name} holds values beyond +-{limit:g}"))
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
