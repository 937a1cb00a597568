"""What the dashboard knows of the fleet: one row per device, and a trace of the devices someone is looking at.

No zenoh, no HTTP: the ingest loop feeds decoded messages in (``on_*``), the web handlers take JSON-able snapshots
out. Every change of a row stamps it with a new ``version`` so a stream sends only the rows changed since its last
snapshot. One lock guards everything (the ingest thread writes, the web loop reads).

Units: angles in degrees, fields in uT, times ``*_ns`` (wall clock, ns) or ``*_s`` (monotonic seconds).
"""

from __future__ import annotations

import math
import threading
import time
from collections import OrderedDict, deque
from collections.abc import Callable, Mapping
from typing import Any, TypeVar

import numpy as np

from magnet import wire
from magnet.drift import Alert
from magnet.earth.geomag import EarthField, earth_field
from magnet.earth.location import Location
from services.dashboard.figures import (
    covered_cells,
    decimate,
    dip_deg,
    earth_json,
    quat_of,
    recent_headings,
)
from services.dashboard.rows import DeviceRow, finite_or_none

T = TypeVar("T")
TRACE_POINTS = 1500  # raw and calibrated field points kept per watched device
TRACE_HEADINGS = 6000  # heading samples kept per watched device (60 s at 100 Hz)
INTERVAL_WEIGHT = 0.2  # weight of the newest interval in a device's running interval between heading batches
WATCH_LINGER_S = 15.0  # a device stays watched this long after its last viewer left
#: rows kept at most (``--max-devices``): past it the least recently heard-of device's row is forgotten
MAX_ROWS = 10_000
#: a row nothing was heard of for this long (and whose liveliness token is not alive) is forgotten (``--forget-after``)
FORGET_AFTER_S = 600.0
#: forgotten devices remembered for the event streams (a stream further behind gets every row again, ``full``)
GONE_KEPT = 4096


class Trace:
    """Recent samples of one watched device: raw and calibrated field (uT), headings with their time."""

    def __init__(self) -> None:
        self.raw: deque = deque(maxlen=TRACE_POINTS)
        self.calibrated: deque = deque(maxlen=TRACE_POINTS)
        self.headings: deque = deque(maxlen=TRACE_HEADINGS)  # (t_ns, magnetic, true)
        self.truth: dict[int, float] = {}  # raw seq -> true heading of its last sample
        self.viewers = 0
        self.left_s = time.monotonic()

    def reset_raw(self) -> None:
        self.raw.clear()


