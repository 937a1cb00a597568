"""``magnet edge --mavlink URL``: the magnetometers of MAVLink vehicles (pymavlink connection; the conversion is
``magnet.autopilot.mavlink_stream``). One device per vehicle and compass instance, ``<prefix><SYSID>-mag<N>``, appearing
as their vehicles send; a vehicle silent for ``--vehicle-timeout`` seconds turns its devices unhealthy (the edge's
unhealthy token per device, as for a dead bus) until it sends again; a device with no sample for ``--forget-after``
seconds is forgotten (its tokens withdrawn, its place under ``--max-port-devices`` and ``--max-devices`` free).
Bytes that are not MAVLink and messages magnet cannot use are dropped and counted (status ``reads.dropped``), with one
log line per cause. The id of the sensor behind each compass instance is asked of the vehicle (PARAM_REQUEST_READ of
ArduPilot's COMPASS_DEV_ID.., PX4's CAL_MAGn_ID, at first contact and after a reboot) and sent with every batch
(status ``reads.hardware_ids``; docs/mavlink.md)."""

from __future__ import annotations

import logging
import time
from collections.abc import Iterator
from typing import Any

import zenoh
from pymavlink import mavutil

from magnet import wire
from magnet.autopilot import mavlink
from magnet.autopilot.mavlink_stream import MavlinkStream
from services.common.allocator import give_back_now
from services.edge.settings import EdgeSettings
from services.edge.source import DeviceEvents, Stop, ticked

log = logging.getLogger("magnet.edge")

#: how long one call waits for messages before it returns what is due (so the edge checks for stop often)
POLL_S = 0.05
#: messages read at most per call
MAX_MESSAGES = 2000
#: the freed heap is given back to the system this often (s): a flood of ids leaves it fragmented
TRIM_S = 10.0
#: the addresses a UDP server link (``udpin``) remembers at most, the latest senders (its parameter reads go to them)
MAX_UDP_CLIENTS = 16


def shed_link_state(connection: Any) -> None:
    """Drop what pymavlink keeps per sender and magnet never reads (``MavlinkStream`` keeps what it uses): per system
    id, the last message of every type and instance (``sysid_state``: two copies per HIGHRES_IMU id, 40,000 messages
    and 40 MB after one flood of 20,000 (system id, id) pairs, 65,280 pairs possible); per (system, component) the
    last sequence number (``last_seq``) and every PARAM_VALUE by name (``param_state``: any names a sender makes up);
    of a UDP server link, every address that ever sent (``clients``: the latest ``MAX_UDP_CLIENTS`` kept). Called
    after each read, so at most one read's messages (``MAX_MESSAGES``) are held."""
    states = connection.sysid_state
    if len(states) > 1 or any(len(state.messages) > 2 for state in states.values()):  # a fresh one holds MAV, HOME
        connection.sysid_state = {connection.sysid: mavutil.mavfile_state()}
    connection.last_seq.clear()
    if len(connection.param_state) > 1 or any(state.params for state in connection.param_state.values()):
        connection.param_state = {connection.param_sysid: mavutil.param_state()}
    clients = getattr(connection, "clients", None)
    if clients is not None and len(clients) > MAX_UDP_CLIENTS:
        alive = connection.clients_last_alive
        latest = sorted(clients, key=lambda address: alive.get(address, 0.0))[-MAX_UDP_CLIENTS:]
        connection.clients = set(latest)
        connection.clients_last_alive = {address: alive[address] for address in latest if address in alive}


class MavlinkStats:
    """The status's ``reads``: messages, samples, drops by cause, resyncs, vehicles and their health, the devices
    whose gyroscope reads exactly zero while the field turns (``gyro_absent``: sent without one)."""

    def __init__(self, stream: MavlinkStream) -> None:
        self.stream = stream
        self.healthy = True

    def as_dict(self) -> dict[str, Any]:
        counts = self.stream.counts
        dropped = {k.split(":", 1)[1]: v for k, v in counts.items() if k.startswith("dropped:")}
        return {
            "healthy": self.healthy,
            "attempts": counts["messages"],
            "errors": sum(dropped.values()),
            "last_error": self.stream.last_error,
            "samples": counts["samples"],
            "ignored": counts["ignored"],
            "resyncs": counts["resyncs"],
            "dropped": dropped,
            "vehicles": sorted(self.stream.vehicles),
            "gyro_absent": self.stream.gyro_absent,
            "hardware_ids": self.stream.hardware_ids(),
            "id_timeouts": counts["id-timeouts"],
            "forgotten": counts["forgotten"],
        }


