"""The compasses of one vehicle compared in the body frame (docs/vehicles.md). Pure numpy.

Every compass of a vehicle sees the same Earth's field in the vehicle's body frame, so at any instant their fields
(uT, body axes, each with its calibration's offset and the symmetric part of its matrix: what the sensor sees, not
a rotation a fit may have taken up) should be one vector. ``judge`` puts every compass's samples on the times of the
first one, takes as the reference the compass that agrees best with the others, and compares each other compass
with it:

1. mounting rotation: the rotation R that best turns its field onto the reference's (Wahba's problem, by SVD, on the
   samples at the lower half of the current); turned by more than ``ROTATION_MIN_DEG`` and within
   ``NAMED_TOLERANCE_DEG`` of one of the autopilots' named rotations (``magnet.frames.ROTATIONS``), that rotation is
   the cause and ``COMPASS_ORIENTn`` (ArduPilot) / ``CAL_MAGn_ROT`` (PX4) the parameter;
2. motor interference: what it has beyond the reference after R, regressed on the battery current (else the
   throttle) per axis, r = c + s I (s: the motors' field per amp); the motors' field at the most current seen, as a
   percentage of the Earth's field (extrapolated to full throttle where the throttle is known, as ArduPilot's
   compassmot reports it), is the cause when it is at least ``INTERFERENCE_MIN_PCT`` and the field follows the
   current (correlation at least ``CORRELATION_MIN``);
3. a calibration that no longer fits: what is left after both, RMS, beyond ``RESIDUAL_MIN_UT`` or
   ``RESIDUAL_MIN_FRACTION`` of the field (or a field size ``SCALE_TOLERANCE`` away from the reference's);
4. a local anomaly: when every compass agrees, the field's size further than ``ANOMALY_FRACTION`` from what the WMM
   expects at the vehicle's place is the place's doing, not the vehicle's.
"""

from __future__ import annotations

import dataclasses
import enum
import functools
from collections.abc import Mapping
from typing import Any

import numpy as np

from magnet.frames import ROTATIONS, rotation_angle_deg, rotation_matrix
from magnet.vehicle.membership import instance_of

ROTATION_MIN_DEG = 20.0
NAMED_TOLERANCE_DEG = 15.0
INTERFERENCE_MIN_PCT = 10.0
CORRELATION_MIN = 0.5
RESIDUAL_MIN_UT = 3.0
RESIDUAL_MIN_FRACTION = 0.06
SCALE_TOLERANCE = 0.1
ANOMALY_FRACTION = 0.15
#: samples (on the common times) a comparison needs; and how far (deg) the field must turn in the body for a
#: rotation to be known about every axis
MIN_SAMPLES = 50
MIN_SPREAD_DEG = 8.0
#: a sample of another compass is matched to a time of the first within this (s)
MATCH_S = 0.15
#: the current must vary at least this much (A, or 0.1 of throttle) to tell interference
MIN_CURRENT_RANGE_A, MIN_THROTTLE_RANGE = 2.0, 0.1


@functools.cache
def _named() -> tuple[np.ndarray, np.ndarray]:
    """The named rotations (numbers (R,), matrices (R, 3, 3)), built once, when first compared (not on import: the
    compass and ``magnet heading`` import this module but compare vehicles rarely or never)."""
    numbers = np.array(list(ROTATIONS))
    return numbers, np.stack([rotation_matrix(int(n)) for n in numbers])


def nearest_named(matrix: np.ndarray) -> tuple[int, float]:
    """(the named rotation nearest ``matrix`` (3, 3), the angle between them in deg): as
    ``magnet.frames.nearest_rotation``, all at once."""
    numbers, named = _named()
    cos = (np.einsum("nij,ij->n", named, matrix) - 1.0) / 2.0  # trace(N^T M) = sum of N * M
    best = int(np.argmax(cos))
    return int(numbers[best]), float(np.degrees(np.arccos(np.clip(cos[best], -1.0, 1.0))))


class Verdict(enum.StrEnum):
    REFERENCE = "reference"
    AGREES = "agrees"
    ROTATION = "rotation"
    INTERFERENCE = "interference"
    CALIBRATION = "calibration"
    TOO_FEW = "too-few-samples"


