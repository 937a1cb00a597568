"""The wire format: key expressions and msgpack messages between edge, calibrator, compass and their clients.

Every payload is a msgpack map with ``v`` (schema version, ``WIRE_VERSION``) and ``device``. Field names carry their
unit. Keys are ``<prefix>/<device>/<kind>`` with the device id as one key chunk (see ``Kind``). Decoders turn lists
into numpy arrays and reject anything malformed with ``WireError``, whose ``cause`` is a short token a service counts
drops by (``DropCounter``). Pure: no sockets, no clocks, no zenoh.

Messages (arrays aligned sample by sample, N = batch length):

- raw: ``{v, device, seq, sensor, t_ns: [N ints], mag_ut: [[x, y, z]] * N, acc_ms2: [[x, y, z]] * N (optional),
  truth: {heading_deg: [N], pitch_deg: [N], roll_deg: [N]} (optional, simulator only)}``
- calibration: ``Calibration.to_dict()`` plus ``v, device, id (content id), created_ns``
- progress: ``{v, device, state, method, session, samples, coverage, cells_hit, cell_count, missing: [str],
  residual_rms_ut, reason, t_ns}``
- heading: ``{v, device, seq, t_ns: [N], heading_deg: [N] (magnetic), true_heading_deg: [N], pitch_deg: [N],
  roll_deg: [N], field_ut: [[x, y, z]] * N, declination_deg, calibration_id, flags: [N ints]}``
"""

from __future__ import annotations

import dataclasses
import enum
import math
from typing import Any, Mapping, Sequence

import msgpack
import numpy as np

from magnet.model import Calibration

WIRE_VERSION = 1
DEFAULT_PREFIX = "magnet"
#: Larger payloads are refused before they are unpacked.
MAX_PAYLOAD_BYTES = 4 * 1024 * 1024
#: Most samples in one raw or heading batch.
MAX_BATCH_SAMPLES = 10_000
#: Magnitudes beyond these are not a magnetometer or an accelerometer on Earth (a +-8 gauss chip reads 800 uT).
MAX_FIELD_UT = 5_000.0
MAX_ACC_MS2 = 2_000.0
_FORBIDDEN_ID_CHARS = frozenset("/*$?#")
_FORBIDDEN_PREFIX_CHARS = frozenset("*$?#")
_TRUTH_FIELDS = ("heading_deg", "pitch_deg", "roll_deg")


class WireError(ValueError):
    """A message that cannot be used. ``cause`` is a short token to count drops by."""

    def __init__(self, cause: str, message: str) -> None:
        super().__init__(message)
        self.cause = cause


class Kind(enum.Enum):
    """What a key carries: the key suffix after ``<prefix>/<device>/``."""

    RAW = "raw"
    CALIBRATION = "calibration"
    HISTORY = "calibration/history"
    PROGRESS = "calibration/progress"
    CALIBRATE = "calibrate"
    HEADING = "heading"


def validate_device_id(device: Any) -> str:
    """Return ``device`` if it is a usable single key chunk, else raise ValueError saying why."""
    if not isinstance(device, str) or not device:
        raise ValueError("a device id must be a non-empty string")
    bad = sorted(set(device) & _FORBIDDEN_ID_CHARS)
    if bad:
        raise ValueError(f"device id {device!r} contains {' '.join(bad)}: ids may not contain / * $ ? #")
    if len(device) > 128 or not device.isprintable() or device.strip() != device:
        raise ValueError(f"device id {device!r} must be printable, without surrounding spaces, at most 128 chars")
    return device


def validate_prefix(prefix: str) -> str:
    """Return ``prefix`` (one or more key chunks, no wildcards) or raise ValueError."""
    if not isinstance(prefix, str) or not prefix or prefix.startswith("/") or prefix.endswith("/") or "//" in prefix:
        raise ValueError(f"key prefix {prefix!r} must be non-empty chunks separated by single '/'")
    bad = sorted(set(prefix) & _FORBIDDEN_PREFIX_CHARS)
    if bad:
        raise ValueError(f"key prefix {prefix!r} contains {' '.join(bad)}: no wildcards or special characters")
    return prefix


