"""The offset from the velocity over the ground: a vehicle that has not turned yet (docs/field-calibration.md,
"A vehicle that drives straight").

A car on a straight road sees one field direction: the magnetometer and the gyroscope cannot tell its offset (any
offset that leaves |B| and the dip right is as good). Its GNSS velocity can: while the vehicle speeds up, slows down
or turns, its accelerometer reads the acceleration dv/dt in body axes while the receiver gives it in NED, and the
turn between the two is the body's heading (in-motion alignment; the device's own accelerometer, so however the
device sits in the vehicle, as long as it is fixed). With the heading, the attitude is whole, the World Magnetic
Model's field vector (|B|, dip and declination at the place) turned into body axes is what a calibrated sensor
reads, and the offset is the mean of what the raw sensor reads beyond it (the matrix kept: the record in force's,
else the identity).

How (``course_attitude``): the gyroscope + accelerometer filter without the magnetometer gives the attitude up to
one turn about the vertical; the specific force levelled by the samples' mean down direction (a car stays within a
few degrees of it; the filter's own tilt leans with the accelerations it should show) is compared, smoothed over
the velocity's window, with the velocity's acceleration where the latter exceeds ``MIN_ACCELERATION_MS2``: the
least-squares turn between the two horizontal vectors is the filter's heading offset. Its uncertainty is the
residual's spread over the acceleration's power, samples within the velocity's window counted as one. Then the
accelerometer is freed of the acceleration (turned into body axes with that heading), the filter runs again on what
is left (gravity: its tilt no longer leans) and the turn is taken again.

Used by the field ladder (``magnet.calibration.field``) only when the magnetometer and gyroscope identify nothing,
the device is planar and its samples carry a velocity and a place: the record says so (quality ``heading_source``).
Pure numpy.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from magnet import frames
from magnet.attitude.aiding import VelocityFixes
from magnet.calibration.ladder import IDENTIFIED_DEG
from magnet.calibration.rungs import PLANAR_NOTE
from magnet.model import Calibration
from magnet.quality import GateThresholds, Geometry, assess, gate

#: samples whose velocity's acceleration is below this (m/s^2) say nothing of the heading (a receiver's noise over
#: the velocity's window is 0.14 m/s^2; a car's speed changes and turns are 0.5-3 m/s^2)
MIN_ACCELERATION_MS2 = 0.5
#: fewest such samples (s of them at any rate) before a heading is taken
MIN_ACCELERATING_S = 5.0
#: a record from the velocity's heading must make the field point where the WMM says within this (deg RMS): the
#: attitude's heading and tilt (under 1 deg each on the simulated cars) and a phone's soft iron (a few %) leave less
COURSE_AGREEMENT_DEG = 3.0
#: what such a record says in its quality ``heading_source``
COURSE_SOURCE = "velocity over the ground"


@dataclasses.dataclass(frozen=True)
class Place:
    """The WMM's field at the device's place: strength (uT), dip and declination (deg)."""

    field_ut: float
    dip_deg: float
    declination_deg: float


@dataclasses.dataclass(frozen=True)
class Motion:
    """Consecutive samples: mag (N, 3) uT raw, acc (N, 3) m/s^2 (or g), gyr (N, 3) rad/s, every period_s s,
    vel_ned_ms (N, 3) m/s geographic NED as held on the wire (NaN rows before the first fix), and kept (N,) bool: the
    samples whose field the offset is taken from (None: all; ``magnet.calibration.disturbed``: a field disturbed
    on the way, a parked car or a bridge passed, enters no fit). The attitude is worked out from every sample, whose
    gyroscope, accelerometer and velocity a magnetic disturbance does not touch."""

    mag: np.ndarray
    acc: np.ndarray
    gyr: np.ndarray
    period_s: float
    vel_ned_ms: np.ndarray
    kept: np.ndarray | None = None


@dataclasses.dataclass(frozen=True)
class CourseAttitude:
    """The attitude (N, 4) body -> geographic NED (the velocity's north) of every sample, the heading's uncertainty
    (deg, one sigma), the specific force's residual spread against the velocity's acceleration (m/s^2) and the
    seconds of samples that told the heading."""

    quat_wxyz: np.ndarray
    sigma_deg: float
    residual_ms2: float
    accelerating_s: float


def _turn(level: np.ndarray, accel: np.ndarray, rows: np.ndarray, period_s: float) -> tuple[float, float, float]:
    """(the turn psi, rad, that takes the velocity's horizontal acceleration accel (N, 2) NED onto the levelled
    specific force level (N, 2) in the filter's frame, least squares over ``rows``; its sigma, rad; the residual
    spread, m/s^2)."""
    g, h = accel[rows], level[rows]
    psi = math.atan2(float(np.sum(g[:, 0] * h[:, 1] - g[:, 1] * h[:, 0])), float(np.sum(g * h)))
    c, s = math.cos(psi), math.sin(psi)
    turned = np.column_stack([c * g[:, 0] - s * g[:, 1], s * g[:, 0] + c * g[:, 1]])
    residual = float(np.sqrt(np.mean((h - turned) ** 2)))
    correlated = max(2.0 * VelocityFixes().half_window_s / period_s, 1.0)  # samples in one velocity window
    sigma = residual * math.sqrt(correlated / float(np.sum(g * g)))
    return psi, sigma, residual


def _smoothed(values: np.ndarray, count: int) -> np.ndarray:
    """A centred moving mean (N, k) over ``count`` samples (the velocity's window)."""
    kernel = np.ones(max(count, 1)) / max(count, 1)
    return np.column_stack([np.convolve(values[:, k], kernel, mode="same") for k in range(values.shape[1])])


def _accelerating(
    vel_ned_ms: np.ndarray, period_s: float
) -> tuple[VelocityFixes, np.ndarray, np.ndarray, np.ndarray] | None:
    """The velocity's fixes, their acceleration (N, 3) m/s^2 at each sample, where it is known (N,) bool and where
    it tells the heading (N,) bool: known and horizontally over ``MIN_ACCELERATION_MS2``; None with fewer than 3
    fixes."""
    vel = np.asarray(vel_ned_ms, dtype=float)
    t_s = np.arange(len(vel)) * period_s
    fixes = VelocityFixes(max_fixes=len(t_s) + 2)
    fixes.observe(t_s, vel)
    if len(fixes.times_s) < 3:
        return None
    accel = fixes.acceleration(t_s)
    known = (t_s >= fixes.times_s[0] + fixes.half_window_s) & (t_s <= fixes.known_until_s)
    return fixes, accel, known, known & (np.linalg.norm(accel[:, :2], axis=1) > MIN_ACCELERATION_MS2)


def accelerating_s(vel_ned_ms: np.ndarray, period_s: float) -> float:
    """Seconds of consecutive samples (velocity (N, 3) m/s NED as held on the wire, NaN rows before the first fix,
    every ``period_s`` s) whose velocity's acceleration tells the heading (what ``course_attitude`` needs
    ``MIN_ACCELERATING_S`` of): the information the velocity holds, as a turn is the gyroscope's."""
    told = _accelerating(vel_ned_ms, period_s)
    return 0.0 if told is None else float(told[3].sum() * period_s)


def course_attitude(
    gyr_rads: np.ndarray, acc_ms2: np.ndarray, period_s: float, vel_ned_ms: np.ndarray
) -> CourseAttitude | None:
    """The velocity-aligned attitude (module docstring) of consecutive samples: gyr (N, 3) rad/s, acc (N, 3) m/s^2
    (or g), body FRD, every ``period_s`` s; vel_ned_ms (N, 3) m/s geographic NED as held on the wire (NaN rows before
    the first fix). None when fewer than ``MIN_ACCELERATING_S`` of samples accelerate enough."""
    from magnet.attitude import fusion  # vqf's wrapper: only where a gyroscope's attitudes are needed

    acc = fusion.acc_in_ms2(np.asarray(acc_ms2, dtype=float))
    told = _accelerating(vel_ned_ms, period_s)
    if told is None:
        return None
    fixes, accel, known, rows = told
    if rows.sum() * period_s < MIN_ACCELERATING_S:
        return None
    window = round(2.0 * fixes.half_window_s / period_s)
    down = -acc.mean(axis=0)
    down /= np.linalg.norm(down)
    horizontal = acc - np.outer(acc @ down, down)  # the specific force in the plane square to the mean vertical
    fused = fusion.fuse_offline(gyr_rads, acc, None, period_s)
    rotation = frames.quaternion_to_matrix(fused.quat_wxyz)
    level = _smoothed(np.einsum("nij,nj->ni", rotation, horizontal)[:, :2], window)
    psi, _, _ = _turn(level, accel[:, :2], rows, period_s)
    # again with the accelerometer freed of the acceleration (turned into body axes by the heading just found)
    aligned = frames.quaternion_to_matrix(frames.rotate_heading(fused.quat_wxyz, -math.degrees(psi)))
    gravity = acc - np.where(known[:, None], np.einsum("nji,nj->ni", aligned, accel), 0.0)
    fused = fusion.fuse_offline(gyr_rads, gravity, None, period_s)
    rotation = frames.quaternion_to_matrix(fused.quat_wxyz)
    level = _smoothed(np.einsum("nij,nj->ni", rotation, acc)[:, :2], window)
    psi, sigma, residual = _turn(level, accel[:, :2], rows, period_s)
    quat = frames.rotate_heading(fused.quat_wxyz, -math.degrees(psi))
    return CourseAttitude(quat, math.degrees(sigma), residual, float(rows.sum() * period_s))


def earth_vector_ut(field_ut: float, dip_deg: float, declination_deg: float) -> np.ndarray:
    """The WMM's field (3,) uT in geographic NED from its strength, dip and declination."""
    dip, declination = math.radians(dip_deg), math.radians(declination_deg)
    return field_ut * np.array(
        [math.cos(dip) * math.cos(declination), math.cos(dip) * math.sin(declination), math.sin(dip)]
    )


def fit_course(
    samples: Motion,
    place: Place,
    matrix0: np.ndarray,
    reference: Calibration | None,
    kept_from: str,
    thresholds: GateThresholds,
    min_gain: float,
) -> Calibration | None:
    """The offset record (uT) from the velocity's attitude (module docstring) with the matrix ``matrix0`` (3, 3)
    kept; None when the attitude is not known well enough (heading uncertainty over IDENTIFIED_DEG). Accepted when
    the field then points where the WMM says within COURSE_AGREEMENT_DEG (RMS), the gate's residual and radius
    checks pass (``thresholds``) and, against a ``reference`` in force, it points closer by ``min_gain`` of the
    reference's figure."""
    try:
        aligned = course_attitude(samples.gyr, samples.acc, samples.period_s, samples.vel_ned_ms)
    except ValueError:
        return None
    if aligned is None or aligned.sigma_deg > IDENTIFIED_DEG:
        return None
    earth = earth_vector_ut(place.field_ut, place.dip_deg, place.declination_deg)
    expected = np.einsum("nji,j->ni", frames.quaternion_to_matrix(aligned.quat_wxyz), earth)  # R^T B, body uT
    mag = np.asarray(samples.mag, dtype=float)
    if samples.kept is not None:  # the undisturbed samples' field alone (the attitude is every sample's)
        kept = np.asarray(samples.kept, dtype=bool)
        if kept.shape != (len(mag),) or not kept.any():
            return None
        mag, expected = mag[kept], expected[kept]
    offset = np.mean(mag - expected @ np.linalg.inv(matrix0).T, axis=0)
    calibration = Calibration(
        method="offset",
        offset=offset,
        matrix=matrix0,
        field_strength=float(place.field_ut),
        sample_count=len(mag),
        unit="ut",
        output_unit="ut",
    )
    corrected = calibration.apply(mag)
    agreement = agreement_deg(corrected, expected)
    in_force = None if reference is None else agreement_deg(reference.apply(mag), expected)
    quality = assess(
        mag,
        calibration,
        corrected=corrected,
        geometry=Geometry.SPHERE,
        expected_field_ut=place.field_ut,
        fitted_radius_ut=None,
        holdout=None,
    )
    why = (
        f"offset: the velocity over the ground gives the heading ({aligned.accelerating_s:.0f} s of accelerations, "
        f"heading uncertainty {aligned.sigma_deg:.2g} deg <= {IDENTIFIED_DEG:g}), the WMM the field's direction "
        f"(agreement {agreement:.2g} deg RMS); {PLANAR_NOTE}"
    )
    quality = quality.with_extra(
        model="offset",
        estimated=["offset"],
        kept=["matrix"],
        kept_from=kept_from,
        identified_deg={"offset": aligned.sigma_deg},
        heading_source=COURSE_SOURCE,
        course_agreement_deg=agreement,
        reference_course_agreement_deg=in_force,
        course_residual_ms2=aligned.residual_ms2,
        planar=PLANAR_NOTE,
        why=why,
    )
    accepted, reason = gate(quality, thresholds)
    refusals = []
    if agreement > COURSE_AGREEMENT_DEG:
        refusals.append(
            f"the field points {agreement:.1f} deg (RMS) from where the WMM says with the attitude the velocity gives "
            f"(limit {COURSE_AGREEMENT_DEG:g}): a disturbed place, a device that moves in the vehicle, or the wrong "
            "place; turn the vehicle to calibrate from the turns"
        )
    if in_force is not None and agreement > (1.0 - min_gain) * in_force:
        refusals.append(
            f"the field points {agreement:.2f} deg (RMS) from the WMM's direction against {in_force:.2f} deg with the "
            f"calibration in force (a refresh must gain {100 * min_gain:.0f} %): good enough"
        )
    if refusals:
        reason = "; ".join(refusals) + ("" if accepted else f"; {reason}")
        accepted = False
    return calibration.replace(quality=quality, accepted=accepted, reason=f"{reason}; {why}")


def agreement_deg(field: np.ndarray, expected: np.ndarray) -> float:
    """RMS angle (deg) between the fields (N, 3) and the expected ones (N, 3)."""
    cosine = np.einsum("ij,ij->i", field, expected) / (np.linalg.norm(field, axis=1) * np.linalg.norm(expected, axis=1))
    return float(np.degrees(np.sqrt(np.mean(np.arccos(np.clip(cosine, -1.0, 1.0)) ** 2))))
