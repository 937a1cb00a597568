"""The calibrations a compass applies: which are in force per device, which it refuses and why (not accepted by the
quality gate, not signed by a trusted key, older than the one in force), which it holds back from a batch of another
sensor (the record's ``hardware_id`` not the batch's: docs/mavlink.md), and each sample's correction from them
(``Correction``: offset, matrix, motors and the magnetometer's lag, applied in one place).

Pure: records in, decisions out; the compass core (``magnet.compass.core``) counts and logs."""

from __future__ import annotations

import dataclasses

import numpy as np

from magnet import signing, wire
from magnet.attitude import offset_learn
from magnet.attitude.causal_drift import delta_moved
from magnet.attitude.mag_delay import advance_field
from magnet.attitude.refresh_shift import shift_heading
from magnet.bounded import Recent
from magnet.compass.filters import DeviceFilters
from magnet.compass.replay import corrector
from magnet.compiled import kernels as _kernels
from magnet.model import Calibration

#: devices remembered as refused between two asks of the calibrators (a flood beyond: one query for all)
MAX_REFUSED = 1024

_ZERO3, _EYE3 = np.zeros(3), np.eye(3)


class CalibrationsInForce:
    """The calibration in force per device (at most ``max_devices``, the least recently used forgotten first) and
    the devices whose calibration was refused since the calibrators were last asked."""

    def __init__(self, trusted: signing.TrustedKeys | None, max_devices: int) -> None:
        self.trusted = trusted or signing.TrustedKeys()
        self.in_force: Recent[str, wire.DeviceCalibration] = Recent(max_devices)
        self.refused: Recent[str, bool] = Recent(MAX_REFUSED)
        self._refused_evicted = 0
        self.updates = 0  # calibrations that came into force
        #: the latest ``created_ns`` of a record put in force per device (a rollback puts an older one in force)
        self.newest_created: Recent[str, int] = Recent(max_devices)
        self.renumbered = 0  # records put in force although numbered below the one held (``check``: history lost)
        #: per device whose numbering started again: when its first renumbered record was made (ns); a record made
        #: before it is from the lost history, however high its version (a replay), and stays refused
        self.renumbered_at: Recent[str, int] = Recent(max_devices)
        #: batches left uncorrected because their sensor is not the one their device's record was made for, and per
        #: device the last such pair (the record's hardware id, the batch's)
        self.hardware_mismatches = 0
        self.mismatched: Recent[str, tuple[int, int]] = Recent(max_devices)

    def check(self, record: wire.DeviceCalibration) -> str | None:
        """WireError unless ``record`` may be applied: accepted by the quality gate (its plausibility was checked
        when it was read), signed by a trusted key where keys are trusted, and newer than the one in force: a
        higher version, which the signature covers (``created_ns`` only between equal versions,
        ``DeviceCalibration.newer_than``).

        One exception, said out loud: a record numbered *below* the one held but made later than any record this
        compass put in force for the device is what a calibrator that lost its history (its database deleted or
        replaced, numbering again from 1) sends for an operator's commit. Refusing it as stale would drop every
        new calibration of the device while the calibrator reports them stored; it is applied, and the returned
        line (None otherwise) says what happened, for the log and the ``renumbered`` count. A replayed older record
        (made no later than the newest seen) stays stale, and so, once a device's numbering started again, does any
        record made before that (the lost history's high versions)."""
        if not record.calibration.accepted:
            raise wire.WireError(
                "not-accepted",
                f"calibration {record.id} of {record.device} is marked accepted: false (the quality gate refused it)",
            )
        if self.trusted.enabled:
            try:
                self.trusted.verify(record.to_record())
            except signing.SignatureError as exc:
                raise wire.WireError(exc.cause, f"calibration {record.id} of {record.device}: {exc}") from None
        current = self.in_force.get(record.device)
        restarted_ns = self.renumbered_at.get(record.device)
        if (
            restarted_ns is not None
            and record.created_ns < restarted_ns
            and (current is None or current.id != record.id)
        ):
            raise wire.WireError(
                "stale",
                f"calibration {record.id} (version {record.version}) of {record.device} was made before its "
                "calibrators' numbering started again (their history was lost): a record of the lost history",
            )
        if current is None or current.id == record.id or record.newer_than(current):
            return None
        newest_ns = max(current.created_ns, self.newest_created.get(record.device, 0))
        if 0 < record.version < current.version and record.created_ns > newest_ns:
            return (
                f"calibration {record.id} of {record.device} is numbered version {record.version}, below the one in "
                f"force ({current.id}, version {current.version}), but made later than any held: the calibrators' "
                "history was lost (a database deleted or replaced?); applied as the newer one. Check the "
                "calibrator's status (store) and restore its database if it was lost"
            )
        raise wire.WireError(
            "stale",
            f"calibration {record.id} (version {record.version}) of {record.device} is not newer than the one in "
            f"force ({current.id}, version {current.version})",
        )

    def put(self, record: wire.DeviceCalibration) -> bool:
        """Put a checked record in force; True when it is a new calibration for its device (not the one in force
        again, which only takes the new numbering: a rollback to it)."""
        current = self.in_force.get(record.device)
        if current is not None and current.id == record.id:
            if record.newer_than(current):
                self.in_force[record.device] = record
            return False
        if current is not None and record.version < current.version:
            self.renumbered += 1
            self.renumbered_at[record.device] = record.created_ns
        self.in_force[record.device] = record
        self.newest_created[record.device] = max(record.created_ns, self.newest_created.get(record.device, 0))
        self.updates += 1
        return True

    def refuse(self, device: str) -> None:
        """Remember that ``device``'s calibration was just refused (the calibrators are asked again)."""
        self.refused[device] = True

    def take_refused(self) -> tuple[list[str], bool]:
        """(the devices refused since the last call, sorted; whether more were refused than remembered), and forget
        them."""
        overflow = self.refused.evicted > self._refused_evicted
        devices = sorted(self.refused)
        self.refused.clear()
        self._refused_evicted = self.refused.evicted
        return devices, overflow

    def of_batches(
        self, devices: list[str], hardware_ids: list[int] | None = None
    ) -> list[wire.DeviceCalibration | None]:
        """The calibration in force for each batch's device (None where there is none), marked as just used; None
        too where the record names a sensor (``hardware_id``) and the batch another (``hardware_ids``, 0 where not
        known): a calibration is never moved onto another sensor. Those are counted (``hardware_mismatches``) and
        remembered per device (``mismatched``) until a batch of the record's sensor, or a record for this one,
        comes."""
        cals = [self.in_force.get(device) for device in devices]
        for i, (device, cal) in enumerate(zip(devices, cals)):
            if cal is None:
                continue
            self.in_force.touch(device)
            wanted, sensor = cal.calibration.hardware_id, 0 if hardware_ids is None else hardware_ids[i]
            if wanted is not None and sensor and sensor != wanted:
                cals[i] = None
                self.hardware_mismatches += 1
                self.mismatched[device] = (wanted, sensor)
            elif device in self.mismatched and (sensor or wanted is None):
                self.mismatched.pop(device, None)
        return cals

    def mismatch_report(self) -> dict[str, dict[str, int]]:
        """Per device whose record is held back now: ``{"record": its hardware id, "sensor": the batches'}``."""
        return {d: {"record": r, "sensor": s} for d, (r, s) in sorted(self.mismatched.items())}


