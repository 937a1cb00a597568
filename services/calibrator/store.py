"""SQLite storage of calibrations: every accepted calibration of every device, newest last, history kept.

One table, one row per stored calibration; the record is the JSON map the wire publishes
(``magnet.wire.DeviceCalibration.to_record``), with the signature it was given when it was made: the store never
signs, and a record read back is served exactly as stored. The ``version`` column repeats the record's version (the
device's record number; 0 for rows from before versions, which a database of an older magnet gets when it is opened:
``_migrate``), so that the next one is counted on from the store (``append``); a UNIQUE index on (device, version)
(versions above 0) refuses a second record of one version whatever a writer does. ``services.calibrator.pgstore`` is
the same schema and semantics on PostgreSQL.

Rows are read back through ``magnet.wire.calibration_from_record``, the one entry check of a calibration: a row that
fails it is skipped, counted (``skipped_rows``) and logged once with the file and row, and the rest is served. WAL
journal with ``synchronous=FULL``: a row is on disk when ``save`` returns, and a kill -9 at any moment leaves either
the previous or the new calibration in force, never a torn one.
"""

from __future__ import annotations

import contextlib
import errno
import json
import logging
import sqlite3
from collections.abc import Callable, Iterable, Iterator, Mapping
from pathlib import Path
from typing import Any

from magnet import wire
from services.common.dbfile import OpenedFile
from services.common.stores import PostgresUrl, RowCheck, Store, StoredRow, StoreError, StoreLocation, next_row

log = logging.getLogger(__name__)

_SCHEMA = """
CREATE TABLE IF NOT EXISTS calibrations (
    seq        INTEGER PRIMARY KEY AUTOINCREMENT,
    device     TEXT    NOT NULL,
    id         TEXT    NOT NULL,
    created_ns INTEGER NOT NULL,
    record     TEXT    NOT NULL,
    version    INTEGER NOT NULL DEFAULT 0
);
CREATE INDEX IF NOT EXISTS calibrations_by_device ON calibrations (device, seq);
CREATE TABLE IF NOT EXISTS changes (
    seq        INTEGER PRIMARY KEY,
    change     TEXT    NOT NULL
);
"""
#: versions unique per device (a constraint, not only the lease); version 0: the rows from before versions
_UNIQUE_VERSIONS = (
    "CREATE UNIQUE INDEX IF NOT EXISTS calibrations_version_per_device ON calibrations (device, version) "
    "WHERE version > 0"
)


class StoreGoneError(StoreError):
    """The database file this store opened is no longer at its path (deleted, or replaced by another file or one
    that is not a database): a row written now would go into a file nobody reads again, so nothing is written."""


#: sqlite result codes (``sqlite_errorcode``, low byte) of a full disk, of a file it may not write or a failing disk,
#: of a lock, and of a damaged file
_FULL = {13}
_CANNOT = {3, 8, 10, 14, 23}  # PERM, READONLY, IOERR, CANTOPEN, AUTH
_BUSY = {5, 6}
_DAMAGED = {11, 26}  # CORRUPT, NOTADB


def describe_failure(path: Path, exc: BaseException, doing: str = "use") -> str:
    """One line for a failure to ``doing`` ("read", "write") the database ``path``: a full disk as a full disk
    (nothing written, free space), a file it may not write or a failing disk, a lock, a damaged file (restore it or
    move it aside), or else the error itself."""
    code = (getattr(exc, "sqlite_errorcode", None) or 0) & 0xFF
    text, errno_ = str(exc), getattr(exc, "errno", None)
    if code in _FULL or errno_ in (errno.ENOSPC, errno.EDQUOT) or "disk is full" in text:
        return (
            f"the calibrator could not write its database {path}: disk full (the disk is full: {text}); nothing was "
            "written and the calibration in force stays: free space on its filesystem (or raise the quota), then try "
            "again"
        )
    if code in _CANNOT or errno_ in (errno.EACCES, errno.EPERM, errno.EROFS, errno.EIO) or "readonly" in text:
        return (
            f"the calibrator could not {doing} its database {path} ({text}); nothing was changed: check the disk, the "
            "permissions of the file and of its directory, and that the filesystem is not read-only"
        )
    if code in _BUSY:
        return f"calibration database {path} is locked by another process ({text}): try again"
    if code in _DAMAGED or (isinstance(exc, sqlite3.DatabaseError) and not code):
        return (
            f"calibration database {path} is damaged or unusable ({text}): restore it from a backup, or move it "
            "aside to start with an empty one"
        )
    return f"calibration database {path} could not be used ({text}): check the disk and the file, then try again"


