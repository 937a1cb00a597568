"""SQLite storage of calibrations: every accepted calibration of every device, newest last, history kept.

One table, one row per stored calibration; the record is the JSON map the wire publishes
(``magnet.wire.DeviceCalibration.to_record``). Rows are read back through ``magnet.wire.calibration_from_record``, the
one entry check of a calibration: a row that fails it is skipped, counted (``skipped_rows``) and logged once with the
file and row, and the rest is served. WAL journal with ``synchronous=FULL``: a row is on disk when ``save`` returns,
and a kill -9 at any moment leaves either the previous or the new calibration in force, never a torn one.
"""

from __future__ import annotations

import contextlib
import json
import logging
import sqlite3
from collections.abc import Iterable, Iterator, Mapping
from pathlib import Path
from typing import Any

from magnet import wire

log = logging.getLogger(__name__)

_SCHEMA = """
CREATE TABLE IF NOT EXISTS calibrations (
    seq        INTEGER PRIMARY KEY AUTOINCREMENT,
    device     TEXT    NOT NULL,
    id         TEXT    NOT NULL,
    created_ns INTEGER NOT NULL,
    record     TEXT    NOT NULL
);
CREATE INDEX IF NOT EXISTS calibrations_by_device ON calibrations (device, seq);
CREATE TABLE IF NOT EXISTS changes (
    seq        INTEGER PRIMARY KEY,
    change     TEXT    NOT NULL
);
"""


class StoreError(OSError):
    """The database cannot be read or written (damaged, not a database, disk full): one line naming the file and
    what to do."""


#: sqlite result codes (``sqlite3.Error.sqlite_errorcode``, low byte) that are not a damaged file
_SQLITE_FULL, _SQLITE_IOERR, _SQLITE_READONLY, _SQLITE_CANTOPEN, _SQLITE_BUSY = 13, 10, 8, 14, 5


def store_error(path: Path, doing: str, exc: sqlite3.DatabaseError) -> StoreError:
    """The one line for a failed ``doing`` ("read", "write") of the database at ``path``: a full disk, a read-only
    or failing disk and a damaged file each say what to do."""
    code = (getattr(exc, "sqlite_errorcode", None) or 0) & 0xFF
    if code == _SQLITE_FULL:
        return StoreError(
            f"the calibrator could not write its database {path}: disk full ({exc}); nothing was changed: free "
            "space on that filesystem and ask again"
        )
    if code in (_SQLITE_IOERR, _SQLITE_READONLY, _SQLITE_CANTOPEN, _SQLITE_BUSY):
        return StoreError(
            f"the calibrator could not {doing} its database {path} ({exc}); nothing was changed: check the disk "
            "and the file's permissions, then ask again"
        )
    return StoreError(
        f"calibration database {path} is damaged or unusable ({exc}): restore it from a "
        "backup, or move it aside to start with an empty one"
    )


