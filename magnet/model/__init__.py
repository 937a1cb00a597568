"""The calibration model shared by every method, and the one record that carries a calibration.

Model (docs/design.md, "The calibration model"). A raw reading u (3-vector, raw unit) relates to the true field B
in the body frame by

    u = K B + u0

with K (3x3) holding axis gains and cross-axis / non-orthogonality / soft-iron terms and u0 the zero offset plus hard
iron. The correction inverts it:

    B = A (u - b),   A = K^-1,   b = u0

``offset`` is b (raw unit), ``matrix`` is A (output unit per raw unit). The output unit is uT when the raw unit is
known or an expected field strength in uT was given; otherwise it is the raw unit (see ``output_unit``).

``Calibration`` is the one record, from fit to wire to store to compass. Its constructor checks shapes and finiteness
(a fit may produce a poor calibration, which the quality gate then refuses); ``Calibration.from_dict`` is the one
entry of a record from outside (a JSON file, a stored row, a message) and also checks that it is physically
plausible (``check_plausible``, in ``magnet.plausible``): matrix entries, condition number, gain, determinant, offset
magnitude; and that its method and units are ones a record can name (``KNOWN_METHODS``, ``KNOWN_UNITS``).
"""

from __future__ import annotations

import dataclasses
import json
import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from magnet.model.fields import MAX_HARDWARE_ID
from magnet.model.fields import flag as _flag
from magnet.model.fields import hardware_id as _hardware_id
from magnet.model.fields import known as _known
from magnet.model.fields import number as _number
from magnet.model.fields import text as _text
from magnet.motor import MotorModel, motor_from_dict
from magnet.plausible import (
    MAX_CONDITION,
    MAX_GAIN,
    MAX_MATRIX_ENTRY,
    MAX_OFFSET_RAW,
    MAX_OFFSET_UT,
    UNKNOWN_SCALE_GAIN,
    check_plausible,
)
from magnet.units import FieldUnit

#: the methods that make records (``magnet.calibration.Method`` values, the turntable's least-squares variant, the
#: self-test, a hand-written record, the identity and the simulator's truth); a record naming another is refused
KNOWN_METHODS = frozenset(
    {"minmax2d", "minmax", "sphere", "ellipsoid", "ellipsoid+align", "turntable", "turntable-lsq", "gyro-ellipsoid"}
    | {"offset", "offset+scale", "planar"}
    | {"selftest", "manual", "identity", "truth"}
)
#: the units a record may name (``magnet.units.FieldUnit``)
KNOWN_UNITS = frozenset(u.value for u in FieldUnit)
#: the largest magnetometer delay a record may carry (s, ``Calibration.mag_lag_s``); beyond it the value is not a
#: sensor's filter delay and is ignored
MAX_LAG_S = 0.1


def _holds_bool(value: Any) -> bool:
    """Whether an array-like of at most two levels (checked to be of shape (3,) or (3, 3)) holds a boolean: numpy
    would read true as 1 and false as 0."""
    if isinstance(value, np.ndarray):
        return value.dtype == bool or (value.dtype == object and any(_holds_bool(v) for v in value.tolist()))
    if isinstance(value, (list, tuple)):
        return any(_holds_bool(v) for v in value)
    return isinstance(value, (bool, np.bool_))


def _as_vector3(value: Any, name: str) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError, OverflowError):
        raise ValueError(f"{name} must be 3 numbers, got {type(value).__name__}") from None
    if arr.shape != (3,):
        raise ValueError(f"{name} must be 3 numbers, got shape {arr.shape}")
    if _holds_bool(value):
        raise ValueError(f"{name} holds true/false where numbers belong")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} holds non-finite values: {arr.tolist()}")
    return arr


def _as_matrix3(value: Any, name: str) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError, OverflowError):
        raise ValueError(f"{name} must be a 3x3 matrix (row-major nested lists) of numbers") from None
    if arr.shape != (3, 3):
        raise ValueError(f"{name} must be a 3x3 matrix (row-major nested lists), got shape {arr.shape}")
    if _holds_bool(value):
        raise ValueError(f"{name} holds true/false where numbers belong")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} holds non-finite values")
    return arr


