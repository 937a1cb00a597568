"""PX4 ULog (``.ulg``) files as recorded inputs, read with ``pyulog`` (see ``docs/autopilots.md``).

Magnetometer, best first: ``sensor_mag`` (the driver's raw reading in gauss, before PX4's calibration, in the
sensor board's axes), turned into the body frame with the rotation PX4 itself would apply after its calibration
(``CAL_MAGn_ROT`` for an external magnetometer, the board rotation ``SENS_BOARD_ROT`` with ``SENS_BOARD_{X,Y,Z}_OFF``
for an internal one; ``n`` is the calibration slot whose ``CAL_MAGn_ID`` is the instance's ``device_id``); then
``vehicle_magnetometer`` and the ``magnetometer_ga`` of old ``sensor_combined`` records, both already calibrated by
PX4 in the body frame. ``--mag N`` is the topic's instance (multi id). Accelerometer and gyroscope from
``sensor_combined`` (body frame, m/s^2 and rad/s); battery current from ``battery_status.current_a``; throttle from
``actuator_motors`` (0..1, mean of the motors) or else ``actuator_outputs`` (PWM, 1000..2000 us mapped to 0..1).
"""

from __future__ import annotations

import contextlib
import functools
import io
import itertools
import mmap
import os
import struct
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from magnet.frames import euler_to_matrix, quaternion_to_euler, rotation_matrix
from magnet.units import UT_PER_GAUSS
from services.common.inputs.csvio import SampleTable
from services.common.inputs.flightlogs import LogStreams, ReferenceYaw, Stream, described, to_table
from services.common.inputs.input_options import InputOptions

TOPICS = [
    "sensor_mag",
    "vehicle_magnetometer",
    "sensor_combined",
    "battery_status",
    "actuator_motors",
    "actuator_outputs",
    "vehicle_attitude",
]
#: the first PX4 release whose sensor_mag is the raw reading (calibration moved out of the drivers into sensors)
RAW_SENSOR_MAG_SINCE = (1, 12)
#: sensor_combined's marker of a relative timestamp that is not valid
RELATIVE_INVALID = 2**31 - 1


#: a ULog message's size is 16 bits: no format flattens to more bytes than one message can hold
MAX_FORMAT_BYTES = 65_535
#: fields of one format, flattened (PX4's largest topics have a few hundred; pyulog spends about 10 us on each)
MAX_FORMAT_FIELDS = 4096
#: nested formats deeper than this are refused (PX4 nests two or three levels)
MAX_FORMAT_NESTING = 16
#: fields pyulog flattens over all the subscriptions of a log (a real log: a few thousand): about 2 s and 60 MB
MAX_SUBSCRIBED_FIELDS = 200_000
#: ULog's message types (pyulog's letters): formats, subscriptions, the first of the data section, flag bits
_FORMAT, _SUBSCRIBE, _FLAG_BITS = ord("F"), ord("A"), ord("B")
_DATA_SECTION = {ord("A"), ord("L"), ord("C")}
_KNOWN = {ord(c) for c in "IMPQARSOLCDFB"}
_TYPE_BYTES = {
    "int8_t": 1, "uint8_t": 1, "bool": 1, "char": 1, "int16_t": 2, "uint16_t": 2, "int32_t": 4, "uint32_t": 4,
    "float": 4, "int64_t": 8, "uint64_t": 8, "double": 8,
}  # fmt: skip


def _format_fields(payload: bytes) -> tuple[str, list[tuple[str, int]]] | None:
    """(name, [(type, array size or 0), ...]) of a format message, None when pyulog would not read it either."""
    try:
        name, fields = payload.split(b"\0", 1)[0].decode("utf-8", "ignore").split(":")[:2]
        parsed = []
        for field in filter(None, fields.split(";")):
            kind = field.split(" ")[0]
            count = 0
            if "[" in kind:
                kind, count = kind[: kind.find("[")], int(field[field.find("[") + 1 : field.find("]")])
            parsed.append((kind, count))
        return name, parsed
    except ValueError:
        return None