class CalibrationStore:
    """Calibrations per device in one SQLite file. Use from one thread (the service's own).

    A damaged file is found when opening (``PRAGMA quick_check``) or when a damaged page is read later: both raise
    ``StoreError`` naming the file and what to do, never sqlite3's own exception."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        if str(path) != ":memory:":
            self.path.parent.mkdir(parents=True, exist_ok=True)
        self.skipped_rows = 0
        self._reported: set[int] = set()
        try:
            self._db = sqlite3.connect(str(path), isolation_level=None)
        except sqlite3.DatabaseError as exc:
            raise StoreError(f"cannot open calibration database {path}: {exc}") from None
        try:
            with self._guard():
                self._db.execute("PRAGMA journal_mode=WAL")
                self._db.execute("PRAGMA synchronous=FULL")
                self._db.executescript(_SCHEMA)
                problems = [row[0] for row in self._db.execute("PRAGMA quick_check(3)")]
                if problems != ["ok"]:
                    raise sqlite3.DatabaseError("; ".join(problems))
        except StoreError:
            self._db.close()
            raise

    @contextlib.contextmanager
    def _guard(self, doing: str = "read") -> Iterator[None]:
        """sqlite3 errors inside become one ``StoreError`` line naming the file, what failed and what to do
        (``store_error``); ``doing``: "read" or "write"."""
        try:
            yield
        except sqlite3.DatabaseError as exc:
            raise store_error(self.path, doing, exc) from None

    def close(self) -> None:
        self._db.close()

    def __enter__(self) -> CalibrationStore:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def save(self, record: wire.DeviceCalibration, change: Mapping[str, Any] | None = None) -> bool:
        """Store ``record`` as its device's calibration in force, with ``change`` (who, when, from which id: a
        JSON-able map kept beside it in the ``changes`` table, shown by ``history_changes``).

        Returns False (and stores nothing) when it is identical to the one already in force."""
        text = json.dumps(record.to_record(), sort_keys=True, allow_nan=False)
        with self._guard("write"), self._transaction():
            row = self._db.execute(
                "SELECT id FROM calibrations WHERE device = ? ORDER BY seq DESC LIMIT 1", (record.device,)
            ).fetchone()
            if row is not None and row[0] == record.id:
                return False
            cursor = self._db.execute(
                "INSERT INTO calibrations (device, id, created_ns, record) VALUES (?, ?, ?, ?)",
                (record.device, record.id, int(record.created_ns), text),
            )
            if change is not None:
                self._db.execute(
                    "INSERT INTO changes (seq, change) VALUES (?, ?)",
                    (cursor.lastrowid, json.dumps(dict(change), sort_keys=True, allow_nan=False)),
                )
        return True

    def latest(self, device: str) -> wire.DeviceCalibration | None:
        """The calibration in force for ``device`` (its newest valid record), or None."""
        with self._guard():
            rows = self._db.execute(
                "SELECT seq, record FROM calibrations WHERE device = ? ORDER BY seq DESC", (device,)
            )
            return next(self._valid(rows), None)

    def history(self, device: str, limit: int | None = None) -> list[wire.DeviceCalibration]:
        """Valid records of ``device``, newest first, at most ``limit``."""
        out: list[wire.DeviceCalibration] = []
        with self._guard():
            rows = self._db.execute(
                "SELECT seq, record FROM calibrations WHERE device = ? ORDER BY seq DESC", (device,)
            )
            for record in self._valid(rows):
                if limit is not None and len(out) >= max(0, limit):
                    break
                out.append(record)
        return out

    def history_changes(
        self, device: str, limit: int | None = None
    ) -> list[tuple[wire.DeviceCalibration, dict[str, Any] | None]]:
        """``history`` with each record's change (None where none was recorded), newest first."""
        with self._guard():
            rows = self._db.execute(
                "SELECT c.seq, c.record, h.change FROM calibrations c LEFT JOIN changes h "
                "ON h.seq = c.seq WHERE c.device = ? ORDER BY c.seq DESC",
                (device,),
            ).fetchall()
        changes = {seq: change for seq, _, change in rows}
        out: list[tuple[wire.DeviceCalibration, dict[str, Any] | None]] = []
        for seq, record in self._valid_seq((seq, text) for seq, text, _ in rows):
            if limit is not None and len(out) >= max(0, limit):
                break
            text = changes.get(seq)
            try:
                change = None if text is None else json.loads(text)
            except ValueError:  # a damaged change note does not hide the record
                change = None
            out.append((record, change))
        return out

    def _valid_seq(self, rows: Iterable[tuple[int, str]]) -> Iterable[tuple[int, wire.DeviceCalibration]]:
        """(seq, record) of the rows that pass the entry check (``_valid``)."""
        for seq, text in rows:
            for record in self._valid([(seq, text)]):
                yield seq, record

    def all_latest(self) -> dict[str, wire.DeviceCalibration]:
        """device -> the record in force (its newest valid one), for every device stored."""
        out: dict[str, wire.DeviceCalibration] = {}
        with self._guard():
            rows = self._db.execute("SELECT seq, record FROM calibrations ORDER BY device, seq DESC")
            for record in self._valid(rows):
                out.setdefault(record.device, record)
        return out

    def _valid(self, rows: Iterable[tuple[int, str]]) -> Iterator[wire.DeviceCalibration]:
        """The records of ``rows`` (seq, JSON text) that pass the entry check; the others skipped and counted."""
        for seq, text in rows:
            try:
                yield wire.calibration_from_record(json.loads(text))
            except (ValueError, RecursionError) as exc:  # WireError and JSONDecodeError are ValueErrors
                self.skipped_rows += 1
                if seq not in self._reported:
                    self._reported.add(seq)
                    log.warning("%s: skipping calibration row %d: %s", self.path, seq, exc)

    def _transaction(self) -> _Transaction:
        return _Transaction(self._db)


class _Transaction:
    """BEGIN IMMEDIATE ... COMMIT, rolled back on any exception (the exception raised is the first one)."""

    def __init__(self, db: sqlite3.Connection) -> None:
        self._db = db

    def __enter__(self) -> None:
        self._db.execute("BEGIN IMMEDIATE")

    def __exit__(self, exc_type: object, *rest: object) -> None:
        if not exc_type:
            self._db.execute("COMMIT")
        elif self._db.in_transaction:  # sqlite rolls back itself on some errors (a full disk): keep their message
            with contextlib.suppress(sqlite3.Error):
                self._db.execute("ROLLBACK")
