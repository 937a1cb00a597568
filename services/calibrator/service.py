"""``magnet calibrator``: collect raw samples per device, fit, gate, store (SQLite) and serve calibrations.

Collection keeps samples evenly spread over the sphere: the direction of each raw reading from the running centre of
the cloud (per-axis (max + min) / 2) falls in one of ``FINE_BANDS x FINE_SECTORS`` equal-area cells, and a sample is
kept only when its cell is still empty (bounded by ``--max-samples``). Without a session, a device that has no
calibration is fitted whenever enough new cells filled and coverage reached ``--min-coverage``; the first fit the
quality gate accepts is stored and published, and collection for it ends. An operator's session (``calibrate``
queryable: start / status / commit / abort) collects afresh with its method and stores only on commit. A rejected fit
changes nothing: its reason goes out on ``calibration/progress``.

Queryables: ``<prefix>/<dev>/calibration`` (record in force), ``<prefix>/<dev>/calibration/history?limit=N``
(``{v, device, records: [...]}`` newest first), ``<prefix>/<dev>/calibrate?action=...&method=...``,
``<prefix>/@status/<name>``. One thread: zenoh delivers into channels, this loop drains them.
"""

from __future__ import annotations

import argparse
import dataclasses
import enum
import logging
import os
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

from magnet import wire
from magnet.model import Calibration
from services.calibrator.store import CalibrationStore
from services.common.zenoh_session import add_zenoh_arguments, drain, open_session, payload_bytes, stop_event

log = logging.getLogger("magnet.calibrator")

FINE_BANDS = 24      # equal-area bands in z (uniform in z = equal area on the sphere) ...
FINE_SECTORS = 48    # ... times sectors in longitude: 1152 fine cells, one kept sample each
REBIN_SHIFT_UT = 2.0  # re-sort kept samples into cells when the cloud's centre moved this far
FIT_EVERY_NEW = 25   # fit again after this many newly kept samples
FIT_INTERVAL_S = 0.5
PROGRESS_INTERVAL_S = 0.5
CHANNEL_CAPACITY = 65536
IDLE_SLEEP_S = 0.0005


def default_db_path() -> Path:
    base = Path(os.environ.get("XDG_DATA_HOME", Path.home() / ".local" / "share"))
    return base / "magnet" / "calibrations.db"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--db", type=Path, default=None, help=f"SQLite file (default {default_db_path()})")
    parser.add_argument("--method", default="ellipsoid", help="fit method for automatic calibration (default "
                                                              "ellipsoid; sessions may choose another)")
    parser.add_argument("--location", help="LAT,LON[,ALT_M]: scale fits to the WMM field strength there")
    parser.add_argument("--field-ut", type=float, help="expected field strength in uT (instead of --location)")
    parser.add_argument("--min-coverage", type=float, default=0.8,
                        help="sphere coverage before an automatic fit is tried (default 0.8)")
    parser.add_argument("--min-samples", type=int, default=150, help="kept samples before a fit (default 150)")
    parser.add_argument("--max-samples", type=int, default=1500, help="kept samples per device at most")
    parser.add_argument("--no-auto", action="store_true", help="calibrate only in operator sessions")
    parser.add_argument("--name", default="calibrator", help="service name for liveliness and status")
    parser.add_argument("--devices", default="*", help="key expression of the devices served (default *)")
    add_zenoh_arguments(parser)


@dataclasses.dataclass(frozen=True)
class CalibratorSettings:
    method: str = "ellipsoid"
    field_ut: float | None = None
    min_coverage: float = 0.8
    min_samples: int = 150
    max_samples: int = 1500
    auto: bool = True

    def __post_init__(self) -> None:
        from magnet.calibration import Method

        Method.parse(self.method)
        if not 0 <= self.min_coverage <= 1:
            raise ValueError(f"--min-coverage must be a fraction in [0, 1], got {self.min_coverage}")
        if not 30 <= self.min_samples <= self.max_samples:
            raise ValueError(f"need 30 <= --min-samples <= --max-samples, got {self.min_samples}, {self.max_samples}")
        if self.field_ut is not None and not 1 <= self.field_ut <= 1000:
            raise ValueError(f"--field-ut must be a field strength in uT (1..1000), got {self.field_ut}")


