"""Where a calibrator keeps its calibrations (``--db``): a SQLite file (the default, one host) or a PostgreSQL
database (``postgresql://USER@HOST:PORT/DB``: calibrators on several hosts, a replicated server). One protocol
(``magnet.calibrator.store.CalibrationStore``), two implementations with the same schema and semantics:
``services.calibrator.store`` (SQLite, and ``open_store`` for either) and ``services.calibrator.pgstore``
(PostgreSQL, psycopg 3, imported only when used). This module is what both share (the URL, the rows as stored, the
error), so neither imports the other's home and nothing here imports a store.

Both also hand out and take in their rows as stored (``StoredRow``: the record's JSON text and its change's, byte for
byte), which ``magnet db copy`` and ``magnet db check`` use; the calibrator never does.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import re
import urllib.parse
from collections.abc import Callable, Iterable, Iterator, Mapping
from pathlib import Path
from typing import Any, Protocol

from magnet import wire


class StoreError(OSError):
    """The database cannot be read or written (damaged, not a database, disk full): one line naming the file and
    what to do."""


log = logging.getLogger("magnet.store")


#: URL schemes of a PostgreSQL database (libpq's two)
POSTGRES_SCHEMES = ("postgresql", "postgres")
_SCHEME = re.compile(r"^([A-Za-z][A-Za-z0-9+.-]*):(//|$)")


@dataclasses.dataclass(frozen=True)
class PostgresUrl:
    """A PostgreSQL database, ``postgresql://USER[:PASSWORD]@HOST:PORT/DB[?PARAMS]`` (libpq's URL; a password is
    better kept in ~/.pgpass or PGPASSWORD). ``str()`` hides the password (it goes into logs and messages)."""

    url: str

    def __post_init__(self) -> None:
        parts = urllib.parse.urlsplit(self.url)
        if parts.scheme not in POSTGRES_SCHEMES:
            raise ValueError(f"a PostgreSQL URL starts with postgresql://, got {self!s}")
        if not parts.path.strip("/") and not parts.hostname:
            raise ValueError(f"{self!s} names no database: give postgresql://USER@HOST:PORT/DB")

    def __str__(self) -> str:
        parts = urllib.parse.urlsplit(self.url)
        if parts.password is None:
            return self.url
        netloc = parts.netloc.replace(f":{parts.password}@", ":***@", 1)
        return urllib.parse.urlunsplit((parts.scheme, netloc, parts.path, parts.query, parts.fragment))


#: a store's location: a SQLite file or a PostgreSQL database
StoreLocation = Path | PostgresUrl


def parse_db(text: str) -> StoreLocation:
    """``--db``: ``postgresql://...`` (or ``postgres://``) is a PostgreSQL database, text without a URL scheme a SQLite
    file; any other scheme is refused (ValueError), never taken for a folder of that name."""
    match = _SCHEME.match(text)
    if match is None:
        if not text.strip():
            raise ValueError("empty: give a SQLite file (FILE.sqlite3) or postgresql://USER@HOST:PORT/DB")
        return Path(text)
    if match.group(1).lower() in POSTGRES_SCHEMES:
        return PostgresUrl(text)
    raise ValueError(
        f"unknown scheme {match.group(1)}: (not a store magnet knows, and not taken for a folder of that name): give a "
        "SQLite file (FILE.sqlite3) or postgresql://USER@HOST:PORT/DB"
    )


@dataclasses.dataclass(frozen=True)
class StoredRow:
    """One stored calibration as its store holds it: device, id, created_ns (ns since the epoch), version, the
    record's JSON text and its change's (None where none was recorded), both byte for byte."""

    device: str
    id: str
    created_ns: int
    version: int
    record: str
    change: str | None = None


def next_row(
    device: str,
    make: Callable[[int], wire.DeviceCalibration],
    highest: int,
    floor: int,
    latest_id: str | None,
    change: Mapping[str, Any] | None,
) -> tuple[wire.DeviceCalibration, StoredRow | None]:
    """What an append stores, the same in both stores: the record ``make`` builds for the next version (above the
    device's ``highest`` and ``floor``, below ``wire.MAX_VERSION``) and its row, or None for the row when it is the
    record already in force (``latest_id``). ValueError for a record of another device."""
    record = make(min(max(highest, floor), wire.MAX_VERSION - 1) + 1)
    if record.device != device:
        raise ValueError(f"a record of {record.device} cannot be stored as one of {device}")
    if latest_id == record.id:
        return record, None
    text = json.dumps(record.to_record(), sort_keys=True, allow_nan=False)
    note = None if change is None else json.dumps(dict(change), sort_keys=True, allow_nan=False)
    return record, StoredRow(device, record.id, int(record.created_ns), int(record.version), text, note)


class RowStore(Protocol):
    """What ``magnet db`` reads and writes of a store, beside the calibrator's protocol: rows as stored."""

    def rows(self) -> Iterator[StoredRow]:
        """Every row, in the order they were stored (oldest first)."""
        ...

    def load_rows(self, rows: Iterable[StoredRow]) -> int:
        """Store ``rows`` as they are, in order and in one transaction; how many. OSError: nothing stored."""
        ...

    def count(self) -> int:
        """Rows stored."""
        ...

    def close(self) -> None: ...


class Store(RowStore, Protocol):
    """A store of either kind, as the service and ``magnet db`` use it."""

    def append(
        self, device: str, make: Any, change: Any = None, floor: int = 0
    ) -> tuple[wire.DeviceCalibration, bool]: ...

    def latest(self, device: str) -> wire.DeviceCalibration | None: ...

    def all_latest(self) -> dict[str, wire.DeviceCalibration]: ...

    def history(self, device: str, limit: int | None = None) -> list[wire.DeviceCalibration]: ...

    def history_changes(
        self, device: str, limit: int | None = None
    ) -> list[tuple[wire.DeviceCalibration, dict[str, Any] | None]]: ...

    def __enter__(self) -> Any: ...

    def __exit__(self, *exc: object) -> None: ...


class RowCheck:
    """The entry check of stored rows, a base of both stores: a row whose record does not pass it is skipped, counted
    (``skipped_rows``) and logged once (naming ``where`` and the row), and the rest is served."""

    def __init__(self, where: object) -> None:
        self.where = where
        self.skipped_rows = 0
        self._reported: set[int] = set()

    def valid(self, rows: Iterable[tuple[int, str]]) -> Iterator[wire.DeviceCalibration]:
        """The records of ``rows`` (seq, JSON text) that pass the entry check."""
        for seq, text in rows:
            try:
                yield wire.calibration_from_record(json.loads(text))
            except (ValueError, RecursionError) as exc:  # WireError and JSONDecodeError are ValueErrors
                self.skipped_rows += 1
                if seq not in self._reported:
                    self._reported.add(seq)
                    log.warning("%s: skipping calibration row %d: %s", self.where, seq, exc)