def store_error(path: Path, doing: str, exc: BaseException) -> StoreError:
    """``describe_failure`` as the ``StoreError`` the store raises."""
    return StoreError(describe_failure(path, exc, doing))


class CalibrationStore(RowCheck):
    """Calibrations per device in one SQLite file. Use from one thread (the service's own).

    A damaged file is found when opening (``PRAGMA quick_check``) or when a damaged page is read later: both raise
    ``StoreError`` naming the file and what to do, never sqlite3's own exception."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        if str(path) != ":memory:":
            self.path.parent.mkdir(parents=True, exist_ok=True)
        RowCheck.__init__(self, self.path)
        try:
            self._db = sqlite3.connect(str(path), isolation_level=None)
        except sqlite3.DatabaseError as exc:
            raise StoreError(f"cannot open calibration database {path}: {exc}") from None
        try:
            with self._guard():
                self._db.execute("PRAGMA journal_mode=WAL")
                self._db.execute("PRAGMA synchronous=FULL")
                self._db.executescript(_SCHEMA)
                self._migrate()
                problems = [row[0] for row in self._db.execute("PRAGMA quick_check(3)")]
                if problems != ["ok"]:
                    raise sqlite3.DatabaseError("; ".join(problems))
        except StoreError:
            self._db.close()
            raise
        self._gone: str | None = None
        self._file = OpenedFile(self.path)

    @property
    def gone(self) -> str | None:
        """Why the file this store opened is no longer its database (deleted, replaced, overwritten:
        ``services.common.dbfile``), or None. Gone for good: only a restart opens the file now at the path."""
        if self._gone is None:
            self._gone = self._file.check()
            if self._gone is not None:
                log.error("%s", self._gone)
        return self._gone

    def _writable(self) -> None:
        """StoreGoneError unless the file opened is still the database at the path (``gone``)."""
        reason = self.gone
        if reason is not None:
            raise StoreGoneError(reason)

    @contextlib.contextmanager
    def _guard(self, doing: str = "use") -> Iterator[None]:
        """sqlite3 errors (and OSErrors) inside become one ``StoreError`` line naming the file, what went wrong
        and what to do (``describe_failure``); ``doing``: what was being done ("read", "write"), for the line."""
        try:
            yield
        except StoreError:
            raise
        except (sqlite3.DatabaseError, OSError) as exc:
            raise store_error(self.path, doing, exc) from None

    def close(self) -> None:
        self._db.close()

    def __enter__(self) -> CalibrationStore:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _migrate(self) -> None:
        """A database written before versions gets the ``version`` column, 0 on every old row (their records carry
        no version, and their signatures, if any, stay as they were made)."""
        columns = {row[1] for row in self._db.execute("PRAGMA table_info(calibrations)")}
        if "version" not in columns:
            self._db.execute("ALTER TABLE calibrations ADD COLUMN version INTEGER NOT NULL DEFAULT 0")
            log.info("%s: calibrations table given a version column (old rows: version 0)", self.path)
        try:
            self._db.execute(_UNIQUE_VERSIONS)
        except sqlite3.IntegrityError as exc:  # an older file with two rows of one version: served, flagged
            log.warning(
                "%s: two records of one device share a version (%s); versions are not enforced unique in this file: "
                "run magnet db check --db %s",
                self.path,
                exc,
                self.path,
            )

    def save(self, record: wire.DeviceCalibration, change: Mapping[str, Any] | None = None) -> bool:
        """Store ``record`` as its device's calibration in force, with ``change`` (who, when, from which id: a
        JSON-able map kept beside it in the ``changes`` table, shown by ``history_changes``).

        Returns False (and stores nothing) when it is identical to the one already in force."""
        return self.append(record.device, lambda version: record, change)[1]

    def append(
        self,
        device: str,
        make: Callable[[int], wire.DeviceCalibration],
        change: Mapping[str, Any] | None = None,
        floor: int = 0,
    ) -> tuple[wire.DeviceCalibration, bool]:
        """Store the record ``make(version)`` builds (and signs) for ``device``, ``version`` being one more than the
        highest stored for it (or than ``floor``, the version of the record in force as its JSON says), read in the
        same write transaction (two calibrators on one file never number two records alike). Returns (record,
        stored): not stored when identical to the one already in force. ``StoreGoneError`` (nothing stored) when the
        file was deleted or replaced under the open store (``gone``), checked before and after the write."""
        self._writable()
        with self._guard("write"), self._transaction():
            latest = self._db.execute(
                "SELECT id FROM calibrations WHERE device = ? ORDER BY seq DESC LIMIT 1", (device,)
            ).fetchone()
            (highest,) = self._db.execute(
                "SELECT COALESCE(MAX(version), 0) FROM calibrations WHERE device = ?", (device,)
            ).fetchone()
            latest_id = None if latest is None else latest[0]
            record, row = next_row(device, make, int(highest), floor, latest_id, change)
            if row is None:
                return record, False
            self._insert(row)
            self._writable()  # gone during the write: rolled back, not acknowledged
        return record, True

    def _insert(self, row: StoredRow) -> None:
        cursor = self._db.execute(
            "INSERT INTO calibrations (device, id, created_ns, record, version) VALUES (?, ?, ?, ?, ?)",
            (row.device, row.id, row.created_ns, row.record, row.version),
        )
        if row.change is not None:
            self._db.execute("INSERT INTO changes (seq, change) VALUES (?, ?)", (cursor.lastrowid, row.change))

    def rows(self) -> Iterator[StoredRow]:
        """Every row as stored (the record's and its change's text byte for byte), oldest first."""
        with self._guard("read"):
            rows = self._db.execute(
                "SELECT c.device, c.id, c.created_ns, c.version, c.record, h.change FROM calibrations c "
                "LEFT JOIN changes h ON h.seq = c.seq ORDER BY c.seq"
            ).fetchall()
        for device, id_, created_ns, version, record, change in rows:
            yield StoredRow(device, id_, int(created_ns), int(version), record, change)

    def load_rows(self, rows: Iterable[StoredRow]) -> int:
        """Store ``rows`` as they are, in order, in one transaction; how many."""
        count = 0
        self._writable()
        with self._guard("write"), self._transaction():
            for row in rows:
                self._insert(row)
                count += 1
            self._writable()
        return count

    def count(self) -> int:
        """Rows stored."""
        with self._guard("read"):
            (n,) = self._db.execute("SELECT COUNT(*) FROM calibrations").fetchone()
        return int(n)

    def latest(self, device: str) -> wire.DeviceCalibration | None:
        """The calibration in force for ``device`` (its newest valid record), or None."""
        with self._guard("read"):
            rows = self._db.execute(
                "SELECT seq, record FROM calibrations WHERE device = ? ORDER BY seq DESC", (device,)
            )
            return next(self.valid(rows), None)

    def history(self, device: str, limit: int | None = None) -> list[wire.DeviceCalibration]:
        """Valid records of ``device``, newest first, at most ``limit``."""
        out: list[wire.DeviceCalibration] = []
        with self._guard("read"):
            rows = self._db.execute(
                "SELECT seq, record FROM calibrations WHERE device = ? ORDER BY seq DESC", (device,)
            )
            for record in self.valid(rows):
                if limit is not None and len(out) >= max(0, limit):
                    break
                out.append(record)
        return out

    def history_changes(
        self, device: str, limit: int | None = None
    ) -> list[tuple[wire.DeviceCalibration, dict[str, Any] | None]]:
        """``history`` with each record's change (None where none was recorded), newest first."""
        with self._guard("read"):
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
            for record in self.valid([(seq, text)]):
                yield seq, record

    def all_latest(self) -> dict[str, wire.DeviceCalibration]:
        """device -> the record in force (its newest valid one), for every device stored."""
        out: dict[str, wire.DeviceCalibration] = {}
        with self._guard("read"):
            rows = self._db.execute("SELECT seq, record FROM calibrations ORDER BY device, seq DESC")
            for record in self.valid(rows):
                out.setdefault(record.device, record)
        return out

    def _transaction(self) -> _Transaction:
        return _Transaction(self._db)


class _Transaction:
    """BEGIN IMMEDIATE ... COMMIT, rolled back on any exception. SQLite ends a transaction itself on some errors
    (a full disk among them): then there is nothing to roll back, and the error that ended it is the one raised."""

    def __init__(self, db: sqlite3.Connection) -> None:
        self._db = db

    def __enter__(self) -> None:
        self._db.execute("BEGIN IMMEDIATE")

    def __exit__(self, exc_type: object, *rest: object) -> None:
        if not exc_type:
            self._db.execute("COMMIT")
        elif getattr(self._db, "in_transaction", True):
            with contextlib.suppress(sqlite3.Error):  # the first error is the one to report
                self._db.execute("ROLLBACK")


def open_store(location: StoreLocation) -> Store:
    """The store at ``location`` (``services.common.stores.parse_db``), opened (its schema made when new): this
    SQLite store, or the PostgreSQL one (``services.calibrator.pgstore``, imported only when used); OSError
    (``StoreError``) naming it when it cannot be."""
    if isinstance(location, PostgresUrl):
        from services.calibrator.pgstore import PostgresStore

        return PostgresStore(location)
    return CalibrationStore(location)
