"""The devices a compass has not heard of for a while: their filters forgotten (docs/front-door.md, "Memory per
service").

A device's filter (``filters.DeviceFilter``: vqf's state, its history of the last 30 s of batches for the drift fit,
its first-heading take, an aided filter's recent samples; 60-250 kB a device) starts again anyway on a batch that
comes more than ``filters.MAX_GAP_S`` after its last sample. Kept for a device that stopped, it only held memory until
``--max-devices`` newer devices pushed it out: every edge restarted with new ids (an app reinstalled, the soak's edge
every third round) left its devices' filters behind, about 1.4 MB for 10 devices each time. So a device not heard of
for ``SILENT_S`` (the wall clock a step is given) has its filter dropped; its next batch, if one ever comes, starts a
filter as after any gap. What outlives a gap stays: its record in force, drift tracker, place and vehicle window
(bounded by ``--max-devices`` as before).

Pure; no clock: ``now_ns`` is given.
"""

from __future__ import annotations

from collections.abc import Iterable

from magnet.bounded import Recent

#: seconds without a batch after which a device's filter is forgotten: far beyond any gap a filter survives (0.5 s),
#: and longer than a router's restart or a backlog, so that a device that sends goes on with its filter
SILENT_S = 60.0


class Silence:
    """When each device was last heard of (ns, the wall clock), at most ``max_devices`` (the least recently heard
    forgotten first, as every other per-device table); ``forgotten`` counts the devices found silent."""

    def __init__(self, max_devices: int, silent_s: float = SILENT_S) -> None:
        if not silent_s > 0:
            raise ValueError(f"the silence after which a device is forgotten must be > 0 s, got {silent_s!r}")
        self.heard_ns: Recent[str, int] = Recent(max_devices)
        self.silent_ns = int(silent_s * 1e9)
        self.forgotten = 0

    def heard(self, devices: Iterable[str], now_ns: int) -> list[str]:
        """Note ``devices`` as heard of at ``now_ns``; the devices not heard of for ``silent_s`` before it, least
        recently heard first (each given once, then no longer noted)."""
        heard = self.heard_ns
        for device in devices:
            heard[device] = now_ns
        silent = []
        for device, last_ns in heard.items():
            if now_ns - last_ns < self.silent_ns:
                break
            silent.append(device)
        for device in silent:
            del heard[device]
        self.forgotten += len(silent)
        return silent
