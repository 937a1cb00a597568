"""Issue 32: the compass's ``--metrics`` built its status (status, open alerts, vehicles' reports) on the metrics
server's thread, reading the compass's core while its loop changed it. A real compass (``run``, in this process so
its threads can be watched) on loopback, scraped several times: what it serves is only ever made on the loop's
thread (the loop writes it on a board, as the calibrator's does), and it parses."""

from __future__ import annotations

import argparse
import threading
from typing import Any

import pytest
from helpers import NO_SCOUT, free_ports, wait_for
from test_metrics import LOCATION, scrape

from services.common import metrics
from services.compass import service

pytestmark = pytest.mark.integration


def test_compass_metrics_are_read_from_a_board_never_made_off_the_loop(monkeypatch: pytest.MonkeyPatch) -> None:
    stop = threading.Event()
    monkeypatch.setattr(service, "stop_event", lambda: stop)
    made_on: set[str] = set()
    status, report = service.CompassCore.status, service.CompassCore.vehicle_report

    def watched_status(self: Any, name: str) -> Any:
        made_on.add(threading.current_thread().name)
        return status(self, name)

    def watched_report(self: Any, vehicle: str) -> Any:
        made_on.add(threading.current_thread().name)
        return report(self, vehicle)

    monkeypatch.setattr(service.CompassCore, "status", watched_status)
    monkeypatch.setattr(service.CompassCore, "vehicle_report", watched_report)

    zport, mport = free_ports(2)
    parser = argparse.ArgumentParser()
    service.add_arguments(parser)
    args = ["--location", LOCATION, *NO_SCOUT, "--listen", f"tcp/127.0.0.1:{zport}"]
    settings = service.settings_from_args(parser.parse_args(args))
    loop = threading.Thread(target=service.run, args=(settings, f"127.0.0.1:{mport}"), name="compass-loop")
    loop.start()
    try:

        def scraped() -> dict | None:
            try:
                return scrape(mport)
            except OSError:
                return None

        samples = wait_for(scraped, 30, "the compass's metrics")
        for _ in range(5):
            samples = scrape(mport)
        assert ("magnet_devices", (("service", "compass"), ("state", "calibrated"))) in samples, sorted(samples)[:20]
    finally:
        stop.set()
        loop.join(15)
        if metrics._CURRENT is not None:
            metrics._CURRENT.close()
            metrics._CURRENT = None
    assert not loop.is_alive()
    assert made_on == {"compass-loop"}, made_on