class _Formats:
    """The flattened size (fields, bytes) of each format of a log, as pyulog would flatten it; ValueError naming the
    format when one nests too deeply, contains itself or flattens beyond one message."""

    def __init__(self, path: Path, formats: dict[str, list[tuple[str, int]]]) -> None:
        self.path, self.formats = path, formats
        self.sizes: dict[str, tuple[int, int]] = {}

    def size(self, name: str, depth: int = 0) -> tuple[int, int]:
        if name in self.sizes:
            return self.sizes[name]
        if depth > MAX_FORMAT_NESTING:
            raise ValueError(f"{self.path}: format {name!r} nests more than {MAX_FORMAT_NESTING} levels (or itself)")
        fields = total = 0
        for kind, count in self.formats.get(name, []):
            inner = (1, _TYPE_BYTES[kind]) if kind in _TYPE_BYTES else self.size(kind, depth + 1)
            fields += inner[0] * max(count, 1)
            total += inner[1] * max(count, 1)
            if total > MAX_FORMAT_BYTES or fields > MAX_FORMAT_FIELDS:
                raise ValueError(
                    f"{self.path}: format {name!r} flattens to more than {MAX_FORMAT_FIELDS} fields or "
                    f"{MAX_FORMAT_BYTES} bytes (a ULog message holds no more): a damaged or crafted file"
                )
        self.sizes[name] = (fields, total)
        return fields, total


def _messages(view: Any, start: int, stop: int) -> Iterator[tuple[int, int, int]]:
    """(offset, type, size) of each message from ``start`` to ``stop`` as pyulog walks them: a message cut short
    ends the walk; one of an unknown type that looks damaged (type 0, size 0 or over 10,000) is skipped a byte."""
    position = start
    while position + 3 <= stop:
        size, kind = struct.unpack_from("<HB", view, position)
        if position + 3 + size > stop:
            return
        yield position, kind, size
        damaged = kind not in _KNOWN and (kind == 0 or size == 0 or size > 10_000)
        position += 1 if damaged else 3 + size


def check_ulog(path: Path) -> None:
    """Walk the ULog at ``path`` (its message headers, its formats and subscriptions) before pyulog parses it;
    ValueError naming the file for one whose subscriptions would make pyulog flatten more than
    ``MAX_SUBSCRIBED_FIELDS`` fields, or that holds a format beyond ``MAX_FORMAT_FIELDS``, ``MAX_FORMAT_BYTES`` or
    ``MAX_FORMAT_NESTING``. Memory: none beyond the formats (the file is mapped); about 50 ms for 4 MB."""
    with open(path, "rb") as handle:
        if os.fstat(handle.fileno()).st_size < 16:
            return  # pyulog says what is wrong with it
        with mmap.mmap(handle.fileno(), 0, access=mmap.ACCESS_READ) as view:
            _check_view(path, view)


def _check_view(path: Path, view: Any) -> None:
    formats: dict[str, list[tuple[str, int]]] = {}
    data_start, appended = len(view), []
    for position, kind, size in _messages(view, 16, len(view)):
        payload = view[position + 3 : position + 3 + size]
        if kind in _DATA_SECTION:
            data_start = position
            break
        if kind == _FORMAT and (parsed := _format_fields(payload)) is not None:
            formats[parsed[0]] = parsed[1]
        elif kind == _FLAG_BITS and size >= 40:
            appended = [o for o in struct.unpack_from("<3Q", payload, 16) if o]
    sizes = _Formats(path, formats)
    subscribed = 0
    bounds = [data_start, *appended, len(view)]
    for start, stop in itertools.pairwise(bounds):
        for position, kind, size in _messages(view, min(start, len(view)), min(stop, len(view))):
            if kind != _SUBSCRIBE or size < 4:
                continue
            name = view[position + 6 : position + 3 + size].split(b"\0", 1)[0].decode("utf-8", "ignore")
            fields = sizes.size(name)[0] if name in formats else 0
            subscribed += fields
            if subscribed > MAX_SUBSCRIBED_FIELDS:
                raise ValueError(
                    f"{path}: its subscriptions flatten to more than {MAX_SUBSCRIBED_FIELDS} fields in all "
                    "(a real log: a few thousand): a damaged or crafted file"
                )


