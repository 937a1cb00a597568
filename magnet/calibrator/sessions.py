"""The sessions part of the calibrator: an operator's calibration of one device (the ``calibrate`` queryable's
actions start / status / commit / abort). A session collects afresh with its method and stores only on commit; the
calibration in force stays until then.

Each action returns (ok, message, extra reply fields); the composition (``magnet.calibrator.core``) adds the
device's state and progress to make the reply map. The parts it works with are handed in: the collections, the
fitter, and the few calls of the composition it needs (``known``, ``state``, ``commit``).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from magnet import wire
from magnet.calibration import Method
from magnet.calibration.choose import parse_choice
from magnet.calibrator.collecting import Collections
from magnet.calibrator.fitting import Fitter
from magnet.calibrator.status import State
from magnet.model import Calibration

#: an action's outcome: (ok, message, extra reply fields)
Outcome = tuple[bool, str, dict[str, Any]]
#: store a calibration as the one in force, with its change record (action, by): the record now in force
Commit = Callable[[str, Calibration, dict[str, Any]], wire.DeviceCalibration]

#: who asked is kept to this many characters
MAX_BY = 128

TURNTABLE_REFUSED = (
    "a turntable calibration cannot be collected from live samples (it needs the turntable's headings and the field's "
    "components): record the turns and run `magnet fit --method turntable` on the file"
)


class Sessions:
    """Operator sessions: ``act(device, action, method, by)``. ``default_method``: --method; ``clock``: monotonic s;
    ``by``: device -> who asked for its session's last action, kept while the session is open."""

    def __init__(
        self,
        default_method: str,
        collections: Collections,
        fitter: Fitter,
        known: Callable[[str], bool],
        state: Callable[[str], State],
        commit: Commit,
        clock: Callable[[], float],
    ) -> None:
        self.default_method, self.collections, self.fitter = default_method, collections, fitter
        self.known, self.state, self.commit, self.clock = known, state, commit, clock
        self.by: dict[str, str] = {}
        self.actions: dict[str, Callable[[str, str | None], Outcome]] = {
            "start": self._start,
            "status": self._status,
            "commit": self._commit,
            "abort": self._abort,
        }

    def act(self, device: str, action: str, method: str | None, by: str | None = None) -> Outcome:
        """Run ``action`` for ``device``; ValueError for an unknown action or method. ``by``: who asks (user@host,
        or the dashboard's operator), recorded with a commit."""
        run = self.actions.get(action)
        if run is None:
            raise ValueError(f"unknown action {action!r}: use one of {', '.join(self.actions)}")
        if by:
            self.by[device] = str(by)[:MAX_BY]
        outcome = run(device, method)
        if not self.collections.in_session(device):  # no session open: nothing to remember (bounded)
            self.by.pop(device, None)
        return outcome

    def _start(self, device: str, method: str | None) -> Outcome:
        chosen = parse_choice(method or self.default_method)
        if chosen == Method.TURNTABLE.value:  # it needs each sample's known heading and the field's components
            return False, TURNTABLE_REFUSED, {}
        if not self.known(device):
            return (
                False,
                (
                    f"{device} is unknown to this calibrator: no raw samples seen from it, no calibration stored and "
                    "not in its fleet file; check the id (magnet get fleet) and that its edge is publishing, then "
                    "start again"
                ),
                {},
            )
        self.collections.open_session(device, chosen)
        return True, f"session started with {chosen}: move the device through every attitude, then commit", {}

    def _status(self, device: str, method: str | None) -> Outcome:
        return True, self.state(device).value, {}

    def _commit(self, device: str, method: str | None) -> Outcome:
        collection = self.collections.get(device)
        if collection is None or not collection.session:
            return False, "no session to commit: start one first", {}
        result = self.fitter.fit(collection, self.clock(), device)
        if result is None:
            return False, f"not committed, the calibration in force stays: {collection.last_reason}", {}
        change: dict[str, Any] = {"action": "session", "by": self.by.get(device, "")}
        if collection.in_service:  # proposed by an in-service refresh (``magnet.calibrator.refresh``)
            change["in_service"] = True
        try:
            return True, "committed", {"calibration": self.commit(device, result, change).to_record()}
        except OSError as exc:
            return False, f"not committed, the calibration in force stays: {exc}", {}

    def _abort(self, device: str, method: str | None) -> Outcome:
        if not self.collections.in_session(device):
            return False, "no session to abort", {}
        self.collections.end(device)
        return True, "session aborted; the calibration in force stays", {}
