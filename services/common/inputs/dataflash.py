"""ArduPilot DataFlash logs (``.bin``) as recorded inputs, read with ``pymavlink`` (see ``docs/autopilots.md``).

Magnetometer: the ``MAG`` records of instance ``--mag N`` (field ``I`` in current logs; ``MAG``, ``MAG2``, ``MAG3``
in old ones). ArduPilot logs the field after its own correction (MagX..Z, milligauss, body frame) together with the
offsets it added (OfsX..Z) and the motor offsets (MOX..Z in current logs, MOfsX..Z before, none in the oldest:
``MAG_FORMATS`` lists the layouts ArduPilot has logged); the reader undoes the correction
(``magnet.autopilot.conventions.ardupilot_raw_field``) with the soft-iron matrix and scale factor of the log's ``PARM``
records (``COMPASS_DIA*``, ``COMPASS_ODI*``, ``COMPASS_SCALE*``; their first logged values), giving the uncorrected
field in the body frame. Accelerometer and gyroscope: ``IMU`` instance 0 (m/s^2, rad/s, body frame). Battery current:
``BAT`` instance 0 (``Curr``, A; ``CURR`` in very old logs, centiamps). Throttle: ``RCOU`` channels 1-4 (PWM, 1000..2000
us mapped to 0..1). Times: ``TimeUS`` (``TimeMS`` in logs before 2015).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from magnet.autopilot.conventions import ardupilot_raw_field, ardupilot_scale, ardupilot_soft_iron
from magnet.units import UT_PER_MGAUSS
from services.common.inputs.csvio import SampleTable
from services.common.inputs.flightlogs import (
    LogStreams,
    ReferenceYaw,
    Stream,
    Table,
    described,
    read_pymavlink,
    to_table,
)
from services.common.inputs.input_options import InputOptions

TYPES = ["MAG", "MAG2", "MAG3", "IMU", "IMU2", "PARM", "BAT", "CURR", "RCOU", "ATT"]
#: every DataFlash log starts with a FMT record: the two header bytes, then FMT's own type number (128)
HEADER = bytes([0xA3, 0x95, 0x80])
#: RCOU's first four channels as they were named: C1.. (current), Chan1.. (before 2015)
RCOU_CHANNELS = (("C1", "C2", "C3", "C4"), ("Chan1", "Chan2", "Chan3", "Chan4"))
#: the MAG layouts ArduPilot has logged (read from its LogStructure.h over the years), oldest first:
#: (time field, motor offset fields or None), each with MagX..Z and OfsX..Z; a motor offset not logged was zero
MAG_FORMATS: tuple[tuple[str, tuple[str, str, str] | None], ...] = (
    ("TimeMS", None),  # 2013: Ihhhhhh, no motor compensation logged
    ("TimeMS", ("MOfsX", "MOfsY", "MOfsZ")),  # 2013-2015: Ihhhhhhhhh, MAG2
    ("TimeUS", ("MOfsX", "MOfsY", "MOfsZ")),  # 2015-2019: + Health, S; MAG2, MAG3
    ("TimeUS", ("MOX", "MOY", "MOZ")),  # 2019-: field I names the instance
)
MAG_OFFSETS = ("OfsX", "OfsY", "OfsZ")


#: the fields kept of each record type, where a record has them: a record is reduced to these numbers as it is
#: read (a pymavlink record object is about a kilobyte, its numbers a few dozen bytes), so memory follows what is
#: kept, not the log's size
_TIMES = ("TimeUS", "TimeMS")
KEPT_FIELDS = {
    "MAG": (*_TIMES, "I", "MagX", "MagY", "MagZ", *MAG_OFFSETS, "MOfsX", "MOfsY", "MOfsZ", "MOX", "MOY", "MOZ"),
    "IMU": (*_TIMES, "I", "AccX", "AccY", "AccZ", "GyrX", "GyrY", "GyrZ"),
    "BAT": (*_TIMES, "I", "Curr"),
    "CURR": (*_TIMES, "Curr"),
    "RCOU": (*_TIMES, *RCOU_CHANNELS[0], *RCOU_CHANNELS[1]),
    "ATT": (*_TIMES, "Yaw"),
}
KEPT_FIELDS |= {"MAG2": KEPT_FIELDS["MAG"], "MAG3": KEPT_FIELDS["MAG"], "IMU2": KEPT_FIELDS["IMU"]}


def _kept_names(kind: str, record: Any) -> tuple[str, ...]:
    """The fields of ``KEPT_FIELDS[kind]`` that ``record`` has."""
    present = set(record.get_fieldnames())
    return tuple(n for n in KEPT_FIELDS[kind] if n in present)


def _records(path: Path, types: list[str]) -> tuple[dict[str, Table], dict[str, float]]:
    """(kept numbers of the records of ``types`` by name, PARM name -> first logged value); ValueError naming the
    file when it is not a DataFlash log pymavlink can read."""
    with open(path, "rb") as handle:
        start = handle.read(3)
    if not start:
        raise ValueError(f"{path}: the file is empty")
    if start != HEADER:  # checked here: pymavlink's fast indexer prints every bad byte of a foreign file
        raise ValueError(f"{path}: not an ArduPilot DataFlash log (it does not start with a DataFlash FMT record)")
    found: dict[str, Table] = {}
    params: dict[str, float] = {}

    def take(record: Any) -> None:
        kind = record.get_type()
        if kind == "PARM":
            params.setdefault(str(record.Name), float(record.Value))
            return
        if kind not in found:
            found[kind] = Table(_kept_names(kind, record), tuple(record.get_fieldnames()))
        found[kind].add(record)

    read_pymavlink(path, types, "ArduPilot DataFlash log", take, quiet_open=True, opener=_open_without_clock)
    if not found and not params:
        raise ValueError(f"{path}: no DataFlash records found: not an ArduPilot .bin log, or damaged from its start")
    return found, params


def _open_without_clock(path: str) -> Any:
    """pymavlink's DataFlash reader without its clock: to set one it parses records until a GPS record with a week,
    every record of a log that has none (a bench or indoor log: half the reading of a 10 MB log); the records' own
    TimeUS or TimeMS are what is read here, not pymavlink's times."""
    from pymavlink import DFReader

    class Reader(DFReader.DFReader_binary):  # type: ignore[misc]
        def init_clock(self) -> None:
            self._rewind(keep_messages=True)

    return Reader(path)


