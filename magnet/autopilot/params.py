"""A calibration record as autopilot parameters: the maths of ``magnet export`` (see ``docs/autopilots.md``).

magnet's record says B = A (u - b): u the raw reading in the body frame, b the offset (raw unit), A the matrix. The
raw frame is the body frame as the autopilot's orientation parameter *in force when the samples were taken* made it
(``rotation_in_force``, 0 = none): u = R_f s, s the reading in the sensor's own axes.

- ArduPilot corrects in the body frame, after its rotation R (``COMPASS_ORIENTn``), in milligauss:
  B = W (R s + o), W symmetric (``COMPASS_DIA*`` on the diagonal, ``COMPASS_ODI*`` off it), o = ``COMPASS_OFS*``,
  and ``COMPASS_SCALE*`` a common factor (written 1). So W R = A R_f (W = the symmetric factor of the left polar
  decomposition) and o = -R R_f^T b.
- PX4 corrects in the sensor's axes, then rotates (``CAL_MAGn_ROT``, or the board rotation for an internal
  magnetometer), in gauss: B = R S (s - o), S symmetric (``CAL_MAGn_{X,Y,Z}SCALE`` on the diagonal,
  ``CAL_MAGn_{X,Y,Z}ODIAG`` off it), o = ``CAL_MAGn_{X,Y,Z}OFF``. So R S = A R_f (S from the right polar
  decomposition) and o = R_f^T b.

Neither autopilot applies a general matrix: the rotation part of A R_f must be the rotation in force (within
ROTATION_TOLERANCE_DEG) or one of the named orientations (``magnet.frames.ROTATIONS``), which is then exported as
the orientation parameter. A rotation no symmetric matrix can carry (a gyro-ellipsoid's small alignment of the
magnetometer to the gyroscope, say) is dropped with its angle in a note when it is at most DROPPED_ROTATION_MAX_DEG
from the nearest of those (the autopilot's headings then differ from magnet's by at most that angle); a larger one is
refused with the angle. ArduPilot's own calibrator refuses
diagonals outside (0.2, 5), off-diagonals beyond +-1 and offsets beyond ``COMPASS_OFFS_MAX`` (default 1800
mGauss); so does this. A motor-interference model becomes ``COMPASS_MOT*``/``COMPASS_MOTCT`` or
``CAL_MAGn_xCOMP``/``CAL_MAG_COMP_TYP`` (``motor_parameters``).
"""

from __future__ import annotations

import dataclasses
import enum

import numpy as np

from magnet.autopilot import hwid
from magnet.frames import nearest_rotation, rotation_angle_deg, rotation_matrix
from magnet.model import Calibration
from magnet.motor import CURRENT, THROTTLE
from magnet.units import UT_PER_GAUSS, UT_PER_MGAUSS, ut_per_unit

#: the largest rotation the symmetric matrix may leave out: 0.05 deg changes the field by under 0.09 %
ROTATION_TOLERANCE_DEG = 0.05
#: the largest rotation dropped with a note rather than refused: a rotation by an angle moves a heading by at most
#: that angle, and 1 deg is within what an autopilot's own calibration leaves (its fitness gate is 16 mG, ~1.8 %)
DROPPED_ROTATION_MAX_DEG = 1.0
ARDUPILOT_DIAGONAL_RANGE = (0.2, 5.0)
ARDUPILOT_OFFDIAGONAL_MAX = 1.0
ARDUPILOT_OFFSETS_MAX_MGAUSS = 1800.0
ARDUPILOT_INSTANCES = 3
PX4_INSTANCES = 4


class Autopilot(enum.Enum):
    ARDUPILOT = "ardupilot"
    PX4 = "px4"


@dataclasses.dataclass(frozen=True)
class Parameter:
    """One autopilot parameter: its name, value and whether the autopilot stores it as an integer; ``check_only``:
    the sensor's hardware id, which names the compass the values are for: written in the file, but on a vehicle
    (``--apply``) read and compared, never set."""

    name: str
    value: float
    integer: bool = False
    check_only: bool = False


