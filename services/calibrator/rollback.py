"""Rollback of a device's calibration (the ``calibrate`` queryable's ``rollback`` action): an earlier record this
calibrator made put back in force, as a new version, recorded as a change in the history."""

from __future__ import annotations

import logging
from typing import Any

from services.calibrator.core import Calibrator

#: a rollback without --to looks this far back in the history for the previous calibration
ROLLBACK_DEPTH = 1_000


log = logging.getLogger("magnet.calibrator")


def rollback(calibrator: Calibrator, device: str, to_id: str | None, by: str | None) -> dict[str, Any]:
    """Put an earlier calibration of ``device`` back in force (``to_id``, else the one before the current), recorded
    in the history as a change (action rollback, by, at_ns, from_id). The reply map of the calibrate queryable; a
    store that cannot be read or written (full disk, damaged file) is a refusal saying so, nothing changed."""
    try:
        ok, message, extra = _roll_back(calibrator, device, to_id, by)
    except OSError as exc:
        ok, message, extra = False, f"not rolled back, the calibration in force stays: {exc}", {}
        log.warning("rollback of %s refused: %s", device, exc)
    return {
        "ok": ok,
        "action": "rollback",
        "device": device,
        "state": calibrator.state(device).value,
        "message": message,
        "progress": calibrator.progress(device).to_dict(),
        **extra,
    }


def _roll_back(calibrator: Calibrator, device: str, to_id: str | None, by: str | None) -> tuple[bool, str, dict]:
    current = calibrator.in_force.get(device)
    history = calibrator.store.history(device, limit=ROLLBACK_DEPTH)
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
    if not calibrator.made_here(target):
        unsigned = (
            f"calibration {target.id} of {device} is not signed by this calibrator's key: it was not made by a "
            "calibrator you trust (or before the key), so it is not signed now; calibrate the device instead"
        )
        return False, unsigned, {}
    record = calibrator.commit(
        device, target.calibration, change={"action": "rollback", "by": by or "", "to_id": target.id}
    )
    message = (
        f"calibration {target.id} (made at {target.created_ns} ns, version {target.version}) back in force for "
        f"{device} as version {record.version}, replacing {current.id if current else 'none'}"
    )
    return True, message, {"calibration": record.to_record()}