@dataclasses.dataclass(frozen=True)
class Series:
    """One compass's recent samples: t_s (N,) s, field_ut (N, 3) uT body frame, current_a and throttle (N,) (NaN
    where unknown)."""

    t_s: np.ndarray
    field_ut: np.ndarray
    current_a: np.ndarray
    throttle: np.ndarray


@dataclasses.dataclass(frozen=True)
class CompassVerdict:
    """One compass against the reference: its verdict (the first cause found, in the order of the module
    docstring), every cause found, the median angle between its field and the reference's (deg), the rotation found
    (deg) and the named one nearest (number, its distance in deg), the interference (% of the Earth's field, the
    correlation with the current or throttle, uT per A or per unit throttle (3,)), the residual (uT RMS), the
    parameters to set and a sentence saying the fix."""

    device: str
    verdict: Verdict
    causes: tuple[Verdict, ...] = ()
    samples: int = 0
    angle_deg: float = 0.0
    rotation_deg: float = 0.0
    named_rotation: int | None = None
    named_distance_deg: float | None = None
    interference_pct: float | None = None
    correlation: float | None = None
    motor_ut: tuple[float, float, float] | None = None
    motor_per: str | None = None
    residual_ut: float = 0.0
    parameters: dict[str, float] = dataclasses.field(default_factory=dict)
    fix: str = ""

    def to_dict(self) -> dict[str, Any]:
        out = dataclasses.asdict(self)
        out["verdict"] = self.verdict.value
        out["causes"] = [c.value for c in self.causes]
        return {k: (round(v, 4) if isinstance(v, float) else v) for k, v in out.items()}


@dataclasses.dataclass(frozen=True)
class VehicleReport:
    """A vehicle's compasses judged (``judge``): the reference, each compass's verdict, the field's size (uT, the
    reference's median) and the WMM's (None where unknown), whether it is a local anomaly, and one line of summary."""

    vehicle: str
    reference: str | None
    compasses: tuple[CompassVerdict, ...]
    field_ut: float | None
    expected_ut: float | None
    anomaly: bool
    summary: str

    def to_dict(self) -> dict[str, Any]:
        return {
            "vehicle": self.vehicle,
            "reference": self.reference,
            "field_ut": None if self.field_ut is None else round(self.field_ut, 3),
            "expected_ut": None if self.expected_ut is None else round(self.expected_ut, 3),
            "anomaly": self.anomaly,
            "summary": self.summary,
            "compasses": [c.to_dict() for c in self.compasses],
        }

    @property
    def disagreeing(self) -> list[CompassVerdict]:
        return [c for c in self.compasses if c.verdict not in (Verdict.REFERENCE, Verdict.AGREES, Verdict.TOO_FEW)]


def parameter_names(device: str) -> tuple[str, str, str]:
    """(ArduPilot orientation, PX4 rotation, ArduPilot motor suffix) of a compass ``<vehicle>-mag<N>``: instance 0 is
    ArduPilot's first compass (no number: ``COMPASS_ORIENT``, ``COMPASS_MOT_X``), N >= 1 its (N + 1)th
    (``COMPASS_ORIENT2``, ``COMPASS_MOT2_X``); PX4 counts from 0 (``CAL_MAG0_ROT``)."""
    n = instance_of(device) or 0
    suffix = "" if n == 0 else str(n + 1)
    return f"COMPASS_ORIENT{suffix}", f"CAL_MAG{n}_ROT", suffix


def _aligned(first: Series, other: Series) -> tuple[np.ndarray, np.ndarray]:
    """Indices into ``first`` (K,) and the other's field interpolated at those times (K, 3): the times of ``first``
    with a sample of ``other`` within ``MATCH_S`` on both sides."""
    t, s = first.t_s, other.t_s
    if len(s) < 2:
        return np.zeros(0, dtype=int), np.zeros((0, 3))
    after = np.clip(np.searchsorted(s, t), 1, len(s) - 1)
    ok = (t >= s[0]) & (t <= s[-1]) & (s[after] - s[after - 1] <= 2 * MATCH_S)
    index = np.flatnonzero(ok)
    field = np.column_stack([np.interp(t[index], s, other.field_ut[:, k]) for k in range(3)])
    return index, field


