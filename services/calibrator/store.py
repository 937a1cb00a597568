"""SQLite storage of calibrations: every accepted calibration of every device, newest last, history kept.

One table, one row per stored calibration; the record is the JSON map the wire publishes (``magnet.wire
.calibration_record``). WAL journal with ``synchronous=FULL``: a row is on disk when ``save`` returns, and a kill -9 at
any moment leaves either the previous or the new calibration in force, never a torn one.
"""

from __future__ import annotations

import json
import logging
import sqlite3
from pathlib import Path
from typing import Any, Mapping

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
"""


class CalibrationStore:
    """Calibrations per device in one SQLite file. Use from one thread (the service's own)."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        if str(path) != ":memory:":
            self.path.parent.mkdir(parents=True, exist_ok=True)
        try:
            self._db = sqlite3.connect(str(path), isolation_level=None)
            self._db.execute("PRAGMA journal_mode=WAL")
            self._db.execute("PRAGMA synchronous=FULL")
            self._db.executescript(_SCHEMA)
        except sqlite3.DatabaseError as exc:
            raise OSError(f"cannot open calibration database {path}: {exc}") from None

    def close(self) -> None:
        self._db.close()

    def __enter__(self) -> "CalibrationStore":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def save(self, record: Mapping[str, Any]) -> bool:
        """Store ``record`` (with ``device``, ``id``, ``created_ns``) as the device's calibration in force.

        Returns False (and stores nothing) when it is identical to the one already in force."""
        device, content_id = str(record["device"]), str(record["id"])
        text = json.dumps(record, sort_keys=True, allow_nan=False)
        with self._transaction():
            row = self._db.execute("SELECT id FROM calibrations WHERE device = ? ORDER BY seq DESC LIMIT 1",
                                   (device,)).fetchone()
            if row is not None and row[0] == content_id:
                return False
            self._db.execute("INSERT INTO calibrations (device, id, created_ns, record) VALUES (?, ?, ?, ?)",
                             (device, content_id, int(record["created_ns"]), text))
        return True

    def latest(self, device: str) -> dict[str, Any] | None:
        """The calibration in force for ``device`` (its record), or None."""
        rows = self.history(device, limit=1)
        return rows[0] if rows else None

    def history(self, device: str, limit: int | None = None) -> list[dict[str, Any]]:
        """Records of ``device``, newest first, at most ``limit``."""
        sql = "SELECT record FROM calibrations WHERE device = ? ORDER BY seq DESC"
        params: tuple[Any, ...] = (device,)
        if limit is not None:
            sql += " LIMIT ?"
            params += (max(0, int(limit)),)
        return [json.loads(text) for (text,) in self._db.execute(sql, params)]

    def all_latest(self) -> dict[str, dict[str, Any]]:
        """device -> the record in force, for every device stored."""
        sql = ("SELECT c.device, c.record FROM calibrations c JOIN (SELECT device, MAX(seq) AS seq FROM calibrations "
               "GROUP BY device) m ON c.device = m.device AND c.seq = m.seq ORDER BY c.device")
        return {device: json.loads(text) for device, text in self._db.execute(sql)}

    def _transaction(self) -> "_Transaction":
        return _Transaction(self._db)


class _Transaction:
    """BEGIN IMMEDIATE ... COMMIT, rolled back on any exception."""

    def __init__(self, db: sqlite3.Connection) -> None:
        self._db = db

    def __enter__(self) -> None:
        self._db.execute("BEGIN IMMEDIATE")

    def __exit__(self, exc_type: object, *rest: object) -> None:
        self._db.execute("ROLLBACK" if exc_type else "COMMIT")
