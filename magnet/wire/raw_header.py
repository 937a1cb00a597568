"""The structure checks of one unpacked raw message (either version), before any number is looked at."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, NamedTuple

from magnet.wire.codec import FLOAT_DTYPES, MAX_BATCH_SAMPLES, TIME_DTYPES, binary_message, check_bin, int_field
from magnet.wire.errors import WireError
from magnet.wire.keys import message_device
from magnet.wire.raw import VECTOR_FIELDS


class Header(NamedTuple):
    """The structure of one raw message, checked: its device, seq, sensor, sample count, optional fields present,
    and its arrays: lists (v 1) or checked ``Bin`` (v 2), t_ns first then one per VECTOR_FIELDS entry (None where
    absent)."""

    device: str
    seq: int
    sensor: str
    n: int
    present: tuple[bool, ...]  # per VECTOR_FIELDS entry
    arrays: tuple[Any, ...]


def check_header(message: Mapping[str, Any]) -> Header:
    """Check the structure of one unpacked raw message (either version); WireError with the cause otherwise."""
    device = message_device(message)
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
    sensor = message.get("sensor", "")
    if type(sensor) is not str:
        raise WireError("bad-field", "sensor must be a string")
    return Header(
        device, int_field(message, "seq", 0), sensor, n, tuple(a is not None for a in arrays[1:]), tuple(arrays)
    )
