"""In-service recalibration (``--recalibrate auto|propose|off``; docs/field-calibration.md, "In service").

After a device's first record the calibrator keeps listening: each calibrated device has a bounded refresh
collection (``Collection`` with auto, a ring of ``REFRESH_RUN_CAPACITY`` consecutive samples and the sphere
cells), fitted at most every ``REFRESH_INTERVAL_S`` once its longest run spans ``REFRESH_MIN_S``, on the run's
last ``REFRESH_WINDOW_S`` seconds. The fit is judged against
the record in force (``FitInput.reference``: held-out heading consistency, with its margin) and must also gain
``MIN_GAIN`` of the in-force record's held-out consistency (a refresh that changes little is churn, not a gain).

The iron changed when the record in force misses the field strength by CHANGED_PCT, or, with a gyroscope, when
the record's offset error measured from the turns moved by a few uT (``iron_moved``: a phone's board currents, its
warming): the samples before are then dropped and refreshes tried sooner (CHANGED_MIN_S, CHANGED_INTERVAL_S).

A device that travels (its batches carry a velocity over TRAVEL_MS) is a vehicle whose linear accelerations tilt a
judgement's attitude that has no velocity aiding: measured through the services, a car's offset-only refresh judged
so looked 70 % more consistent and turned its heading 118 deg wrong. The field ladder judges with the velocity-aided
attitude when the samples carry the velocity (quality ``dip_source`` "velocity-aided gravity",
``magnet.calibration.field``); a travelling device's refresh judged so is committed under ``auto``, any other (a
sphere's method, judged without aiding) is proposed (as ``propose`` does) instead. A travelling level device's
refresh that the held-out consistency refused may still pass by its field's turn against the gyroscope's
(``turning.judged_by_turns``): its ``gain_pct`` is then how much lower its turn residual is, and it must reach
``REFRESH_TURN_GAIN``.

What passes: ``auto`` commits it as a new version (change ``action: refresh``, ``in_service: true``, ``gain_pct``,
and ``resolves``: the device's open drift alerts it was made against); ``propose`` turns the refresh collection into
an operator's session holding the fit (``magnet calibrate DEV commit`` stores it, marked in service); ``off`` keeps
no refresh collection at all. Memory per device: one ring (112 bytes a sample) and the cells; devices at most
``max_devices`` (least recently seen dropped). Pure: no clock of its own, no store.
"""

from __future__ import annotations

import enum

import numpy as np

from magnet import wire
from magnet.bounded import Recent
from magnet.calibration.collection import Collection
from magnet.calibration.field import COURSE_SOURCE, MIN_GAIN
from magnet.calibration.turning import REFRESH_TURN_GAIN
from magnet.calibrator import iron_moved
from magnet.model import Calibration
from magnet.quality.motion import AIDED_SOURCE

#: a device whose batches carry a speed above this (m/s, faster than a person runs) travels: its refreshes are
#: proposed, not committed
TRAVEL_MS = 5.0
#: a device's refresh is fitted at most this often (s): the CPU a device costs stays one fit in this time
REFRESH_INTERVAL_S = 15.0
#: ... and at least this long by the calibrator's clock (s)
MIN_WALL_S = 1.0
#: a refresh fits the last this many seconds of the device's samples: what changed (a new case, a magnet nearby) is
#: judged on what came after it, not averaged with what came before
REFRESH_WINDOW_S = 30.0
#: seconds of consecutive samples before a refresh is tried
REFRESH_MIN_S = 12.0
#: consecutive samples a refresh ring keeps at most (a minute at 200 Hz; 112 bytes each: about 1.3 MB per device)
REFRESH_RUN_CAPACITY = 12_000
#: without a gyroscope (no ring): kept samples in the cells before a refresh is tried
REFRESH_MIN_SAMPLES = 300
#: the record in force's field strength this far off (%) ...
CHANGED_PCT = 15.0
#: ... for this long in a row (s, by the samples' times: four of ``magnet bench field``'s batches of 0.5 s): the
#: device's iron changed, the samples before are dropped. Counted in batches (4) it was 0.2 s of a 200 Hz stream in
#: ``magnet edge``'s batches of 10 samples, where a door passed looks like a new iron (docs/field-calibration.md,
#: "Sample rates"); CHANGED_BATCHES is what it was
CHANGED_S = 2.0
CHANGED_BATCHES = 4
#: after the iron changed the record in force is known wrong: a refresh is tried from this many seconds of samples
#: after the change, and then this often (s), until one is made (the ladder's identifiability and judgement decide
#: whether the samples tell enough; the gyroscope holds the heading meanwhile)
CHANGED_MIN_S = 6.0
CHANGED_INTERVAL_S = 3.0
#: what ``--recalibrate`` accepts
MODES = ("auto", "propose", "off")