@dataclasses.dataclass(frozen=True)
class Export:
    """The parameters of one calibration for one autopilot, and notes for the person loading them."""

    autopilot: Autopilot
    parameters: tuple[Parameter, ...]
    notes: tuple[str, ...]


def in_microtesla(calibration: Calibration) -> tuple[np.ndarray, np.ndarray]:
    """(offset (3,) uT, matrix (3, 3) uT per uT) of ``calibration``; ValueError when a unit has no scale in uT."""
    raw, out = ut_per_unit(calibration.unit), ut_per_unit(calibration.output_unit)
    if raw is None or out is None:
        raise ValueError(
            f"the record maps {calibration.unit!r} to {calibration.output_unit!r}: an autopilot needs a field in "
            "known units (fit with --unit ut/gauss/nt and --field-ut or --location)"
        )
    return calibration.offset * raw, calibration.matrix * (out / raw)


def _polar(matrix: np.ndarray, rotation_first: bool) -> tuple[np.ndarray, np.ndarray]:
    """(rotation U, symmetric positive P) with matrix = U P (rotation_first) or matrix = P U."""
    left, singular, right = np.linalg.svd(matrix)
    rotation = left @ right
    if rotation_first:
        return rotation, right.T @ np.diag(singular) @ right
    return rotation, left @ np.diag(singular) @ left.T


def _orientation(rotation: np.ndarray, in_force: int, name: str) -> tuple[int, list[str]]:
    """The orientation number to export for ``rotation`` (the in-force one when within tolerance), with notes;
    ValueError naming the angle when it is no named orientation."""
    if float(rotation_angle_deg(rotation_matrix(in_force).T @ rotation)) <= ROTATION_TOLERANCE_DEG:
        return in_force, []
    away = float(rotation_angle_deg(rotation_matrix(in_force).T @ rotation))
    if away <= DROPPED_ROTATION_MAX_DEG:
        note = (
            f"the record rotates the field by {away:.2f} deg, which the autopilot cannot apply ({name} and a "
            f"symmetric matrix): dropped, so its headings may differ from magnet's by up to {away:.2f} deg"
        )
        return in_force, [note]
    number, angle = nearest_rotation(rotation)
    if angle > DROPPED_ROTATION_MAX_DEG:
        raise ValueError(
            f"the calibration matrix rotates the field by {away:.2f} deg, and the autopilot applies only a "
            f"symmetric matrix and a named orientation ({name}); the nearest named orientation, {number}, is "
            f"{angle:.2f} deg away (more than the {DROPPED_ROTATION_MAX_DEG:g} deg that may be dropped): fit with a "
            "method that gives a symmetric matrix (ellipsoid, sphere, minmax)"
        )
    notes = [f"{name} changes to {number}: the sensor is mounted differently from the orientation in force"]
    if angle > ROTATION_TOLERANCE_DEG:
        notes.append(f"a further rotation of {angle:.2f} deg is dropped (the autopilot cannot apply it)")
    return number, notes


def _check_instance(instance: int, count: int, autopilot: Autopilot) -> None:
    if not 0 <= instance < count:
        raise ValueError(f"--instance {instance}: {autopilot.value} has compass instances 0..{count - 1}")


def ardupilot_parameters(calibration: Calibration, instance: int = 0, rotation_in_force: int = 0) -> Export:
    """The ArduPilot parameters that apply ``calibration`` to compass ``instance`` (0..2); ValueError when ArduPilot
    cannot represent it (the reason named)."""
    _check_instance(instance, ARDUPILOT_INSTANCES, Autopilot.ARDUPILOT)
    offset_ut, matrix = in_microtesla(calibration)
    r_f = rotation_matrix(rotation_in_force)
    rotation, soft_iron = _polar(matrix @ r_f, rotation_first=False)
    n = "" if instance == 0 else str(instance + 1)
    number, notes = _orientation(rotation, rotation_in_force, f"COMPASS_ORIENT{n}")
    offsets_mg = -(rotation_matrix(number) @ r_f.T @ offset_ut) / UT_PER_MGAUSS
    _check_ardupilot(soft_iron, offsets_mg)
    offdiagonals = (soft_iron[0, 1], soft_iron[0, 2], soft_iron[1, 2])
    parameters = [Parameter(f"COMPASS_OFS{n}_{a}", float(v)) for a, v in zip("XYZ", offsets_mg, strict=True)]
    parameters += [Parameter(f"COMPASS_DIA{n}_{a}", float(soft_iron[k, k])) for k, a in enumerate("XYZ")]
    parameters += [Parameter(f"COMPASS_ODI{n}_{a}", float(v)) for a, v in zip("XYZ", offdiagonals, strict=True)]
    parameters.append(Parameter(f"COMPASS_SCALE{n}", 1.0))
    if number != rotation_in_force:
        parameters.append(Parameter(f"COMPASS_ORIENT{n}", number, integer=True))
        notes.append(f"COMPASS_ORIENT{n} applies to an external compass; an internal one follows AHRS_ORIENTATION")
    parameters += motor_parameters(calibration, Autopilot.ARDUPILOT, instance)
    return Export(Autopilot.ARDUPILOT, tuple(parameters), tuple(notes))


