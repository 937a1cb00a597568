"""CDR bytes of the fixed-shape stamped messages magnet publishes per sample, built for many samples at once.

A ``std_msgs/msg/Header`` followed only by float64 values (MagneticField: 12, Imu: 37) has one layout per frame id
(XCDR1, little-endian): the encapsulation header ``00 01 00 00``; then, counted from the byte after it, the stamp's
int32 seconds and uint32 nanoseconds, the frame id as a uint32 length (with its terminating NUL), its bytes and the
NUL, zero padding up to a multiple of 8, and the doubles. So a whole batch is one numpy record array turned into
bytes and cut per sample, the same bytes rosbags' serialiser gives for each message
(``tests/magnet/ros2/test_ros2_core.py``).
"""

from __future__ import annotations

import functools
from typing import Any

import numpy as np

__all__ = ["stamped_doubles_cdr"]

_ENCAPSULATION = b"\x00\x01\x00\x00"  # CDR, little-endian


@functools.lru_cache(maxsize=1024)  # one entry per frame id (a device) and width: bounded, least recent forgotten
def _layout(name: bytes, width: int) -> tuple[np.dtype[Any], bytes]:
    """The record layout of one message with frame id ``name`` (NUL included) and ``width`` doubles, and the bytes
    of the frame id field (the name and the padding)."""
    padding = -(len(name) + 12) % 8  # sec, nanosec, length, the name with its NUL
    field = name + b"\x00" * padding
    layout = np.dtype(
        [
            ("enc", "V4"),
            ("sec", "<i4"),
            ("nanosec", "<u4"),
            ("length", "<u4"),
            ("name", f"V{len(field)}"),
            ("values", "<f8", (width,)),
        ]
    )
    return layout, field


def stamped_doubles_cdr(t_ns: np.ndarray, frame_id: str, values: np.ndarray) -> list[bytes]:
    """One message per row: t_ns (S,) ns since the epoch (up to 2038: int32 seconds), ``frame_id``, values (S, K)
    float64 in the message's field order."""
    values = np.asarray(values, dtype="<f8")
    count, width = values.shape
    name = frame_id.encode() + b"\x00"
    layout, field = _layout(name, width)
    rows = np.empty(count, dtype=layout)
    rows["enc"] = np.frombuffer(_ENCAPSULATION, dtype="V4")[0]
    sec, nanosec = np.divmod(np.asarray(t_ns, dtype=np.int64), 1_000_000_000)
    rows["sec"], rows["nanosec"], rows["length"] = sec, nanosec, len(name)
    rows["name"] = np.frombuffer(field, dtype=f"V{len(field)}")[0]
    rows["values"] = values
    data, size = rows.tobytes(), layout.itemsize
    return [data[i * size : (i + 1) * size] for i in range(count)]
