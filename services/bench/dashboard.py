"""``magnet bench dashboard [--devices 1000] [--seconds 10]``: the dashboard under a fleet's headings.

A publisher process puts a heading message for every device 10 times a second (5 samples each, with liveliness
tokens for all devices) straight to a ``magnet dashboard`` process, on 127.0.0.1 with explicit ports and multicast
scouting off. Measured over ``seconds`` after a warm-up: the dashboard's CPU (user + system time of its process, in %
of one core), the publisher's achieved rate, and what a page sees: headless chromium (when /usr/bin/chromium and
playwright are there) reporting its event rate, rows updated per second, render time and how old the headings it
shows are; otherwise a plain event-stream client reports the same without rendering.
"""

from __future__ import annotations

import contextlib
import json
import os
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path
from typing import Any

from services.common.zenoh_session import free_ports

RATE_HZ = 10.0
BATCH = 5
WARMUP_S = 5.0
STARTUP_TIMEOUT_S = 30.0
CHROMIUM = Path("/usr/bin/chromium")
CHROMIUM_ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--no-first-run",
]


def publish(port: int, devices: int, seconds: float) -> None:
    """Put ``devices`` heading messages every 1 / RATE_HZ s for ``seconds`` (run in its own process)."""
    import numpy as np
    import zenoh

    from magnet import wire

    conf = zenoh.Config()
    conf.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    names = [f"bench-{i:04d}" for i in range(devices)]
    samples = devices * BATCH
    nan3 = np.full((samples, 3), np.nan)
    field = np.tile([19.0, 0.0, 47.0], (samples, 1))
    zeros, ones = np.zeros(samples), np.ones(samples, dtype=np.int64)
    base = np.repeat(np.arange(devices) * 7.0, BATCH)
    with contextlib.ExitStack() as declared:
        session = declared.enter_context(zenoh.open(conf))
        for n in names:
            declared.enter_context(session.liveliness().declare_token(wire.liveliness_key("magnet", "device", n)))
        keys = [wire.key("magnet", n, wire.Kind.HEADING) for n in names]
        started, sent, tick = time.monotonic(), 0, 0
        while time.monotonic() - started < seconds:
            t_ns = np.tile(time.time_ns() - np.arange(BATCH)[::-1] * int(1e9 / RATE_HZ / BATCH), devices)
            columns = wire.RawColumns(
                names, [tick] * devices, np.full(devices, BATCH), t_ns, field, nan3, nan3, [""] * devices
            )
            heading = (base + tick * 3.0) % 360.0
            payloads = wire.encode_headings(
                columns, heading, (heading + 8.0) % 360.0, zeros, zeros, field, ones, 8.0, ["bench"] * devices
            )
            for key, payload in zip(keys, payloads):
                session.put(key, payload)
            sent += devices
            tick += 1
            time.sleep(max(0.0, started + tick / RATE_HZ - time.monotonic()))
        print(json.dumps({"sent": sent, "seconds": time.monotonic() - started}), flush=True)


