"""Issue 32: the calibrator's ``--metrics`` built its status on the metrics server's thread, reading the calibrator's
state while its loop changed it. A real calibrator (``run``, in this process so its threads can be watched) on
loopback, scraped several times: its status is only ever made on the loop's thread, and what is served parses."""

from __future__ import annotations

import argparse
import threading
from pathlib import Path
from typing import Any

import pytest
from helpers import NO_SCOUT, free_ports, wait_for
from test_metrics import scrape, value

from services.calibrator import service
from services.common import metrics

pytestmark = pytest.mark.integration


def test_calibrator_metrics_are_read_from_the_board_never_made_off_the_loop(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    stop = threading.Event()
    monkeypatch.setattr(service, "stop_event", lambda: stop)
    made_on: set[str] = set()
    status = service.Calibrator.status

    def watched_status(self: Any, name: str) -> Any:
        made_on.add(threading.current_thread().name)
        return status(self, name)

    monkeypatch.setattr(service.Calibrator, "status", watched_status)
    zport, mport = free_ports(2)
    parser = argparse.ArgumentParser()
    service.add_arguments(parser)
    args = ["--db", str(tmp_path / "c.db"), *NO_SCOUT, "--listen", f"tcp/127.0.0.1:{zport}"]
    settings = service.settings_from_args(parser.parse_args(args))
    loop = threading.Thread(target=service.run, args=(settings, f"127.0.0.1:{mport}"), name="calibrator-loop")
    loop.start()
    try:

        def scraped() -> dict | None:
            try:
                return scrape(mport)
            except OSError:
                return None

        samples = wait_for(scraped, 30, "the calibrator's metrics")
        for _ in range(5):
            samples = scrape(mport)
        assert ("magnet_devices", (("service", "calibrator"), ("state", "collecting"))) in samples
        assert value(samples, "magnet_batches_received_total", service="calibrator") == 0.0
    finally:
        stop.set()
        loop.join(15)
        if metrics._CURRENT is not None:
            metrics._CURRENT.close()
            metrics._CURRENT = None
    assert not loop.is_alive()
    assert made_on == {"calibrator-loop"}, made_on
