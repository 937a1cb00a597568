"""Where the calibration of a device stands (``calibration/progress`` and the replies of ``calibrate``): built from its
collection in progress or its record in force; published at most every ``PROGRESS_INTERVAL_S`` per device while
samples arrive, and at once when something was stored (``magnet.calibrator.core``)."""

from __future__ import annotations

from magnet import wire
from magnet.bounded import Recent
from magnet.calibration.collection import Collection
from magnet.calibrator.status import State
from magnet.quality import Coverage

PROGRESS_INTERVAL_S = 0.5


def progress_of(
    state: State,
    now_ns: int,
    collection: Collection | None,
    record: wire.DeviceCalibration | None,
    min_samples: int,
) -> wire.Progress:
    """The progress of a device in ``state``: its ``collection`` in progress (None: none) or else its ``record`` in
    force; ``min_samples`` (--min-samples) is said in what a collection not fitted yet waits for."""
    record_id = record.id if record else None
    if collection is None:
        if record is None:
            return wire.Progress(state.value, now_ns, record_id)
        cal = record.calibration
        return wire.Progress(
            state.value,
            now_ns,
            record_id,
            cal.method,
            cal.sample_count,
            cal.quality.coverage,
            (),
            cal.quality.residual_rms_ut,
            True,
            cal.reason,
        )
    cov = collection.coverage()
    last = collection.last_fit
    return wire.Progress(
        state.value,
        now_ns,
        record_id,
        collection.method,
        collection.kept,
        cov.fraction,
        tuple(cov.missing),
        None if last is None else last.quality.residual_rms_ut,
        None if last is None else bool(last.accepted),
        collection.last_reason or _waiting_reason(collection, cov, min_samples),
        wire.Collecting(collection.session, collection.seen, cov.cells_hit, cov.cell_count),
    )


def _waiting_reason(collection: Collection, cov: Coverage, min_samples: int) -> str:
    if collection.runs is not None:
        return collection.turn_wait(min_samples) or "ready to fit from the gyroscope"
    advice = ", ".join(cov.missing) or "move through more attitudes"
    return f"{collection.kept} of {min_samples} evenly spread samples, coverage {cov.fraction:.0%}: {advice}"


class ProgressTimes:
    """When the progress of each device was last published (monotonic s), for at most ``max_devices`` devices."""

    def __init__(self, max_devices: int, interval_s: float = PROGRESS_INTERVAL_S) -> None:
        self.last: Recent[str, float] = Recent(max_devices)
        self.interval_s = interval_s

    def due(self, device: str, now: float) -> bool:
        """Whether the progress of ``device`` should go out again at ``now``."""
        last = self.last.get(device)
        return last is None or now - last >= self.interval_s

    def sent(self, device: str, now: float) -> None:
        self.last[device] = now