def _parse(path: Path, topics: list[str] | None) -> Any:
    """pyulog's parse of ``path`` (only ``topics`` when given); ValueError naming the file when it cannot. The last
    few parses are kept (keyed by the file's size and modification time): a command that reads a log for its
    magnetometer and again for the autopilot's attitude parses it once."""
    stat = path.stat()
    return _parse_cached(path.resolve(), stat.st_size, stat.st_mtime_ns, None if topics is None else tuple(topics))


@functools.lru_cache(maxsize=4)
def _parse_cached(path: Path, _size: int, _mtime_ns: int, topics: tuple[str, ...] | None) -> Any:
    from pyulog import ULog

    check_ulog(path)
    quiet = io.StringIO()  # pyulog prints its complaints; they become this function's one error
    with open(path, "rb") as handle:
        try:
            with contextlib.redirect_stdout(quiet), contextlib.redirect_stderr(quiet):
                return ULog(handle, message_name_filter_list=None if topics is None else list(topics))
        except Exception as exc:  # pyulog raises whatever its parser meets in a damaged file
            raise ValueError(f"{path}: not a readable PX4 ULog file ({type(exc).__name__}: {exc})") from None


def _open(path: Path, topics: list[str]) -> Any:
    """The parsed log (only ``topics``); ValueError naming the file when pyulog cannot read it, or when it holds no
    logged data at all (cut short before its data, or no flight log)."""
    ulog = _parse(path, topics)
    if not ulog.data_list and not _parse(path, None).data_list:  # the second parse only on the way to an error
        damage = " (pyulog found it damaged)" if ulog.file_corruption else ""
        raise ValueError(f"{path}: the ULog holds no logged data{damage}: it was cut short or is not a flight log")
    return ulog


def px4_version(release: int) -> tuple[int, int] | None:
    """(major, minor) of ULog's ``ver_sw_release`` (0xAABBCCTT: major, minor, patch, type), None when not set."""
    release = int(release)
    return None if release <= 0 else ((release >> 24) & 0xFF, (release >> 16) & 0xFF)


def _datasets(ulog: Any, name: str) -> dict[int, dict[str, np.ndarray]]:
    """multi id -> fields of topic ``name`` (empty when not logged)."""
    return {d.multi_id: d.data for d in ulog.data_list if d.name == name and len(d.data.get("timestamp", ())) > 0}


def _vector(data: dict[str, np.ndarray], name: str) -> np.ndarray:
    return np.column_stack([np.asarray(data[f"{name}[{k}]"], dtype=float) for k in range(3)])


def _board_rotation(params: dict[str, Any], device_id: int) -> tuple[np.ndarray, str]:
    """(sensor -> body rotation PX4 applies after calibrating ``device_id``, in words)."""
    slot = next((n for n in range(4) if int(params.get(f"CAL_MAG{n}_ID", 0)) == device_id and device_id), None)
    rot = int(params.get(f"CAL_MAG{slot}_ROT", -1)) if slot is not None else -1
    if rot >= 0:
        return rotation_matrix(rot), f"CAL_MAG{slot}_ROT={rot}"
    board = int(params.get("SENS_BOARD_ROT", 0))
    offsets = [float(params.get(f"SENS_BOARD_{axis}_OFF", 0.0)) for axis in "XYZ"]
    offset = euler_to_matrix(offsets[2], offsets[1], offsets[0])
    tilted = any(abs(o) > 1e-3 for o in offsets)
    words = f"SENS_BOARD_ROT={board}" + (f" with offsets {[round(o, 2) for o in offsets]} deg" if tilted else "")
    return offset @ rotation_matrix(board), words