def _instance_records(found: dict[str, Table], base: str, instance: int) -> Table | None:
    """The records of ``base`` (MAG, IMU) for one instance: field ``I`` when logged, else MAG, MAG2, MAG3 by name."""
    records = found.get(base)
    if records is not None and "I" in records.names:
        return records.where(records.column("I") == instance)
    return found.get(base if instance == 0 else f"{base}{instance + 1}")


def _instances(found: dict[str, Table], base: str) -> list[int]:
    records = found.get(base)
    if records is not None and "I" in records.names:
        return sorted({int(i) for i in records.column("I")})
    return [k for k, name in enumerate((base, f"{base}2", f"{base}3")) if found.get(name)]


def _columns(records: Table, names: tuple[str, ...]) -> np.ndarray:
    return records.columns(names)


def _times_us(records: Table) -> np.ndarray:
    """Each record's time in us: ``TimeUS``, or ``TimeMS`` x 1000 in old logs."""
    if "TimeUS" not in records.names and "TimeMS" in records.names:
        return records.column("TimeMS") * 1000.0
    return records.column("TimeUS")


def _mag_columns(path: Path, records: Table) -> np.ndarray:
    """(N, 9) MagX..Z, offsets, motor offsets (mGauss) of MAG records in any of ``MAG_FORMATS`` (zero motor offsets
    where the layout logs none); ValueError in one line naming the fields found when the layout is none of them."""
    names = set(records.names)
    for time_field, motor in reversed(MAG_FORMATS):
        if {time_field, "MagX", "MagY", "MagZ", *MAG_OFFSETS, *(motor or ())} <= names:
            zero = np.zeros((len(records), 3))
            fields = _columns(records, ("MagX", "MagY", "MagZ", *MAG_OFFSETS))
            return np.hstack([fields, zero if motor is None else _columns(records, motor)])
    found = ",".join(records.fields)
    raise ValueError(f"{path}: a MAG record layout magnet does not know ({found}): no MagX..Z with a time")


def _suffix(instance: int) -> str:
    """ArduPilot's parameter suffix of compass ``instance``: '' for the first, '2', '3' after."""
    return "" if instance == 0 else str(instance + 1)


