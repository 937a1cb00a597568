"""``--metrics`` under idle connections (issue 32: a thread per connection and no timeout; under a 1,024-file limit
normal scrapes timed out). A service run with a file limit of 256 is held 300 idle connections open, then scraped:
answered within 1 s; a silent connection is closed after its head timeout. The server alone is checked without a
process too (``services.common.metrics_http``)."""

from __future__ import annotations

import contextlib
import resource
import socket
import subprocess
import time
import urllib.request

import pytest
from helpers import MAGNET, NO_SCOUT, REPO_ROOT, wait_for

from services.common import metrics_http
from services.common.metrics import ServiceMetrics
from services.common.processes import stop_processes
from services.common.zenoh_session import free_ports

FILE_LIMIT = 256


def _limit_files() -> None:
    resource.setrlimit(resource.RLIMIT_NOFILE, (FILE_LIMIT, FILE_LIMIT))


def scrape(port: int, timeout_s: float) -> str:
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=timeout_s) as reply:
        return reply.read().decode()


@pytest.mark.integration
def test_idle_connections_past_the_file_limit_do_not_stop_a_scrape(tmp_path):
    zenoh_port, metrics_port = free_ports(2)
    with open(tmp_path / "edge.log", "w") as log:
        edge = subprocess.Popen(
            [*MAGNET, "edge", "--emulate", "--devices", "1", "--rate", "10", *NO_SCOUT,
             "--listen", f"tcp/127.0.0.1:{zenoh_port}", "--metrics", f"127.0.0.1:{metrics_port}"],
            stdout=log, stderr=subprocess.STDOUT, cwd=REPO_ROOT, preexec_fn=_limit_files,
        )  # fmt: skip
        idle: list[socket.socket] = []
        try:
            wait_for(lambda: _answers(metrics_port), 30, "the edge's metrics")
            for _ in range(FILE_LIMIT + 44):  # each would have been a thread and a file in the edge until it ended
                with contextlib.suppress(OSError):
                    idle.append(socket.create_connection(("127.0.0.1", metrics_port), timeout=2))
            for sock in idle[:10]:
                sock.sendall(b"GET /metrics HTTP/1.1\r\n")  # a head begun and never finished (slowloris)
            time.sleep(0.5)
            started = time.monotonic()
            text = scrape(metrics_port, timeout_s=5)
            took = time.monotonic() - started
            assert "magnet_samples_received_total" in text
            assert took < 1.0, f"a scrape behind {len(idle)} idle connections took {took:.2f} s"
            assert edge.poll() is None
        finally:
            for sock in idle:
                sock.close()
            stop_processes([edge])


def _answers(port: int) -> bool:
    try:
        return bool(scrape(port, timeout_s=2))
    except OSError:
        return False


@pytest.mark.integration
def test_the_oldest_idle_connection_makes_room_and_a_silent_one_is_closed(monkeypatch):
    monkeypatch.setattr(metrics_http, "HEAD_TIMEOUT_S", 1.0)
    service = ServiceMetrics("test", lambda: {"service": "test", "received_samples": 5})
    server = metrics_http.MetricsServer("127.0.0.1", 0, service.registry, max_connections=8)
    try:
        idle = [socket.create_connection(("127.0.0.1", server.port), timeout=5) for _ in range(12)]
        assert "magnet_samples_received_total" in scrape(server.port, timeout_s=5)
        closed = sum(sock.recv(1) == b"" for sock in idle[:5])  # the oldest were closed to admit newer ones
        assert closed == 5 and server.closed_oldest >= 5
        assert idle[-1].recv(1) == b""  # the newest, silent, closed after the head timeout
        with socket.create_connection(("127.0.0.1", server.port), timeout=5) as other:
            other.sendall(b"GET /elsewhere HTTP/1.1\r\nHost: x\r\n\r\n")
            assert other.recv(100).startswith(b"HTTP/1.1 404")
        for sock in idle:
            sock.close()
    finally:
        server.close()
