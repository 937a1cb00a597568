"""Issue 32: a service's status is answered from Zenoh's thread, but behind a router every message reaches the
service on one link, read by one task: when the pump that empties the raw channel is starved of CPU, the channel
fills, that task blocks on it, and a status query behind the raw messages waits with them (a soak at load 7-8: one
status of 258 unanswered after a flood). Behind a router (client mode) the calibrator and the compass answer their
status on a session of their own (``zenoh_session.queries_session``): its own link, never behind a raw message.

A real router; the service (``run``, in this process) as its client, its pump held (standing for a starved CPU)
while 2,000 raw messages arrive, more than the channel holds: the status is still answered at once."""

from __future__ import annotations

import argparse
import threading
import time
from pathlib import Path
from types import ModuleType
from typing import Any

import pytest
import zenoh
from helpers import NO_SCOUT, free_ports, wait_for

from magnet import wire
from services.calibrator import intake as calibrator_intake
from services.calibrator import service as calibrator_service
from services.common.zenoh_session import ZenohSettings, open_session
from services.compass import intake as compass_intake
from services.compass import service as compass_service

pytestmark = pytest.mark.integration

#: each service: its module, the intake class whose pump empties the raw channel, its arguments but Zenoh's
SERVICES: dict[str, tuple[ModuleType, type, list[str]]] = {
    "calibrator": (calibrator_service, calibrator_intake.RawIntake, ["--db", "{tmp}/c.db"]),
    "compass": (compass_service, compass_intake.PayloadIntake, ["--location", "50.45,30.52"]),
}


@pytest.mark.parametrize("name", sorted(SERVICES))
def test_a_status_is_answered_while_the_raw_channel_is_full(
    name: str, procs: Any, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    service, intake, own_args = SERVICES[name]
    stop, release = threading.Event(), threading.Event()
    monkeypatch.setattr(service, "stop_event", lambda: stop)
    pump = intake.pump

    def held_pump(self: Any, *args: Any, **kwargs: Any) -> None:
        release.wait()  # the pump gets no CPU until released: the raw channel fills
        pump(self, *args, **kwargs)

    monkeypatch.setattr(intake, "pump", held_pump)
    (port,) = free_ports(1)
    procs.start("router", "router", "--listen", f"tcp/127.0.0.1:{port}", *NO_SCOUT)
    client = ZenohSettings(mode="client", connect=(f"tcp/127.0.0.1:{port}",), no_multicast_scouting=True)
    parser = argparse.ArgumentParser()
    service.add_arguments(parser)
    args = [a.format(tmp=tmp_path) for a in own_args]
    args += [*NO_SCOUT, "--mode", "client", "--connect", f"tcp/127.0.0.1:{port}"]
    settings = service.settings_from_args(parser.parse_args(args))
    loop = threading.Thread(target=service.run, args=(settings,), name=f"{name}-loop", daemon=True)
    time.sleep(0.5)  # the router listening
    loop.start()
    try:
        with open_session(client) as asker:
            key = wire.status_key(wire.DEFAULT_PREFIX, settings.name)

            def status(timeout_s: float) -> dict | None:
                for reply in asker.get(key, timeout=timeout_s):
                    if reply.ok is not None:
                        return wire.unpack(bytes(reply.ok.payload))
                return None

            wait_for(lambda: status(1.0), 30, f"the {name}'s status")
            payload = bytes(400)  # the pump is held: what the messages hold does not matter
            with asker.declare_publisher(
                f"{wire.DEFAULT_PREFIX}/flood/raw", congestion_control=zenoh.CongestionControl.DROP
            ) as publisher:
                for _ in range(2000):
                    publisher.put(payload)
            time.sleep(1.0)  # the raw channel full, the service's link behind it
            asked = time.monotonic()
            answer = status(3.0)
            took_s = time.monotonic() - asked
            assert answer is not None, "the status waited behind the raw messages"
            assert took_s < 1.0, took_s
    finally:
        release.set()
        stop.set()
        loop.join(15)
    assert not loop.is_alive()
