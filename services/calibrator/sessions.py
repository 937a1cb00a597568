"""Operator sessions of the calibrator (the ``calibrate`` queryable): start / status / commit / abort.

Each action takes (calibrator, device, method) and returns (ok, message, extra reply fields); ``Calibrator.session``
wraps that into the reply map. The actions see the calibrator only through ``SessionHost`` (what they read and call
of it), so this module does not import the core that runs them.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Protocol

from magnet import wire
from magnet.bounded import Recent
from magnet.calibration import Method
from magnet.collection import Collection
from magnet.model import Calibration
from services.calibrator.settings import CalibratorSettings
from services.calibrator.status import State


class SessionHost(Protocol):
    """What a session action reads and calls of the calibrator (``services.calibrator.core.Calibrator``)."""

    settings: CalibratorSettings
    collections: Recent[str, Collection]
    clock: Callable[[], float]

    def known(self, device: str) -> bool: ...

    def state(self, device: str) -> State: ...

    def fit_collection(self, collection: Collection, now: float, device: str | None = None) -> Calibration | None: ...

    def commit(
        self, device: str, calibration: Calibration, change: dict[str, Any] | None = None
    ) -> wire.DeviceCalibration: ...


#: a session action: (calibrator, device, method) -> (ok, message, extra reply fields)
Action = Callable[[SessionHost, str, "str | None"], "tuple[bool, str, dict[str, Any]]"]


def _start(calibrator: SessionHost, device: str, method: str | None) -> tuple[bool, str, dict[str, Any]]:
    chosen = Method.parse(method or calibrator.settings.method).value
    if chosen == Method.TURNTABLE.value:  # it needs each sample's known heading and the field's components
        return (
            False,
            (
                "a turntable calibration cannot be collected from live samples (it needs the turntable's "
                "headings and the field's components): record the turns and run `magnet fit --method "
                "turntable` on the file"
            ),
            {},
        )
    if not calibrator.known(device):
        return (
            False,
            (
                f"{device} is unknown to this calibrator: no raw samples seen from it, no calibration stored and "
                "not in its fleet file; check the id (magnet get fleet) and that its edge is publishing, then start "
                "again"
            ),
            {},
        )
    calibrator.collections[device] = Collection(chosen, True, calibrator.settings.max_samples)
    return True, f"session started with {chosen}: move the device through every attitude, then commit", {}


def _status(calibrator: SessionHost, device: str, method: str | None) -> tuple[bool, str, dict[str, Any]]:
    return True, calibrator.state(device).value, {}


def _commit(calibrator: SessionHost, device: str, method: str | None) -> tuple[bool, str, dict[str, Any]]:
    collection = calibrator.collections.get(device)
    if collection is None or not collection.session:
        return False, "no session to commit: start one first", {}
    result = calibrator.fit_collection(collection, calibrator.clock(), device)
    if result is None:
        return False, f"not committed, the calibration in force stays: {collection.last_reason}", {}
    try:
        return True, "committed", {"calibration": calibrator.commit(device, result).to_record()}
    except OSError as exc:
        return False, f"not committed, the calibration in force stays: {exc}", {}


def _abort(calibrator: SessionHost, device: str, method: str | None) -> tuple[bool, str, dict[str, Any]]:
    collection = calibrator.collections.get(device)
    if collection is None or not collection.session:
        return False, "no session to abort", {}
    del calibrator.collections[device]
    return True, "session aborted; the calibration in force stays", {}


ACTIONS: dict[str, Action] = {"start": _start, "status": _status, "commit": _commit, "abort": _abort}
