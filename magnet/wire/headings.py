"""Headings: ``HeadingBatch`` and the one heading encoder (many batches at once; one batch is the case B = 1).

Message: ``{v, device, seq, t_ns: [N], heading_deg: [N] (magnetic), true_heading_deg: [N], pitch_deg: [N],
roll_deg: [N], field_ut: [[x, y, z]] * N, declination_deg, calibration_id, flags: [N ints],
quat_wxyz: [[w, x, y, z]] * N (optional: attitude, body to NED, unit quaternion)}``.

``flags`` holds ``magnet.heading.HeadingFlag`` bits; the per-sample magnetic disturbance flag is its
FIELD_DISTURBED (|B| away from the expected field) and DIP_DISTURBED (dip away from the expected inclination) bits,
``DISTURBED`` for either.
"""

from __future__ import annotations

import dataclasses
import itertools
from typing import Any
from collections.abc import Sequence

import msgpack
import numpy as np

from magnet.heading import HeadingFlag
from magnet.wire.codec import Payload, WIRE_VERSION, check_lengths, float_array, int_array, int_field, number_field
from magnet.wire.codec import unpack
from magnet.wire.errors import WireError
from magnet.wire.keys import message_device
from magnet.wire.raw import RawColumns

ANGLE_FIELDS = ("heading_deg", "true_heading_deg", "pitch_deg", "roll_deg")
#: flags bits that mark a sample's field as magnetically disturbed
DISTURBED = int(HeadingFlag.FIELD_DISTURBED | HeadingFlag.DIP_DISTURBED)
#: a quaternion on the wire must have a norm within this of 1
QUAT_NORM_TOLERANCE = 0.01


@dataclasses.dataclass(frozen=True, eq=False)
class HeadingBatch:
    """N headings of one device, aligned with one raw batch. Angles in degrees, field_ut (N, 3) corrected uT,
    flags (N,) ``magnet.heading.HeadingFlag`` bits, declination_deg east-positive, quat_wxyz (N, 4) attitude (body
    to NED) or None."""

    device: str
    seq: int
    t_ns: np.ndarray
    heading_deg: np.ndarray
    true_heading_deg: np.ndarray
    pitch_deg: np.ndarray
    roll_deg: np.ndarray
    field_ut: np.ndarray
    declination_deg: float
    calibration_id: str
    flags: np.ndarray
    quat_wxyz: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.t_ns.shape[0])

    @property
    def disturbed(self) -> np.ndarray:
        """(N,) bool: the field of the sample is magnetically disturbed (|B| or dip away from the reference)."""
        return (np.asarray(self.flags, dtype=np.int64) & DISTURBED) != 0


def encode_headings(columns: RawColumns, heading_deg: np.ndarray, true_heading_deg: np.ndarray,
                    pitch_deg: np.ndarray, roll_deg: np.ndarray, field_ut: np.ndarray, flags: np.ndarray,
                    declination_deg: float | Sequence[float], calibration_ids: Sequence[str],
                    quat_wxyz: np.ndarray | None = None) -> list[bytes]:
    """One heading message per batch of ``columns`` (the one heading encoder).

    The arrays are aligned with ``columns``' S samples (angles (S,) deg, field_ut (S, 3) uT, flags (S,) int,
    quat_wxyz (S, 4) or None); each is turned into Python lists once and sliced per batch. A batch whose quaternion
    rows are not all finite carries no ``quat_wxyz``. ``declination_deg``: one for all, or one per batch (each
    device's place)."""
    return _encode(columns.devices, columns.seqs, columns.bounds, columns.t_ns,
                   (heading_deg, true_heading_deg, pitch_deg, roll_deg), field_ut, flags, declination_deg,
                   calibration_ids, quat_wxyz)


