"""What the calibrator asks of a store of calibrations (``CalibrationStore``): the store's whole contract, so that
any store (the service's SQLite file, ``services.calibrator.store``; a PostgreSQL database,
``services.calibrator.pgstore``; an in-memory fake in the tests) serves the same decisions.

The contract:

- **One record and its change in one transaction** (``append``): the record a device is given and the change beside
  it (who, when, from which id: a JSON-able map) are stored together or not at all.
- **Versions per device**: ``append`` reads the highest version stored for the device (or ``floor``, the version of
  the record in force as its JSON says, if higher) in the same write transaction and hands one more, at most
  ``wire.MAX_VERSION``, to ``make``; two calibrators on one store never number two records of a device alike.
- **Not twice**: a record whose id equals the device's newest is not stored again (``append`` says so).
- **Signature stored as made**: a store never signs; what ``make`` built (signed or not) is stored, and read back it
  is served exactly as stored. Rows that fail ``wire.calibration_from_record`` (the one entry check of a
  calibration) are skipped, never served, and the rest is.
- **History**: every record of a device is kept, newest first (``history``), with its change (``history_changes``:
  None where none was recorded); the record in force is the newest (``latest``, ``all_latest``).
- **Failures**: a store that cannot be read or written raises ``OSError`` (one line naming the store and what to
  do) and changes nothing.
- **Gone**: a store whose file can be deleted or replaced under it (the SQLite store) says so in an optional ``gone``
  attribute (why, one line; None while it is its own): then ``append`` raises ``OSError`` before acknowledging
  anything, the calibrator refuses sessions and commits with that reason and its status says ``store: gone``. A
  store without the attribute is never gone.

An operator's session (``sessions``) and a rollback (``rollback``) reach the store only through ``append`` (their
change says ``session`` or ``rollback``, by whom, to which id); a session in progress is not stored.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any, Protocol

from magnet import wire

#: builds (and signs) a device's record given its version number
MakeRecord = Callable[[int], wire.DeviceCalibration]


class CalibrationStore(Protocol):
    """Calibrations per device, history kept (see the module docstring for the contract)."""

    def append(
        self,
        device: str,
        make: MakeRecord,
        change: Mapping[str, Any] | None = None,
        floor: int = 0,
    ) -> tuple[wire.DeviceCalibration, bool]:
        """Store ``make(version)`` and ``change`` in one transaction, ``version`` one more than the highest stored
        for ``device`` or than ``floor``; (record, stored), not stored when its id is the newest's. ValueError when
        the record is of another device; OSError: nothing stored."""
        ...

    def latest(self, device: str) -> wire.DeviceCalibration | None:
        """The record in force for ``device`` (its newest valid one), or None."""
        ...

    def all_latest(self) -> dict[str, wire.DeviceCalibration]:
        """device -> the record in force, for every device stored."""
        ...

    def history(self, device: str, limit: int | None = None) -> list[wire.DeviceCalibration]:
        """The valid records of ``device``, newest first, at most ``limit``."""
        ...

    def history_changes(
        self, device: str, limit: int | None = None
    ) -> list[tuple[wire.DeviceCalibration, dict[str, Any] | None]]:
        """``history`` with each record's change (None where none was recorded), newest first."""
        ...
