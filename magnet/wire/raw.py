"""Raw samples: ``RawBatch`` (one message), ``RawColumns`` (many, sample after sample) and the one raw decoder.

Message: ``{v, device, seq, sensor, t_ns: [N ints], mag_ut: [[x, y, z]] * N, acc_ms2: [[x, y, z]] * N (optional),
gyr_rads: [[x, y, z]] * N (optional, body-frame rate of turn in rad/s), truth: {heading_deg: [N], pitch_deg: [N],
roll_deg: [N]} (optional, simulator only), location: [lat_deg, lon_deg, alt_m] (optional: where the device is,
``magnet.place.Location``, checked: cause ``bad-location``)}``. In v 2 (written) every array of samples is a binary
array map (see ``magnet.wire.codec``): t_ns ``<i8`` [N], mag_ut / acc_ms2 / gyr_rads ``<f4`` [N, 3], truth ``<f4``
[N]; ``location`` (three numbers, not samples) stays a list in both versions.

There is one decoder, for both versions: ``decode_raw_many`` checks each message's structure in Python (``_header``:
list lengths in v 1, dtype, shape and byte count in v 2), turns the numbers of all of them into arrays at once (v 1
lists in one ``np.array``, v 2 bytes joined and read with ``np.frombuffer``) and checks them all in one numpy pass
(``_numbers``: finite, within physical limits); when the numbers of a group do not even form arrays, each message
of the group is converted alone by the same code, which names the culprit. ``decode_raw`` is ``decode_raw_many`` of
one payload (plus the simulator's truth), so both give the same verdict and the same cause for every payload.
"""

from __future__ import annotations

import dataclasses
import itertools
from collections.abc import Callable, Mapping, Sequence
from typing import Any, NamedTuple

import msgpack
import numpy as np

from magnet.place import Location
from magnet.wire.codec import (
    BINARY_VERSION,
    FLOAT_DTYPE,
    FLOAT_DTYPES,
    MAX_BATCH_SAMPLES,
    TIME_DTYPE,
    TIME_DTYPES,
    VERSIONS,
    WIRE_VERSION,
    Bin,
    Payload,
    bin_array,
    binary_message,
    check_bin,
    check_lengths,
    float_array,
    from_bins,
    int_field,
    unpack,
)
from magnet.wire.errors import WireError
from magnet.wire.keys import message_device

#: Magnitudes beyond these are not a magnetometer, an accelerometer or a gyroscope on Earth (a +-8 gauss chip reads
#: 800 uT; the fastest MEMS gyroscopes saturate near 70 rad/s).
MAX_FIELD_UT = 5_000.0
MAX_ACC_MS2 = 2_000.0
MAX_GYR_RADS = 100.0
#: the (N, 3) vector fields of a raw message, their limit, and whether a message must carry them
VECTOR_FIELDS: tuple[tuple[str, float, bool], ...] = (
    ("mag_ut", MAX_FIELD_UT, True),
    ("acc_ms2", MAX_ACC_MS2, False),
    ("gyr_rads", MAX_GYR_RADS, False),
)
TRUTH_FIELDS = ("heading_deg", "pitch_deg", "roll_deg")


@dataclasses.dataclass(frozen=True, eq=False)
class RawBatch:
    """N raw samples of one device. t_ns (N,) int64 ns; mag_ut (N, 3) uT body frame; acc_ms2 (N, 3) m/s^2 or None;
    truth: {"heading_deg", "pitch_deg", "roll_deg"} -> (N,) degrees, simulator only, else None; gyr_rads (N, 3)
    rad/s body frame or None; location where the device is, or None."""

    device: str
    seq: int
    sensor: str
    t_ns: np.ndarray
    mag_ut: np.ndarray
    acc_ms2: np.ndarray | None = None
    truth: Mapping[str, np.ndarray] | None = None
    gyr_rads: np.ndarray | None = None
    location: Location | None = None

    def __len__(self) -> int:
        return int(self.t_ns.shape[0])


def _nan_rows(n: int) -> np.ndarray:
    return np.full((n, 3), np.nan)