def _mag(path: Path, found: dict[str, Table], params: dict[str, float], instance: int) -> tuple[Stream, str]:
    records = _instance_records(found, "MAG", instance)
    if not records:
        instances = _instances(found, "MAG")
        if not instances:
            raise ValueError(f"{path}: this log holds no magnetometer (no MAG records; LOG_BITMASK may leave them out)")
        raise ValueError(f"{path}: no MAG records of instance {instance} (instances: {instances}): pick one with --mag")
    values = _mag_columns(path, records)
    n = _suffix(instance)
    diagonals = [params.get(f"COMPASS_DIA{n}_{a}", 1.0) for a in "XYZ"]
    offdiagonals = [params.get(f"COMPASS_ODI{n}_{a}", 0.0) for a in "XYZ"]
    scale = params.get(f"COMPASS_SCALE{n}", 0.0)
    raw_mg = ardupilot_raw_field(
        values[:, 0:3], values[:, 3:6], values[:, 6:9], ardupilot_soft_iron(diagonals, offdiagonals), scale
    )
    note = (
        f"MAG instance {instance} with ArduPilot's correction removed (offsets and motor offsets as logged, "
        f"COMPASS_DIA{n}_*={_rounded(diagonals)}, COMPASS_ODI{n}_*={_rounded(offdiagonals)}, "
        f"scale {ardupilot_scale(scale):g}; milligauss, body frame)"
    )
    return Stream(_times_us(records), raw_mg * UT_PER_MGAUSS), note


def _rounded(values: list[float]) -> list[float]:
    return [round(float(v), 4) for v in values]


def _extra(found: dict[str, Table]) -> tuple[dict[str, Stream], list[str]]:
    extra: dict[str, Stream] = {}
    words: list[str] = []
    battery = found.get("BAT")
    if battery is not None and "I" in battery.names:
        battery = battery.where(battery.column("I") == 0)
    if battery:
        extra["current_a"] = Stream(_times_us(battery), _columns(battery, ("Curr",))[:, 0])
        words.append("BAT current")
    elif found.get("CURR"):
        extra["current_a"] = Stream(_times_us(found["CURR"]), _columns(found["CURR"], ("Curr",))[:, 0] / 100.0)
        words.append("CURR current")
    rcou = found.get("RCOU")
    channels = [c for c in RCOU_CHANNELS if rcou and set(c) <= set(rcou.names)]
    if channels:
        pwm = _columns(found["RCOU"], channels[0]).mean(axis=1)
        extra["throttle"] = Stream(_times_us(found["RCOU"]), np.clip((pwm - 1000.0) / 1000.0, 0.0, 1.0))
        words.append("RCOU throttle (PWM)")
    return extra, words


def read_dataflash(path: Path, options: InputOptions) -> SampleTable:
    """The samples of an ArduPilot DataFlash log (see the module docstring); ValueError naming the file otherwise."""
    found, params = _records(path, TYPES)
    mag, note = _mag(path, found, params, options.mag or 0)
    imu = _instance_records(found, "IMU", 0)
    acc = gyr = None
    others = []
    if imu:
        acc = Stream(_times_us(imu), _columns(imu, ("AccX", "AccY", "AccZ")))
        gyr = Stream(_times_us(imu), _columns(imu, ("GyrX", "GyrY", "GyrZ")))
        others.append("IMU 0 accelerometer and gyroscope")
    extra, words = _extra(found)
    others += words
    if others:
        note += "; with " + described(others)
    count = len(mag.t_us)
    if count < 50:
        note += f"; only {count} magnetometer samples (a fit needs hundreds over many attitudes)"
    return to_table(path, LogStreams(mag, acc, gyr, extra, f"ArduPilot DataFlash: {note}"))


def dataflash_reference_yaw(path: Path) -> ReferenceYaw:
    """ArduPilot's own attitude estimate in the log (``ATT.Yaw``, degrees); ValueError when it is not logged."""
    found, params = _records(path, ["ATT", "PARM"])
    records = found.get("ATT")
    if records is None or len(records) < 2:
        raise ValueError(f"{path}: fewer than 2 ATT records: the log holds no attitude estimate to compare with")
    declination = "COMPASS_DEC not in the log's parameters"
    if "COMPASS_DEC" in params:
        declination = f"COMPASS_DEC={np.degrees(params['COMPASS_DEC']):.2f} deg"
        if params.get("COMPASS_AUTODEC"):
            declination += " (COMPASS_AUTODEC=1: set from the position)"
    yaw = _columns(records, ("Yaw",))[:, 0]
    return ReferenceYaw(_times_us(records) / 1e6, np.mod(yaw, 360.0), "ATT", declination)
