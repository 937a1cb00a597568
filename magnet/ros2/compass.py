"""What the compass says on ROS 2, from its own arrays (pure): per sample a MagneticField and an Imu, per device a
diagnostic status. The frames are converted here, once, by ``magnet.ros2.frames.to_ros``."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np

from magnet.frames import euler_to_quaternion
from magnet.ros2 import messages
from magnet.ros2.cdr import stamped_doubles_cdr
from magnet.ros2.frames import TESLA_PER_UT, to_ros
from magnet.ros2.names import ros_name_of_device
from magnet.vehicle import CompassVerdict, VehicleReport, Verdict

#: a heading sigma (deg) beyond which the device's diagnostic warns
UNCERTAIN_HEADING_DEG = 10.0

__all__ = [
    "DeviceState",
    "attitude_wxyz",
    "device_diagnostic",
    "drain_messages",
    "field_variance_t2",
    "orientation_variance_rad2",
    "sample_messages",
]


def attitude_wxyz(
    quat_wxyz: np.ndarray | None, true_heading_deg: np.ndarray, pitch_deg: np.ndarray, roll_deg: np.ndarray
) -> np.ndarray:
    """(S, 4) body FRD -> NED (true north): the fused quaternion where there is one, else the one of (true heading,
    pitch, roll); NaN rows where neither is known."""
    euler = euler_to_quaternion(true_heading_deg, pitch_deg, roll_deg)
    if quat_wxyz is None:
        return euler
    fused = np.isfinite(quat_wxyz).all(axis=1)
    return np.where(fused[:, None], quat_wxyz, euler)


def orientation_variance_rad2(
    heading_sigma_deg: np.ndarray | None, tilt_sigma_deg: np.ndarray | None
) -> np.ndarray | None:
    """(S, 3) rad^2, the orientation's variances about ENU's x, y (the tilt about each horizontal axis) and z (the
    yaw: the heading's sigma, ``magnet.attitude.uncertainty``), for Imu's ``orientation_covariance``; None when the
    compass gave no sigma."""
    if heading_sigma_deg is None or tilt_sigma_deg is None:
        return None
    tilt, yaw = np.radians(tilt_sigma_deg) ** 2, np.radians(heading_sigma_deg) ** 2
    return np.column_stack([tilt, tilt, yaw])


def field_variance_t2(residual_rms_ut: float | None) -> float:
    """The per-axis variance (T^2) of the calibrated field: the calibration's residual RMS (uT) squared; 0 (unknown)
    without a calibration or a residual."""
    if residual_rms_ut is None or not np.isfinite(residual_rms_ut) or residual_rms_ut <= 0:
        return 0.0
    return float((residual_rms_ut * TESLA_PER_UT) ** 2)


def sample_messages(
    device: str,
    t_ns: np.ndarray,
    field_ut: np.ndarray,
    acc_ms2: np.ndarray,
    gyr_rads: np.ndarray,
    quat_wxyz: np.ndarray,
    variance_t2: float,
) -> tuple[list[bytes], list[bytes]]:
    """(MagneticField CDR, Imu CDR) per sample of one device: ``drain_messages`` of one batch."""
    return drain_messages([device], [0, len(t_ns)], t_ns, field_ut, acc_ms2, gyr_rads, quat_wxyz, [variance_t2])[0]


def drain_messages(
    devices: Sequence[str],
    bounds: Sequence[int],
    t_ns: np.ndarray,
    field_ut: np.ndarray,
    acc_ms2: np.ndarray,
    gyr_rads: np.ndarray,
    quat_wxyz: np.ndarray,
    variances_t2: Sequence[float],
    orientation_variance: np.ndarray | None = None,
) -> list[tuple[list[bytes], list[bytes]]]:
    """Per batch (device ``devices[i]``, rows ``bounds[i]:bounds[i+1]``): (MagneticField CDR, Imu CDR) per sample.
    t_ns (S,), field_ut (S, 3) calibrated uT FRD, acc_ms2 and gyr_rads (S, 3) FRD with NaN rows where the device
    has none, quat_wxyz (S, 4) body FRD -> NED (NaN rows: unknown), one field variance (T^2) per batch, and the
    orientation's variances (S, 3) rad^2 about ENU's x, y, z (``orientation_variance_rad2``) or None (unknown).
    frame_id: the device's ROS name. The frames are converted once for the whole drain."""
    ros = to_ros(field_ut, acc_ms2, gyr_rads, quat_wxyz)
    counts = np.diff(np.asarray(bounds, dtype=np.int64)).astype(np.int64)
    mag = messages.magnetic_field_values(ros.field_t, np.repeat(np.asarray(variances_t2, dtype=float), counts))
    imu = messages.imu_values(ros.quat_xyzw, ros.gyr_rads, ros.acc_ms2, len(t_ns), orientation_variance)
    out = []
    for i, device in enumerate(devices):
        lo, hi, frame = bounds[i], bounds[i + 1], ros_name_of_device(device)
        out.append(
            (
                stamped_doubles_cdr(t_ns[lo:hi], frame, mag[lo:hi]),
                stamped_doubles_cdr(t_ns[lo:hi], frame, imu[lo:hi]),
            )
        )
    return out


@dataclasses.dataclass(frozen=True)
class DeviceState:
    """What ``/diagnostics`` says of one device: its calibration (id, method, residual in uT, accepted) or none, the
    kinds of its open drift alerts, and the share of its last samples flagged disturbed."""

    device: str
    calibration_id: str = ""
    method: str = ""
    residual_rms_ut: float | None = None
    coverage: float | None = None
    alerts: tuple[str, ...] = ()
    disturbed_share: float = 0.0
    heading_sigma_deg: float | None = None  # the median heading sigma of the last batch (deg)


def device_diagnostic(state: DeviceState) -> messages.DeviceDiagnostic:
    """OK: calibrated, no alert, field undisturbed; WARN: not calibrated, over half the last samples disturbed, or the
    heading's sigma over ``UNCERTAIN_HEADING_DEG``; ERROR: a drift alert is open."""
    problems, level = [], 0
    if not state.calibration_id:
        problems.append("not calibrated")
        level = 1
    if state.disturbed_share > 0.5:
        problems.append(f"field disturbed in {state.disturbed_share:.0%} of samples")
        level = 1
    if state.heading_sigma_deg is not None and state.heading_sigma_deg > UNCERTAIN_HEADING_DEG:
        problems.append(f"heading uncertain: +-{state.heading_sigma_deg:.3g} deg (one sigma)")
        level = max(level, 1)
    if state.alerts:
        problems.append("drift: " + ", ".join(state.alerts))
        level = 2
    values = [
        ("calibrated", str(bool(state.calibration_id)).lower()),
        ("calibration_id", state.calibration_id),
        ("method", state.method),
        ("residual_rms_ut", "" if state.residual_rms_ut is None else f"{state.residual_rms_ut:.4g}"),
        ("coverage", "" if state.coverage is None else f"{state.coverage:.3g}"),
        ("alerts", ",".join(state.alerts)),
        ("disturbed_share", f"{state.disturbed_share:.3g}"),
        ("heading_sigma_deg", "" if state.heading_sigma_deg is None else f"{state.heading_sigma_deg:.3g}"),
    ]
    message = "; ".join(problems) if problems else "calibrated, no alerts"
    return messages.DeviceDiagnostic(state.device, level, message, tuple(values))


def vehicle_diagnostic(report: VehicleReport) -> messages.DeviceDiagnostic:
    """A vehicle's compasses compared (docs/vehicles.md) as one status, named ``vehicle <ID>``: OK when they agree,
    WARN when one disagrees (its verdict and fix as the message) or the place is a local anomaly, STALE while there
    are too few samples to compare; one value per compass (its verdict and fix) and the parameters to set."""
    wrong = report.disagreeing
    level = 1 if wrong or report.anomaly else 0
    if report.reference is None:
        level = 3
    values = [
        ("reference", report.reference or ""),
        ("field_ut", "" if report.field_ut is None else f"{report.field_ut:.1f}"),
    ]
    values += [(c.device, _said(c)) for c in report.compasses]
    values += [(name, f"{value:g}") for c in wrong for name, value in c.parameters.items()]
    return messages.DeviceDiagnostic(f"vehicle {report.vehicle}", level, report.summary, tuple(values))


def _said(compass: CompassVerdict) -> str:
    return compass.verdict.value if compass.verdict is Verdict.TOO_FEW else f"{compass.verdict.value}: {compass.fix}"