def key(prefix: str, device: str, kind: Kind) -> str:
    """``<prefix>/<device>/<kind>``; ``device`` may be ``*`` to match every device."""
    if device != "*":
        validate_device_id(device)
    return f"{prefix}/{device}/{kind.value}"


def device_from_key(prefix: str, key_expr: str, kind: Kind) -> str:
    """The device chunk of ``<prefix>/<device>/<kind>``; WireError if the key has another shape."""
    head, tail = f"{prefix}/", f"/{kind.value}"
    if not (key_expr.startswith(head) and key_expr.endswith(tail)):
        raise WireError("bad-key", f"key {key_expr!r} is not {head}<device>{tail}")
    device = key_expr[len(head):-len(tail)]
    try:
        return validate_device_id(device)
    except ValueError as exc:
        raise WireError("bad-key", str(exc)) from None


def key_mismatch(key_expr: str, device: str) -> WireError:
    """The error for a message whose device is not the one its key names."""
    return WireError("key-mismatch", f"key {key_expr} carries device {device}")


def check_key(prefix: str, key_expr: str, kind: Kind, device: str) -> None:
    """WireError unless ``key_expr`` is ``<prefix>/<device>/<kind>`` for the message's own ``device``."""
    if device_from_key(prefix, key_expr, kind) != device:
        raise key_mismatch(key_expr, device)


def status_key(prefix: str, service: str) -> str:
    """Queryable key of a service's counters: ``<prefix>/@status/<service>``."""
    return f"{prefix}/@status/{service}"


def liveliness_key(prefix: str, role: str, name: str) -> str:
    """Liveliness token key: ``<prefix>/@alive/<role>/<name>`` (role: edge, device, calibrator, compass, router)."""
    return f"{prefix}/@alive/{role}/{name}"


# --------------------------------------------------------------------------------------------------------- records


@dataclasses.dataclass(frozen=True, eq=False)
class RawBatch:
    """N raw samples of one device. t_ns (N,) int64 ns; mag_ut (N, 3) uT body frame; acc_ms2 (N, 3) m/s^2 or None;
    truth: {"heading_deg", "pitch_deg", "roll_deg"} -> (N,) degrees, simulator only, else None."""

    device: str
    seq: int
    sensor: str
    t_ns: np.ndarray
    mag_ut: np.ndarray
    acc_ms2: np.ndarray | None = None
    truth: Mapping[str, np.ndarray] | None = None

    def __len__(self) -> int:
        return int(self.t_ns.shape[0])


@dataclasses.dataclass(frozen=True, eq=False)
class HeadingBatch:
    """N headings of one device, aligned with one raw batch. Angles in degrees, field_ut (N, 3) corrected uT,
    flags (N,) ``magnet.heading.HeadingFlag`` bits, declination_deg east-positive."""

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

    def __len__(self) -> int:
        return int(self.t_ns.shape[0])


@dataclasses.dataclass(frozen=True, eq=False)
class CalibrationMessage:
    """A calibration as published: the record plus the device, its content id and when it was made (ns)."""

    device: str
    id: str
    created_ns: int
    calibration: Calibration


# ---------------------------------------------------------------------------------------------------------- counting


class DropCounter:
    """Counts dropped messages by cause. ``count`` returns True the first time a cause is seen (log it then)."""

    def __init__(self) -> None:
        self.counts: dict[str, int] = {}

    def count(self, cause: str) -> bool:
        first = cause not in self.counts
        self.counts[cause] = self.counts.get(cause, 0) + 1
        return first

    def drop(self, exc: WireError, what: str, logger: Any) -> None:
        """Count a dropped ``what`` message (``<what>:<cause>``); log only the first of each cause."""
        if self.count(f"{what}:{exc.cause}"):
            logger.warning("dropping malformed %s message (%s): %s; further ones only counted", what, exc.cause, exc)

    @property
    def total(self) -> int:
        return sum(self.counts.values())