def _cpu_s(pid: int) -> float:
    """User + system CPU seconds of a process (Linux /proc)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _wait_http(url: str, proc: subprocess.Popen) -> None:
    deadline = time.monotonic() + STARTUP_TIMEOUT_S
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise OSError("the dashboard stopped at start")
        try:
            with urllib.request.urlopen(url, timeout=1):
                return
        except OSError:
            time.sleep(0.2)
    raise OSError(f"the dashboard did not answer at {url}")


def _browser_figures(url: str, devices: int, seconds: float) -> dict[str, Any]:
    from playwright.sync_api import sync_playwright

    with sync_playwright() as playwright:
        browser = playwright.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS)
        try:
            page = browser.new_page(viewport={"width": 1500, "height": 950})
            page.goto(url, wait_until="commit", timeout=60_000)
            page.wait_for_function(f"document.querySelectorAll('#fleet-body tr').length >= {devices}", timeout=60_000)
            start = page.evaluate("({...window.magnetStats, window: undefined})")
            time.sleep(seconds)
            end = page.evaluate("({...window.magnetStats, window: undefined})")
            shown = page.evaluate("document.querySelectorAll('#fleet-body tr').length")
            lag = page.evaluate("""() => { const out = []; const now = Date.now();
                for (const row of window.magnetRows.values()) if (row.t_ms) out.push(now - row.t_ms);
                out.sort((a, b) => a - b); return out.length ? [out[Math.floor(out.length / 2)],
                out[Math.floor(out.length * 0.99)]] : null; }""")
        finally:
            browser.close()
    span = seconds
    return {
        "client": "chromium",
        "events_per_s": (end["events"] - start["events"]) / span,
        "rows_per_s": (end["rowsApplied"] - start["rowsApplied"]) / span,
        "renders_per_s": (end["renders"] - start["renders"]) / span,
        "render_ms": end["renderMs"],
        "rows_shown": shown,
        "age_ms_p50_p99": lag,
    }


def _stream_figures(url: str, seconds: float) -> dict[str, Any]:
    """A plain event-stream client: events and rows per second, age of the newest heading of each row."""
    events = rows = 0
    ages: list[float] = []
    deadline = time.monotonic() + seconds
    with urllib.request.urlopen(url, timeout=10) as stream:
        for line in stream:
            if time.monotonic() >= deadline:
                break
            if line.startswith(b"data: "):
                message = json.loads(line[6:])
                events += 1
                rows += len(message.get("rows", []))
                now_ms = time.time() * 1000
                ages += [now_ms - r["t_ms"] for r in message.get("rows", []) if r.get("t_ms")]
    ages.sort()
    return {
        "client": "event stream (no browser)",
        "events_per_s": events / seconds,
        "rows_per_s": rows / seconds,
        "age_ms_p50_p99": [ages[len(ages) // 2], ages[int(len(ages) * 0.99)]] if ages else None,
    }


def run_dashboard_benchmark(devices: int = 1000, seconds: float = 10.0) -> str:
    zenoh_port, http_port = free_ports(2)
    magnet = [sys.executable, "-m", "services.cli"]
    log_path = Path(tempfile.gettempdir()) / "magnet-bench-dashboard.log"
    with open(log_path, "w") as log:  # the child keeps its own descriptor
        dashboard = subprocess.Popen(
            [
                *magnet,
                "dashboard",
                "--http",
                f"127.0.0.1:{http_port}",
                "--token",
                "bench",
                "--no-multicast-scouting",
                "--listen",
                f"tcp/127.0.0.1:{zenoh_port}",
            ],
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            stderr=log,
        )
    publisher = None
    try:
        _wait_http(f"http://127.0.0.1:{http_port}/api/fleet", dashboard)
        publisher = subprocess.Popen(
            [
                sys.executable,
                "-c",
                (f"import sys; from services.bench.dashboard import publish; publish({zenoh_port}, {devices}, 3600)"),
            ],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        time.sleep(WARMUP_S)
        cpu0, t0, received0 = _cpu_s(dashboard.pid), time.monotonic(), _fleet(http_port)["summary"]["messages"]
        use_browser = CHROMIUM.exists()
        try:
            page = (
                _browser_figures(f"http://127.0.0.1:{http_port}/", devices, seconds)
                if use_browser
                else _stream_figures(f"http://127.0.0.1:{http_port}/api/stream", seconds)
            )
        except ImportError:
            page = _stream_figures(f"http://127.0.0.1:{http_port}/api/stream", seconds)
        fleet = _fleet(http_port)
        span = time.monotonic() - t0
        cpu = (_cpu_s(dashboard.pid) - cpu0) / span
        received = (fleet["summary"]["messages"] - received0) / span
    finally:
        for proc in (publisher, dashboard):
            if proc is not None and proc.poll() is None:
                proc.terminate()
        for proc in (publisher, dashboard):
            if proc is not None:
                proc.wait(timeout=10)
    return _summary(devices, cpu, page, fleet, received)


def _fleet(http_port: int) -> dict[str, Any]:
    with urllib.request.urlopen(f"http://127.0.0.1:{http_port}/api/fleet", timeout=30) as answer:
        return json.loads(answer.read())


def _summary(devices: int, cpu: float, page: dict[str, Any], fleet: dict[str, Any], received: float) -> str:
    age = page.get("age_ms_p50_p99")
    lines = [
        (
            f"dashboard bench: {devices} devices x {RATE_HZ:g} Hz headings ({BATCH} samples each); "
            f"the dashboard received {received:,.0f} messages/s (target {devices * RATE_HZ:,.0f})"
        ),
        (
            f"  dashboard process CPU: {100 * cpu:.0f} % of one core; fleet rows: {len(fleet['rows'])}, "
            f"alive {fleet['summary']['alive']}"
        ),
        f"  page ({page['client']}): {page['events_per_s']:.1f} events/s, {page['rows_per_s']:,.0f} rows/s"
        + (
            f", {page['renders_per_s']:.1f} renders/s, last render {page['render_ms']:.0f} ms"
            if "renders_per_s" in page
            else ""
        )
        + (f"; age of the headings shown p50 {age[0]:.0f} ms, p99 {age[1]:.0f} ms" if age else "")
        + (f"; {page['rows_shown']} rows in the table" if "rows_shown" in page else ""),
    ]
    return "\n".join(lines)