def _check_ardupilot(soft_iron: np.ndarray, offsets_mg: np.ndarray) -> None:
    low, high = ARDUPILOT_DIAGONAL_RANGE
    diagonal = np.diag(soft_iron)
    if not np.all((diagonal > low) & (diagonal < high)):
        raise ValueError(f"ArduPilot takes soft-iron diagonals in ({low:g}, {high:g}); this one needs {diagonal}")
    off = np.abs(soft_iron[np.triu_indices(3, 1)])
    if np.any(off >= ARDUPILOT_OFFDIAGONAL_MAX):
        raise ValueError(f"ArduPilot takes soft-iron off-diagonals within +-1; this one needs {off.max():.3g}")
    worst = float(np.abs(offsets_mg).max())
    if worst >= ARDUPILOT_OFFSETS_MAX_MGAUSS:
        raise ValueError(
            f"the offsets reach {worst:.0f} mGauss; ArduPilot refuses offsets beyond COMPASS_OFFS_MAX (default "
            f"{ARDUPILOT_OFFSETS_MAX_MGAUSS:.0f} mGauss): move the compass away from the iron, or raise that limit"
        )


def px4_parameters(calibration: Calibration, instance: int = 0, rotation_in_force: int = 0) -> Export:
    """The PX4 parameters that apply ``calibration`` to calibration slot ``instance`` (CAL_MAGn, 0..3); ValueError
    when PX4 cannot represent it (the reason named)."""
    _check_instance(instance, PX4_INSTANCES, Autopilot.PX4)
    offset_ut, matrix = in_microtesla(calibration)
    r_f = rotation_matrix(rotation_in_force)
    rotation, scale = _polar(matrix @ r_f, rotation_first=True)
    number, notes = _orientation(rotation, rotation_in_force, f"CAL_MAG{instance}_ROT")
    offsets_gauss = r_f.T @ offset_ut / UT_PER_GAUSS
    prefix = f"CAL_MAG{instance}_"
    offdiagonals = (scale[0, 1], scale[0, 2], scale[1, 2])
    parameters = [Parameter(f"{prefix}{a}OFF", float(v)) for a, v in zip("XYZ", offsets_gauss, strict=True)]
    parameters += [Parameter(f"{prefix}{a}SCALE", float(scale[k, k])) for k, a in enumerate("XYZ")]
    parameters += [Parameter(f"{prefix}{a}ODIAG", float(v)) for a, v in zip("XYZ", offdiagonals, strict=True)]
    if number != rotation_in_force:
        parameters.append(Parameter(f"{prefix}ROT", number, integer=True))
        notes.append(f"{prefix}ROT applies to an external magnetometer; an internal one follows SENS_BOARD_ROT")
    if calibration.hardware_id is None:
        notes.append(f"{prefix}ID must already name the magnetometer (it does after any PX4 calibration of it)")
    parameters += motor_parameters(calibration, Autopilot.PX4, instance, r_f)
    return Export(Autopilot.PX4, tuple(parameters), tuple(notes))