class Mode(enum.Enum):
    AUTO = "auto"  # commit a better record as a new version
    PROPOSE = "propose"  # open a session holding it, for a person to commit
    OFF = "off"  # no refinement after the first record


def gain_pct(calibration: Calibration) -> float | None:
    """How much more constant (%) the fit makes the field than the record in force on held-out data (for an offset
    from the velocity over the ground: how much closer to the WMM's direction); None when not measured (no
    accelerometer)."""
    quality = calibration.quality
    if quality.get("turn_gain_pct") is not None:  # a travelling level device's, judged by its turns
        return float(quality["turn_gain_pct"])
    held, ref = quality.get("holdout_consistency_deg"), quality.get("reference_holdout_consistency_deg")
    if held is None and ref is None:
        held, ref = quality.get("course_agreement_deg"), quality.get("reference_course_agreement_deg")
    if held is None or ref is None or ref <= 0:
        return None
    return 100.0 * (1.0 - float(held) / float(ref))


def small_gain(calibration: Calibration) -> str | None:
    """Why an accepted refresh is still not taken: it gains less than MIN_GAIN (None: it gains enough)."""
    gain = gain_pct(calibration)
    if gain is None:
        return (
            "no held-out heading consistency to judge a refresh by (the device sends no accelerometer, or the fit "
            "without the held-out samples failed)"
        )
    if calibration.quality.get("turn_gain_pct") is not None:
        if gain < 100.0 * REFRESH_TURN_GAIN:
            least = 100 * REFRESH_TURN_GAIN
            return f"a refresh's field turns with the gyroscope {gain:.1f} % better, less than {least:g} %"
        return None
    if gain < 100.0 * MIN_GAIN:
        return f"a refresh gains {gain:.0f} % of held-out consistency, less than {100 * MIN_GAIN:.0f} %"
    return None