@dataclasses.dataclass(frozen=True, eq=False)
class RawColumns:
    """B raw batches decoded together, S samples in all, batch after batch.

    devices, seqs, sensors: per batch (B); counts (B,) int samples per batch; t_ns (S,) int64; mag_ut (S, 3) uT;
    acc_ms2 (S, 3) m/s^2 and gyr_rads (S, 3) rad/s, with NaN rows for batches that carry none; locations per batch
    (a Location or None), or None when no batch carries one."""

    devices: list[str]
    seqs: list[int]
    counts: np.ndarray
    t_ns: np.ndarray
    mag_ut: np.ndarray
    acc_ms2: np.ndarray
    gyr_rads: np.ndarray
    sensors: list[str]
    locations: list[Location | None] | None = None

    @classmethod
    def from_batches(cls, batches: Sequence[RawBatch]) -> RawColumns:
        if not batches:
            return cls(
                [], [], np.zeros(0, np.int64), np.empty(0, np.int64), _nan_rows(0), _nan_rows(0), _nan_rows(0), []
            )
        return cls(
            [b.device for b in batches],
            [b.seq for b in batches],
            np.array([len(b) for b in batches], dtype=np.int64),
            np.concatenate([b.t_ns for b in batches]).astype(np.int64),
            np.concatenate([b.mag_ut for b in batches]).astype(np.float64),
            np.concatenate([_nan_rows(len(b)) if b.acc_ms2 is None else b.acc_ms2 for b in batches]),
            np.concatenate([_nan_rows(len(b)) if b.gyr_rads is None else b.gyr_rads for b in batches]),
            [b.sensor for b in batches],
            _locations([b.location for b in batches]),
        )

    @property
    def bounds(self) -> list[int]:
        """Sample index where each batch starts, and S at the end: B + 1 ints."""
        return np.concatenate([[0], np.cumsum(self.counts)]).astype(int).tolist()

    def batches(self) -> list[RawBatch]:
        """One RawBatch (views) per batch."""
        bounds = self.bounds
        out = []
        for i, (lo, hi) in enumerate(itertools.pairwise(bounds)):
            acc, gyr = self.acc_ms2[lo:hi], self.gyr_rads[lo:hi]
            out.append(
                RawBatch(
                    self.devices[i],
                    self.seqs[i],
                    self.sensors[i],
                    self.t_ns[lo:hi],
                    self.mag_ut[lo:hi],
                    None if np.isnan(acc).all() else acc,
                    None,
                    None if np.isnan(gyr).all() else gyr,
                    None if self.locations is None else self.locations[i],
                )
            )
        return out

    def select(self, keep: np.ndarray) -> RawColumns:
        """The batches where ``keep`` (B,) bool is True."""
        keep = np.asarray(keep, dtype=bool)
        per_sample = np.repeat(keep, self.counts)
        pick = [i for i, k in enumerate(keep.tolist()) if k]
        return RawColumns(
            [self.devices[i] for i in pick],
            [self.seqs[i] for i in pick],
            self.counts[keep],
            self.t_ns[per_sample],
            self.mag_ut[per_sample],
            self.acc_ms2[per_sample],
            self.gyr_rads[per_sample],
            [self.sensors[i] for i in pick],
            None if self.locations is None else _locations([self.locations[i] for i in pick]),
        )


def _locations(locations: list[Location | None]) -> list[Location | None] | None:
    """Per-batch locations, or None when no batch carries one."""
    return locations if any(loc is not None for loc in locations) else None


def message_location(message: Mapping[str, Any]) -> Location | None:
    """The optional ``location`` of a raw message; WireError ``bad-location`` when it is not a valid place."""
    value = message.get("location")
    if value is None:
        return None
    if type(value) is not list:
        raise WireError("bad-location", "location must be a list [lat_deg, lon_deg, alt_m]")
    try:
        return Location.parse(value)
    except ValueError as exc:
        raise WireError("bad-location", str(exc)) from None


# ------------------------------------------------------------------------------------------------------ encoding


def encode_raw(batch: RawBatch, version: int = BINARY_VERSION) -> bytes:
    """The message of one batch, in ``version`` 2 (binary arrays, the default) or 1 (lists, for old readers)."""
    if version not in VERSIONS:
        raise ValueError(f"wire version must be one of {VERSIONS}, got {version}")
    floats: Callable[[Any], Any]
    times: Callable[[Any], Any]
    if version == WIRE_VERSION:
        floats, times = (lambda a: np.asarray(a, dtype=float).tolist()), (lambda a: np.asarray(a, np.int64).tolist())
    else:
        floats, times = (lambda a: bin_array(a, FLOAT_DTYPE)), (lambda a: bin_array(a, TIME_DTYPE))
    message: dict[str, Any] = {
        "v": version,
        "device": batch.device,
        "seq": int(batch.seq),
        "sensor": batch.sensor,
        "t_ns": times(batch.t_ns),
        "mag_ut": floats(batch.mag_ut),
    }
    if batch.acc_ms2 is not None:
        message["acc_ms2"] = floats(batch.acc_ms2)
    if batch.gyr_rads is not None:
        message["gyr_rads"] = floats(batch.gyr_rads)
    if batch.location is not None:
        message["location"] = batch.location.to_wire()
    if batch.truth is not None:
        message["truth"] = {name: floats(batch.truth[name]) for name in TRUTH_FIELDS}
    return msgpack.packb(message, use_bin_type=True)