# ------------------------------------------------------------------------------------------------------- primitives


def pack(message: Mapping[str, Any]) -> bytes:
    """msgpack bytes of a map (with ``v`` added when missing)."""
    if "v" not in message:
        message = {"v": WIRE_VERSION, **message}
    return msgpack.packb(message, use_bin_type=True)


def unpack(payload: bytes | bytearray | memoryview) -> dict[str, Any]:
    """The map inside ``payload``; WireError when oversized, not msgpack, not a map or of another version."""
    if len(payload) > MAX_PAYLOAD_BYTES:
        raise WireError("oversized", f"payload of {len(payload)} bytes exceeds {MAX_PAYLOAD_BYTES}")
    try:
        message = msgpack.unpackb(payload, raw=False, strict_map_key=True)
    except Exception as exc:  # msgpack raises several unrelated types for garbage
        raise WireError("not-msgpack", f"payload is not msgpack: {type(exc).__name__}") from None
    if not isinstance(message, dict):
        raise WireError("not-a-map", f"payload is a msgpack {type(message).__name__}, not a map")
    if message.get("v") != WIRE_VERSION:
        raise WireError("wrong-version", f"schema version {message.get('v')!r}, expected {WIRE_VERSION}")
    return message


def _device(message: Mapping[str, Any]) -> str:
    try:
        return validate_device_id(message.get("device"))
    except ValueError as exc:
        raise WireError("bad-device", str(exc)) from None


def _int(message: Mapping[str, Any], name: str, default: int | None = None) -> int:
    value = message.get(name, default)
    if isinstance(value, bool) or not isinstance(value, int):
        raise WireError("bad-field", f"{name} must be an integer, got {type(value).__name__}")
    return value


def _array(value: Any, name: str, shape_tail: tuple[int, ...], limit: float | None) -> np.ndarray:
    """float64 array of shape (N, *shape_tail), finite, |x| <= limit."""
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise WireError("bad-shape", f"{name} is not an array of numbers") from None
    if arr.ndim != 1 + len(shape_tail) or arr.shape[1:] != shape_tail:
        raise WireError("bad-shape", f"{name} has shape {arr.shape}, expected (N, {', '.join(map(str, shape_tail))})")
    if arr.shape[0] > MAX_BATCH_SAMPLES:
        raise WireError("oversized", f"{name} holds {arr.shape[0]} samples, more than {MAX_BATCH_SAMPLES}")
    if not np.isfinite(arr).all():
        raise WireError("non-finite", f"{name} holds non-finite values")
    if limit is not None and arr.size and np.abs(arr).max() > limit:
        raise WireError("absurd-magnitude", f"{name} holds values beyond +-{limit:g}")
    return arr


def _time_array(value: Any) -> np.ndarray:
    try:
        arr = np.asarray(value)
    except (TypeError, ValueError, OverflowError):
        raise WireError("bad-shape", "t_ns is not an array of integers") from None
    if arr.ndim != 1 or (arr.size and arr.dtype.kind not in "iu"):
        raise WireError("bad-shape", f"t_ns must be a list of integers, got shape {arr.shape} dtype {arr.dtype}")
    if arr.shape[0] > MAX_BATCH_SAMPLES:
        raise WireError("oversized", f"t_ns holds {arr.shape[0]} samples, more than {MAX_BATCH_SAMPLES}")
    return arr.astype(np.int64)


def _check_length(n: int, arrays: Mapping[str, np.ndarray]) -> None:
    for name, arr in arrays.items():
        if arr.shape[0] != n:
            raise WireError("bad-shape", f"{name} holds {arr.shape[0]} samples but t_ns holds {n}")


# ------------------------------------------------------------------------------------------------------------ raw