class Refresher:
    """The refresh collections of calibrated devices (module docstring). ``capacity``: the cells' samples
    (``--max-samples``); ``max_devices``: devices kept at most."""

    def __init__(self, mode: Mode | str, capacity: int, max_devices: int) -> None:
        self.mode = Mode(mode)
        self.capacity = capacity
        self.by_device: Recent[str, Collection] = Recent(max_devices)
        self.fits = self.refreshed = self.proposed = 0

    def receive(self, batch: wire.RawBatch, in_force: Calibration | None = None) -> Collection | None:
        """Add a calibrated device's batch to its refresh collection (made on its first batch); None when off.
        ``in_force``: the record in force; when its field strength is off by CHANGED_PCT for CHANGED_S seconds of
        batches in a row, the device's iron changed (a new case, a magnet): what came before is dropped, so that
        the refresh fits what came after the change only."""
        if self.mode is Mode.OFF:
            return None
        collection = self.by_device.get(batch.device)
        changed = collection is not None and in_force is not None and self._changed(collection, batch, in_force)
        if changed:
            self.by_device.pop(batch.device, None)
            collection = None
        if collection is None:
            collection = Collection("auto", False, self.capacity, REFRESH_RUN_CAPACITY)
            collection.in_service, collection.window_s = True, REFRESH_WINDOW_S
            collection.after_change = changed
            self.by_device[batch.device] = collection
        self.by_device.touch(batch.device)
        collection.travelled = collection.travelled or travels(batch)
        collection.add(batch.mag_ut, batch.acc_ms2, batch.gyr_rads, batch.t_ns, batch.seq, batch.vel_ned_ms)
        return collection

    @staticmethod
    def _changed(collection: Collection, batch: wire.RawBatch, in_force: Calibration) -> bool:
        """Whether the record's field strength has been CHANGED_PCT off for CHANGED_S seconds of batches in a row
        now (from the first sample of the first such batch to one step after the last sample of this one) while
        the collection still holds samples from before (a collection made after the change is kept)."""
        strength = in_force.field_strength
        if not strength or in_force.output_unit != "ut" or in_force.unit != "ut":
            return False
        norm = np.linalg.norm(in_force.apply(batch.mag_ut), axis=1)
        off = abs(float(np.median(norm)) / strength - 1.0) * 100.0 > CHANGED_PCT
        collection.changed_batches = collection.changed_batches + 1 if off else 0
        first, last = int(batch.t_ns[0]), int(batch.t_ns[-1])
        if collection.changed_batches == 1:
            collection.changed_since_ns = first
        step = (last - first) / (len(batch) - 1) if len(batch) > 1 else 0.0
        long_off = off and last + step - collection.changed_since_ns >= CHANGED_S * 1e9 - 1e6  # 1 ms: jitter
        older = collection.seen > (collection.changed_batches + 1) * len(batch)  # samples from before the change
        return (long_off or _moved(collection, batch, in_force)) and older

    def proposes(self, collection: Collection, calibration: Calibration | None = None) -> bool:
        """Whether a refresh that passed (``calibration``) is proposed as a session rather than committed:
        ``propose``, or a device that travelled while its samples were collected and whose refresh was not judged
        with the velocity-aided attitude (see the module docstring)."""
        return self.mode is Mode.PROPOSE or (collection.travelled and not velocity_aided(calibration))

    def due(self, collection: Collection, now_s: float) -> bool:
        """Whether to try a refresh now: REFRESH_INTERVAL_S of the device's samples (by their times; by the clock
        without a gyroscope) and MIN_WALL_S of the clock since the last try, and the ring (or, without a
        gyroscope, the cells) holds enough samples. The samples' time keeps a replay at 10x refreshed as often
        per sample as live; the clock bounds the CPU of a device sending fast."""
        if now_s - collection.last_fit_s < (MIN_WALL_S if collection.runs is not None else REFRESH_INTERVAL_S):
            return False
        if collection.runs is None:
            return collection.kept >= min(self.capacity, REFRESH_MIN_SAMPLES)
        run = collection.runs.longest()
        changed = collection.after_change
        if run is None or len(run) * run.period_s < (CHANGED_MIN_S if changed else REFRESH_MIN_S):
            return False
        last = int(run.t_ns[-1])
        if last - collection.tried_ns < (CHANGED_INTERVAL_S if changed else REFRESH_INTERVAL_S) * 1e9:
            return False
        collection.tried_ns = last
        return True

    def restart(self, device: str) -> None:
        """Forget the device's refresh samples (a new record is in force: what follows is judged against it)."""
        self.by_device.pop(device, None)


def _moved(collection: Collection, batch: wire.RawBatch, in_force: Calibration) -> bool:
    """Whether the device's hard iron moved by a few uT under the record in force (``iron_moved.IronWatch``, fed
    every ``iron_moved.BLOCK_S`` of the device's samples from its last run of consecutive samples; never without a
    gyroscope, nor with a motor model, whose field needs each batch's current)."""
    if collection.runs is None or in_force.motor is not None or batch.gyr_rads is None:
        return False
    watch = collection.iron_watch = collection.iron_watch or iron_moved.IronWatch()
    if watch.done_ns is not None and int(batch.t_ns[-1]) - watch.done_ns < iron_moved.BLOCK_S * 1e9:
        return False
    run = collection.runs.longest()
    if run is None:
        return False
    run = run.tail(iron_moved.BLOCK_S + iron_moved.WINDOW_S + 1.0)
    return watch.add(in_force.apply(run.mag), run.turn_rads, run.t_ns, run.period_s)


def velocity_aided(calibration: Calibration | None) -> bool:
    """Whether the record was judged with the velocity-aided attitude (a vehicle's accelerations removed), or fitted
    and judged with the attitude the velocity over the ground gives (``magnet.calibration.course``)."""
    if calibration is None:
        return False
    quality = calibration.quality
    return quality.get("dip_source") == AIDED_SOURCE or quality.get("heading_source") == COURSE_SOURCE


def travels(batch: wire.RawBatch) -> bool:
    """Whether the batch's velocity (if it carries one) says the device moves faster than TRAVEL_MS."""
    vel = batch.vel_ned_ms
    if vel is None:
        return False
    speed = np.linalg.norm(np.asarray(vel, dtype=float), axis=1)
    return bool(np.any(speed[np.isfinite(speed)] > TRAVEL_MS))