# ------------------------------------------------------------------------------------------------------ decoding


class _Header(NamedTuple):
    """The structure of one raw message, checked: its device, seq, sensor, sample count, optional fields present,
    and its arrays: lists (v 1) or checked ``Bin`` (v 2), t_ns first then one per VECTOR_FIELDS entry (None where
    absent)."""

    device: str
    seq: int
    sensor: str
    n: int
    present: tuple[bool, ...]  # per VECTOR_FIELDS entry
    arrays: tuple[Any, ...]


def _header(message: Mapping[str, Any]) -> _Header:
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
    return _Header(
        device, int_field(message, "seq", 0), sensor, n, tuple(a is not None for a in arrays[1:]), tuple(arrays)
    )


def _stack(parts: list[Any], name: str, rows: int) -> np.ndarray:
    """float64 (rows, 3) from concatenated [x, y, z] rows; WireError ``bad-shape`` when they are not that."""
    try:
        arr = np.array(parts, dtype=np.float64)
    except (TypeError, ValueError, OverflowError):
        raise WireError("bad-shape", f"{name} is not an array of numbers of shape (N, 3)") from None
    if arr.shape != (rows, 3):
        raise WireError("bad-shape", f"{name} has shape {arr.shape}, expected (N, 3)")
    return arr


def _stack_times(parts: list[Any]) -> np.ndarray:
    try:
        arr = np.array(parts)
    except (TypeError, ValueError, OverflowError):
        raise WireError("bad-shape", "t_ns is not an array of integers") from None
    if arr.ndim != 1 or arr.dtype.kind not in "iu":
        raise WireError("bad-shape", f"t_ns must be a list of integers, got dtype {arr.dtype}")
    return arr.astype(np.int64)


def _gather(values: list[Any], name: str, times: bool) -> np.ndarray:
    """The rows of ``values`` (per message, in order: a list of rows (v 1) or a ``Bin`` (v 2)) as one array: t_ns
    (S,) int64 or (S, 3) float64. Lists in one ``np.array`` per run of v 1 messages, bytes in one ``np.frombuffer``
    per run of v 2 messages. WireError when the lists do not form such an array."""
    parts: list[np.ndarray] = []
    start = 0
    for i in range(1, len(values) + 1):
        if i < len(values) and type(values[i]) is type(values[start]):
            continue
        run = values[start:i]
        if type(run[0]) is Bin:
            parts.append(from_bins(run, () if times else (3,), "i8" if times else "f8"))
        else:
            rows = [row for value in run for row in value]
            parts.append(_stack_times(rows) if times else _stack(rows, name, len(rows)))
        start = i
    return parts[0] if len(parts) == 1 else np.concatenate(parts)


def _arrays(headers: Sequence[_Header]) -> tuple[np.ndarray, list[np.ndarray]]:
    """t_ns (S,) and one (S, 3) array per VECTOR_FIELDS entry (NaN rows where absent); WireError when the numbers
    of these messages do not form such arrays."""
    counts = [h.n for h in headers]
    total = sum(counts)
    vectors = []
    for k, (name, _, _) in enumerate(VECTOR_FIELDS):
        mask = [h.present[k] for h in headers]
        values = [h.arrays[k + 1] for h in headers if h.present[k]]
        if all(mask):
            vectors.append(_gather(values, name, False))
            continue
        arr = _nan_rows(total)
        if values:
            arr[np.repeat(mask, counts)] = _gather(values, name, False)
        vectors.append(arr)
    return _gather([h.arrays[0] for h in headers], "t_ns", True), vectors


def _sample_faults(vectors: list[np.ndarray]) -> list[tuple[np.ndarray, str, str]]:
    """Per-sample faults (S,) bool, most fundamental first, with their cause and message."""
    faults = []
    for arr, (name, _, _) in zip(vectors, VECTOR_FIELDS):
        absent = np.isnan(arr).all(axis=1)
        faults.append((~absent & ~np.isfinite(arr).all(axis=1), "non-finite", f"{name} holds non-finite values"))
    for arr, (name, limit, _) in zip(vectors, VECTOR_FIELDS):
        with np.errstate(invalid="ignore"):
            faults.append(
                ((np.abs(arr) > limit).any(axis=1), "absurd-magnitude", f"{name} holds values beyond +-{limit:g}")
            )
    return faults


