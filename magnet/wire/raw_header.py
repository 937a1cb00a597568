"""The structure checks of one unpacked raw message (either version), before any number is looked at.

Besides the shapes: ``seq`` within 0..2**63 - 1 (cause ``out-of-range``), ``sensor`` text of at most
``MAX_SENSOR_CHARS`` (``bad-field``), at most ``MAX_EXTRA_FIELDS`` fields beyond ``RAW_FIELDS`` (room for later
fields, no flood: ``too-many-fields``), and a payload no larger than its samples can need (``oversized``).

The optional per-sample scalars (``SCALAR_FIELDS``: ``current_a``, ``throttle``) are few and small, so they are checked
here in full, message by message: N numbers (no booleans), NaN where not known at that sample, never infinite
(``non-finite``), within their range (``absurd-magnitude``).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, NamedTuple

import numpy as np

from magnet.wire.arrays import FLOAT_DTYPES, INT64_MAX, TIME_DTYPES, check_bin, from_bins, numbers
from magnet.wire.codec import MAX_BATCH_SAMPLES, Limits, binary_message, int_field
from magnet.wire.errors import WireError
from magnet.wire.keys import MAX_DEVICE_ID_CHARS, message_device
from magnet.wire.raw import MAX_HARDWARE_ID, SCALAR_FIELDS, TRUTH_FIELDS, VECTOR_FIELDS

#: the fields a raw message may carry; others are ignored, up to MAX_EXTRA_FIELDS of them
RAW_FIELDS = frozenset(
    {"v", "device", "seq", "sensor", "t_ns", "mag_ut", "acc_ms2", "gyr_rads", "vel_ned_ms", "truth", "location"}
    | {"vehicle", "hardware_id"}
    | {name for name, _, _ in SCALAR_FIELDS}
)
MAX_EXTRA_FIELDS = 32
MAX_SENSOR_CHARS = 64
#: a raw payload of N samples holds at most MAX_HEADER_BYTES + N * MAX_BYTES_PER_SAMPLE bytes: the widest honest
#: encoding (v 1, float64 everywhere, with the simulator's truth) needs about 125 bytes a sample
MAX_BYTES_PER_SAMPLE = 256
MAX_HEADER_BYTES = 16 * 1024
#: what msgpack may build of one raw payload (``codec.Limits``), from the message's own maxima: the payload its
#: samples can need; arrays of at most MAX_BATCH_SAMPLES entries (t_ns, rows); maps of the raw fields and the extra
#: ones; strings of a device id or sensor (4 bytes a character at most in UTF-8); a v 2 array of N rows of 3 float64;
#: in all the entries of a v 1 message of N samples: N times, 4 per row of each vector field, 1 per truth figure
#: (about 20 a sample), plus room for the header; and its arrays and maps: a row of each vector field a sample, plus
#: the few of the header and the v 2 array maps
MAX_ITEMS_PER_SAMPLE = 1 + 4 * len(VECTOR_FIELDS) + len(TRUTH_FIELDS)
RAW_LIMITS = Limits(
    payload_bytes=MAX_HEADER_BYTES + MAX_BATCH_SAMPLES * MAX_BYTES_PER_SAMPLE,
    array=MAX_BATCH_SAMPLES,
    map=len(RAW_FIELDS) + MAX_EXTRA_FIELDS,
    text=4 * max(MAX_DEVICE_ID_CHARS, MAX_SENSOR_CHARS),
    binary=MAX_BATCH_SAMPLES * 3 * 8,
    items=MAX_BATCH_SAMPLES * MAX_ITEMS_PER_SAMPLE + 1024,
    containers=MAX_BATCH_SAMPLES * len(VECTOR_FIELDS) + 64,
)


class Header(NamedTuple):
    """The structure of one raw message, checked: its device, seq, sensor, sample count, optional fields present,
    and its arrays: lists (v 1) or checked ``Bin`` (v 2), t_ns first then one per VECTOR_FIELDS entry (None where
    absent); scalars: one checked float64 (N,) array per SCALAR_FIELDS entry, or None where absent."""

    device: str
    seq: int
    sensor: str
    n: int
    present: tuple[bool, ...]  # per VECTOR_FIELDS entry
    arrays: tuple[Any, ...]
    scalars: tuple[np.ndarray | None, ...] = ()
    vehicle: str = ""
    hardware_id: int = 0


def check_header(message: Mapping[str, Any], size: int | None = None) -> Header:
    """Check the structure of one unpacked raw message (either version) of ``size`` bytes (None: unknown); WireError
    with the cause otherwise."""
    device = message_device(message)
    if len(message) > MAX_EXTRA_FIELDS:
        extra = sum(name not in RAW_FIELDS for name in message)
        if extra > MAX_EXTRA_FIELDS:
            raise WireError("too-many-fields", f"{extra} unknown fields, more than {MAX_EXTRA_FIELDS}")
    sensor = message.get("sensor", "")
    if type(sensor) is not str or len(sensor) > MAX_SENSOR_CHARS:
        raise WireError("bad-field", f"sensor must be a string of at most {MAX_SENSOR_CHARS} characters")
    vehicle = message.get("vehicle", "")
    if type(vehicle) is not str or len(vehicle) > MAX_DEVICE_ID_CHARS:
        raise WireError("bad-field", f"vehicle must be a string of at most {MAX_DEVICE_ID_CHARS} characters")
    hardware_id = int_field(message, "hardware_id", 0)
    if not 0 <= hardware_id <= MAX_HARDWARE_ID:
        raise WireError("out-of-range", f"hardware_id must be within 0..{MAX_HARDWARE_ID}, got {hardware_id}")
    seq = int_field(message, "seq", 0)
    if not 0 <= seq <= INT64_MAX:
        raise WireError("out-of-range", f"seq must be within 0..{INT64_MAX}, got {seq}")
    n, arrays = _arrays(message)
    if size is not None and size > MAX_HEADER_BYTES + n * MAX_BYTES_PER_SAMPLE:
        raise WireError("oversized", f"payload of {size} bytes is more than {n} samples can need")
    # (lists, not generators, and no call for an absent scalar: a few us a message in the compass's decode)
    scalars = tuple(
        [None if name not in message else _scalar(message, name, lo, hi, n) for name, lo, hi in SCALAR_FIELDS]
    )
    present = tuple([a is not None for a in arrays[1:]])
    return Header(device, seq, sensor, n, present, tuple(arrays), scalars, vehicle, hardware_id)


def _scalar(message: Mapping[str, Any], name: str, low: float, high: float, n: int) -> np.ndarray | None:
    """The optional (N,) scalar ``name`` of a message as float64, checked; None when absent; WireError otherwise."""
    value = message.get(name)
    if value is None:
        return None
    if binary_message(message):
        arr = from_bins([check_bin(value, name, FLOAT_DTYPES, (), n)], (), "f8")
    elif type(value) is not list or len(value) != n:
        raise WireError("bad-shape", f"{name} must be a list of N = len(t_ns) = {n} numbers")
    else:
        arr = numbers(value, name)
    if np.isinf(arr).any():  # NaN: not known at that sample (as vel_ned_ms's NaN rows)
        raise WireError("non-finite", f"{name} holds infinite values")
    known = arr[~np.isnan(arr)]
    if known.size and (known.min() < low or known.max() > high):
        raise WireError("absurd-magnitude", f"{name} holds values outside [{low:g}, {high:g}]")
    return arr


def _arrays(message: Mapping[str, Any]) -> tuple[int, list[Any]]:
    """The sample count N and the arrays of one message (t_ns, then one per VECTOR_FIELDS entry, None where
    absent), their shapes checked; WireError otherwise."""
    binary = binary_message(message)
    t_ns = message.get("t_ns")
    if binary:
        t_ns = check_bin(t_ns, "t_ns", TIME_DTYPES, ())
        n = t_ns.rows
    elif type(t_ns) is not list:
        raise WireError("bad-shape", "t_ns must be a list of integers")
    else:
        n = len(t_ns)
    if n > MAX_BATCH_SAMPLES:
        raise WireError("oversized", f"t_ns holds {n} samples, more than {MAX_BATCH_SAMPLES}")
    if n == 0:
        raise WireError("empty", "a raw batch holds no samples")
    arrays: list[Any] = [t_ns]
    for name, _, required in VECTOR_FIELDS:
        value = message.get(name)
        if value is None and not required:
            arrays.append(None)
        elif binary:
            arrays.append(check_bin(value, name, FLOAT_DTYPES, (3,), n))
        elif type(value) is not list or len(value) != n:
            raise WireError("bad-shape", f"{name} must be a list of N = len(t_ns) = {n} [x, y, z] rows")
        else:
            arrays.append(value)
    return n, arrays
