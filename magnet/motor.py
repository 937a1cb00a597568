"""The motors' field: a per-axis offset proportional to the battery current (or to the throttle).

Model (docs/mavlink.md, "Motor interference"). Current through the motors' wires and magnets adds a field at the
sensor that grows with the current I (A) or, more loosely, with the throttle T (0..1):

    B_corrected = B_earth + m_a * I          or          B_corrected = B_earth + m_t * T

where B_corrected is the calibrated field ``Calibration.apply`` gives (uT, body frame) and m_a (uT per A) or m_t (uT
at full throttle) is ``MotorModel``. The compass subtracts ``m * I`` after the calibration, as ArduPilot adds its
``COMPASS_MOT`` vector (= -m, in milligauss) after its soft-iron matrix. A record holds one of the two, never both.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

import numpy as np

#: ArduPilot's COMPASS_MOT_X/Y/Z range is +-1000 milligauss per amp (or per full throttle): 100 uT
MAX_MOTOR_UT = 100.0
#: the record's keys, per kind of motor model: uT per amp, uT at full throttle
CURRENT, THROTTLE = "current", "throttle"
KEYS = {CURRENT: "motor_ut_per_a", THROTTLE: "motor_ut_per_throttle"}


@dataclasses.dataclass(frozen=True, eq=False)
class MotorModel:
    """coefficients (3,) uT per amp (kind ``current``) or uT at full throttle (kind ``throttle``), body frame."""

    kind: str
    coefficients: np.ndarray

    def __post_init__(self) -> None:
        if self.kind not in KEYS:
            raise ValueError(f"motor model kind must be one of {', '.join(KEYS)}, got {self.kind!r}")
        try:
            arr = np.asarray(self.coefficients, dtype=float)
        except (TypeError, ValueError, OverflowError):
            raise ValueError(f"{KEYS[self.kind]} must be 3 numbers") from None
        if arr.shape != (3,) or not np.isfinite(arr).all():
            raise ValueError(f"{KEYS[self.kind]} must be 3 finite numbers, got {np.asarray(self.coefficients)!r}")
        if np.abs(arr).max() > MAX_MOTOR_UT:
            raise ValueError(
                f"{KEYS[self.kind]} {arr.tolist()} exceeds {MAX_MOTOR_UT:g} uT per unit: no compass could be used "
                "that close to the motors; check the unit (uT, not milligauss) or fit again"
            )
        object.__setattr__(self, "coefficients", arr)

    @property
    def key(self) -> str:
        return KEYS[self.kind]

    def offset_ut(self, current_a: np.ndarray, throttle: np.ndarray) -> np.ndarray:
        """(S, 3) uT the motors add at each sample, from current_a (S,) A or throttle (S,) 0..1 (whichever the kind
        needs); zero rows where that value is unknown (NaN)."""
        driver = np.asarray(current_a if self.kind == CURRENT else throttle, dtype=float)
        return np.where(np.isfinite(driver), driver, 0.0)[:, None] * self.coefficients

    def to_dict(self) -> dict[str, Any]:
        return {self.key: [float(x) for x in self.coefficients]}


def motor_from_dict(data: Mapping[str, Any]) -> MotorModel | None:
    """The motor model of a calibration record (``motor_ut_per_a`` or ``motor_ut_per_throttle``), None when it has
    neither; ValueError when it has both or the numbers are not a motor's."""
    present = [kind for kind, key in KEYS.items() if data.get(key) is not None]
    if not present:
        return None
    if len(present) > 1:
        raise ValueError("a calibration carries motor_ut_per_a or motor_ut_per_throttle, not both")
    value = data[KEYS[present[0]]]
    if not isinstance(value, (list, tuple)) or any(isinstance(x, bool) for x in value):
        raise ValueError(f"{KEYS[present[0]]} must be a list of 3 numbers")
    return MotorModel(present[0], np.asarray(value))


def interference_pct(
    model: MotorModel, earth_ut: float, max_current_a: float = 0.0, max_throttle: float = 1.0
) -> float:
    """The motors' field at full throttle in % of the Earth's field, as ArduPilot's compassmot reports it: |m_t| /
    |B| for a throttle model; |m_a| * (largest current seen / largest throttle seen) / |B| for a current model."""
    if not earth_ut > 0:
        raise ValueError(f"the Earth's field must be > 0 uT, got {earth_ut}")
    size = float(np.linalg.norm(model.coefficients))
    if model.kind == THROTTLE:
        return 100.0 * size / earth_ut
    return 100.0 * size * max_current_a / max(max_throttle, 1e-9) / earth_ut