class FleetState:
    """Rows of every device seen, traces of watched devices, the expected field; thread-safe."""

    def __init__(
        self,
        earth: EarthField | None = None,
        clock: Callable[[], float] = time.monotonic,
        date: Any = None,
        places: Mapping[str, Location] | None = None,
        max_rows: int = MAX_ROWS,
        forget_after_s: float = FORGET_AFTER_S,
    ) -> None:
        if max_rows < 1 or not forget_after_s > 0:
            raise ValueError(f"max_rows must be >= 1 and forget_after_s > 0, got {max_rows} and {forget_after_s}")
        self.earth, self.clock, self.date = earth, clock, date
        self.places = dict(places or {})  # the places file's locations by device
        self.max_rows, self.forget_after_s = max_rows, forget_after_s
        self.lock = threading.Lock()
        #: rows by device, least recently heard of first (``_seen`` moves a row to the end)
        self.rows: OrderedDict[str, DeviceRow] = OrderedDict()
        self.seen_s: dict[str, float] = {}  # device -> when anything was last heard of it (monotonic s)
        self.gone: deque[tuple[int, str]] = deque(maxlen=GONE_KEPT)  # (version, device) of forgotten rows
        self.gone_floor = -1  # version of the newest forgotten row no longer in ``gone``
        self.forgotten = 0  # rows forgotten since the start (silence or the bound)
        self.traces: dict[str, Trace] = {}
        self.version = 0
        self.dropped = wire.DropCounter()
        self.messages = 0

    # ---------------------------------------------------------------------------------------------- writing
    def _seen(self, device: str) -> DeviceRow | None:
        """Note that ``device`` was heard of now (its row, if it has one, becomes the most recently seen)."""
        row = self.rows.get(device)
        if row is not None:
            self.seen_s[device] = self.clock()
            self.rows.move_to_end(device)
        return row

    def _row(self, device: str) -> DeviceRow:
        row = self._seen(device)
        if row is None:
            row = self.rows[device] = DeviceRow(device)
            self.seen_s[device] = self.clock()
            while len(self.rows) > self.max_rows:
                self._forget(next(iter(self.rows)))
        self.version += 1
        row.version = self.version
        return row

    def _forget(self, device: str) -> None:
        self.rows.pop(device, None)
        self.seen_s.pop(device, None)
        trace = self.traces.get(device)
        if trace is not None and not trace.viewers:
            del self.traces[device]
        self.version += 1
        if len(self.gone) == self.gone.maxlen:
            self.gone_floor = self.gone[0][0]
        self.gone.append((self.version, device))
        self.forgotten += 1

    def forget_silent(self) -> int:
        """Forget the rows nothing was heard of for ``forget_after_s`` whose liveliness token is not alive; the
        number forgotten. Cost: the rows forgotten plus the alive ones among the oldest."""
        with self.lock:
            now, before = self.clock(), self.forgotten
            for device in list(self.rows):
                if now - self.seen_s.get(device, now) <= self.forget_after_s:
                    break  # rows are in the order they were last heard of: the rest are more recent
                if self.rows[device].alive is not True:
                    self._forget(device)
            return self.forgotten - before

    def on_alive(self, device: str, alive: bool) -> None:
        with self.lock:
            self._row(device).alive = alive

    def on_sensor(self, device: str, sensor: str) -> None:
        with self.lock:
            row = self._seen(device)
            if row is None or row.sensor != sensor:
                self._row(device).sensor = sensor

    def on_raw(self, batch: wire.RawBatch) -> None:
        """A raw batch of a watched device: its points for the cloud, its truth for the heading error."""
        with self.lock:
            trace = self.traces.get(batch.device)
            if trace is None:
                return
            trace.raw.extend(np.asarray(batch.mag_ut, dtype=float).tolist())
            if batch.truth is not None:
                trace.truth[batch.seq] = float(batch.truth["heading_deg"][-1])
                while len(trace.truth) > 64:
                    trace.truth.pop(next(iter(trace.truth)))
            row = self._seen(batch.device)
            if batch.sensor and row is not None:
                row.sensor = batch.sensor
            if batch.location is not None and row is not None and row.location != batch.location:
                self._row(batch.device).location = batch.location

    def on_heading(self, batch: wire.HeadingBatch, quat_wxyz: Any = None) -> None:
        """The last sample of a heading batch goes into the row; a watched device keeps them all. The fused
        attitude (optional ``quat_wxyz``) is the batch's unless given."""
        if quat_wxyz is None:
            quat_wxyz = getattr(batch, "quat_wxyz", None)
        last = len(batch) - 1
        if last < 0:
            return
        pitch, roll = float(batch.pitch_deg[last]), float(batch.roll_deg[last])
        bx, by, bz = (float(v) for v in batch.field_ut[last])
        magnitude, dip = math.sqrt(bx * bx + by * by + bz * bz), dip_deg(bx, by, bz, pitch, roll)
        with self.lock:
            row = self._row(batch.device)
            now = self.clock()
            if row.heading_s is not None:
                interval = now - row.heading_s
                row.interval_s = (
                    interval
                    if row.interval_s is None
                    else row.interval_s + INTERVAL_WEIGHT * (interval - row.interval_s)
                )
            row.seq, row.heading_s, row.t_ns = batch.seq, now, int(batch.t_ns[last])
            row.heading_deg, row.true_heading_deg = float(batch.heading_deg[last]), float(batch.true_heading_deg[last])
            sigma = batch.heading_sigma_deg
            row.heading_sigma_deg = None if sigma is None else finite_or_none(sigma[last])
            row.pitch_deg, row.roll_deg, row.flags = pitch, roll, int(batch.flags[last])
            row.field_ut, row.dip_deg = magnitude, finite_or_none(dip)
            row.declination_deg = batch.declination_deg
            row.quat_wxyz = quat_of(quat_wxyz, last)
            if batch.calibration_id and not row.calibration_id:
                row.calibration_id = batch.calibration_id
            trace = self.traces.get(batch.device)
            if trace is not None:
                self._trace_heading(trace, row, batch)

    def _trace_heading(self, trace: Trace, row: DeviceRow, batch: wire.HeadingBatch) -> None:
        trace.calibrated.extend(np.asarray(batch.field_ut, dtype=float).tolist())
        trace.headings.extend(zip(batch.t_ns.tolist(), batch.heading_deg.tolist(), batch.true_heading_deg.tolist()))
        truth = trace.truth.get(batch.seq)
        if truth is not None and row.true_heading_deg is not None:
            row.truth_error_deg = float((row.true_heading_deg - truth + 180.0) % 360.0 - 180.0)

    def on_progress(self, message: Mapping[str, Any]) -> None:
        device = message["device"]
        with self.lock:
            row = self._row(device)
            state = str(message.get("state") or row.state)
            trace = self.traces.get(device)
            if state == "session" and row.state != "session" and trace is not None:
                trace.reset_raw()
            row.state, row.session = state, bool(message.get("session", False))
            row.method = message.get("method") or row.method
            row.samples = message.get("samples") if isinstance(message.get("samples"), int) else row.samples
            row.coverage = finite_or_none(message.get("coverage"))
            row.missing = tuple(str(m) for m in (message.get("missing") or ()) if isinstance(m, str))[:6]
            row.reason = str(message.get("reason") or "")[:300]
            row.accepted = message.get("accepted") if isinstance(message.get("accepted"), bool) else None
            row.residual_ut = finite_or_none(message.get("residual_rms_ut"))
            if isinstance(message.get("calibration_id"), str):
                row.calibration_id = message["calibration_id"]

    def on_calibration(self, message: wire.CalibrationMessage) -> None:
        """A calibration put or answered: a new one ends any collection; the one already shown changes nothing."""
        quality = message.calibration.quality
        with self.lock:
            known = self._seen(message.device)  # a calibrator serving its record counts as hearing of it
            if known is not None and known.calibration_id == message.id and known.calibrated_ns == message.created_ns:
                return
            row = self._row(message.device)
            row.state, row.session, row.method = "calibrated", False, message.calibration.method
            row.calibration_id, row.calibrated_ns = message.id, message.created_ns
            row.residual_ut = finite_or_none(quality.get("residual_rms_ut"))
            row.coverage = finite_or_none(quality.get("coverage"))
            row.accepted, row.reason, row.missing = True, message.calibration.reason, ()
            row.samples = message.calibration.sample_count

    def on_alert(self, alert: Alert) -> None:
        """A drift alert raised (kept, by kind) or cleared (forgotten) by a compass."""
        with self.lock:
            known = self._seen(alert.device)
            if alert.cleared:
                if known is not None and alert.kind.value in known.drift:
                    del self._row(alert.device).drift[alert.kind.value]
                return
            if known is not None and known.drift.get(alert.kind.value) == alert:
                return
            self._row(alert.device).drift[alert.kind.value] = alert

    # ---------------------------------------------------------------------------------------------- watching
    def watch(self, device: str, delta: int) -> None:
        """A viewer starts (+1) or stops (-1) looking at ``device``."""
        with self.lock:
            trace = self.traces.get(device)
            if trace is None:
                if delta <= 0:
                    return
                trace = self.traces[device] = Trace()
            trace.viewers = max(0, trace.viewers + delta)
            if trace.viewers == 0:
                trace.left_s = self.clock()

    def watched(self) -> set[str]:
        """Devices watched now (forgetting those nobody looked at for ``WATCH_LINGER_S``)."""
        with self.lock:
            now = self.clock()
            for device in [d for d, t in self.traces.items() if not t.viewers and now - t.left_s > WATCH_LINGER_S]:
                del self.traces[device]
            return set(self.traces)

    # ---------------------------------------------------------------------------------------------- reading
    def knows(self, device: str) -> bool:
        with self.lock:
            return device in self.rows

    def fleet(self, since: int) -> dict[str, Any]:
        """What a page needs to bring its table from version ``since`` to now: ``version``, ``rows`` changed after
        ``since``, ``gone`` (devices forgotten after it), and ``full`` when the page is further behind than the
        forgotten devices kept: ``rows`` is then every row and the page drops any other it holds."""
        rest, chunks = self.fleet_chunks(since, list, len(self.rows) + 1)
        return {"version": rest["version"], "rows": [row for chunk in chunks for row in chunk]} | rest

    def fleet_chunks(
        self, since: int, encode: Callable[[list[dict[str, Any]]], T], chunk_rows: int
    ) -> tuple[dict[str, Any], list[T]]:
        """``fleet(since)`` without its rows (``version``, ``gone``, ``full``), and the rows given to ``encode``
        ``chunk_rows`` at a time as they are made (sorted by device): every row's map is never held at once (10,000
        rows' maps take about 20 MB, their JSON 6 MB)."""
        with self.lock:
            full = since < self.gone_floor
            now, cut = self.clock(), -1 if full else since
            chunks, rows = [], []
            for _, row in sorted(self.rows.items()):
                if row.version > cut:
                    rows.append(row.to_json(now, self.earth_of(row)))
                    if len(rows) >= chunk_rows:
                        chunks.append(encode(rows))
                        rows = []
            if rows:
                chunks.append(encode(rows))
            gone = [] if full or since < 0 else [device for version, device in self.gone if version > since]
            return {"version": self.version, "gone": gone, "full": full or since < 0}, chunks

    def changes(self, since: int) -> tuple[int, list[dict[str, Any]]]:
        """(current version, rows changed after ``since``, as JSON maps, sorted by device)."""
        with self.lock:
            now = self.clock()
            rows = [row.to_json(now, self.earth_of(row)) for _, row in sorted(self.rows.items()) if row.version > since]
            return self.version, rows

    def summary(self) -> dict[str, Any]:
        with self.lock:
            rows = list(self.rows.values())
            return {
                "devices": len(rows),
                "alive": sum(r.alive is True and not r.silent(self.clock()) for r in rows),
                "calibrated": sum(r.state == "calibrated" for r in rows),
                "alerts": sum(len(r.drift) for r in rows),
                "in_alert": sum(bool(r.drift) for r in rows),
                "messages": self.messages,
                "earth": earth_json(self.earth),
            }

    def metrics_status(self) -> dict[str, Any]:
        """The counters ``services.common.metrics`` exposes: messages, drops by cause, devices by state, alerts."""
        with self.lock:
            rows = list(self.rows.values())
            states: dict[str, int] = {}
            alerts: dict[str, int] = {}
            for row in rows:
                states[row.status()] = states.get(row.status(), 0) + 1
                for kind in row.drift:
                    alerts[kind] = alerts.get(kind, 0) + 1
            return {
                "service": "dashboard",
                "messages": self.messages,
                "dropped": dict(self.dropped.counts),
                "devices": states,
                "alerts_open": alerts,
            }

    def earth_of(self, row: DeviceRow) -> EarthField | None:
        """The field expected where the device is: the World Magnetic Model at the place it reports, else at its
        place in the places file (``--fleet``), else the dashboard's own (``--location``), else None."""
        location = row.location or self.places.get(row.device)
        if location is None:
            return self.earth
        try:
            return earth_field(*location.as_tuple(), self.date)
        except ValueError:  # a date outside the model: the dashboard's own place
            return self.earth

    def detail(self, device: str, points: int = 600) -> dict[str, Any] | None:
        """The device's row, its recent clouds (at most ``points`` each), headings and covered cells."""
        with self.lock:
            row = self.rows.get(device)
            if row is None:
                return None
            trace = self.traces.get(device)
            raw = np.array(trace.raw if trace else [], dtype=float).reshape(-1, 3)
            calibrated = np.array(trace.calibrated if trace else [], dtype=float).reshape(-1, 3)
            headings = recent_headings(list(trace.headings)) if trace else []
            earth = self.earth_of(row)
            out: dict[str, Any] = {"row": row.to_json(self.clock(), earth), "earth": earth_json(earth)}
        out.update(
            raw=decimate(raw, points),
            calibrated=decimate(calibrated, points),
            headings=[[t // 1_000_000, round(m, 2), round(tr, 2)] for t, m, tr in headings],
            cells=covered_cells(raw).astype(int).tolist(),
        )
        return out