def encode_raw(batch: RawBatch) -> bytes:
    message: dict[str, Any] = {
        "v": WIRE_VERSION,
        "device": batch.device,
        "seq": int(batch.seq),
        "sensor": batch.sensor,
        "t_ns": np.asarray(batch.t_ns, dtype=np.int64).tolist(),
        "mag_ut": np.asarray(batch.mag_ut, dtype=float).tolist(),
    }
    if batch.acc_ms2 is not None:
        message["acc_ms2"] = np.asarray(batch.acc_ms2, dtype=float).tolist()
    if batch.truth is not None:
        message["truth"] = {name: np.asarray(batch.truth[name], dtype=float).tolist() for name in _TRUTH_FIELDS}
    return msgpack.packb(message, use_bin_type=True)


def decode_raw(payload: bytes | bytearray | memoryview, *, with_truth: bool = True) -> RawBatch:
    """RawBatch from a payload; WireError (with ``cause``) for anything malformed or physically impossible.

    ``with_truth=False`` skips the simulator's truth (faster, for consumers that do not use it)."""
    message = unpack(payload)
    device = _device(message)
    t_ns = _time_array(message.get("t_ns"))
    n = t_ns.shape[0]
    if n == 0:
        raise WireError("empty", "a raw batch holds no samples")
    mag, acc = _vectors(message.get("mag_ut"), message.get("acc_ms2"), n)
    truth = None
    if with_truth and message.get("truth") is not None:
        raw_truth = message["truth"]
        if not isinstance(raw_truth, dict):
            raise WireError("bad-field", "truth must be a map")
        truth = {name: _array(raw_truth.get(name), f"truth.{name}", (), 1e4) for name in _TRUTH_FIELDS}
        _check_length(n, truth)
    sensor = message.get("sensor", "")
    if not isinstance(sensor, str):
        raise WireError("bad-field", "sensor must be a string")
    return RawBatch(device, _int(message, "seq", 0), sensor, t_ns, mag, acc, truth)


def _vectors(mag: Any, acc: Any, n: int) -> tuple[np.ndarray, np.ndarray | None]:
    """mag (n, 3) and acc (n, 3) or None, converted and checked in one pass (the hot path of every consumer)."""
    try:
        both = np.array(mag if acc is None else (mag, acc), dtype=np.float64)
    except (TypeError, ValueError):
        raise WireError("bad-shape", "mag_ut/acc_ms2 are not arrays of numbers of the same shape") from None
    expected = (n, 3) if acc is None else (2, n, 3)
    if both.shape != expected:
        raise WireError("bad-shape", f"mag_ut/acc_ms2 have shape {both.shape}, expected {expected} (N = len(t_ns))")
    if not np.isfinite(both).all():
        raise WireError("non-finite", "mag_ut or acc_ms2 holds non-finite values")
    if acc is None:
        if np.abs(both).max() > MAX_FIELD_UT:
            raise WireError("absurd-magnitude", f"mag_ut holds values beyond +-{MAX_FIELD_UT:g}")
        return both, None
    if np.abs(both[0]).max() > MAX_FIELD_UT or np.abs(both[1]).max() > MAX_ACC_MS2:
        raise WireError("absurd-magnitude", f"mag_ut beyond +-{MAX_FIELD_UT:g} or acc_ms2 beyond +-{MAX_ACC_MS2:g}")
    return both[0], both[1]