def encode_heading(batch: HeadingBatch) -> bytes:
    """The message of one batch: ``encode_headings`` of B = 1."""
    angles = tuple(getattr(batch, name) for name in ANGLE_FIELDS)
    return _encode([batch.device], [batch.seq], [0, len(batch)], batch.t_ns, angles, batch.field_ut, batch.flags,
                   batch.declination_deg, [batch.calibration_id], batch.quat_wxyz)[0]


def _encode(devices: Sequence[str], seqs: Sequence[int], bounds: Sequence[int], t_ns: np.ndarray,
            angles: tuple[np.ndarray, ...], field_ut: np.ndarray, flags: np.ndarray,
            declination_deg: float | Sequence[float],
            calibration_ids: Sequence[str], quat_wxyz: np.ndarray | None) -> list[bytes]:
    times = np.asarray(t_ns, dtype=np.int64).tolist()
    angle_lists = [np.asarray(a, dtype=float).tolist() for a in angles]
    field = np.asarray(field_ut, dtype=float).tolist()
    flag = np.asarray(flags, dtype=np.int64).tolist()
    quat, quat_ok = _quaternions(quat_wxyz, bounds)
    declinations = (np.broadcast_to(np.asarray(declination_deg, dtype=float), (len(devices),))).tolist()
    out = []
    for i, (device, seq, cal_id, declination) in enumerate(zip(devices, seqs, calibration_ids, declinations)):
        lo, hi = bounds[i], bounds[i + 1]
        message: dict[str, Any] = {"v": WIRE_VERSION, "device": device, "seq": int(seq), "t_ns": times[lo:hi]}
        message.update((name, values[lo:hi]) for name, values in zip(ANGLE_FIELDS, angle_lists))
        message.update(field_ut=field[lo:hi], declination_deg=declination, calibration_id=cal_id, flags=flag[lo:hi])
        if quat_ok[i]:
            message["quat_wxyz"] = quat[lo:hi]
        out.append(msgpack.packb(message, use_bin_type=True))
    return out


def _quaternions(quat_wxyz: np.ndarray | None, bounds: Sequence[int]) -> tuple[list[Any], list[bool]]:
    """Quaternion rows as lists and, per batch, whether all its rows are finite."""
    if quat_wxyz is None:
        return [], [False] * (len(bounds) - 1)
    quat = np.asarray(quat_wxyz, dtype=float)
    finite = np.isfinite(quat).all(axis=1)
    ok = [bool(finite[lo:hi].all()) for lo, hi in itertools.pairwise(bounds)]
    return quat.tolist(), ok


def decode_heading(payload: Payload) -> HeadingBatch:
    """HeadingBatch from a payload; WireError (with ``cause``) for anything malformed."""
    message = unpack(payload)
    device = message_device(message)
    t_ns = int_array(message.get("t_ns"), "t_ns")
    angles = {name: float_array(message.get(name), name, (), 1e4) for name in ANGLE_FIELDS}
    field = float_array(message.get("field_ut"), "field_ut", (3,), None)
    flags = int_array(message.get("flags"), "flags")
    quat = _decode_quaternions(message.get("quat_wxyz"))
    check_lengths(t_ns.shape[0], {**angles, "field_ut": field, "flags": flags,
                                  **({} if quat is None else {"quat_wxyz": quat})})
    return HeadingBatch(device, int_field(message, "seq", 0), t_ns, field_ut=field, flags=flags,
                        declination_deg=number_field(message, "declination_deg", 0.0),
                        calibration_id=str(message.get("calibration_id", "")), quat_wxyz=quat, **angles)


def _decode_quaternions(value: Any) -> np.ndarray | None:
    if value is None:
        return None
    quat = float_array(value, "quat_wxyz", (4,), 1.0 + QUAT_NORM_TOLERANCE)
    if quat.size and (np.abs(np.linalg.norm(quat, axis=1) - 1.0) > QUAT_NORM_TOLERANCE).any():
        raise WireError("absurd-magnitude", "quat_wxyz holds quaternions that are not of unit norm")
    return quat