def _angles_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    cos = np.einsum("ij,ij->i", a, b) / (np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1))
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def wahba(reference: np.ndarray, other: np.ndarray) -> np.ndarray:
    """The rotation R (3, 3) minimising sum |reference - R other|^2 over rows (N, 3) (SVD, determinant +1)."""
    u, _, vt = np.linalg.svd(reference.T @ other)
    d = np.sign(np.linalg.det(u @ vt)) or 1.0
    return u @ np.diag([1.0, 1.0, d]) @ vt


def _spread_deg(field: np.ndarray) -> float:
    """How far the field's direction turns in the body (deg): the median angle from its mean direction."""
    unit = field / np.linalg.norm(field, axis=1, keepdims=True)
    mean = unit.mean(axis=0)
    return float(np.median(_angles_deg(unit, np.broadcast_to(mean, unit.shape))))


@dataclasses.dataclass(frozen=True)
class _Pair:
    """A compass and the reference on common times: fields (K, 3) uT, the driver of interference (K,) (current or
    throttle, or None), its name, the largest current and throttle seen (for the percentage)."""

    device: str
    reference: np.ndarray
    field: np.ndarray
    driver: np.ndarray | None
    per: str | None
    full_scale: float


def _pair(device: str, ref: Series, index: np.ndarray, field: np.ndarray, other: Series) -> _Pair:
    """The pair on the reference's times ``index``; the current (else the throttle) is the driver when it is known
    on at least ``MIN_SAMPLES`` of them (NaN where unknown: a late or lost SYS_STATUS, left out of the fits) and
    varies enough."""
    current = np.interp(ref.t_s[index], other.t_s, other.current_a) if len(index) else np.zeros(0)
    throttle = np.interp(ref.t_s[index], other.t_s, other.throttle) if len(index) else np.zeros(0)
    have_current = np.isfinite(current).sum() >= MIN_SAMPLES
    have_throttle = np.isfinite(throttle).sum() >= MIN_SAMPLES
    driver, per, full = None, None, 1.0
    if have_current and np.nanmax(current) - np.nanmin(current) >= MIN_CURRENT_RANGE_A:
        driver, per = current, "A"
        top_throttle = float(np.nanmax(throttle)) if have_throttle else 1.0
        full = float(np.nanmax(current)) / max(top_throttle, 0.1)  # compassmot: extrapolated to full throttle
    elif have_throttle and np.nanmax(throttle) - np.nanmin(throttle) >= MIN_THROTTLE_RANGE:
        driver, per = throttle, "throttle"
    return _Pair(device, ref.field_ut[index], field, driver, per, full)


