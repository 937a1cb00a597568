"""Calibration records and calibration progress on the wire.

- calibration: ``Calibration.to_dict()`` plus ``v, device, id (content id), created_ns`` (``DeviceCalibration``), from
  calibrators that number them ``version`` (the device's record count, 1, 2, ...; absent in older records, read as 0),
  and when signed ``sig`` and ``key_id`` (``magnet.signing``, the signature covers ``version``)
- progress: ``{v, device, state, t_ns, calibration_id, method, session, samples, seen, coverage, cells_hit,
  cell_count, missing: [str], residual_rms_ut, accepted, reason}`` (``Progress``; the collection keys only while
  collecting, the calibration keys only once there is one)

A calibration record enters from outside (a message, a stored row) only through ``calibration_from_record``, which
reads the record with ``Calibration.from_dict`` (the one check of a calibration: shapes, finiteness, condition
number, determinant, offset).
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Mapping
from typing import Any

import msgpack

from magnet.model import Calibration
from magnet.wire.codec import RECORD_VERSION, Limits, Payload, check_version, int_field, unpack
from magnet.wire.errors import WireError
from magnet.wire.keys import message_device, validate_device_id

MAX_SIG_LEN, MAX_KEY_ID_LEN = 128, 64
MAX_VERSION = 2**63 - 1
#: what msgpack may build of one calibration record (``codec.Limits``): a record is a few dozen fields (3 offsets,
#: a 3x3 matrix, units, a map of quality figures, a reason in words, a signature); 64 KiB, lists of 256, maps of
#: 128, strings of 16 KiB and 4096 entries in all are many times the largest a fit writes. No bin.
CALIBRATION_LIMITS = Limits(payload_bytes=64 * 1024, array=256, map=128, text=16 * 1024, binary=0, items=4096)
#: a progress message: the same kind of small record (a list of missing directions, a reason)
PROGRESS_LIMITS = CALIBRATION_LIMITS


@dataclasses.dataclass(frozen=True, eq=False)
class DeviceCalibration:
    """The calibration of one device as published and stored: device id, when it was made (ns since the epoch) and
    the record; ``id`` is the record's content id. ``version``: the device's record number, given by the active
    calibrator (1, 2, ...; 0 for records made before versions), the order in which records supersede each other
    (``newer_than``); ``created_ns`` is a wall-clock time, shown, never used to order."""

    device: str
    created_ns: int
    calibration: Calibration
    sig: str = ""  # Ed25519 signature (base64) of the record's other fields (``magnet.signing``); "" unsigned
    key_id: str = ""  # which key signed it
    version: int = 0  # the device's record number (0: a record from before versions)

    def __post_init__(self) -> None:
        validate_device_id(self.device)
        for name in ("created_ns", "version"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= MAX_VERSION:
                raise ValueError(f"{name} must be a whole number 0..2**63-1, got {value!r}")
        for name, limit in (("sig", MAX_SIG_LEN), ("key_id", MAX_KEY_ID_LEN)):
            value = getattr(self, name)
            if not isinstance(value, str) or len(value) > limit:
                raise ValueError(f"{name} must be a string of at most {limit} characters")

    @functools.cached_property
    def id(self) -> str:
        """The calibration's content id, hashed once per record (the compass stamps it on every heading message)."""
        return self.calibration.content_id

    def newer_than(self, other: DeviceCalibration) -> bool:
        """Whether this record supersedes ``other`` (same device): the higher ``version``; between equal versions (two
        records from before versions, or two calibrators that both wrote while split) the later ``created_ns``."""
        return (self.version, self.created_ns) > (other.version, other.created_ns)

    def to_record(self) -> dict[str, Any]:
        """The published map (JSON-able): ``v, device, id, created_ns`` and the calibration's fields."""
        out = {
            "v": RECORD_VERSION,
            "device": self.device,
            "id": self.id,
            "created_ns": int(self.created_ns),
            **self.calibration.to_dict(),
        }
        if self.version:  # absent when 0: a record from before versions keeps its signed bytes
            out["version"] = int(self.version)
        if self.sig or self.key_id:
            out.update(sig=self.sig, key_id=self.key_id)
        return out