#: the motor-compensation type parameters' values: ArduPilot COMPASS_MOTCT and PX4 CAL_MAG_COMP_TYP
ARDUPILOT_MOTCT = {THROTTLE: 1, CURRENT: 2}
PX4_COMP_TYP = {THROTTLE: 1, CURRENT: 2}
#: PX4 scales current-based compensation per kA (it feeds the battery current / 1000 as the power)
PX4_AMPS_PER_POWER = {THROTTLE: 1.0, CURRENT: 1000.0}


def motor_parameters(
    calibration: Calibration, autopilot: Autopilot, instance: int, r_f: np.ndarray | None = None
) -> list[Parameter]:
    """The motor-interference parameters of ``calibration``: none without a motor model.

    magnet subtracts m x (uT, x the current in A or the throttle 0..1) after its correction. ArduPilot adds
    ``COMPASS_MOT`` x after its soft-iron matrix, in milligauss: MOT = -m (mGauss), with ``COMPASS_MOTCT`` 1
    (throttle) or 2 (current). PX4 adds ``CAL_MAGn_xCOMP`` x power to the sensor's reading before its offset and
    matrix (power = throttle, or current in kA; ``CAL_MAG_COMP_TYP`` 1 or 2): it must cancel m in the raw axes,
    COMP = -(R S)^-1 m = -R_f^T A^-1 m (gauss per unit power; r_f (3, 3) the rotation in force, default none)."""
    motor = calibration.motor
    if motor is None:
        return []
    if autopilot is Autopilot.ARDUPILOT:
        n = "" if instance == 0 else str(instance + 1)
        mot_mg = -motor.coefficients / UT_PER_MGAUSS
        out = [Parameter(f"COMPASS_MOT{n}_{a}", float(v)) for a, v in zip("XYZ", mot_mg, strict=True)]
        return [*out, Parameter("COMPASS_MOTCT", ARDUPILOT_MOTCT[motor.kind], integer=True)]
    _, matrix = in_microtesla(calibration)
    raw_ut = (np.eye(3) if r_f is None else r_f).T @ np.linalg.solve(matrix, motor.coefficients)
    comp = -raw_ut / UT_PER_GAUSS * PX4_AMPS_PER_POWER[motor.kind]
    out = [Parameter(f"CAL_MAG{instance}_{a}COMP", float(v)) for a, v in zip("XYZ", comp, strict=True)]
    return [*out, Parameter("CAL_MAG_COMP_TYP", PX4_COMP_TYP[motor.kind], integer=True)]


def export_parameters(
    calibration: Calibration, autopilot: Autopilot | str, instance: int = 0, rotation_in_force: int = 0
) -> Export:
    """The parameters for ``autopilot`` (``ardupilot`` or ``px4``); ValueError when it cannot represent the record."""
    chosen = Autopilot(autopilot)
    if chosen is Autopilot.ARDUPILOT:
        export = ardupilot_parameters(calibration, instance, rotation_in_force)
    else:
        export = px4_parameters(calibration, instance, rotation_in_force)
    return with_hardware_id(export, calibration, instance)


def with_hardware_id(export: Export, calibration: Calibration, instance: int) -> Export:
    """``export`` with the sensor's id first (``COMPASS_DEV_IDn``, ``CAL_MAGn_ID``) when the record names its sensor
    (``Calibration.hardware_id``; docs/mavlink.md): it says which compass the values were fitted for. An id beyond
    the autopilots' 24 bits (another kind of edge's) is left out, with a note."""
    sensor = calibration.hardware_id
    if sensor is None:
        return export
    ardupilot = export.autopilot is Autopilot.ARDUPILOT
    kind = hwid.MAV_AUTOPILOT_ARDUPILOTMEGA if ardupilot else hwid.MAV_AUTOPILOT_PX4
    name = hwid.id_param(kind, instance)
    if sensor > hwid.MAX_HARDWARE_ID:
        return dataclasses.replace(export, notes=(*export.notes, f"hardware id {sensor} is no {name}: not written"))
    note = f"{name} = {hwid.describe(sensor, kind)}: the compass these values were fitted for"
    parameters = (Parameter(name, float(sensor), integer=True, check_only=True), *export.parameters)
    return dataclasses.replace(export, parameters=parameters, notes=(*export.notes, note))