def _motor_fit(pair: _Pair, residual: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """(offset c (3,), slope s (3,) uT per driver unit, correlation) of residual = c + s * driver (rows where the
    driver is known); s zero and correlation 0 without a driver."""
    if pair.driver is None:
        return residual.mean(axis=0), np.zeros(3), 0.0
    known = np.isfinite(pair.driver)
    x, r = pair.driver[known], residual[known]
    design = np.column_stack([np.ones_like(x), x])
    coef, *_ = np.linalg.lstsq(design, r, rcond=None)
    offset, slope = coef[0], coef[1]
    size = float(np.linalg.norm(slope))
    if size == 0.0 or np.std(x) == 0.0:
        return offset, slope, 0.0
    along = r @ (slope / size)
    correlation = float(np.corrcoef(x, along)[0, 1]) if np.std(along) > 0 else 0.0
    return offset, slope, correlation


@dataclasses.dataclass
class _Found:
    """What the steps of a comparison found: causes in order, the parameters to set, the fixes in words."""

    causes: list[Verdict] = dataclasses.field(default_factory=list)
    parameters: dict[str, float] = dataclasses.field(default_factory=dict)
    fixes: list[str] = dataclasses.field(default_factory=list)

    def add(self, cause: Verdict, fix: str, parameters: Mapping[str, float] | None = None) -> None:
        self.causes.append(cause)
        self.fixes.append(fix)
        self.parameters.update(parameters or {})


def _rotation(pair: _Pair, found: _Found) -> tuple[np.ndarray, float, int, float]:
    """Step 1: (the rotation to apply before the next steps (identity unless it is a cause), the rotation found in
    deg, the nearest named rotation and its distance in deg)."""
    quiet = np.ones(len(pair.field), dtype=bool)
    if pair.driver is not None:
        known = np.isfinite(pair.driver)
        quiet = known & (np.nan_to_num(pair.driver) <= np.median(pair.driver[known]))
    rotation = wahba(pair.reference[quiet], pair.field[quiet])
    turned_deg = float(rotation_angle_deg(rotation))
    named, distance = nearest_named(rotation)
    if turned_deg < ROTATION_MIN_DEG or _spread_deg(pair.reference) < MIN_SPREAD_DEG:
        return np.eye(3), turned_deg, named, distance
    orient, px4, _ = parameter_names(pair.device)
    if distance > NAMED_TOLERANCE_DEG:
        fix = f"turned {turned_deg:.0f} deg, {distance:.0f} deg from any named rotation: check its mounting"
        found.add(Verdict.CALIBRATION, fix)
        return rotation, turned_deg, named, distance
    roll, pitch, yaw = ROTATIONS[named]
    fix = (
        f"mounted turned {turned_deg:.0f} deg: set {orient}={named} (ArduPilot) or {px4}={named} (PX4): "
        f"roll {roll:g}, pitch {pitch:g}, yaw {yaw:g} deg"
    )
    found.add(Verdict.ROTATION, fix, {orient: float(named), px4: float(named)})
    return rotation, turned_deg, named, distance


def _interference(pair: _Pair, residual: np.ndarray, earth_ut: float, found: _Found) -> tuple[np.ndarray, float, float]:
    """Step 2: (the motors' field per unit of the driver (3,) uT, the correlation, the percentage; NaN without a
    driver)."""
    _, slope, correlation = _motor_fit(pair, residual)
    if pair.driver is None:
        return slope, np.nan, np.nan
    scale = pair.full_scale if pair.per == "A" else 1.0
    pct = 100.0 * float(np.linalg.norm(slope)) * scale / earth_ut
    if pct >= INTERFERENCE_MIN_PCT and abs(correlation) >= CORRELATION_MIN:
        suffix = parameter_names(pair.device)[2]
        motor_mg = -10.0 * slope  # ArduPilot adds the opposite of the motors' field: milligauss per A or throttle
        motct = 2.0 if pair.per == "A" else 1.0
        parameters = {"COMPASS_MOTCT": motct}
        parameters.update({f"COMPASS_MOT{suffix}_{a}": round(float(v), 3) for a, v in zip("XYZ", motor_mg)})
        fix = (
            f"motor interference {pct:.0f}% of the Earth's field at full throttle: move it away from the power "
            f"wires, or compensate (ArduPilot compassmot: COMPASS_MOTCT={motct:g}, COMPASS_MOT{suffix}_X/Y/Z)"
        )
        found.add(Verdict.INTERFERENCE, fix, parameters)
    return slope, correlation, pct


def _leftover(pair: _Pair, turned: np.ndarray, slope: np.ndarray, earth_ut: float, found: _Found) -> float:
    """Step 3: what is left against the reference after the rotation and the motors, uT RMS (a constant part
    stays: a disagreement the motors do not explain)."""
    known = np.isfinite(pair.driver) if pair.driver is not None else np.ones(len(turned), dtype=bool)
    if not known.any():
        return 0.0
    motors = 0.0 if pair.driver is None else np.nan_to_num(pair.driver)[:, None] * slope
    left = (turned - motors - pair.reference)[known]
    rms = float(np.sqrt(np.mean(np.sum(left**2, axis=1))))
    sizes = np.linalg.norm(turned - motors, axis=1)[known], np.linalg.norm(pair.reference, axis=1)[known]
    ratio = float(np.median(sizes[0]) / np.median(sizes[1]))
    limit = max(RESIDUAL_MIN_UT, RESIDUAL_MIN_FRACTION * earth_ut)
    if Verdict.CALIBRATION not in found.causes and (rms > limit or abs(ratio - 1) > SCALE_TOLERANCE):
        fix = f"its calibration no longer fits: {rms:.1f} uT RMS from the reference (size ratio {ratio:.2f}): "
        found.add(Verdict.CALIBRATION, fix + "calibrate it again")
    return rms


def _compare(pair: _Pair, earth_ut: float) -> CompassVerdict:
    """One compass against the reference, in the steps of the module docstring."""
    found = _Found()
    matrix, turned_deg, named, distance = _rotation(pair, found)
    turned = pair.field @ matrix.T
    slope, correlation, pct = _interference(pair, turned - pair.reference, earth_ut, found)
    rms = _leftover(pair, turned, slope, earth_ut, found)
    rotated = Verdict.ROTATION in found.causes
    driven = pair.driver is not None
    return CompassVerdict(
        device=pair.device,
        verdict=found.causes[0] if found.causes else Verdict.AGREES,
        causes=tuple(found.causes),
        samples=len(pair.field),
        angle_deg=float(np.median(_angles_deg(pair.reference, pair.field))),
        rotation_deg=turned_deg,
        named_rotation=named if rotated else None,
        named_distance_deg=distance if rotated else None,
        interference_pct=pct if driven else None,
        correlation=correlation if driven else None,
        motor_ut=(float(slope[0]), float(slope[1]), float(slope[2])) if driven else None,
        motor_per=pair.per,
        residual_ut=rms,
        parameters=found.parameters,
        fix="; ".join(found.fixes) or "agrees with the reference",
    )


def _reference(names: list[str], series: Mapping[str, Series]) -> str:
    """The compass whose median angle to the others, summed, is least (the lowest instance on a tie)."""
    totals = dict.fromkeys(names, 0.0)
    for i, a in enumerate(names):
        for b in names[i + 1 :]:
            index, field = _aligned(series[a], series[b])
            angle = float(np.median(_angles_deg(series[a].field_ut[index], field))) if len(index) else 180.0
            totals[a] += angle
            totals[b] += angle
    return min(names, key=lambda n: (round(totals[n], 1), instance_of(n) or 0, n))


def judge(vehicle: str, series: Mapping[str, Series], expected_ut: float | None = None) -> VehicleReport:
    """A vehicle's compasses (device -> its ``Series``) judged against each other; ``expected_ut`` the WMM's
    field size at its place (None: unknown, no anomaly verdict). See the module docstring."""
    enough = sorted(d for d, s in series.items() if len(s.t_s) >= MIN_SAMPLES)
    few = [CompassVerdict(d, Verdict.TOO_FEW, samples=len(s.t_s)) for d, s in sorted(series.items()) if d not in enough]
    if len(enough) < 2:
        text = "fewer than two compasses with enough samples: nothing to compare yet"
        others = [CompassVerdict(d, Verdict.TOO_FEW, samples=len(series[d].t_s)) for d in enough]
        return VehicleReport(vehicle, None, tuple(others + few), None, expected_ut, False, text)
    reference = _reference(enough, series)
    ref = series[reference]
    field_ut = float(np.median(np.linalg.norm(ref.field_ut, axis=1)))
    earth_ut = expected_ut or field_ut
    verdicts = [CompassVerdict(reference, Verdict.REFERENCE, samples=len(ref.t_s), fix="the reference")]
    for device in enough:
        if device == reference:
            continue
        index, field = _aligned(ref, series[device])
        if len(index) < MIN_SAMPLES:
            verdicts.append(CompassVerdict(device, Verdict.TOO_FEW, samples=len(index)))
            continue
        verdicts.append(_compare(_pair(device, ref, index, field, series[device]), earth_ut))
    report = VehicleReport(vehicle, reference, tuple(verdicts + few), field_ut, expected_ut, False, "")
    wrong = report.disagreeing
    anomaly = not wrong and expected_ut is not None and abs(field_ut / expected_ut - 1.0) > ANOMALY_FRACTION
    if wrong:
        summary = "; ".join(f"{c.device}: {c.verdict.value} ({c.fix})" for c in wrong)
    elif anomaly:
        summary = (
            f"all compasses agree, but the field is {field_ut:.1f} uT where the WMM expects {expected_ut:.1f}: a local "
            "anomaly (steel, concrete, a vehicle nearby), not the vehicle's fault: move away before calibrating or "
            "taking off"
        )
    else:
        summary = "all compasses agree"
    return dataclasses.replace(report, anomaly=anomaly, summary=summary)