@dataclasses.dataclass(frozen=True, eq=False)
class RawColumns:
    """B raw batches decoded together, S samples in all, batch after batch.

    devices, seqs: per batch (B); counts (B,) int samples per batch; t_ns (S,) int64; mag_ut (S, 3) uT;
    acc_ms2 (S, 3) m/s^2 with NaN rows for batches that carry no accelerometer."""

    devices: list[str]
    seqs: list[int]
    counts: np.ndarray
    t_ns: np.ndarray
    mag_ut: np.ndarray
    acc_ms2: np.ndarray

    @classmethod
    def from_batches(cls, batches: Sequence[RawBatch]) -> "RawColumns":
        nan3 = np.full((1, 3), np.nan)
        return cls([b.device for b in batches], [b.seq for b in batches],
                   np.array([len(b) for b in batches], dtype=np.int64),
                   np.concatenate([b.t_ns for b in batches]).astype(np.int64) if batches else np.empty(0, np.int64),
                   np.concatenate([b.mag_ut for b in batches]) if batches else np.empty((0, 3)),
                   np.concatenate([b.acc_ms2 if b.acc_ms2 is not None else np.repeat(nan3, len(b), 0)
                                   for b in batches]) if batches else np.empty((0, 3)))

    def batches(self) -> list[RawBatch]:
        """One RawBatch (views) per batch."""
        bounds = np.concatenate([[0], np.cumsum(self.counts)]).tolist()
        out = []
        for i, (lo, hi) in enumerate(zip(bounds[:-1], bounds[1:])):
            acc = self.acc_ms2[lo:hi]
            out.append(RawBatch(self.devices[i], self.seqs[i], "", self.t_ns[lo:hi], self.mag_ut[lo:hi],
                                None if np.isnan(acc).all() else acc))
        return out

    def select(self, keep: np.ndarray) -> "RawColumns":
        """The batches where ``keep`` (B,) bool is True."""
        per_sample = np.repeat(keep, self.counts)
        return RawColumns([d for d, k in zip(self.devices, keep) if k], [q for q, k in zip(self.seqs, keep) if k],
                          self.counts[keep], self.t_ns[per_sample], self.mag_ut[per_sample], self.acc_ms2[per_sample])


def decode_raw_many(payloads: Sequence[bytes]) -> tuple[RawColumns, list[tuple[int, WireError]]]:
    """Decode many raw payloads at once (the hot path of a busy consumer) with the same checks as ``decode_raw``.

    Returns the good batches as columns, in input order, and (index, WireError) for each payload refused. Each
    message's structure is checked in Python and the numbers of all messages in one numpy pass; a message in any
    doubt goes through ``decode_raw`` for its exact verdict. ``truth`` is not decoded."""
    plain: list[tuple[int, dict]] = []
    doubtful: list[int] = []
    errors: list[tuple[int, WireError]] = []
    for index, payload in enumerate(payloads):
        try:
            message = unpack(payload)
        except WireError as exc:
            errors.append((index, exc))
            continue
        if _plain_raw(message):
            plain.append((index, message))
        else:
            doubtful.append(index)
    ok, columns = _columns_of(plain) if plain else (np.zeros(0, bool), None)
    doubtful += [index for (index, _), fine in zip(plain, ok) if not fine]
    rescued: dict[int, RawBatch] = {}
    for index in doubtful:
        try:
            rescued[index] = decode_raw(payloads[index], with_truth=False)
        except WireError as exc:
            errors.append((index, exc))
    fast = columns.select(ok) if columns is not None else RawColumns.from_batches([])
    if rescued:  # rare: fall back to batch objects to keep the input order
        fast_indices = [index for (index, _), fine in zip(plain, ok) if fine]
        batches = dict(zip(fast_indices, fast.batches())) | rescued
        fast = RawColumns.from_batches([batches[index] for index in sorted(batches)])
    return fast, sorted(errors, key=lambda item: item[0])


def _plain_raw(message: Mapping[str, Any]) -> bool:
    """True when the message's structure is the ordinary one (the numbers are checked later, all together)."""
    t_ns, mag, acc, device, seq = (message.get(k) for k in ("t_ns", "mag_ut", "acc_ms2", "device", "seq"))
    n = len(t_ns) if type(t_ns) is list else 0
    return (0 < n <= MAX_BATCH_SAMPLES and type(mag) is list and len(mag) == n
            and (acc is None or (type(acc) is list and len(acc) == n))
            and type(device) is str and device in _valid_ids(device)
            and type(seq) is int and type(message.get("sensor", "")) is str)


_VALID_IDS: set[str] = set()