class MavlinkSource:
    """The vehicles on one MAVLink connection (a ``services.edge.source.Source``); ``attach`` gives it the edge's
    events, through which each new device's liveliness token and each health change is declared. It paces itself:
    each step waits up to ``POLL_S`` for messages."""

    def __init__(self, settings: EdgeSettings) -> None:
        if not settings.mavlink:
            raise ValueError("a MAVLink source needs --mavlink URL")
        self.settings = settings
        self.stream = MavlinkStream(
            settings.device_prefix,
            settings.batch,
            max_devices=settings.max_port_devices,
            forget_ns=int(settings.forget_after_s * 1e9),
        )
        self.stats = MavlinkStats(self.stream)
        self.ids: list[str] = []
        self.events: DeviceEvents | None = None
        self.healthy: dict[str, bool] = {}
        self.logged: set[str] = set()
        self.trimmed_s = time.monotonic()
        try:
            self.connection = mavutil.mavlink_connection(
                settings.mavlink, baud=settings.baud, source_system=255, robust_parsing=True, dialect="common"
            )
        except Exception as exc:  # pymavlink raises what its transport raises (OSError, OverflowError, ...)
            raise ValueError(f"--mavlink {settings.mavlink}: cannot open it: {exc}") from None

    def attach(self, session: zenoh.Session, events: DeviceEvents) -> None:
        self.events = events

    def status(self) -> dict[str, Any]:
        return self.stats.as_dict()

    def close(self) -> None:
        self.connection.close()

    def batches(self, stop: Stop) -> Iterator[list[wire.RawBatch]]:
        return ticked(self.take, 0.0, stop)

    def take(self, seq: int, end_ns: int, stop: Stop) -> list[wire.RawBatch]:
        """The batches due after reading what arrived within ``POLL_S`` (numbered by their device's stream)."""
        deadline = time.monotonic() + POLL_S
        for _ in range(MAX_MESSAGES):
            if stop():
                break
            message = self.connection.recv_match(blocking=True, timeout=max(deadline - time.monotonic(), 0.0))
            if message is None:
                break
            self._feed(message)
            if time.monotonic() >= deadline:
                break
        now = time.time_ns()
        self._ask(now)
        out = self.stream.take(now, flush=stop())
        self._devices_and_health(now)
        shed_link_state(self.connection)
        if time.monotonic() - self.trimmed_s >= TRIM_S:
            self.trimmed_s = time.monotonic()
            give_back_now()
        return out

    def _ask(self, now_ns: int) -> None:
        """Send the parameter reads the stream wants (its vehicles' compass ids); a link that cannot send is logged
        once (the samples then go out without ids)."""
        for sysid, compid, name in self.stream.requests(now_ns):
            try:
                self.connection.mav.param_request_read_send(sysid, compid, name.encode(), -1)
            except OSError as exc:
                if "ask" not in self.logged:
                    self.logged.add("ask")
                    log.warning("cannot ask vehicle %d for %s (%s): compasses go without ids", sysid, name, exc)

    def _feed(self, message: Any) -> None:
        try:
            fields = mavlink.message_dict(message)
        except Exception as exc:  # a message pymavlink could not unpack: counted like garbage
            fields = {"mavpackettype": "BAD_DATA", "sysid": 0, "error": str(exc)}
        cause = self.stream.feed(fields, time.time_ns())
        if cause is not None and cause not in self.logged:
            self.logged.add(cause)
            log.warning("dropping MAVLink input (%s): %s; further ones only counted", cause, self.stream.last_error)

    def _devices_and_health(self, now_ns: int) -> None:
        for device in self.stream.take_forgotten():
            self.healthy.pop(device, None)
            self.logged.discard(f"gyro:{device}")  # said again if it comes back without one
            if device in self.ids:
                self.ids.remove(device)
            log.info("MAVLink device %s forgotten: silent %g s", device, self.settings.forget_after_s)
            if self.events is not None:
                self.events.device_gone(device)
        timeout_ns = int(self.settings.vehicle_timeout_s * 1e9)
        for device, healthy in self.stream.health(now_ns, timeout_ns).items():
            if device not in self.healthy:
                self.ids.append(device)
                log.info("MAVLink device %s appeared", device)
                if self.events is not None:
                    self.events.device_seen(device)
            if self.healthy.get(device) != healthy:
                self.healthy[device] = healthy
                if not healthy:
                    log.warning("MAVLink device %s: its vehicle stopped sending", device)
                if self.events is not None:
                    self.events.device_health(device, healthy)
        self.stats.healthy = all(self.healthy.values())
        for device in self.stream.gyro_absent:
            if f"gyro:{device}" not in self.logged:
                self.logged.add(f"gyro:{device}")
                log.warning(
                    "MAVLink device %s: its gyroscope reads exactly zero while the field turns (no IMU beside this "
                    "compass): sent without a gyroscope (status reads.gyro_absent)",
                    device,
                )