def _optional_number(value: Any, name: str) -> float | None:
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise ValueError(f"quality figure {name} must be a number or null, got {type(value).__name__}")
    return float(value)


def _optional_int(value: Any, name: str) -> int | None:
    number = _optional_number(value, name)
    if number is None:
        return None
    if not number.is_integer():
        raise ValueError(f"quality figure {name} must be a whole number, got {value!r}")
    return int(number)


#: Quality's typed figures in the order they are written, and how each is read
_FIGURES: dict[str, Any] = {
    "geometry": None,
    "residual_rms": _optional_number,
    "residual_rms_ut": _optional_number,
    "residual_rms_pct": _optional_number,
    "coverage": _optional_number,
    "cells_hit": _optional_int,
    "cell_count": _optional_int,
    "missing_directions": None,
    "radius": _optional_number,
    "expected_field_ut": _optional_number,
    "radius_ratio": _optional_number,
    "soft_iron_condition": _optional_number,
    "scatter_condition": _optional_number,
    "dip_spread_deg": _optional_number,
    "holdout_rms_ut": _optional_number,
    "holdout_rms_pct": _optional_number,
}


@dataclasses.dataclass(frozen=True)
class Quality:
    """Figures of merit of a calibration (see ``magnet.quality.figures``); None where a figure does not apply.

    geometry: "sphere", "circle" or "turntable" (None: not assessed); residual_rms (output unit), residual_rms_ut
    (uT), residual_rms_pct (% of the expected magnitude): RMS of |B| - expected; coverage in [0, 1] with cells_hit of
    cell_count and missing_directions (advice phrases); radius (fitted, uT) and expected_field_ut (WMM) with their
    radius_ratio; soft_iron_condition and scatter_condition (ratios); dip_spread_deg (deg); holdout_rms_ut and
    holdout_rms_pct on held-out samples. extra: figures a method adds (``note``, ``vector_rms``, ``selftest``, ...),
    JSON-able. Serialized as one flat map (``to_dict``); ``quality["key"]`` reads a figure by that map's key.
    """

    geometry: str | None = None
    residual_rms: float | None = None
    residual_rms_ut: float | None = None
    residual_rms_pct: float | None = None
    coverage: float | None = None
    cells_hit: int | None = None
    cell_count: int | None = None
    missing_directions: tuple[str, ...] = ()
    radius: float | None = None
    expected_field_ut: float | None = None
    radius_ratio: float | None = None
    soft_iron_condition: float | None = None
    scatter_condition: float | None = None
    dip_spread_deg: float | None = None
    holdout_rms_ut: float | None = None
    holdout_rms_pct: float | None = None
    extra: Mapping[str, Any] = dataclasses.field(default_factory=dict)

    def __getitem__(self, key: str) -> Any:
        if key in _FIGURES:
            value = getattr(self, key)
            return list(value) if key == "missing_directions" else value
        return self.extra[key]

    def get(self, key: str, default: Any = None) -> Any:
        """A figure by its map key, or ``default`` when absent or None."""
        try:
            value = self[key]
        except KeyError:
            return default
        return default if value is None else value

    def with_extra(self, **figures: Any) -> Quality:
        """A copy with more method-specific figures."""
        return dataclasses.replace(self, extra={**self.extra, **figures})

    def to_dict(self) -> dict[str, Any]:
        """JSON-able flat map: every typed figure once assessed (else those set), then ``extra``."""
        assessed = self.geometry is not None
        out = {key: self[key] for key in _FIGURES if assessed or getattr(self, key) not in (None, ())}
        return _jsonable({**out, **self.extra})

    @classmethod
    def from_dict(cls, data: Mapping[str, Any] | Quality | None) -> Quality:
        """Read the flat map ``to_dict`` writes (unknown keys go to ``extra``); ValueError when a figure has the
        wrong type."""
        if data is None:
            return cls()
        if isinstance(data, Quality):
            return data
        if not isinstance(data, Mapping):
            raise ValueError(f"quality must be a map of figures, got {type(data).__name__}")
        typed = {key: reader(data[key], key) for key, reader in _FIGURES.items() if reader and key in data}
        geometry = data.get("geometry")
        if geometry is not None and not isinstance(geometry, str):
            raise ValueError("quality figure geometry must be a string")
        missing = data.get("missing_directions") or ()
        if not isinstance(missing, (list, tuple)) or not all(isinstance(m, str) for m in missing):
            raise ValueError("quality figure missing_directions must be a list of strings")
        extra = {str(k): v for k, v in data.items() if k not in _FIGURES}
        return cls(geometry=geometry, missing_directions=tuple(missing), extra=extra, **typed)