class State(enum.Enum):
    COLLECTING = "collecting"    # automatic collection (device has no calibration)
    SESSION = "session"          # an operator's calibration session
    CALIBRATED = "calibrated"    # a calibration is in force, nothing collected
    IDLE = "idle"                # no calibration, automatic calibration off


def fine_cells(directions: np.ndarray) -> np.ndarray:
    """Fine equal-area cell index (N,) of directions (N, 3) (any length > 0)."""
    unit = directions / np.maximum(np.linalg.norm(directions, axis=1, keepdims=True), 1e-300)
    band = np.minimum(((unit[:, 2] + 1.0) * 0.5 * FINE_BANDS).astype(int), FINE_BANDS - 1)
    sector = np.minimum(((np.arctan2(unit[:, 1], unit[:, 0]) + np.pi) / (2 * np.pi) * FINE_SECTORS).astype(int),
                        FINE_SECTORS - 1)
    return band * FINE_SECTORS + sector


class Collection:
    """Evenly spread samples of one device: mag (K, 3) uT and acc (K, 3) m/s^2 (or none), K <= capacity."""

    def __init__(self, method: str, session: bool, capacity: int) -> None:
        self.method, self.session, self.capacity = method, session, capacity
        self.mag = np.empty((capacity, 3))
        self.acc = np.empty((capacity, 3))
        self.has_acc = True
        self.kept = self.seen = 0
        self.occupied = np.zeros(FINE_BANDS * FINE_SECTORS, dtype=bool)
        self.lo = np.full(3, np.inf)
        self.hi = np.full(3, -np.inf)
        self.binned_centre: np.ndarray | None = None
        self.last_fit_kept = 0
        self.last_fit_s = -np.inf
        self.last_fit: Calibration | None = None
        self.last_reason = ""

    @property
    def centre(self) -> np.ndarray:
        """Running centre of the raw cloud, (max + min) / 2 per axis, uT (zeros before any sample)."""
        return (self.lo + self.hi) / 2 if self.seen else np.zeros(3)

    def add(self, mag: np.ndarray, acc: np.ndarray | None) -> int:
        """Keep the samples of a batch whose fine cell is still empty; returns how many were kept."""
        self.seen += len(mag)
        self.lo = np.minimum(self.lo, mag.min(axis=0))
        self.hi = np.maximum(self.hi, mag.max(axis=0))
        if acc is None:
            self.has_acc = False
        centre = self.centre
        if self.binned_centre is None or np.abs(centre - self.binned_centre).max() > REBIN_SHIFT_UT:
            self._rebin(centre)
        room = self.capacity - self.kept
        if room <= 0:
            return 0
        cells = fine_cells(mag - centre)
        unique, first = np.unique(cells, return_index=True)
        new = first[~self.occupied[unique]][:room]
        if new.size == 0:
            return 0
        self.occupied[cells[new]] = True
        self.mag[self.kept:self.kept + new.size] = mag[new]
        if acc is not None:
            self.acc[self.kept:self.kept + new.size] = acc[new]
        self.kept += new.size
        return int(new.size)

    def _rebin(self, centre: np.ndarray) -> None:
        """Sort the kept samples into cells around the new centre, keeping the first of each cell."""
        self.binned_centre = centre
        self.occupied[:] = False
        if not self.kept:
            return
        cells = fine_cells(self.mag[:self.kept] - centre)
        unique, first = np.unique(cells, return_index=True)
        first = np.sort(first)
        self.mag[:first.size] = self.mag[first]
        self.acc[:first.size] = self.acc[first]
        self.kept = int(first.size)
        self.occupied[unique] = True

    def samples(self) -> tuple[np.ndarray, np.ndarray | None]:
        return self.mag[:self.kept], (self.acc[:self.kept] if self.has_acc else None)

    def coverage(self):
        from magnet.quality import coverage

        return coverage(self.mag[:self.kept] - self.centre)

    def fit(self, settings: CalibratorSettings, now_s: float) -> Calibration | None:
        """Fit the kept samples (records the result or the reason); None when no calibration can be computed."""
        from magnet.calibration import FitError, fit

        self.last_fit_kept, self.last_fit_s = self.kept, now_s
        mag, acc = self.samples()
        try:
            self.last_fit = fit(mag, self.method, acc=acc, unit="ut", field_ut=settings.field_ut)
        except FitError as exc:
            self.last_fit, self.last_reason = None, str(exc)
            return None
        self.last_reason = self.last_fit.reason
        return self.last_fit

    def due(self, settings: CalibratorSettings, now_s: float) -> bool:
        return (self.kept >= settings.min_samples and self.kept - self.last_fit_kept >= FIT_EVERY_NEW
                and now_s - self.last_fit_s >= FIT_INTERVAL_S)


