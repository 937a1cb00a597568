"""The wire format: key expressions and msgpack messages between edge, calibrator, compass and their clients.

Every payload is a msgpack map with ``v`` (schema version: ``RECORD_VERSION`` for records, ``BINARY_ARRAYS_VERSION``
or ``LISTS_VERSION`` for samples) and ``device``. Field names carry their unit. Keys are ``<prefix>/<device>/<kind>``
with the device id as one key chunk (see ``Kind``). Decoders turn lists into numpy arrays and reject anything
malformed with ``WireError``, whose ``cause`` is a short token a service counts drops by (``DropCounter``).
Pure: no sockets, no clocks, no zenoh.

Modules, one idea each (every name is re-exported here, so ``from magnet import wire; wire.X`` works). A module is
imported when one of its names is first used (PEP 562): ``magnet heading`` reads raw batches and never encodes or
decodes a message, so it does not load msgpack, the records or the heading encoder (a tenth of its imports).

- ``keys``: ``Kind``, ``key``, ``device_from_key``, ``check_key`` (the one key check), ``validate_device_id``
  (the one id check), ``validate_prefix``, status and liveliness keys.
- ``errors``: ``WireError``, ``DropCounter``.
- ``codec``: ``LISTS_VERSION`` (1: arrays as lists), ``RECORD_VERSION`` (1: the records), ``BINARY_ARRAYS_VERSION``
  (2: sample arrays as little-endian bytes with dtype and shape, written by the services), ``VERSIONS`` (both read),
  size limits, ``pack``/``unpack`` (bounded: ``Limits`` per kind of message, ``RAW_LIMITS``, ``HEADING_LIMITS``,
  ``CALIBRATION_LIMITS``, ...),
  ``plain`` (v 2 arrays as lists, for printing) and the checks of single fields.
- ``arrays``: the one set of array checks, both versions (v 2 binary array maps, v 1 lists of numbers or integers,
  the values of float arrays), used by the raw and heading decoders alike.
- ``raw``: ``RawBatch``, ``RawColumns``, ``encode_raw``; ``raw_decode``: the one raw decoder ``decode_raw_many``
  (``decode_raw`` is it applied to one payload), with the structure checks of one message in ``raw_header``.
  Optional ``gyr_rads`` (N, 3) rad/s beside ``mag_ut`` and ``acc_ms2``, and optional ``location`` [lat_deg, lon_deg,
  alt_m] (``magnet.earth.location.Location``; cause ``bad-location``); optional per-sample ``current_a`` (N,) A and
  ``throttle`` (N,) 0..1 (``SCALAR_FIELDS``) for the motors' field.
- ``headings``: ``HeadingBatch``, the one heading encoder ``encode_headings`` (``encode_heading`` is it for one
  batch), ``decode_heading``; optional ``quat_wxyz`` and the ``DISTURBED`` flag bits.
- ``records``: ``DeviceCalibration`` (a device's calibration as published and stored; its one entry is
  ``calibration_from_record``) and ``Progress``.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from magnet.wire.codec import (
        ANY_LIMITS,
        BINARY_ARRAYS_VERSION,
        LISTS_VERSION,
        MAX_BATCH_SAMPLES,
        MAX_PAYLOAD_BYTES,
        RECORD_VERSION,
        VERSIONS,
        Limits,
        check_version,
        detached,
        pack,
        plain,
        unpack,
    )
    from magnet.wire.errors import DropCounter, WireError
    from magnet.wire.headings import (
        ANGLE_FIELDS,
        DISTURBED,
        HEADING_LIMITS,
        HeadingBatch,
        decode_heading,
        encode_heading,
        encode_headings,
    )
    from magnet.wire.keys import (
        DEFAULT_PREFIX,
        Kind,
        check_key,
        device_from_key,
        key,
        key_mismatch,
        liveliness_key,
        message_device,
        status_key,
        validate_device_id,
        validate_prefix,
        vehicle_key,
    )
    from magnet.wire.raw import (
        MAX_ACC_MS2,
        MAX_CURRENT_A,
        MAX_FIELD_UT,
        MAX_GYR_RADS,
        SCALAR_FIELDS,
        TRUTH_FIELDS,
        RawBatch,
        RawColumns,
        encode_raw,
        message_location,
    )
    from magnet.wire.raw_decode import decode_messages, decode_raw, decode_raw_many
    from magnet.wire.raw_header import RAW_LIMITS
    from magnet.wire.records import (
        CALIBRATION_LIMITS,
        MAX_VERSION,
        PROGRESS_LIMITS,
        CalibrationMessage,
        Collecting,
        DeviceCalibration,
        Progress,
        calibration_from_record,
        calibration_record,
        decode_calibration,
        decode_progress,
        encode_calibration,
        encode_progress,
    )

#: the module of each name re-exported here
_MODULE_OF: dict[str, str] = {
    "ANY_LIMITS": "codec",
    "BINARY_ARRAYS_VERSION": "codec",
    "LISTS_VERSION": "codec",
    "MAX_BATCH_SAMPLES": "codec",
    "MAX_PAYLOAD_BYTES": "codec",
    "RECORD_VERSION": "codec",
    "VERSIONS": "codec",
    "Limits": "codec",
    "check_version": "codec",
    "detached": "codec",
    "pack": "codec",
    "plain": "codec",
    "unpack": "codec",
    "DropCounter": "errors",
    "WireError": "errors",
    "ANGLE_FIELDS": "headings",
    "DISTURBED": "headings",
    "HEADING_LIMITS": "headings",
    "HeadingBatch": "headings",
    "decode_heading": "headings",
    "encode_heading": "headings",
    "encode_headings": "headings",
    "DEFAULT_PREFIX": "keys",
    "Kind": "keys",
    "check_key": "keys",
    "device_from_key": "keys",
    "key": "keys",
    "key_mismatch": "keys",
    "liveliness_key": "keys",
    "message_device": "keys",
    "status_key": "keys",
    "validate_device_id": "keys",
    "validate_prefix": "keys",
    "vehicle_key": "keys",
    "MAX_ACC_MS2": "raw",
    "MAX_CURRENT_A": "raw",
    "MAX_FIELD_UT": "raw",
    "MAX_GYR_RADS": "raw",
    "SCALAR_FIELDS": "raw",
    "TRUTH_FIELDS": "raw",
    "RawBatch": "raw",
    "RawColumns": "raw",
    "encode_raw": "raw",
    "message_location": "raw",
    "decode_messages": "raw_decode",
    "decode_raw": "raw_decode",
    "decode_raw_many": "raw_decode",
    "RAW_LIMITS": "raw_header",
    "CALIBRATION_LIMITS": "records",
    "MAX_VERSION": "records",
    "PROGRESS_LIMITS": "records",
    "CalibrationMessage": "records",
    "Collecting": "records",
    "DeviceCalibration": "records",
    "Progress": "records",
    "calibration_from_record": "records",
    "calibration_record": "records",
    "decode_calibration": "records",
    "decode_progress": "records",
    "encode_calibration": "records",
    "encode_progress": "records",
}

__all__ = [
    "ANGLE_FIELDS",
    "ANY_LIMITS",
    "BINARY_ARRAYS_VERSION",
    "CALIBRATION_LIMITS",
    "DEFAULT_PREFIX",
    "DISTURBED",
    "HEADING_LIMITS",
    "LISTS_VERSION",
    "MAX_ACC_MS2",
    "MAX_BATCH_SAMPLES",
    "MAX_CURRENT_A",
    "MAX_FIELD_UT",
    "MAX_GYR_RADS",
    "MAX_PAYLOAD_BYTES",
    "MAX_VERSION",
    "PROGRESS_LIMITS",
    "RAW_LIMITS",
    "RECORD_VERSION",
    "SCALAR_FIELDS",
    "TRUTH_FIELDS",
    "VERSIONS",
    "CalibrationMessage",
    "Collecting",
    "DeviceCalibration",
    "DropCounter",
    "HeadingBatch",
    "Kind",
    "Limits",
    "Progress",
    "RawBatch",
    "RawColumns",
    "WireError",
    "calibration_from_record",
    "calibration_record",
    "check_key",
    "check_version",
    "decode_calibration",
    "decode_heading",
    "decode_messages",
    "decode_progress",
    "decode_raw",
    "decode_raw_many",
    "detached",
    "device_from_key",
    "encode_calibration",
    "encode_heading",
    "encode_headings",
    "encode_progress",
    "encode_raw",
    "key",
    "key_mismatch",
    "liveliness_key",
    "message_device",
    "message_location",
    "pack",
    "plain",
    "status_key",
    "unpack",
    "validate_device_id",
    "validate_prefix",
    "vehicle_key",
]


def __getattr__(name: str) -> Any:
    """A re-exported name, its module imported on first use (then held here: later uses are plain lookups); a
    module's own name (``wire.raw_header``) imports it."""
    module = _MODULE_OF.get(name)
    if module is None:
        if name in _MODULE_OF.values():
            return importlib.import_module(f"{__name__}.{name}")
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f"{__name__}.{module}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
