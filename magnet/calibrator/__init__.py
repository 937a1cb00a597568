"""The calibrator's decisions, pure (no zenoh, no database, no thread, clocks injected), beside the compass's, and one
object holding them (``CalibratorCore``: ``on_raw``, ``commit``, ``session``, ``rollback``, ``status``).

- ``store``: what it asks of a store of calibrations (``CalibrationStore``, a protocol: the store's whole contract).
- ``settings``: what it reads of its settings (``Settings``, a protocol).
- ``keys``: which raw keys name a device of its shard (``ShardKeys``).
- ``collecting``: per-device sample buffers and their coverage (``Collections``).
- ``fitting``: fit and gate (``Fitter``).
- ``signatures`` and ``records``: a record signed once, when made; the records in force (``Records``).
- ``sessions`` and ``rollback``: an operator's actions.
- ``roster`` and ``roster_reply``: where each device is, last seen, open alerts; the ``@fleet`` answer.
- ``progress`` and ``status``: what it says about a device and about itself.
- ``core``: ``CalibratorCore`` holding those parts.

The process (Zenoh session, raw intake, lease tokens, the SQLite store, queryables, options) is
``services.calibrator``; see docs/calibrator.md.
"""

from magnet.calibrator.core import CalibratorCore, Publish
from magnet.calibrator.settings import Settings
from magnet.calibrator.status import CalibratorStatus, State
from magnet.calibrator.store import CalibrationStore

__all__ = ["CalibrationStore", "CalibratorCore", "CalibratorStatus", "Publish", "Settings", "State"]