class Calibrator:
    """Per-device collections, the calibrations in force, the store; no zenoh inside (``publish`` is injected:
    ``publish(kind, device, payload_bytes)``)."""

    def __init__(self, store: CalibrationStore, settings: CalibratorSettings,
                 publish: Callable[[wire.Kind, str, bytes], None], clock: Callable[[], float] = time.monotonic,
                 clock_ns: Callable[[], int] = time.time_ns) -> None:
        self.store, self.settings, self.publish = store, settings, publish
        self.clock, self.clock_ns = clock, clock_ns
        self.in_force: dict[str, dict[str, Any]] = store.all_latest()
        self.collections: dict[str, Collection] = {}
        self.last_progress: dict[str, float] = {}
        self.drops = wire.DropCounter()
        self.counters = {"received_batches": 0, "received_samples": 0, "fits": 0, "accepted": 0, "rejected": 0,
                         "stored": 0}

    # ------------------------------------------------------------------------------------------------ raw data
    def state(self, device: str) -> State:
        collection = self.collections.get(device)
        if collection is not None:
            return State.SESSION if collection.session else State.COLLECTING
        return State.CALIBRATED if device in self.in_force else State.IDLE

    def on_raw(self, key_expr: str, payload: bytes, prefix: str) -> None:
        try:
            batch = wire.decode_raw(payload)
            wire.check_key(prefix, key_expr, wire.Kind.RAW, batch.device)
        except wire.WireError as exc:
            self.drops.drop(exc, "raw", log)
            return
        self.counters["received_batches"] += 1
        self.counters["received_samples"] += len(batch)
        collection = self.collections.get(batch.device)
        if collection is None:
            if batch.device in self.in_force or not self.settings.auto:
                return
            collection = self.collections[batch.device] = Collection(self.settings.method, False,
                                                                     self.settings.max_samples)
        collection.add(batch.mag_ut, batch.acc_ms2)
        now = self.clock()
        if collection.due(self.settings, now):
            self._try(batch.device, collection, now)
        if now - self.last_progress.get(batch.device, -np.inf) >= PROGRESS_INTERVAL_S:
            self._progress(batch.device)

    def _try(self, device: str, collection: Collection, now: float) -> None:
        cov = collection.coverage()
        if not collection.session and cov.fraction < self.settings.min_coverage:
            collection.last_reason = (f"coverage {cov.fraction:.0%} below {self.settings.min_coverage:.0%}: "
                                      f"{', '.join(cov.missing) or 'move through more attitudes'}")
            collection.last_fit_kept, collection.last_fit_s = collection.kept, now
            return
        result = collection.fit(self.settings, now)
        self.counters["fits"] += 1
        accepted = result is not None and result.accepted
        self.counters["accepted" if accepted else "rejected"] += 1
        if accepted and not collection.session:
            self.commit(device, result)
        elif not accepted:
            log.info("%s: fit not accepted: %s", device, collection.last_reason)

    # ---------------------------------------------------------------------------------------------- storing
    def commit(self, device: str, calibration: Calibration) -> dict[str, Any]:
        """Store ``calibration`` as the one in force for ``device``, publish it, end collection."""
        record = wire.calibration_record(device, calibration, self.clock_ns())
        if self.store.save(record):
            self.counters["stored"] += 1
        self.in_force[device] = self.store.latest(device) or record
        self.collections.pop(device, None)
        log.info("%s: calibration %s stored (%s, residual %s uT, coverage %s)", device, record["id"],
                 calibration.method, calibration.quality.get("residual_rms_ut"), calibration.quality.get("coverage"))
        self.publish(wire.Kind.CALIBRATION, device, wire.pack(self.in_force[device]))
        self._progress(device)
        return self.in_force[device]

    def progress(self, device: str) -> dict[str, Any]:
        state = self.state(device)
        collection = self.collections.get(device)
        record = self.in_force.get(device)
        out: dict[str, Any] = {"state": state.value, "t_ns": self.clock_ns(),
                               "calibration_id": record["id"] if record else None}
        if collection is None:
            if record is not None:
                quality = record.get("quality", {})
                out.update(method=record.get("method"), samples=record.get("sample_count"),
                           coverage=quality.get("coverage"), missing=[], residual_rms_ut=quality.get("residual_rms_ut"),
                           accepted=True, reason=record.get("reason", ""))
            return out
        cov = collection.coverage()
        last = collection.last_fit
        out.update(method=collection.method, session=collection.session, samples=collection.kept,
                   seen=collection.seen, coverage=cov.fraction, cells_hit=cov.cells_hit, cell_count=cov.cell_count,
                   missing=list(cov.missing),
                   residual_rms_ut=None if last is None else last.quality.get("residual_rms_ut"),
                   accepted=None if last is None else bool(last.accepted),
                   reason=collection.last_reason or self._waiting_reason(collection, cov))
        return out

    def _waiting_reason(self, collection: Collection, cov: Any) -> str:
        advice = ", ".join(cov.missing) or "move through more attitudes"
        return (f"{collection.kept} of {self.settings.min_samples} evenly spread samples, coverage "
                f"{cov.fraction:.0%}: {advice}")

    def _progress(self, device: str) -> None:
        self.last_progress[device] = self.clock()
        self.publish(wire.Kind.PROGRESS, device, wire.encode_progress(device, self.progress(device)))

    # ---------------------------------------------------------------------------------------------- sessions
    def session(self, device: str, action: str, method: str | None) -> dict[str, Any]:
        """Run a session action; returns the reply map ``{ok, action, state, message, progress, calibration?}``."""
        handler = self._ACTIONS.get(action)
        if handler is None:
            raise ValueError(f"unknown action {action!r}: use one of {', '.join(self._ACTIONS)}")
        ok, message, extra = handler(self, device, method)
        return {"ok": ok, "action": action, "device": device, "state": self.state(device).value, "message": message,
                "progress": self.progress(device), **extra}

    def _start(self, device: str, method: str | None) -> tuple[bool, str, dict]:
        from magnet.calibration import Method

        chosen = Method.parse(method or self.settings.method).value
        self.collections[device] = Collection(chosen, True, self.settings.max_samples)
        return True, f"session started with {chosen}: move the device through every attitude, then commit", {}

    def _status(self, device: str, method: str | None) -> tuple[bool, str, dict]:
        return True, self.state(device).value, {}

    def _commit(self, device: str, method: str | None) -> tuple[bool, str, dict]:
        collection = self.collections.get(device)
        if collection is None or not collection.session:
            return False, "no session to commit: start one first", {}
        result = collection.fit(self.settings, self.clock())
        self.counters["fits"] += 1
        if result is None or not result.accepted:
            self.counters["rejected"] += 1
            return False, f"not committed, the calibration in force stays: {collection.last_reason}", {}
        self.counters["accepted"] += 1
        return True, "committed", {"calibration": self.commit(device, result)}

    def _abort(self, device: str, method: str | None) -> tuple[bool, str, dict]:
        collection = self.collections.get(device)
        if collection is None or not collection.session:
            return False, "no session to abort", {}
        del self.collections[device]
        return True, "session aborted; the calibration in force stays", {}

    _ACTIONS: dict[str, Callable[["Calibrator", str, str | None], tuple[bool, str, dict]]] = {
        "start": _start, "status": _status, "commit": _commit, "abort": _abort}

    def status(self, name: str) -> dict[str, Any]:
        states = [self.state(d).value for d in set(self.collections) | set(self.in_force)]
        return {"v": wire.WIRE_VERSION, "service": "calibrator", "name": name, **self.counters,
                "devices": {s.value: states.count(s.value) for s in State}, "dropped": dict(self.drops.counts),
                "dropped_total": self.drops.total}