def _valid_ids(device: str) -> set[str]:
    """The cache of device ids seen valid (validated once each)."""
    if device not in _VALID_IDS and len(_VALID_IDS) < 100_000:
        try:
            _VALID_IDS.add(validate_device_id(device))
        except ValueError:
            pass
    return _VALID_IDS


def _columns_of(items: list[tuple[int, dict]]) -> tuple[np.ndarray, RawColumns | None]:
    """(ok (B,), columns) for plain messages; all not ok when their numbers do not form arrays (judged one by one)."""
    messages = [m for _, m in items]
    counts = np.array([len(m["t_ns"]) for m in messages], dtype=np.int64)
    t_all: list = []
    mag_all: list = []
    acc_all: list = []
    nan_rows = [[math.nan] * 3]
    for m, n in zip(messages, counts.tolist()):
        t_all += m["t_ns"]
        mag_all += m["mag_ut"]
        acc = m.get("acc_ms2")
        acc_all += acc if acc is not None else nan_rows * n
    try:
        t_ns = np.array(t_all)
        mag = np.array(mag_all, dtype=np.float64)
        acc = np.array(acc_all, dtype=np.float64)
    except (TypeError, ValueError, OverflowError):
        return np.zeros(len(messages), bool), None
    if t_ns.dtype.kind not in "iu" or mag.shape != (len(t_all), 3) or acc.shape != mag.shape:
        return np.zeros(len(messages), bool), None
    has_acc = np.repeat(np.array([m.get("acc_ms2") is not None for m in messages]), counts)
    sample_ok = (np.isfinite(mag).all(axis=1) & (np.abs(mag) <= MAX_FIELD_UT).all(axis=1)
                 & (~has_acc | (np.isfinite(acc).all(axis=1) & (np.abs(acc) <= MAX_ACC_MS2).all(axis=1))))
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    ok = np.logical_and.reduceat(sample_ok, starts) if len(sample_ok) else np.zeros(0, bool)
    columns = RawColumns([m["device"] for m in messages], [m["seq"] for m in messages], counts,
                         t_ns.astype(np.int64), mag, acc)
    return ok, columns


# -------------------------------------------------------------------------------------------------------- heading


def encode_heading(batch: HeadingBatch) -> bytes:
    return msgpack.packb({
        "v": WIRE_VERSION,
        "device": batch.device,
        "seq": int(batch.seq),
        "t_ns": np.asarray(batch.t_ns, dtype=np.int64).tolist(),
        "heading_deg": np.asarray(batch.heading_deg, dtype=float).tolist(),
        "true_heading_deg": np.asarray(batch.true_heading_deg, dtype=float).tolist(),
        "pitch_deg": np.asarray(batch.pitch_deg, dtype=float).tolist(),
        "roll_deg": np.asarray(batch.roll_deg, dtype=float).tolist(),
        "field_ut": np.asarray(batch.field_ut, dtype=float).tolist(),
        "declination_deg": float(batch.declination_deg),
        "calibration_id": batch.calibration_id,
        "flags": np.asarray(batch.flags, dtype=np.int64).tolist(),
    }, use_bin_type=True)


def encode_headings(columns: RawColumns, heading_deg: np.ndarray, true_heading_deg: np.ndarray,
                    pitch_deg: np.ndarray, roll_deg: np.ndarray, field_ut: np.ndarray, flags: np.ndarray,
                    declination_deg: float, calibration_ids: Sequence[str]) -> list[bytes]:
    """One heading message per batch of ``columns`` (byte for byte what ``encode_heading`` gives for each).

    The arrays are aligned with ``columns``' S samples; each is turned into Python lists once and sliced per batch."""
    t_ns, heading, true_heading, pitch, roll, field, flag = (
        np.asarray(a, dtype=dtype).tolist() for a, dtype in (
            (columns.t_ns, np.int64), (heading_deg, float), (true_heading_deg, float), (pitch_deg, float),
            (roll_deg, float), (field_ut, float), (flags, np.int64)))
    bounds = np.concatenate([[0], np.cumsum(columns.counts)]).tolist()
    declination = float(declination_deg)
    return [msgpack.packb({
        "v": WIRE_VERSION, "device": device, "seq": int(seq), "t_ns": t_ns[lo:hi], "heading_deg": heading[lo:hi],
        "true_heading_deg": true_heading[lo:hi], "pitch_deg": pitch[lo:hi], "roll_deg": roll[lo:hi],
        "field_ut": field[lo:hi], "declination_deg": declination, "calibration_id": cal_id, "flags": flag[lo:hi],
    }, use_bin_type=True) for device, seq, cal_id, lo, hi in zip(columns.devices, columns.seqs, calibration_ids,
                                                                  bounds[:-1], bounds[1:])]


