"""HMC5883L self-test maths (seed 003, after the Honeywell datasheet): pure functions of the bias readings.

In positive-bias mode the chip's offset straps add a known field to every axis, about 1.16 Ga on x and y and
1.08 Ga on z, and the chip reports that bias field alone (it subtracts the unbiased measurement); negative bias
gives the same with the opposite sign. With the gain GN in use (LSB per gauss from the datasheet table):

    expected counts  e = bias_ga * LSB_PER_GAUSS[GN]                  (seed: GN=3 -> 766, 766, 713)
    measured counts  m = (positive - negative) / 2                      (per axis; cancels any residual offset)
    pass limits      243..575 counts at GN=5 (datasheet), i.e. 0.623..1.474 Ga times the gain's LSB per gauss,
                     checked on the positive reading and (mirrored) on the negative one
    scale factor     s = e / m, to multiply every later reading of that axis (seed: 766 / 750)
    temperature      f = m_reference / m_now, from a self-test at a known temperature (seed: 750 / 700); multiply
                     current readings by f. No temperature sensor is needed.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
import numpy.typing as npt

from magnet.model import Calibration, Quality

#: the straps' bias field per axis x, y, z, in gauss
BIAS_FIELD_GA = np.array([1.16, 1.16, 1.08])
#: GN -> LSB per gauss (datasheet table)
LSB_PER_GAUSS: tuple[int, ...] = (1370, 1090, 820, 660, 440, 390, 330, 230)
#: datasheet pass limits at GN=5 (390 LSB/Ga), in counts
LIMITS_GN5_COUNTS = (243.0, 575.0)
OVERFLOW_COUNTS = -4096


def _check_gain(gain: int) -> int:
    if not 0 <= int(gain) <= 7:
        raise ValueError(f"HMC5883L gain GN must be 0..7, got {gain}")
    return int(gain)


def expected_counts(gain: int) -> np.ndarray:
    """Expected self-test output for gain GN, counts per axis, shape (3,)."""
    return BIAS_FIELD_GA * LSB_PER_GAUSS[_check_gain(gain)]


def limits_counts(gain: int) -> tuple[float, float]:
    """Pass limits (low, high) for the positive-bias output at gain GN, counts (the GN=5 limits scaled)."""
    ratio = LSB_PER_GAUSS[_check_gain(gain)] / LSB_PER_GAUSS[5]
    return LIMITS_GN5_COUNTS[0] * ratio, LIMITS_GN5_COUNTS[1] * ratio


@dataclasses.dataclass(frozen=True, eq=False)
class SelfTestResult:
    """Outcome of one self-test. Arrays are per axis x, y, z; counts are raw codes at ``gain``.

    Attributes:
        gain: GN used. positive, negative: bias readings (counts, (3,)). expected: expected counts (3,).
        measured: (positive - negative) / 2, counts (3,). limits: (low, high) counts for the positive reading.
        axis_passed: (3,) bool. passed: every axis within limits for both signs. scale: expected / measured (3,),
        NaN where the axis failed. message: one line for a person.
    """

    gain: int
    positive: np.ndarray
    negative: np.ndarray
    expected: np.ndarray
    measured: np.ndarray
    limits: tuple[float, float]
    axis_passed: np.ndarray
    passed: bool
    scale: np.ndarray
    message: str

    def to_dict(self) -> dict[str, Any]:
        return {
            "gain": self.gain,
            "passed": self.passed,
            "message": self.message,
            "limits": list(self.limits),
            **{
                k: getattr(self, k).tolist()
                for k in ("positive", "negative", "expected", "measured", "axis_passed", "scale")
            },
        }


def evaluate(positive_counts: npt.ArrayLike, negative_counts: npt.ArrayLike, gain: int) -> SelfTestResult:
    """Judge positive and negative bias readings (counts (3,), x, y, z) taken at gain GN."""
    positive = np.asarray(positive_counts, dtype=float)
    negative = np.asarray(negative_counts, dtype=float)
    if positive.shape != (3,) or negative.shape != (3,):
        raise ValueError("self-test readings must be 3 counts each (x, y, z)")
    low, high = limits_counts(gain)
    overflow = (positive == OVERFLOW_COUNTS) | (negative == OVERFLOW_COUNTS)
    axis_passed = (positive >= low) & (positive <= high) & (-negative >= low) & (-negative <= high) & ~overflow
    expected = expected_counts(gain)
    measured = (positive - negative) / 2.0
    scale = np.where(axis_passed, expected / np.where(measured == 0, np.nan, measured), np.nan)
    names = [axis for axis, ok in zip("xyz", axis_passed) if not ok]
    if not names:
        message = f"self-test passed at GN={gain}: scale factors " + ", ".join(f"{s:.4f}" for s in scale)
    else:
        hint = " (overflow: try a higher GN)" if overflow.any() else ""
        message = (
            f"self-test FAILED at GN={gain} on axis {', '.join(names)}: bias readings must lie within "
            f"{low:.0f}..{high:.0f} counts{hint}"
        )
    return SelfTestResult(
        gain, positive, negative, expected, measured, (low, high), axis_passed, bool(axis_passed.all()), scale, message
    )


def temperature_factor(reference_measured: npt.ArrayLike, current_measured: npt.ArrayLike) -> np.ndarray:
    """Sensitivity compensation factor per axis (3,): reference self-test output / current output.

    Multiply readings taken now by it to restore the sensitivity the axis had at the reference temperature.
    """
    reference = np.asarray(reference_measured, dtype=float)
    current = np.asarray(current_measured, dtype=float)
    if reference.shape != (3,) or current.shape != (3,):
        raise ValueError("temperature compensation needs two self-test outputs of 3 counts each")
    if np.any(current == 0) or not np.all(np.isfinite(current)):
        raise ValueError("current self-test output has a zero or non-finite axis: rerun the self-test")
    return reference / current


def to_calibration(result: SelfTestResult) -> Calibration:
    """The self-test's per-axis correction as a calibration record (offset 0, matrix diag(scale), counts in)."""
    if not result.passed:
        raise ValueError(f"no calibration from a failed self-test: {result.message}")
    ut_per_count = 100.0 / LSB_PER_GAUSS[result.gain]
    return Calibration(
        method="selftest",
        offset=np.zeros(3),
        matrix=np.diag(result.scale),
        unit="ut",
        output_unit="ut",
        quality=Quality.from_dict({"selftest": result.to_dict(), "ut_per_count_at_gain": ut_per_count}),
        accepted=True,
        reason=result.message,
    )