#: the name this envelope had before
CalibrationMessage = DeviceCalibration


def calibration_record(device: str, calibration: Calibration, created_ns: int) -> dict[str, Any]:
    """The published map: ``Calibration.to_dict()`` plus ``v, device, id, created_ns`` (JSON-able)."""
    return DeviceCalibration(device, int(created_ns), calibration).to_record()


def encode_calibration(device: str, calibration: Calibration, created_ns: int) -> bytes:
    return msgpack.packb(calibration_record(device, calibration, created_ns), use_bin_type=True)


def calibration_from_record(record: Mapping[str, Any]) -> DeviceCalibration:
    """The one entry of a published or stored calibration map; WireError (``bad-calibration``, or the cause of a
    bad version, device or created_ns) with what is wrong."""
    if not isinstance(record, Mapping):
        raise WireError("not-a-map", "a calibration record must be a map")
    check_version(record)
    device = message_device(record)
    created_ns, version = int_field(record, "created_ns", 0), int_field(record, "version", 0)
    for name, value in (("created_ns", created_ns), ("version", version)):
        if not 0 <= value <= MAX_VERSION:
            raise WireError("bad-field", f"{name} must be 0..2**63-1, got {value}")
    try:
        calibration = Calibration.from_dict(record)
    except (ValueError, TypeError) as exc:
        raise WireError("bad-calibration", f"unusable calibration: {exc}") from None
    try:
        sig, key_id = record.get("sig") or "", record.get("key_id") or ""
        return DeviceCalibration(device, created_ns, calibration, sig, key_id, version)
    except ValueError as exc:
        raise WireError("bad-field", str(exc)) from None


def decode_calibration(payload: Payload) -> DeviceCalibration:
    """The record of a calibration message (unpacked within ``CALIBRATION_LIMITS``); WireError as
    ``calibration_from_record``."""
    return calibration_from_record(unpack(payload, CALIBRATION_LIMITS))


@dataclasses.dataclass(frozen=True)
class Collecting:
    """What a collection in progress adds to ``Progress``: session or automatic, samples seen, coverage cells."""

    session: bool
    seen: int
    cells_hit: int
    cell_count: int


@dataclasses.dataclass(frozen=True)
class Progress:
    """A device's calibration progress. state: collecting / session / calibrated / idle; t_ns: when (ns);
    calibration_id: the record in force or None. method ... reason: the latest fit or the record in force (absent
    while there is neither, ``method`` None); collecting: while samples are being collected."""

    state: str
    t_ns: int
    calibration_id: str | None = None
    method: str | None = None
    samples: int | None = None
    coverage: float | None = None
    missing: tuple[str, ...] = ()
    residual_rms_ut: float | None = None
    accepted: bool | None = None
    reason: str = ""
    collecting: Collecting | None = None

    def to_dict(self) -> dict[str, Any]:
        """The message's fields (without ``v`` and ``device``)."""
        out: dict[str, Any] = {"state": self.state, "t_ns": int(self.t_ns), "calibration_id": self.calibration_id}
        if self.method is None:
            return out
        out["method"] = self.method
        if self.collecting is not None:
            out.update(
                session=self.collecting.session,
                samples=self.samples,
                seen=self.collecting.seen,
                coverage=self.coverage,
                cells_hit=self.collecting.cells_hit,
                cell_count=self.collecting.cell_count,
            )
        else:
            out.update(samples=self.samples, coverage=self.coverage)
        out.update(
            missing=list(self.missing), residual_rms_ut=self.residual_rms_ut, accepted=self.accepted, reason=self.reason
        )
        return out


def encode_progress(device: str, progress: Progress | Mapping[str, Any]) -> bytes:
    """Progress message of a device's calibration (``Progress``, or its map)."""
    fields = progress.to_dict() if isinstance(progress, Progress) else dict(progress)
    return msgpack.packb({"v": RECORD_VERSION, "device": validate_device_id(device), **fields}, use_bin_type=True)


def decode_progress(payload: Payload) -> dict[str, Any]:
    """The progress message's map (checked: version and device)."""
    message = unpack(payload, PROGRESS_LIMITS)
    message_device(message)
    return message
