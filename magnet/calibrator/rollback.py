"""Rollback of a device's calibration (the ``calibrate`` queryable's ``rollback`` action): an earlier record this
calibrator made put back in force, as a new version, recorded as a change in the history."""

from __future__ import annotations

import logging

from magnet.calibrator.records import Records
from magnet.calibrator.sessions import Commit, Outcome

#: a rollback without --to looks this far back in the history for the previous calibration
ROLLBACK_DEPTH = 1_000


log = logging.getLogger("magnet.calibrator")


def roll_back(records: Records, commit: Commit, device: str, to_id: str | None, by: str | None) -> Outcome:
    """Put an earlier calibration of ``device`` back in force (``to_id``, else the one before the current) through
    ``commit``, recorded in the history as a change (action rollback, by, to_id). (ok, message, extra reply fields);
    a store that cannot be read or written (full disk, damaged file) is a refusal saying so, nothing changed."""
    try:
        return _roll_back(records, commit, device, to_id, by)
    except OSError as exc:
        log.warning("rollback of %s refused: %s", device, exc)
        return False, f"not rolled back, the calibration in force stays: {exc}", {}


def _roll_back(records: Records, commit: Commit, device: str, to_id: str | None, by: str | None) -> Outcome:
    current = records.get(device)
    history = records.store.history(device, limit=ROLLBACK_DEPTH)
    if to_id:
        target = next((r for r in history if r.id == to_id), None)
        missing = f"no calibration {to_id} in the history of {device} (magnet get calibration {device} --history)"
    else:
        target = next((r for r in history if current is None or r.id != current.id), None)
        missing = f"no earlier calibration of {device} to roll back to"
    if target is None:
        return False, missing, {}
    if current is not None and target.id == current.id:
        return False, f"calibration {target.id} is already in force for {device}", {}
    if not records.made_here(target):
        unsigned = (
            f"calibration {target.id} of {device} is not signed by this calibrator's key: it was not made by a "
            "calibrator you trust (or before the key), so it is not signed now; calibrate the device instead"
        )
        return False, unsigned, {}
    record = commit(device, target.calibration, {"action": "rollback", "by": by or "", "to_id": target.id})
    message = (
        f"calibration {target.id} (made at {target.created_ns} ns, version {target.version}) back in force for "
        f"{device} as version {record.version}, replacing {current.id if current else 'none'}"
    )
    return True, message, {"calibration": record.to_record()}
