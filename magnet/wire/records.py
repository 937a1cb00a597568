"""Calibration records and calibration progress on the wire.

- calibration: ``Calibration.to_dict()`` plus ``v, device, id (content id), created_ns``
- progress: ``{v, device, state, method, session, samples, coverage, cells_hit, cell_count, missing: [str],
  residual_rms_ut, reason, t_ns}``
"""

from __future__ import annotations

import dataclasses
from typing import Any, Mapping

import msgpack
import numpy as np

from magnet.model import Calibration
from magnet.wire.codec import WIRE_VERSION, Payload, check_version, int_field, unpack
from magnet.wire.errors import WireError
from magnet.wire.keys import message_device, validate_device_id
from magnet.wire.raw import MAX_FIELD_UT


@dataclasses.dataclass(frozen=True, eq=False)
class CalibrationMessage:
    """A calibration as published: the record plus the device, its content id and when it was made (ns)."""

    device: str
    id: str
    created_ns: int
    calibration: Calibration


def calibration_record(device: str, calibration: Calibration, created_ns: int) -> dict[str, Any]:
    """The published map: ``Calibration.to_dict()`` plus ``v, device, id, created_ns`` (JSON-able)."""
    return {"v": WIRE_VERSION, "device": validate_device_id(device), "id": calibration.content_id,
            "created_ns": int(created_ns), **calibration.to_dict()}


def encode_calibration(device: str, calibration: Calibration, created_ns: int) -> bytes:
    return msgpack.packb(calibration_record(device, calibration, created_ns), use_bin_type=True)


def calibration_from_record(record: Mapping[str, Any]) -> CalibrationMessage:
    """Validate a calibration map (as ``calibration_record`` builds it); WireError when unusable."""
    check_version(record)
    device = message_device(record)
    try:
        calibration = Calibration.from_dict(record)
    except (ValueError, TypeError) as exc:
        raise WireError("bad-calibration", f"unusable calibration: {exc}") from None
    if np.abs(calibration.offset).max() > MAX_FIELD_UT * 10 or not np.isfinite(np.linalg.cond(calibration.matrix)) \
            or np.linalg.cond(calibration.matrix) > 1e6:
        raise WireError("absurd-magnitude", "calibration offset is absurd or its matrix is singular")
    created_ns = int_field(record, "created_ns", 0)
    return CalibrationMessage(device, calibration.content_id, created_ns, calibration)


def decode_calibration(payload: Payload) -> CalibrationMessage:
    return calibration_from_record(unpack(payload))


def encode_progress(device: str, progress: Mapping[str, Any]) -> bytes:
    """Progress map of a calibration in collection; ``progress`` holds state, samples, coverage, missing, ..."""
    return msgpack.packb({"v": WIRE_VERSION, "device": validate_device_id(device), **progress}, use_bin_type=True)


def decode_progress(payload: Payload) -> dict[str, Any]:
    message = unpack(payload)
    message_device(message)
    return message