def _numbers(headers: Sequence[_Header]) -> tuple[RawColumns, list[WireError | None]]:
    """All messages as columns and, per message, the WireError its numbers earn (None when good); WireError when
    the numbers of these messages do not even form arrays. The same checks for both versions."""
    t_ns, vectors = _arrays(headers)
    counts = np.array([h.n for h in headers], dtype=np.int64)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    verdicts: list[WireError | None] = [None] * len(headers)
    for bad, cause, text in _sample_faults(vectors):
        if bad.any():
            for i in np.flatnonzero(np.logical_or.reduceat(bad, starts)).tolist():
                verdicts[i] = verdicts[i] or WireError(cause, text)
    mag_ut, acc_ms2, gyr_rads = vectors
    columns = RawColumns(
        [h.device for h in headers],
        [h.seq for h in headers],
        counts,
        t_ns,
        mag_ut,
        acc_ms2,
        gyr_rads,
        [h.sensor for h in headers],
    )
    return columns, verdicts


def _alone(header: _Header) -> tuple[list[RawBatch], WireError | None]:
    """``_numbers`` of one message: its batch (or none) and its verdict."""
    try:
        columns, (verdict,) = _numbers([header])
    except WireError as exc:
        return [], exc
    return ([] if verdict else columns.batches()), verdict


def decode_messages(messages: Sequence[Mapping[str, Any]]) -> tuple[RawColumns, list[tuple[int, WireError]]]:
    """The raw decoder: unpacked messages -> (good batches as columns, in order; (index, WireError) per refusal,
    sorted by index)."""
    errors: list[tuple[int, WireError]] = []
    kept: list[int] = []
    headers: list[_Header] = []
    locations: list[Location | None] = []
    for index, message in enumerate(messages):
        try:
            header, location = _header(message), message_location(message)
        except WireError as exc:
            errors.append((index, exc))
            continue
        headers.append(header)
        locations.append(location)
        kept.append(index)
    if not headers:
        return RawColumns.from_batches([]), errors
    try:
        columns, verdicts = _numbers(headers)
        columns = dataclasses.replace(columns, locations=_locations(locations))
        columns = columns.select(np.array([v is None for v in verdicts], dtype=bool))
    except WireError:  # rare: some message's numbers are not arrays; judge each alone to name it
        alone = [_alone(h) for h in headers]
        verdicts = [verdict for _, verdict in alone]
        columns = RawColumns.from_batches(
            [
                dataclasses.replace(batch, location=location)
                for (batches, _), location in zip(alone, locations)
                for batch in batches
            ]
        )
    errors += [(index, v) for index, v in zip(kept, verdicts) if v is not None]
    return columns, sorted(errors, key=lambda e: e[0])


def decode_raw_many(payloads: Sequence[Payload]) -> tuple[RawColumns, list[tuple[int, WireError]]]:
    """Decode many raw payloads at once (the hot path of a busy consumer).

    Returns the good batches as columns, in input order, and (index, WireError) for each payload refused, sorted by
    index. ``truth`` is not decoded."""
    messages: list[Mapping[str, Any]] = []
    where: list[int] = []
    errors: list[tuple[int, WireError]] = []
    for index, payload in enumerate(payloads):
        try:
            messages.append(unpack(payload))
            where.append(index)
        except WireError as exc:
            errors.append((index, exc))
    columns, refused = decode_messages(messages)
    errors += [(where[i], exc) for i, exc in refused]
    return columns, sorted(errors, key=lambda e: e[0])


def decode_raw(payload: Payload, *, with_truth: bool = True) -> RawBatch:
    """RawBatch from a payload; WireError (with ``cause``) for anything malformed or physically impossible.

    The verdict is ``decode_raw_many``'s; ``with_truth=False`` skips the simulator's truth (faster, for consumers
    that do not use it)."""
    message = unpack(payload)
    columns, errors = decode_messages([message])
    if errors:
        raise errors[0][1]
    batch = columns.batches()[0]
    if not with_truth or message.get("truth") is None:
        return batch
    return dataclasses.replace(batch, truth=_truth(message["truth"], len(batch), binary_message(message)))


def _truth(raw_truth: Any, n: int, binary: bool) -> dict[str, np.ndarray]:
    if not isinstance(raw_truth, dict):
        raise WireError("bad-field", "truth must be a map")
    truth = {name: float_array(raw_truth.get(name), f"truth.{name}", (), 1e4, binary) for name in TRUTH_FIELDS}
    check_lengths(n, truth)
    return truth