@dataclasses.dataclass(frozen=True, eq=False)
class Calibration:
    """One calibration: the correction B = matrix @ (raw - offset) and what is known of its quality.

    Attributes:
        method: name of the method that produced it (``minmax2d``, ``minmax``, ``sphere``, ``ellipsoid``,
            ``ellipsoid+align``, ``turntable``, ``turntable-lsq``, ``selftest``, or ``manual``).
        offset: b, shape (3,), in the raw unit.
        matrix: A, shape (3, 3); corrected field (output unit) = A @ (raw - b).
        field_strength: expected magnitude of the corrected field, in the output unit (0 when unknown).
        sample_count: number of samples the fit used.
        unit: the raw unit (``ut``, ``gauss``, ``nt``, ``counts`` or a free word such as ``gamma-codes``).
        output_unit: unit of the corrected field (``ut`` or the raw unit).
        quality: figures of merit (``Quality``; a map of them is read with ``Quality.from_dict``).
        accepted: whether the quality gate accepted the fit.
        reason: why it was rejected (or notes when accepted), in words a person can act on.
        motor: the motors' field (``magnet.motor.MotorModel``: uT per amp or at full throttle, subtracted after the
            correction), or None; written as ``motor_ut_per_a`` or ``motor_ut_per_throttle``.
        hardware_id: the id the vehicle reported for the sensor the samples came from (ArduPilot's COMPASS_DEV_ID,
            PX4's CAL_MAGn_ID; 1..2**32-1), or None when not known; a compass applies the record only to batches of
            that sensor (docs/mavlink.md). Written only when known: records without one read and hash as before.
    """

    method: str
    offset: np.ndarray
    matrix: np.ndarray
    field_strength: float = 0.0
    sample_count: int = 0
    unit: str = "ut"
    output_unit: str = "ut"
    quality: Quality = dataclasses.field(default_factory=Quality)
    accepted: bool = True
    reason: str = ""
    motor: MotorModel | None = None
    hardware_id: int | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "offset", _as_vector3(self.offset, "offset"))
        hw = self.hardware_id
        if hw is not None and (isinstance(hw, bool) or not isinstance(hw, int) or not 0 < hw <= MAX_HARDWARE_ID):
            raise ValueError(f"hardware_id must be a whole number 1..{MAX_HARDWARE_ID} or null, got {hw!r}")
        object.__setattr__(self, "matrix", _as_matrix3(self.matrix, "matrix"))
        object.__setattr__(self, "quality", Quality.from_dict(self.quality))
        if not math.isfinite(float(self.field_strength)) or self.field_strength < 0:
            raise ValueError(f"field_strength must be a finite number >= 0, got {self.field_strength!r}")

    def apply(self, raw: np.ndarray) -> np.ndarray:
        """Corrected field, shape (..., 3) in ``output_unit``, from raw readings of shape (..., 3) in ``unit``."""
        raw = np.asarray(raw, dtype=float)
        return (raw - self.offset) @ self.matrix.T

    def replace(self, **changes: Any) -> Calibration:
        return dataclasses.replace(self, **changes)

    @property
    def mag_lag_s(self) -> float:
        """How far the magnetometer's readings come behind the gyroscope's (s): the quality figure ``mag_lag_s`` a
        gyro-ellipsoid fit writes (the record's wire and store form), typed here; 0.0 when the record carries none or
        an unusable one (not a finite number within +-``MAX_LAG_S``): records come from files and the network. The
        compass turns the field its filter gets forward over it (``magnet.attitude.mag_delay``)."""
        value = self.quality.get("mag_lag_s")
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            return 0.0
        lag = float(value)
        return lag if math.isfinite(lag) and abs(lag) <= MAX_LAG_S else 0.0

    @property
    def content_id(self) -> str:
        """A stable id for the coefficients: identical method, offset, matrix and units give the same id."""
        content: dict[str, object] = {
            "method": self.method,
            "offset": [round(float(x), 12) for x in self.offset],
            "matrix": [[round(float(x), 12) for x in row] for row in self.matrix],
            "unit": self.unit,
            "output_unit": self.output_unit,
        }
        if self.motor is not None:  # only then: the ids of records without one stay as they were
            content["motor"] = {self.motor.key: [round(float(x), 12) for x in self.motor.coefficients]}
        if self.hardware_id is not None:  # likewise: one sensor's record is not another's
            content["hardware_id"] = int(self.hardware_id)
        import hashlib  # here: loading OpenSSL's hashes is a few ms of every command's start that never needs an id

        digest = hashlib.sha256(json.dumps(content, sort_keys=True).encode()).hexdigest()
        return digest[:16]

    def to_dict(self) -> dict[str, Any]:
        """JSON-able mapping: the record ``magnet fit`` writes."""
        out = {
            "method": self.method,
            "offset": [float(x) for x in self.offset],
            "matrix": [[float(x) for x in row] for row in self.matrix],
            "field_strength": float(self.field_strength),
            "sample_count": int(self.sample_count),
            "unit": self.unit,
            "output_unit": self.output_unit,
            "quality": self.quality.to_dict(),
            "accepted": bool(self.accepted),
            "reason": self.reason,
        }
        if self.hardware_id is not None:
            out["hardware_id"] = int(self.hardware_id)
        return out if self.motor is None else {**out, **self.motor.to_dict()}

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> Calibration:
        """The one entry of a record from outside (file, store, wire): read it as ``to_dict`` writes it (``offset``
        and ``matrix`` are enough) and check it is plausible (``check_plausible``); ValueError saying what is wrong."""
        if not isinstance(data, Mapping):
            raise ValueError("a calibration must be a JSON object with at least 'offset' and 'matrix'")
        missing = [key for key in ("offset", "matrix") if key not in data]
        if missing:
            raise ValueError(
                f"calibration is missing {', '.join(missing)}: a record as 'magnet fit' writes it is needed"
            )
        calibration = cls(
            method=_known(data, "method", "manual", KNOWN_METHODS),
            offset=data["offset"],
            matrix=data["matrix"],
            field_strength=_number(data, "field_strength"),
            sample_count=int(_number(data, "sample_count")),
            unit=_known(data, "unit", "ut", KNOWN_UNITS),
            output_unit=_known(data, "output_unit", "ut", KNOWN_UNITS),
            quality=Quality.from_dict(data.get("quality")),
            accepted=_flag(data, "accepted"),
            reason=_text(data, "reason", ""),
            motor=motor_from_dict(data),
            hardware_id=_hardware_id(data),
        )
        return check_plausible(calibration)


__all__ = [
    "IDENTITY",
    "KNOWN_METHODS",
    "KNOWN_UNITS",
    "MAX_CONDITION",
    "MAX_GAIN",
    "MAX_LAG_S",
    "MAX_MATRIX_ENTRY",
    "MAX_OFFSET_RAW",
    "MAX_OFFSET_UT",
    "UNKNOWN_SCALE_GAIN",
    "Calibration",
    "Quality",
    "check_plausible",
]

IDENTITY = Calibration(method="identity", offset=np.zeros(3), matrix=np.eye(3), reason="no calibration")


def _jsonable(value: Any) -> Any:
    """Turn numpy scalars/arrays inside nested containers into plain Python values; non-finite floats into None."""
    if isinstance(value, Mapping):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return _jsonable(value.tolist())
    if isinstance(value, (np.floating, float)):
        f = float(value)
        return f if math.isfinite(f) else None
    if isinstance(value, (np.integer,)):
        return int(value)
    if isinstance(value, np.bool_):
        return bool(value)
    return value