# ------------------------------------------------------------------------------------------------------- shell


def _field_ut(args: argparse.Namespace) -> float | None:
    if args.field_ut is not None:
        return args.field_ut
    if args.location:
        from magnet.geomag import earth_field, parse_location

        return earth_field(*parse_location(args.location)).total_ut
    return None


def _matching_devices(records: dict[str, Any], prefix: str, key_expr: str, kind: wire.Kind) -> list[str]:
    import zenoh

    if not any(c in key_expr for c in "*$"):
        try:
            device = wire.device_from_key(prefix, key_expr, kind)
        except wire.WireError:
            return []
        return [device] if device in records else []
    asked = zenoh.KeyExpr(key_expr)
    return [d for d in records if asked.intersects(zenoh.KeyExpr(wire.key(prefix, d, kind)))]


def _answer_calibration(query: Any, calibrator: Calibrator, prefix: str) -> None:
    for device in _matching_devices(calibrator.in_force, prefix, str(query.key_expr), wire.Kind.CALIBRATION):
        query.reply(wire.key(prefix, device, wire.Kind.CALIBRATION), wire.pack(calibrator.in_force[device]))


def _answer_history(query: Any, calibrator: Calibrator, prefix: str) -> None:
    try:
        limit = int(query.parameters.get("limit") or 100)
    except ValueError:
        query.reply_err(b"limit must be a whole number")
        return
    for device in _matching_devices(calibrator.in_force, prefix, str(query.key_expr), wire.Kind.HISTORY):
        records = calibrator.store.history(device, limit=limit)
        query.reply(wire.key(prefix, device, wire.Kind.HISTORY), wire.pack({"device": device, "records": records}))