def _mag(ulog: Any, path: Path, instance: int) -> tuple[Stream, str]:
    """(the magnetometer instance's stream in uT body frame, what it is); ValueError when there is none."""
    params = ulog.initial_parameters
    raw = _datasets(ulog, "sensor_mag")
    calibrated = _datasets(ulog, "vehicle_magnetometer")
    if instance in raw:
        data = raw[instance]
        field = np.column_stack([np.asarray(data[a], dtype=float) for a in "xyz"]) * UT_PER_GAUSS
        t = np.asarray(data.get("timestamp_sample", data["timestamp"]), dtype=float)
        version = px4_version(ulog.msg_info_dict.get("ver_sw_release", 0))
        if version is not None and version < RAW_SENSOR_MAG_SINCE:
            note = (
                f"sensor_mag instance {instance} (PX4 {version[0]}.{version[1]} logs it after the driver's calibration)"
            )
            return Stream(t, field), note
        rotation, words = _board_rotation(params, int(data.get("device_id", [0])[0]))
        note = f"sensor_mag instance {instance} (raw, uncalibrated; gauss; into the body frame by {words})"
        return Stream(t, field @ rotation.T), note
    if instance in calibrated:
        data = calibrated[instance]
        t = data.get("timestamp_sample", data["timestamp"])
        field = _vector(data, "magnetometer_ga") * UT_PER_GAUSS
        note = f"vehicle_magnetometer instance {instance} (already calibrated by PX4, body frame; no raw sensor_mag)"
        return Stream(np.asarray(t, dtype=float), field), note
    combined = _datasets(ulog, "sensor_combined").get(0)
    if instance == 0 and combined is not None and "magnetometer_ga[0]" in combined:
        t = _relative(combined, "magnetometer_timestamp_relative")
        note = "sensor_combined.magnetometer_ga (already calibrated by PX4, body frame; this log has no sensor_mag)"
        return Stream(t, _vector(combined, "magnetometer_ga") * UT_PER_GAUSS), note
    counts = [len(raw), len(calibrated)]
    if not any(counts) and not (combined is not None and "magnetometer_ga[0]" in combined):
        if any(name in ulog.message_formats for name in ("sensor_mag", "vehicle_magnetometer", "sensor_combined")):
            raise ValueError(f"{path}: this log defines magnetometer topics but holds no samples of them (cut short?)")
        raise ValueError(
            f"{path}: this log holds no magnetometer (no sensor_mag, vehicle_magnetometer or "
            "sensor_combined.magnetometer_ga records)"
        )
    found = sorted(set(raw) | set(calibrated) | ({0} if combined is not None else set()))
    raise ValueError(
        f"{path}: no magnetometer instance {instance} in this log (instances: {found}): pick one with --mag"
    )


def _relative(data: dict[str, np.ndarray], field: str) -> np.ndarray:
    """Absolute times (us) of a sensor_combined field logged relative to the record's timestamp."""
    t = np.asarray(data["timestamp"], dtype=float)
    relative = np.asarray(data[field], dtype=float)
    return np.where(relative == RELATIVE_INVALID, np.nan, t + relative)


def _inertial(ulog: Any) -> tuple[Stream | None, Stream | None, str]:
    combined = _datasets(ulog, "sensor_combined").get(0)
    if combined is None:
        return None, None, ""
    t = np.asarray(combined["timestamp"], dtype=float)
    acc_t = _relative(combined, "accelerometer_timestamp_relative")
    acc = Stream(acc_t, _vector(combined, "accelerometer_m_s2"))
    return acc, Stream(t, _vector(combined, "gyro_rad")), "sensor_combined accelerometer and gyroscope"


