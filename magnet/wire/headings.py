"""Headings: ``HeadingBatch`` and the one heading encoder (many batches at once; one batch is the case B = 1).

Message: ``{v, device, seq, t_ns: [N], heading_deg: [N] (magnetic), true_heading_deg: [N], pitch_deg: [N],
roll_deg: [N], field_ut: [[x, y, z]] * N, declination_deg, calibration_id, flags: [N ints],
quat_wxyz: [[w, x, y, z]] * N (optional: attitude, body to NED, unit quaternion), heading_sigma_deg: [N] (optional:
one sigma of each heading, deg, ``magnet.attitude.uncertainty``)}``. In v 2 (written) every array is a binary array
map (see ``magnet.wire.arrays``): t_ns ``<i8`` [N], the angles ``<f4`` [N] (heading_deg and true_heading_deg kept in
[0, 360) after rounding to ``<f4``), field_ut ``<f4`` [N, 3], flags ``<u2`` [N], quat_wxyz ``<f4`` [N, 4],
heading_sigma_deg ``<f4`` [N]. The optional fields come last; a reader that knows them not ignores them (msgpack
maps are read by key), so a message with a sigma reads as before.

``flags`` holds ``magnet.attitude.heading.HeadingFlag`` bits; the per-sample magnetic disturbance flag is its
FIELD_DISTURBED (|B| away from the expected field) and DIP_DISTURBED (dip away from the expected inclination) bits,
``DISTURBED`` for either.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from typing import Any, NamedTuple

import msgpack
import numpy as np

from magnet.attitude.heading import HeadingFlag
from magnet.wire.arrays import (
    FLAG_DTYPE,
    FLAG_DTYPES,
    FLOAT_DTYPE,
    TIME_DTYPE,
    TIME_DTYPES,
    check_lengths,
    float_array,
    int_array,
)
from magnet.wire.codec import (
    BINARY_ARRAYS_VERSION,
    LISTS_VERSION,
    MAX_BATCH_SAMPLES,
    VERSIONS,
    Limits,
    Payload,
    binary_message,
    int_field,
    number_field,
    unpack,
)
from magnet.wire.errors import WireError
from magnet.wire.keys import MAX_DEVICE_ID_CHARS, message_device
from magnet.wire.raw import RawColumns

#: the optional per-sample heading uncertainty (one sigma, deg): a contract name (issue 27)
SIGMA_FIELD = "heading_sigma_deg"
ANGLE_FIELDS = ("heading_deg", "true_heading_deg", "pitch_deg", "roll_deg")
#: flags bits that mark a sample's field as magnetically disturbed
DISTURBED = int(HeadingFlag.FIELD_DISTURBED | HeadingFlag.DIP_DISTURBED)
#: a quaternion on the wire must have a norm within this of 1
QUAT_NORM_TOLERANCE = 0.01
#: what msgpack may build of one heading payload (``codec.Limits``), from the message's own maxima: at most 256
#: bytes a sample (v 1 with float64 everywhere needs about 115) plus a header; arrays of MAX_BATCH_SAMPLES entries;
#: 64 fields; strings of a device id; a v 2 array of N quaternions in float64; in all, the entries of a v 1 message
#: (1 time, 4 angles, 4 per field row, 1 flag, 5 per quaternion row, 1 sigma: 16 a sample) plus room for the header; and
#: its arrays and maps (a field row and a quaternion row a sample, and the few of the header)
HEADING_LIMITS = Limits(
    payload_bytes=16 * 1024 + MAX_BATCH_SAMPLES * 256,
    array=MAX_BATCH_SAMPLES,
    map=64,
    text=4 * MAX_DEVICE_ID_CHARS,
    binary=MAX_BATCH_SAMPLES * 4 * 8,
    items=MAX_BATCH_SAMPLES * 16 + 1024,
    containers=MAX_BATCH_SAMPLES * 2 + 64,
)


@dataclasses.dataclass(frozen=True, eq=False)
class HeadingBatch:
    """N headings of one device, aligned with one raw batch. Angles in degrees, field_ut (N, 3) corrected uT,
    flags (N,) ``magnet.attitude.heading.HeadingFlag`` bits, declination_deg east-positive, quat_wxyz (N, 4) attitude
    (body to NED) or None."""

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
    heading_sigma_deg: np.ndarray | None = None  # (N,) deg, one sigma; None: a sender that gives none

    def __len__(self) -> int:
        return int(self.t_ns.shape[0])

    @property
    def disturbed(self) -> np.ndarray:
        """(N,) bool: the field of the sample is magnetically disturbed (|B| or dip away from the reference)."""
        return (np.asarray(self.flags, dtype=np.int64) & DISTURBED) != 0


def encode_headings(
    columns: RawColumns,
    heading_deg: np.ndarray,
    true_heading_deg: np.ndarray,
    pitch_deg: np.ndarray,
    roll_deg: np.ndarray,
    field_ut: np.ndarray,
    flags: np.ndarray,
    declination_deg: float | Sequence[float],
    calibration_ids: Sequence[str],
    quat_wxyz: np.ndarray | None = None,
    heading_sigma_deg: np.ndarray | None = None,
    version: int = BINARY_ARRAYS_VERSION,
) -> list[bytes]:
    """One heading message per batch of ``columns`` (the one heading encoder), in ``version`` 2 (binary arrays, the
    default) or 1 (lists).

    The arrays are aligned with ``columns``' S samples (angles (S,) deg, field_ut (S, 3) uT, flags (S,) int,
    quat_wxyz (S, 4) or None); each is converted once (to lists, or to little-endian bytes) and sliced per batch.
    A batch whose quaternion rows are not all finite carries no ``quat_wxyz``. ``declination_deg``: one for all, or
    one per batch (each device's place). ``heading_sigma_deg`` (S,) deg or None: each heading's one sigma (a batch
    with a sigma that is not finite carries none)."""
    return _encode(
        columns.devices,
        columns.seqs,
        columns.bounds,
        columns.t_ns,
        (heading_deg, true_heading_deg, pitch_deg, roll_deg),
        field_ut,
        flags,
        declination_deg,
        calibration_ids,
        quat_wxyz,
        version,
        heading_sigma_deg,
    )


def encode_heading(batch: HeadingBatch, version: int = BINARY_ARRAYS_VERSION) -> bytes:
    """The message of one batch: ``encode_headings`` of B = 1."""
    angles = tuple(getattr(batch, name) for name in ANGLE_FIELDS)
    return _encode(
        [batch.device],
        [batch.seq],
        [0, len(batch)],
        batch.t_ns,
        angles,
        batch.field_ut,
        batch.flags,
        batch.declination_deg,
        [batch.calibration_id],
        batch.quat_wxyz,
        version,
        batch.heading_sigma_deg,
    )[0]


class _Lists:
    """v 1: a whole column as Python lists, sliced per batch."""

    def __init__(self, values: np.ndarray, dtype: Any, tail: tuple[int, ...], name: str = "") -> None:
        self.values = np.asarray(values, dtype=dtype).tolist()

    def __getitem__(self, bounds: slice) -> Any:
        return self.values[bounds]


class _Bytes:
    """v 2: a whole column as little-endian bytes, sliced per batch into a binary array map, or straight into the
    msgpack bytes of ``name`` and that map (``packed``)."""

    def __init__(self, values: np.ndarray, dtype: Any, tail: tuple[int, ...], name: str = "") -> None:
        self.dtype, self.tail, self.name = dtype, list(tail), name
        self.data = np.ascontiguousarray(values, dtype=dtype).tobytes()
        self.row = np.dtype(dtype).itemsize * math.prod(tail)
        self._heads = _HEADS.setdefault((name, np.dtype(dtype).str, tuple(tail)), {})

    def __getitem__(self, bounds: slice) -> Any:
        return {
            "dtype": self.dtype,
            "shape": [bounds.stop - bounds.start, *self.tail],
            "data": self.data[bounds.start * self.row : bounds.stop * self.row],
        }

    def packed(self, lo: int, hi: int) -> tuple[bytes, bytes]:
        """The msgpack bytes of the key ``name`` and of the map of rows lo .. hi, as (everything up to the data,
        the data): the same bytes ``msgpack.packb`` gives for them, the part before the data made once per N."""
        head = self._heads.get(hi - lo)
        if head is None:
            empty = msgpack.packb({"dtype": self.dtype, "shape": [hi - lo, *self.tail], "data": b""})
            head = msgpack.packb(self.name) + empty[:-2] + _bin_header((hi - lo) * self.row)
            if len(self._heads) < HEADS_KEPT:
                self._heads[hi - lo] = head
        return head, self.data[lo * self.row : hi * self.row]


#: the msgpack bytes before a column's data, per (name, dtype, tail) and rows: made once, not per drain (at most
#: ``HEADS_KEPT`` row counts per column kept; others made each time)
_HEADS: dict[tuple[str, str, tuple[int, ...]], dict[int, bytes]] = {}
HEADS_KEPT = 256


def _bin_header(size: int) -> bytes:
    """msgpack's header of a bin of ``size`` bytes (bin 8, 16 or 32)."""
    if size < 1 << 8:
        return bytes((0xC4, size))
    if size < 1 << 16:
        return b"\xc5" + size.to_bytes(2, "big")
    return b"\xc6" + size.to_bytes(4, "big")


def _columns(
    version: int,
    t_ns: np.ndarray,
    angles: tuple[np.ndarray, ...],
    field_ut: np.ndarray,
    flags: np.ndarray,
    quat: np.ndarray | None,
) -> tuple[Any, list[Any], Any, Any, Any]:
    """t_ns, angles, field, flags and quaternion columns ready to slice, in the form of ``version``."""
    if version not in VERSIONS:
        raise ValueError(f"wire version must be one of {VERSIONS}, got {version}")
    column: type[_Lists] | type[_Bytes]
    types: tuple[Any, Any, Any]
    if version == LISTS_VERSION:
        column, types = _Lists, (np.int64, float, np.int64)
    else:
        column, types = _Bytes, (TIME_DTYPE, FLOAT_DTYPE, FLAG_DTYPE)
        angles = tuple(
            _wrap(a) if name in ("heading_deg", "true_heading_deg") else a for name, a in zip(ANGLE_FIELDS, angles)
        )
    return (
        column(t_ns, types[0], (), "t_ns"),
        [column(a, types[1], (), name) for a, name in zip(angles, ANGLE_FIELDS)],
        column(field_ut, types[1], (3,), "field_ut"),
        column(flags, types[2], (), "flags"),
        None if quat is None else column(quat, types[1], (4,), "quat_wxyz"),
    )


def _wrap(heading_deg: np.ndarray) -> np.ndarray:
    """Headings as ``<f4`` in [0, 360): 359.99999 rounds to 360.0 in single precision, which is 0."""
    single = np.asarray(heading_deg, dtype=np.float32)
    return np.where(single >= np.float32(360.0), np.float32(0.0), single)


def _encode(
    devices: Sequence[str],
    seqs: Sequence[int],
    bounds: Sequence[int],
    t_ns: np.ndarray,
    angles: tuple[np.ndarray, ...],
    field_ut: np.ndarray,
    flags: np.ndarray,
    declination_deg: float | Sequence[float],
    calibration_ids: Sequence[str],
    quat_wxyz: np.ndarray | None,
    version: int,
    heading_sigma_deg: np.ndarray | None = None,
) -> list[bytes]:
    quat_ok = _quaternions_ok(quat_wxyz, bounds)
    sigma_ok = _sigmas_ok(heading_sigma_deg, bounds)
    times, angle_columns, field, flag, quat = _columns(version, t_ns, angles, field_ut, flags, quat_wxyz)
    sigma = None
    if heading_sigma_deg is not None:
        column = _Lists if version == LISTS_VERSION else _Bytes
        sigma = column(heading_sigma_deg, float if version == LISTS_VERSION else FLOAT_DTYPE, (), SIGMA_FIELD)
    if isinstance(declination_deg, list) and len(declination_deg) == len(devices):  # the compass's: one a batch
        declinations = [float(d) for d in declination_deg]
    else:
        declinations = np.broadcast_to(np.asarray(declination_deg, dtype=float), (len(devices),)).tolist()
    if version == BINARY_ARRAYS_VERSION:
        columns = [times, *angle_columns, field]
        optional = _Optional(quat, quat_ok, sigma, sigma_ok)
        return _encode_binary(devices, seqs, bounds, columns, flag, optional, declinations, calibration_ids)
    out = []
    for i, (device, seq, cal_id, declination) in enumerate(zip(devices, seqs, calibration_ids, declinations)):
        rows = slice(bounds[i], bounds[i + 1])
        message: dict[str, Any] = {"v": version, "device": device, "seq": int(seq), "t_ns": times[rows]}
        message.update((name, values[rows]) for name, values in zip(ANGLE_FIELDS, angle_columns))
        message.update(field_ut=field[rows], declination_deg=declination, calibration_id=cal_id, flags=flag[rows])
        if quat_ok[i]:
            message["quat_wxyz"] = quat[rows]
        if sigma is not None and sigma_ok[i]:
            message[SIGMA_FIELD] = sigma[rows]
        out.append(msgpack.packb(message, use_bin_type=True))
    return out


_PACKED_KEYS = {name: msgpack.packb(name) for name in ("v", "device", "seq", "declination_deg", "calibration_id")}


class _Optional(NamedTuple):
    """The optional columns of the v 2 messages and, per batch, whether it carries them."""

    quat: _Bytes | None
    quat_ok: list[bool]
    sigma: Any
    sigma_ok: list[bool]


def _encode_binary(
    devices: Sequence[str],
    seqs: Sequence[int],
    bounds: Sequence[int],
    columns: list[_Bytes],
    flag: _Bytes,
    optional: _Optional,
    declinations: list[float],
    calibration_ids: Sequence[str],
) -> list[bytes]:
    """The v 2 messages of ``_encode``, their msgpack bytes joined from pieces (the same bytes ``msgpack.packb``
    gives for the message map: keys in the same order, the same smallest encodings), a few us per message."""
    pack, keys = msgpack.packb, _PACKED_KEYS
    version = keys["v"] + pack(BINARY_ARRAYS_VERSION) + keys["device"]
    out = []
    for i, (device, seq, cal_id, declination) in enumerate(zip(devices, seqs, calibration_ids, declinations)):
        lo, hi = bounds[i], bounds[i + 1]
        with_quat, with_sigma = optional.quat_ok[i] and optional.quat is not None, optional.sigma_ok[i]
        head = bytes((0x8C + with_quat + with_sigma,))
        parts = [head, version, pack(device), keys["seq"], pack(int(seq))]
        for column in columns:
            parts += column.packed(lo, hi)
        parts += (keys["declination_deg"], pack(declination), keys["calibration_id"], pack(cal_id))
        parts += flag.packed(lo, hi)
        if with_quat and optional.quat is not None:
            parts += optional.quat.packed(lo, hi)
        if with_sigma:
            parts += optional.sigma.packed(lo, hi)
        out.append(b"".join(parts))
    return out


def _sigmas_ok(sigma_deg: np.ndarray | None, bounds: Sequence[int]) -> list[bool]:
    """Per batch, whether all its sigmas are finite (False for all without sigmas)."""
    return _batches_all(None if sigma_deg is None else np.isfinite(np.asarray(sigma_deg, dtype=float)), bounds)


def _quaternions_ok(quat_wxyz: np.ndarray | None, bounds: Sequence[int]) -> list[bool]:
    """Per batch, whether all its quaternion rows are finite (False for all without quaternions)."""
    return _batches_all(None if quat_wxyz is None else np.isfinite(np.asarray(quat_wxyz, dtype=float)).all(1), bounds)


def _batches_all(ok: np.ndarray | None, bounds: Sequence[int]) -> list[bool]:
    """Per batch, whether ``ok`` (S,) is true throughout it (None: False): one count over the drain, not a
    reduction a batch (these were a quarter of the compass's encode)."""
    if ok is None or ok.all():
        return [ok is not None] * (len(bounds) - 1)
    bad = np.concatenate(([0], np.cumsum(~ok)))[np.asarray(bounds, dtype=np.intp)]
    return (bad[1:] == bad[:-1]).tolist()


def decode_heading(payload: Payload) -> HeadingBatch:
    """HeadingBatch from a payload; WireError (with ``cause``) for anything malformed."""
    message = unpack(payload, HEADING_LIMITS)
    device = message_device(message)
    binary = binary_message(message)
    t_ns = int_array(message.get("t_ns"), "t_ns", binary, TIME_DTYPES)
    angles = {name: float_array(message.get(name), name, (), 1e4, binary) for name in ANGLE_FIELDS}
    field = float_array(message.get("field_ut"), "field_ut", (3,), None, binary)
    flags = int_array(message.get("flags"), "flags", binary, FLAG_DTYPES)
    quat = _decode_quaternions(message.get("quat_wxyz"), binary)
    sigma = _decode_sigma(message.get(SIGMA_FIELD), binary)
    optional = {name: v for name, v in (("quat_wxyz", quat), (SIGMA_FIELD, sigma)) if v is not None}
    check_lengths(t_ns.shape[0], {**angles, "field_ut": field, "flags": flags, **optional})
    return HeadingBatch(
        device,
        int_field(message, "seq", 0),
        t_ns,
        field_ut=field,
        flags=flags,
        declination_deg=number_field(message, "declination_deg", 0.0),
        calibration_id=str(message.get("calibration_id", "")),
        quat_wxyz=quat,
        heading_sigma_deg=sigma,
        **angles,
    )


def _decode_sigma(value: Any, binary: bool) -> np.ndarray | None:
    if value is None:
        return None
    sigma = float_array(value, SIGMA_FIELD, (), 1e4, binary)
    if sigma.size and (sigma < 0).any():
        raise WireError("absurd-magnitude", f"{SIGMA_FIELD} holds negative values")
    return sigma


def _decode_quaternions(value: Any, binary: bool) -> np.ndarray | None:
    if value is None:
        return None
    quat = float_array(value, "quat_wxyz", (4,), 1.0 + QUAT_NORM_TOLERANCE, binary)
    if quat.size and (np.abs(np.linalg.norm(quat, axis=1) - 1.0) > QUAT_NORM_TOLERANCE).any():
        raise WireError("absurd-magnitude", "quat_wxyz holds quaternions that are not of unit norm")
    return quat