def decode_heading(payload: bytes | bytearray | memoryview) -> HeadingBatch:
    message = unpack(payload)
    device = _device(message)
    t_ns = _time_array(message.get("t_ns"))
    angles = {name: _array(message.get(name), name, (), 1e4)
              for name in ("heading_deg", "true_heading_deg", "pitch_deg", "roll_deg")}
    field = _array(message.get("field_ut"), "field_ut", (3,), None)
    flags = _time_array(message.get("flags"))
    _check_length(t_ns.shape[0], {**angles, "field_ut": field, "flags": flags})
    declination = message.get("declination_deg", 0.0)
    if not isinstance(declination, (int, float)) or not math.isfinite(declination):
        raise WireError("bad-field", "declination_deg must be a finite number")
    return HeadingBatch(device, _int(message, "seq", 0), t_ns, field_ut=field, flags=flags,
                        declination_deg=float(declination), calibration_id=str(message.get("calibration_id", "")),
                        **angles)


# ---------------------------------------------------------------------------------------------------- calibration


def calibration_record(device: str, calibration: Calibration, created_ns: int) -> dict[str, Any]:
    """The published map: ``Calibration.to_dict()`` plus ``v, device, id, created_ns`` (JSON-able)."""
    return {"v": WIRE_VERSION, "device": validate_device_id(device), "id": calibration.content_id,
            "created_ns": int(created_ns), **calibration.to_dict()}


def encode_calibration(device: str, calibration: Calibration, created_ns: int) -> bytes:
    return msgpack.packb(calibration_record(device, calibration, created_ns), use_bin_type=True)


def calibration_from_record(record: Mapping[str, Any]) -> CalibrationMessage:
    """Validate a calibration map (as ``calibration_record`` builds it); WireError when unusable."""
    if record.get("v") != WIRE_VERSION:
        raise WireError("wrong-version", f"schema version {record.get('v')!r}, expected {WIRE_VERSION}")
    device = _device(record)
    try:
        calibration = Calibration.from_dict(record)
    except (ValueError, TypeError) as exc:
        raise WireError("bad-calibration", f"unusable calibration: {exc}") from None
    if np.abs(calibration.offset).max() > MAX_FIELD_UT * 10 or not np.isfinite(np.linalg.cond(calibration.matrix)) \
            or np.linalg.cond(calibration.matrix) > 1e6:
        raise WireError("absurd-magnitude", "calibration offset is absurd or its matrix is singular")
    created_ns = _int(record, "created_ns", 0)
    return CalibrationMessage(device, calibration.content_id, created_ns, calibration)


def decode_calibration(payload: bytes | bytearray | memoryview) -> CalibrationMessage:
    return calibration_from_record(unpack(payload))


# ------------------------------------------------------------------------------------------------------- progress


def encode_progress(device: str, progress: Mapping[str, Any]) -> bytes:
    """Progress map of a calibration in collection; ``progress`` holds state, samples, coverage, missing, ..."""
    return msgpack.packb({"v": WIRE_VERSION, "device": validate_device_id(device), **progress}, use_bin_type=True)


def decode_progress(payload: bytes | bytearray | memoryview) -> dict[str, Any]:
    message = unpack(payload)
    _device(message)
    return message
