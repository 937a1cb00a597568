"""The calibration model shared by every method, and the record that carries a calibration.

Model (docs/design.md, "The calibration model"). A raw reading u (3-vector, raw unit) relates to the true field B
in the body frame by

    u = K B + u0

with K (3x3) holding axis gains and cross-axis / non-orthogonality / soft-iron terms and u0 the zero offset plus hard
iron. The correction inverts it:

    B = A (u - b),   A = K^-1,   b = u0

``offset`` is b (raw unit), ``matrix`` is A (output unit per raw unit). The output unit is uT when the raw unit is
known or an expected field strength in uT was given; otherwise it is the raw unit (see ``output_unit``).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
from typing import Any, Mapping

import numpy as np


def _as_vector3(value: Any, name: str) -> np.ndarray:
    arr = np.asarray(value, dtype=float)
    if arr.shape != (3,):
        raise ValueError(f"{name} must be 3 numbers, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} holds non-finite values: {arr.tolist()}")
    return arr


def _as_matrix3(value: Any, name: str) -> np.ndarray:
    arr = np.asarray(value, dtype=float)
    if arr.shape != (3, 3):
        raise ValueError(f"{name} must be a 3x3 matrix (row-major nested lists), got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} holds non-finite values")
    return arr


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
        quality: figures of merit (see ``magnet.quality``), JSON-able.
        accepted: whether the quality gate accepted the fit.
        reason: why it was rejected (or notes when accepted), in words a person can act on.
    """

    method: str
    offset: np.ndarray
    matrix: np.ndarray
    field_strength: float = 0.0
    sample_count: int = 0
    unit: str = "ut"
    output_unit: str = "ut"
    quality: Mapping[str, Any] = dataclasses.field(default_factory=dict)
    accepted: bool = True
    reason: str = ""

    def __post_init__(self) -> None:
        object.__setattr__(self, "offset", _as_vector3(self.offset, "offset"))
        object.__setattr__(self, "matrix", _as_matrix3(self.matrix, "matrix"))
        if not math.isfinite(float(self.field_strength)) or self.field_strength < 0:
            raise ValueError(f"field_strength must be a finite number >= 0, got {self.field_strength!r}")

    def apply(self, raw: np.ndarray) -> np.ndarray:
        """Corrected field, shape (..., 3) in ``output_unit``, from raw readings of shape (..., 3) in ``unit``."""
        raw = np.asarray(raw, dtype=float)
        return (raw - self.offset) @ self.matrix.T

    def replace(self, **changes: Any) -> "Calibration":
        return dataclasses.replace(self, **changes)

    @property
    def content_id(self) -> str:
        """A stable id for the coefficients: identical method, offset, matrix and units give the same id."""
        content = {
            "method": self.method,
            "offset": [round(float(x), 12) for x in self.offset],
            "matrix": [[round(float(x), 12) for x in row] for row in self.matrix],
            "unit": self.unit,
            "output_unit": self.output_unit,
        }
        digest = hashlib.sha256(json.dumps(content, sort_keys=True).encode()).hexdigest()
        return digest[:16]

    def to_dict(self) -> dict[str, Any]:
        """JSON-able mapping: the record ``magnet fit`` writes."""
        return {
            "method": self.method,
            "offset": [float(x) for x in self.offset],
            "matrix": [[float(x) for x in row] for row in self.matrix],
            "field_strength": float(self.field_strength),
            "sample_count": int(self.sample_count),
            "unit": self.unit,
            "output_unit": self.output_unit,
            "quality": _jsonable(dict(self.quality)),
            "accepted": bool(self.accepted),
            "reason": self.reason,
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> "Calibration":
        """Read a record as ``to_dict`` writes it; ``offset`` and ``matrix`` are enough."""
        if not isinstance(data, Mapping):
            raise ValueError("a calibration must be a JSON object with at least 'offset' and 'matrix'")
        missing = [key for key in ("offset", "matrix") if key not in data]
        if missing:
            raise ValueError(f"calibration is missing {', '.join(missing)}: a record as 'magnet fit' writes it is needed")
        return cls(
            method=str(data.get("method", "manual")),
            offset=data["offset"],
            matrix=data["matrix"],
            field_strength=float(data.get("field_strength", 0.0) or 0.0),
            sample_count=int(data.get("sample_count", 0) or 0),
            unit=str(data.get("unit", "ut")),
            output_unit=str(data.get("output_unit", "ut")),
            quality=dict(data.get("quality", {}) or {}),
            accepted=bool(data.get("accepted", True)),
            reason=str(data.get("reason", "")),
        )


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