def _throttle(ulog: Any) -> tuple[Stream | None, str]:
    motors = _datasets(ulog, "actuator_motors").get(0)
    if motors is not None:
        controls = np.column_stack([v for k, v in motors.items() if k.startswith("control[")]).astype(float)
        with np.errstate(invalid="ignore"):
            mean = np.nanmean(np.where(np.isfinite(controls), controls, np.nan), axis=1)
        return Stream(np.asarray(motors["timestamp"], dtype=float), np.clip(mean, 0, 1)), "actuator_motors throttle"
    outputs = _datasets(ulog, "actuator_outputs").get(0)
    if outputs is None or "noutputs" not in outputs:
        return None, ""
    used = max(1, min(4, int(np.max(outputs["noutputs"]))))
    pwm = np.column_stack([np.asarray(outputs[f"output[{k}]"], dtype=float) for k in range(used)]).mean(axis=1)
    throttle = np.clip((pwm - 1000.0) / 1000.0, 0.0, 1.0)
    return Stream(np.asarray(outputs["timestamp"], dtype=float), throttle), "actuator_outputs throttle (PWM)"


def _current(ulog: Any) -> tuple[Stream | None, str]:
    battery = _datasets(ulog, "battery_status").get(0)
    if battery is None or "current_a" not in battery:
        return None, ""
    current = np.asarray(battery["current_a"], dtype=float)
    current = np.where(current < 0, np.nan, current)  # -1: not measured
    return Stream(np.asarray(battery["timestamp"], dtype=float), current), "battery_status current"


def read_ulog(path: Path, options: InputOptions) -> SampleTable:
    """The samples of a PX4 ULog file (see the module docstring); ValueError naming the file otherwise."""
    ulog = _open(path, TOPICS)
    mag, note = _mag(ulog, path, options.mag or 0)
    acc, gyr, inertial = _inertial(ulog)
    extra: dict[str, Stream] = {}
    others = [inertial] if inertial else []
    for name, (stream, words) in (("current_a", _current(ulog)), ("throttle", _throttle(ulog))):
        if stream is not None:
            extra[name] = stream
            others.append(words)
    if others:
        note += "; with " + described(others)
    return to_table(path, LogStreams(mag, acc, gyr, extra, f"PX4 ULog: {note}"))


def _declination(params: dict[str, Any]) -> str:
    if "EKF2_MAG_DECL" in params:
        auto = int(params.get("EKF2_DECL_TYPE", 0)) & 1
        text = f"EKF2_MAG_DECL={float(params['EKF2_MAG_DECL']):.2f} deg"
        return text + (" (EKF2_DECL_TYPE: looked up from the position)" if auto else "")
    if "ATT_MAG_DECL" in params:
        text = f"ATT_MAG_DECL={float(params['ATT_MAG_DECL']):.2f} deg"
        return text + (" (ATT_MAG_DECL_A=1: looked up from the position)" if params.get("ATT_MAG_DECL_A") else "")
    return "not in the log's parameters"


def ulog_reference_yaw(path: Path) -> ReferenceYaw:
    """PX4's own attitude estimate in the log (``vehicle_attitude``, instance 0); ValueError when it is not logged."""
    ulog = _open(path, ["vehicle_attitude"])
    data = _datasets(ulog, "vehicle_attitude").get(0)
    if data is None:
        raise ValueError(f"{path}: no vehicle_attitude records: the log holds no attitude estimate to compare with")
    quat = np.column_stack([np.asarray(data[f"q[{k}]"], dtype=float) for k in range(4)])
    yaw, _, _ = quaternion_to_euler(quat)
    finite = np.isfinite(yaw) & np.all(np.isfinite(quat), axis=1)
    t = np.asarray(data["timestamp"], dtype=float)[finite] / 1e6
    return ReferenceYaw(t, yaw[finite], "vehicle_attitude", _declination(ulog.initial_parameters))