def _answer_calibrate(query: Any, calibrator: Calibrator, prefix: str) -> None:
    key_expr = str(query.key_expr)
    try:
        device = wire.device_from_key(prefix, key_expr, wire.Kind.CALIBRATE)
        reply = calibrator.session(device, query.parameters.get("action") or "status", query.parameters.get("method"))
    except ValueError as exc:
        query.reply_err(str(exc).encode())
        return
    query.reply(key_expr, wire.pack(reply))


#: queried kind -> how to answer (the status queryable is answered in ``run``)
ANSWERS: dict[wire.Kind, Callable[[Any, Calibrator, str], None]] = {
    wire.Kind.CALIBRATION: _answer_calibration, wire.Kind.HISTORY: _answer_history,
    wire.Kind.CALIBRATE: _answer_calibrate}


def run(args: argparse.Namespace) -> int:
    import zenoh

    settings = CalibratorSettings(method=args.method, field_ut=_field_ut(args), min_coverage=args.min_coverage,
                                  min_samples=args.min_samples, max_samples=args.max_samples, auto=not args.no_auto)
    stop = stop_event()
    prefix, devices = args.prefix, args.devices
    with CalibrationStore(args.db or default_db_path()) as store, open_session(args) as session:
        publishers: dict[tuple[wire.Kind, str], Any] = {}

        def publish(kind: wire.Kind, device: str, payload: bytes) -> None:
            publisher = publishers.get((kind, device))
            if publisher is None:
                publisher = publishers[(kind, device)] = session.declare_publisher(wire.key(prefix, device, kind))
            publisher.put(payload)

        calibrator = Calibrator(store, settings, publish)
        token = session.liveliness().declare_token(wire.liveliness_key(prefix, "calibrator", args.name))
        raw_sub = session.declare_subscriber(f"{prefix}/{devices}/raw", zenoh.handlers.FifoChannel(CHANNEL_CAPACITY))
        queryables = [(ANSWERS[kind], session.declare_queryable(f"{prefix}/{devices}/{kind.value}",
                                                                zenoh.handlers.FifoChannel(256))) for kind in ANSWERS]

        def answer_status(query: Any, calibrator: Calibrator, prefix: str) -> None:
            query.reply(wire.status_key(prefix, args.name), wire.pack(calibrator.status(args.name)))

        queryables.append((answer_status, session.declare_queryable(wire.status_key(prefix, args.name),
                                                                    zenoh.handlers.FifoChannel(64))))
        for device, record in calibrator.in_force.items():
            publish(wire.Kind.CALIBRATION, device, wire.pack(record))
        log.info("calibrator %s: %d calibration(s) in store %s", args.name, len(calibrator.in_force), store.path)
        while not stop.is_set():
            samples = drain(raw_sub, 2000)
            for sample in samples:
                calibrator.on_raw(str(sample.key_expr), payload_bytes(sample), prefix)
            for answer, queryable in queryables:
                for query in drain(queryable, 64):
                    answer(query, calibrator, prefix)
                    query.drop()  # finalize now: the asker waits for it
            if not samples:
                time.sleep(IDLE_SLEEP_S)
        token.undeclare()
    log.info("calibrator stopped: %s", calibrator.status(args.name))
    return 0
