"""Issue 32: the dashboard's ``--metrics`` built its counts (messages, drops, devices by state, alerts) on the metrics
server's thread, walking every row under the table's lock beside the ingest that changes them. Now the ingest thread
writes them on a board at most once a second and a scrape reads what was written, as the calibrator's and the
compass's do.

The dashboard's ``serve`` in this process (so its threads can be watched; the HTTP server stood in for by one that
waits, the rest real: session, ingest, metrics endpoint) beside an edge on loopback, scraped several times: the
counts are only ever made on the ingest's thread, and they parse."""

from __future__ import annotations

import argparse
import threading
from typing import Any

import pytest
from helpers import NO_SCOUT, free_ports, listen_args, wait_for
from test_metrics import LOCATION, scrape

from services.common import metrics
from services.dashboard import service, settings
from services.dashboard.state import FleetState

pytestmark = pytest.mark.integration


def test_dashboard_metrics_are_read_from_a_board_never_made_off_the_ingest(
    procs: Any, monkeypatch: pytest.MonkeyPatch
) -> None:
    made_on: set[str] = set()
    counts = FleetState.metrics_status

    def watched(self: FleetState) -> dict[str, Any]:
        made_on.add(threading.current_thread().name)
        return counts(self)

    monkeypatch.setattr(FleetState, "metrics_status", watched)
    stop = threading.Event()

    class Waiting:  # uvicorn's server stood in for: the page is not what is tested
        def __init__(self, config: Any, dashboard: Any) -> None:
            self.started = True

        def run(self) -> None:
            stop.wait(60)

    monkeypatch.setattr(service, "_Server", Waiting)
    edge, zport, mport, http = free_ports(4)
    procs.start("edge", "edge", "--emulate", "--devices", "2", "--device", "m", "--rate", "50", "--location", LOCATION,
                *listen_args(edge))  # fmt: skip
    parser = argparse.ArgumentParser()
    settings.add_arguments(parser)
    args = ["--http", f"127.0.0.1:{http}", "--location", LOCATION, "--token", "t", *NO_SCOUT]
    args += [
        "--listen",
        f"tcp/127.0.0.1:{zport}",
        "--connect",
        f"tcp/127.0.0.1:{edge}",
        "--metrics",
        f"127.0.0.1:{mport}",
    ]
    dashboard = settings.settings_from_args(parser.parse_args(args))
    serving = threading.Thread(target=service.serve, args=(dashboard,), name="dashboard-serve")
    serving.start()
    try:

        def devices(samples: dict) -> float:
            return sum(v for (name, labels), v in samples.items() if name == "magnet_devices" and labels)

        def seen() -> dict | None:
            try:
                samples = scrape(mport)
            except OSError:
                return None
            return samples if devices(samples) >= 2 else None  # the edge's two devices, from their tokens

        wait_for(seen, 30, "the dashboard's metrics counting the edge's devices")
        for _ in range(6):
            assert devices(scrape(mport)) >= 2
    finally:
        stop.set()
        serving.join(15)
        if metrics._CURRENT is not None:
            metrics._CURRENT.close()
            metrics._CURRENT = None
    assert not serving.is_alive()
    assert made_on == {"dashboard-ingest"}, made_on
