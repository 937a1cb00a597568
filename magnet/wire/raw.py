"""Raw samples: ``RawBatch`` (one message), ``RawColumns`` (many, sample after sample) and the raw encoder.

Message: ``{v, device, seq, sensor, t_ns: [N ints], mag_ut: [[x, y, z]] * N, acc_ms2: [[x, y, z]] * N (optional),
gyr_rads: [[x, y, z]] * N (optional, body-frame rate of turn in rad/s), vel_ned_ms: [[n, e, d]] * N (optional, the
velocity over the ground in m/s, north-east-down, NaN rows where no fix is known), truth: {heading_deg: [N],
pitch_deg: [N], roll_deg: [N]} (optional, simulator only), location: [lat_deg, lon_deg, alt_m] (optional: where the
device is, ``magnet.earth.location.Location``, checked: cause ``bad-location``), current_a: [N] (optional, the battery
current in A at each sample, for the motors' field), throttle: [N] (optional, 0..1; both NaN where unknown),
vehicle: text (optional: the vehicle the device is a compass of, ``magnet edge --vehicle``; docs/vehicles.md),
hardware_id: int (optional, 1..2**32-1: the id the vehicle reports for the sensor behind the device, e.g. ArduPilot's
COMPASS_DEV_ID; docs/mavlink.md)}``.
In v 2 (written) every array of samples is a binary array map (see ``magnet.wire.arrays``): t_ns ``<i8`` [N],
mag_ut / acc_ms2 / gyr_rads / vel_ned_ms ``<f4`` [N, 3], truth, current_a and throttle ``<f4`` [N]; ``location``
(three numbers, not samples) stays a list in both versions.

The one raw decoder is ``magnet.wire.raw_decode``; the structure checks of one message are ``magnet.wire.raw_header``.
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
import typing
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import msgpack
import numpy as np

from magnet.earth.location import Location
from magnet.wire.arrays import FLOAT_DTYPE, TIME_DTYPE, bin_array
from magnet.wire.codec import BINARY_ARRAYS_VERSION, LISTS_VERSION, VERSIONS
from magnet.wire.errors import WireError

#: Magnitudes beyond these are not a magnetometer, an accelerometer or a gyroscope on Earth (a +-8 gauss chip reads
#: 800 uT; the fastest MEMS gyroscopes saturate near 70 rad/s).
MAX_FIELD_UT = 5_000.0
MAX_ACC_MS2 = 2_000.0
MAX_GYR_RADS = 100.0
#: faster than any vehicle that navigates by compass (Mach 3)
MAX_VEL_MS = 1_000.0
#: the (N, 3) vector fields of a raw message, their limit, and whether a message must carry them
VECTOR_FIELDS: tuple[tuple[str, float, bool], ...] = (
    ("mag_ut", MAX_FIELD_UT, True),
    ("acc_ms2", MAX_ACC_MS2, False),
    ("gyr_rads", MAX_GYR_RADS, False),
    ("vel_ned_ms", MAX_VEL_MS, False),
)
TRUTH_FIELDS = ("heading_deg", "pitch_deg", "roll_deg")
#: a large multirotor draws a few hundred amps; a regenerating drive may return current (negative)
MAX_CURRENT_A = 2_000.0
#: the (N,) per-sample scalars of a raw message (all optional): name, lowest and highest value allowed
#: a sensor's hardware id (``RawBatch.hardware_id``) is an unsigned 32-bit number
MAX_HARDWARE_ID = (1 << 32) - 1
SCALAR_FIELDS: tuple[tuple[str, float, float], ...] = (
    ("current_a", -MAX_CURRENT_A, MAX_CURRENT_A),
    ("throttle", 0.0, 1.0),
)


@dataclasses.dataclass(frozen=True, eq=False)
class RawBatch:
    """N raw samples of one device. t_ns (N,) int64 ns; mag_ut (N, 3) uT body frame; acc_ms2 (N, 3) m/s^2 or None;
    truth: {"heading_deg", "pitch_deg", "roll_deg"} -> (N,) degrees, simulator only, else None; gyr_rads (N, 3)
    rad/s body frame or None; location where the device is, or None; vel_ned_ms (N, 3) m/s north-east-down, or
    None (rows may be NaN where no velocity is known); current_a (N,) A battery current and throttle (N,) 0..1 at
    each sample, or None; vehicle: the vehicle the device is a compass of ("" none: ``magnet.vehicle``);
    hardware_id: the id the vehicle reports for the sensor behind the device (0: not known; docs/mavlink.md)."""

    device: str
    seq: int
    sensor: str
    t_ns: np.ndarray
    mag_ut: np.ndarray
    acc_ms2: np.ndarray | None = None
    truth: Mapping[str, np.ndarray] | None = None
    gyr_rads: np.ndarray | None = None
    location: Location | None = None
    vel_ned_ms: np.ndarray | None = None
    current_a: np.ndarray | None = None
    throttle: np.ndarray | None = None
    vehicle: str = ""
    hardware_id: int = 0

    def __len__(self) -> int:
        return int(self.t_ns.shape[0])


def nan_rows(n: int) -> np.ndarray:
    return np.full((n, 3), np.nan)


def nan_values(n: int) -> np.ndarray:
    return np.full(n, np.nan)


def _scalars(batches: Sequence[RawBatch], name: str) -> np.ndarray:
    """(S,) one scalar field of every batch, NaN where a batch carries none."""
    parts = [getattr(b, name) for b in batches]
    return np.concatenate([nan_values(len(b)) if p is None else np.asarray(p, float) for b, p in zip(batches, parts)])


def _present(values: np.ndarray) -> np.ndarray | None:
    return None if np.isnan(values).all() else values


@dataclasses.dataclass(frozen=True, eq=False)
class RawColumns:
    """B raw batches decoded together, S samples in all, batch after batch.

    devices, seqs, sensors: per batch (B); counts (B,) int samples per batch; t_ns (S,) int64; mag_ut (S, 3) uT;
    acc_ms2 (S, 3) m/s^2 and gyr_rads (S, 3) rad/s, with NaN rows for batches that carry none; locations per batch
    (a Location or None), or None when no batch carries one; vel_ned_ms (S, 3) m/s NED, NaN rows where unknown;
    current_a (S,) A and throttle (S,) 0..1, NaN where unknown; vehicles per batch ("" none), or None when no batch
    names one; hardware_ids per batch (0 not known), or None when no batch carries one."""

    devices: list[str]
    seqs: list[int]
    counts: np.ndarray
    t_ns: np.ndarray
    mag_ut: np.ndarray
    acc_ms2: np.ndarray
    gyr_rads: np.ndarray
    sensors: list[str]
    locations: list[Location | None] | None = None
    vel_ned_ms: np.ndarray | None = None
    current_a: np.ndarray | None = None
    throttle: np.ndarray | None = None
    vehicles: list[str] | None = None
    hardware_ids: list[int] | None = None

    def __post_init__(self) -> None:
        n = int(self.t_ns.shape[0])
        if self.vel_ned_ms is None:  # frozen: set once, here
            object.__setattr__(self, "vel_ned_ms", nan_rows(n))
        for name, _, _ in SCALAR_FIELDS:
            if getattr(self, name) is None:
                object.__setattr__(self, name, nan_values(n))

    @property
    def current(self) -> np.ndarray:
        """current_a (S,) A, never None (NaN where unknown)."""
        return typing.cast(np.ndarray, self.current_a)

    @property
    def thr(self) -> np.ndarray:
        """throttle (S,) 0..1, never None (NaN where unknown)."""
        return typing.cast(np.ndarray, self.throttle)

    @property
    def vel(self) -> np.ndarray:
        """vel_ned_ms (S, 3), never None (NaN rows where unknown)."""
        return typing.cast(np.ndarray, self.vel_ned_ms)

    @classmethod
    def from_batches(cls, batches: Sequence[RawBatch]) -> RawColumns:
        if not batches:
            return cls([], [], np.zeros(0, np.int64), np.empty(0, np.int64), nan_rows(0), nan_rows(0), nan_rows(0), [])
        return cls(
            [b.device for b in batches],
            [b.seq for b in batches],
            np.array([len(b) for b in batches], dtype=np.int64),
            np.concatenate([b.t_ns for b in batches]).astype(np.int64),
            np.concatenate([b.mag_ut for b in batches]).astype(np.float64),
            np.concatenate([nan_rows(len(b)) if b.acc_ms2 is None else b.acc_ms2 for b in batches]),
            np.concatenate([nan_rows(len(b)) if b.gyr_rads is None else b.gyr_rads for b in batches]),
            [b.sensor for b in batches],
            batch_locations([b.location for b in batches]),
            np.concatenate([nan_rows(len(b)) if b.vel_ned_ms is None else b.vel_ned_ms for b in batches]),
            _scalars(batches, "current_a"),
            _scalars(batches, "throttle"),
            _vehicles([b.vehicle for b in batches]),
            _ids([b.hardware_id for b in batches]),
        )

    @classmethod
    def joined(cls, parts: Sequence[RawColumns]) -> RawColumns:
        """The batches of ``parts``, in order, as one RawColumns (per-batch lists with their absent values filled:
        None locations, "" vehicles, 0 hardware ids)."""
        if len(parts) == 1:
            return parts[0]
        if not parts:
            return cls.from_batches([])

        def per_batch(name: str, absent: Any) -> list[Any]:
            return [v for p in parts for v in (getattr(p, name) or [absent] * len(p.devices))]

        def column(name: str) -> np.ndarray:
            return np.concatenate([getattr(p, name) for p in parts])

        return cls(
            per_batch("devices", ""),
            per_batch("seqs", 0),
            column("counts"),
            column("t_ns"),
            column("mag_ut"),
            column("acc_ms2"),
            column("gyr_rads"),
            per_batch("sensors", ""),
            batch_locations(per_batch("locations", None)),
            column("vel_ned_ms"),
            column("current_a"),
            column("throttle"),
            _vehicles(per_batch("vehicles", "")),
            _ids(per_batch("hardware_ids", 0)),
        )

    @functools.cached_property
    def bounds(self) -> list[int]:
        """Sample index where each batch starts, and S at the end: B + 1 ints (made once: a step asks for them
        several times; not to be changed)."""
        return np.concatenate([[0], np.cumsum(self.counts)]).astype(int).tolist()

    def batches(self) -> list[RawBatch]:
        """One RawBatch (views) per batch."""
        bounds = self.bounds
        out = []
        for i, (lo, hi) in enumerate(itertools.pairwise(bounds)):
            acc, gyr, vel = self.acc_ms2[lo:hi], self.gyr_rads[lo:hi], self.vel[lo:hi]
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
                    None if np.isnan(vel).all() else vel,
                    _present(self.current[lo:hi]),
                    _present(self.thr[lo:hi]),
                    "" if self.vehicles is None else self.vehicles[i],
                    0 if self.hardware_ids is None else self.hardware_ids[i],
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
            None if self.locations is None else batch_locations([self.locations[i] for i in pick]),
            self.vel[per_sample],
            self.current[per_sample],
            self.thr[per_sample],
            None if self.vehicles is None else _vehicles([self.vehicles[i] for i in pick]),
            None if self.hardware_ids is None else _ids([self.hardware_ids[i] for i in pick]),
        )


def _vehicles(names: list[str]) -> list[str] | None:
    """Per-batch vehicles, or None when no batch names one."""
    return names if any(names) else None


def _ids(ids: list[int]) -> list[int] | None:
    """Per-batch hardware ids, or None when no batch carries one."""
    return ids if any(ids) else None


def batch_locations(locations: list[Location | None]) -> list[Location | None] | None:
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


def encode_raw(batch: RawBatch, version: int = BINARY_ARRAYS_VERSION) -> bytes:
    """The message of one batch, in ``version`` 2 (binary arrays, the default) or 1 (lists, for old readers)."""
    if version not in VERSIONS:
        raise ValueError(f"wire version must be one of {VERSIONS}, got {version}")
    floats: Callable[[Any], Any]
    times: Callable[[Any], Any]
    if version == LISTS_VERSION:
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
    if batch.vel_ned_ms is not None:
        message["vel_ned_ms"] = floats(batch.vel_ned_ms)
    for name, _, _ in SCALAR_FIELDS:
        if getattr(batch, name) is not None:
            message[name] = floats(getattr(batch, name))
    if batch.location is not None:
        message["location"] = batch.location.to_wire()
    if batch.vehicle:
        message["vehicle"] = batch.vehicle
    if batch.hardware_id:
        message["hardware_id"] = int(batch.hardware_id)
    if batch.truth is not None:
        message["truth"] = {name: floats(batch.truth[name]) for name in TRUTH_FIELDS}
    return msgpack.packb(message, use_bin_type=True)