@dataclasses.dataclass(frozen=True, eq=False)
class Correction:
    """Each sample's correction by its batch's record in force, made once per step and applied in one place, as
    PX4's ``calibration::Magnetometer::Correct`` and ArduPilot's ``AP_Compass`` apply theirs: the field
    B = A (u - b) - motors (offset b, matrix A, the motors' field at the sample's current or throttle), and for the
    attitude filter B turned forward over the magnetometer's lag (``magnet.attitude.mag_delay``).

    offsets (B, 3) raw uT and matrices (B, 3, 3) per batch (zero and identity where a batch has no record), bounds
    (B + 1,) int64 where each batch's samples start, calibrated (S,) bool, motor_ut (S, 3) uT (zero where the record
    has no motor model or the batch no current or throttle), None when no record has a motor model; lag_s (S,) s, None
    when no record carries one."""

    offsets: np.ndarray
    matrices: np.ndarray
    bounds: np.ndarray
    calibrated: np.ndarray
    motor_ut: np.ndarray | None = None
    lag_s: np.ndarray | None = None

    @classmethod
    def of_batches(cls, cals: list[wire.DeviceCalibration | None], columns: wire.RawColumns) -> Correction:
        """The correction of every sample of ``columns`` by its batch's record (``cals``, one per batch, None where
        a device has none), each record read once."""
        counts = columns.counts
        bounds = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
        if all(c is None for c in cals):
            count = len(cals)
            return cls(np.zeros((count, 3)), np.broadcast_to(_EYE3, (count, 3, 3)), bounds, np.zeros(bounds[-1], bool))
        records = [c.calibration if c else None for c in cals]
        offsets = np.array([r.offset if r else _ZERO3 for r in records], dtype=float).reshape(-1, 3)
        matrices = np.array([r.matrix if r else _EYE3 for r in records], dtype=float).reshape(-1, 3, 3)
        calibrated = np.array([r is not None for r in records], dtype=bool)
        lags = [r.mag_lag_s if r else 0.0 for r in records]
        return cls(
            offsets,
            matrices,
            bounds,
            np.repeat(calibrated, counts),
            _motor_rows(records, columns),
            np.repeat(np.asarray(lags, dtype=float), counts) if any(lags) else None,
        )

    def apply(self, mag_ut: np.ndarray, gyr_rads: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(the corrected field (S, 3) uT the compass publishes, the field (S, 3) its attitude filter gets: turned
        forward over the lag by the gyroscope's rates gyr_rads (S, 3) rad/s, the same array without a lag) from the
        raw mag_ut (S, 3) uT: each batch's A (u - b), in one compiled pass (``magnet._kernels.correct_field``: numpy's
        ``einsum`` of the per-sample matrices to the bit, without them)."""
        # no calibration anywhere: identity, the same numbers without the per-sample matrix product
        if self.calibrated.any():
            field = np.empty((len(mag_ut), 3))
            matrices = np.ascontiguousarray(self.matrices).reshape(-1, 9)
            _kernels.correct_field(np.asarray(mag_ut, dtype=float), self.offsets, matrices, self.bounds, field)
        else:
            field = np.array(mag_ut, dtype=float)
        if self.motor_ut is not None:
            field = field - self.motor_ut
        return field, field if self.lag_s is None else advance_field(field, gyr_rads, self.lag_s)


def _motor_rows(records: list[Calibration | None], columns: wire.RawColumns) -> np.ndarray | None:
    """(S, 3) uT the motors add at each sample (``magnet.motor``: the record's motor model times the batch's
    current or throttle; zero where either is unknown), or None when no batch's record has a motor model."""
    if all(r is None or r.motor is None for r in records):
        return None
    out = np.zeros((int(columns.counts.sum()), 3))
    bounds = columns.bounds
    for i, record in enumerate(records):
        if record is not None and record.motor is not None:
            lo, hi = bounds[i], bounds[i + 1]
            out[lo:hi] = record.motor.offset_ut(columns.current[lo:hi], columns.thr[lo:hi])
    return out


#: a new record that turns the corrected field by less than this (deg, at any direction of a field of the old
#: record's strength) and changes its strength by less than RESTART_PCT keeps the device's filter: an in-service
#: refresh (``magnet.calibrator.refresh``) moves the field by a degree or two, and a filter started again while a
#: hand swings a phone takes ten seconds and more to find its heading (fieldsim's walk-hand: 22 deg over them)
RESTART_DEG = 8.0
RESTART_PCT = 8.0
_CUBE = np.array([[x, y, z] for x in (-1, 0, 1) for y in (-1, 0, 1) for z in (-1, 0, 1) if x or y or z], dtype=float)
_DIRECTIONS = _CUBE / np.linalg.norm(_CUBE, axis=1)[:, None]


def small_change(old: Calibration, new: Calibration) -> bool:
    """Whether ``new`` corrects every raw reading the old one maps onto a field of its strength, in 26 directions,
    to within RESTART_DEG of direction and RESTART_PCT of strength (same units, no motors' field in either)."""
    if (old.unit, old.output_unit) != (new.unit, new.output_unit) or old.motor is not None or new.motor is not None:
        return False
    try:
        inverse = np.linalg.inv(old.matrix)
    except np.linalg.LinAlgError:
        return False
    strength = old.field_strength or 50.0
    raw = old.offset + (_DIRECTIONS * strength) @ inverse.T
    before, after = old.apply(raw), new.apply(raw)
    norm_before, norm_after = np.linalg.norm(before, axis=1), np.linalg.norm(after, axis=1)
    cosine = np.einsum("ij,ij->i", before, after) / (norm_before * norm_after)
    angle = np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0)))
    ratio = np.abs(norm_after / norm_before - 1.0) * 100.0
    return bool(np.all(angle < RESTART_DEG) and np.all(ratio < RESTART_PCT))


def recalibrate_filter(
    filters: DeviceFilters, previous: wire.DeviceCalibration | None, record: wire.DeviceCalibration
) -> None:
    """``record`` came into force for its device (``previous`` was): the device's filter forgets its magnetic side
    (it was built on the old correction, and the field jumping to the new one would look to vqf like a disturbance it
    takes tens of seconds to trust; the tilt and the gyroscope's bias are kept), unless the field hardly moves
    (``small_change``: an in-service refresh), where its heading moves at once by what the record changes
    (``magnet.attitude.refresh_shift``)."""
    new = corrector(record.calibration)
    if previous is None or not small_change(previous.calibration, record.calibration):
        filters.forget(record.device, magnetic_only=True, correct=new)
    else:
        state = filters.devices.get(record.device)
        if state is not None:  # the old record's learnt offset error goes with it (``offset_learn``)
            delta_moved(state, offset_learn.refresh(state, new))
        shift_heading(state, corrector(previous.calibration), new)
