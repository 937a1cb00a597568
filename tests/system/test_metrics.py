"""Prometheus metrics: edge, calibrator, compass and dashboard each serve ``--metrics HOST:PORT``; a text-format
scrape of each parses with prometheus-client's own parser, and its counters move as the pipeline runs (samples in,
headings out, calibrations, devices, latency). The families of a status map are checked without a process too."""

from __future__ import annotations

import time
import urllib.request

import pytest
from helpers import NO_SCOUT, connect_args, free_ports, listen_args, wait_for
from prometheus_client.parser import text_string_to_metric_families

from services.common.metrics import families, parse_address

LOCATION = "50.45,30.52"


def scrape(port: int) -> dict[tuple[str, tuple[tuple[str, str], ...]], float]:
    """(sample name, sorted labels) -> value, parsed by prometheus-client's text parser."""
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=5) as reply:
        assert reply.headers["Content-Type"].startswith("text/plain")
        text = reply.read().decode()
    return {
        (s.name, tuple(sorted(s.labels.items()))): s.value
        for family in text_string_to_metric_families(text)
        for s in family.samples
    }


def value(samples, name, **labels) -> float:
    return samples.get((name, tuple(sorted(labels.items()))), 0.0)


@pytest.mark.integration
def test_each_service_serves_metrics_that_parse_and_move(procs, tmp_path):
    cal, comp, edge, dash, m_cal, m_comp, m_edge, m_dash, http = free_ports(9)
    procs.start("calibrator", "calibrator", "--db", str(tmp_path / "c.db"), *listen_args(cal), "--metrics",
                f"127.0.0.1:{m_cal}")  # fmt: skip
    procs.start("compass", "compass", "--location", LOCATION, *listen_args(comp), *connect_args(cal), "--metrics",
                f"127.0.0.1:{m_comp}")  # fmt: skip
    procs.start("edge", "edge", "--emulate", "--devices", "3", "--device", "m", "--rate", "50", "--speedup", "10",
                "--location", LOCATION, *listen_args(edge), *connect_args(cal, comp), "--metrics",
                f"127.0.0.1:{m_edge}")  # fmt: skip
    procs.start("dashboard", "dashboard", "--http", f"127.0.0.1:{http}", "--location", LOCATION, *NO_SCOUT,
                "--listen", f"tcp/127.0.0.1:{dash}", *connect_args(cal, comp, edge), "--metrics",
                f"127.0.0.1:{m_dash}")  # fmt: skip

    def flowing(port, name, **labels):
        try:
            samples = scrape(port)
        except OSError:
            return None
        return samples if value(samples, name, **labels) > 0 else None

    first = {
        "edge": wait_for(lambda: flowing(m_edge, "magnet_samples_received_total", service="edge"), 30, "edge"),
        "calibrator": wait_for(
            lambda: flowing(m_cal, "magnet_samples_received_total", service="calibrator"), 30, "calibrator"
        ),
        "compass": wait_for(lambda: flowing(m_comp, "magnet_headings_published_total", service="compass"), 30, "c"),
        "dashboard": wait_for(lambda: flowing(m_dash, "magnet_batches_received_total", service="dashboard"), 30, "d"),
    }
    time.sleep(2)
    again = {
        "edge": scrape(m_edge),
        "calibrator": scrape(m_cal),
        "compass": scrape(m_comp),
        "dashboard": scrape(m_dash),
    }
    for service, name in (
        ("edge", "magnet_samples_received_total"),
        ("calibrator", "magnet_samples_received_total"),
        ("compass", "magnet_samples_received_total"),
        ("compass", "magnet_headings_published_total"),
        ("dashboard", "magnet_batches_received_total"),
    ):
        before, after = value(first[service], name, service=service), value(again[service], name, service=service)
        assert after > before > 0, (service, name, before, after)
    assert value(again["edge"], "magnet_healthy", service="edge") == 1.0
    assert value(again["edge"], "magnet_devices", service="edge", state="all") == 3
    assert value(again["compass"], "magnet_latency_seconds_count", service="compass") > 0
    assert value(again["dashboard"], "magnet_latency_seconds_count", service="dashboard") > 0
    assert (
        0
        < value(again["compass"], "magnet_latency_seconds_sum", service="compass")
        / value(again["compass"], "magnet_latency_seconds_count", service="compass")
        < 5.0
    )  # seconds from a sample to its heading, on average

    def calibrated():
        samples = scrape(m_cal)
        return samples if value(samples, "magnet_devices", service="calibrator", state="calibrated") == 3 else None

    done = wait_for(calibrated, 60, "the calibrator's metrics to count three calibrated devices")
    assert value(done, "magnet_calibrations_total", service="calibrator", result="stored") >= 3
    assert value(done, "magnet_calibrations_total", service="calibrator", result="accepted") >= 3
    for name in ("calibrator", "compass", "edge", "dashboard"):
        assert procs.alive(name), procs.log(name)[-2000:]


def test_the_families_of_a_status_map_and_bad_addresses():
    status = {
        "service": "compass",
        "received_samples": 1200,
        "received_batches": 120,
        "published_batches": 118,
        "dropped": {"bad-key": 2, "truncated": 1},
        "devices": {"calibrated": 3},
        "alerts_open": {"field_strength": 1},
    }
    names = {(f.name, tuple(s.labels.items()), s.value) for f in families("compass", status) for s in f.samples}
    assert ("magnet_headings_published", (("service", "compass"),), 118.0) in {(n, lab, v) for n, lab, v in names}
    assert any(n == "magnet_dropped" and ("cause", "bad-key") in lab and v == 2 for n, lab, v in names)
    assert any(n == "magnet_alerts_open" and ("kind", "field_strength") in lab and v == 1 for n, lab, v in names)
    assert parse_address("127.0.0.1:9464") == ("127.0.0.1", 9464) and parse_address("[::1]:80") == ("::1", 80)
    for bad in ("9464", "host:", ":80", "h:99999"):
        with pytest.raises(ValueError, match="--metrics"):
            parse_address(bad)


def test_a_vehicle_report_becomes_gauges_per_compass():
    compasses = [
        {"device": "mav1-mag0", "verdict": "reference", "angle_deg": 0.0, "residual_ut": 0.0},
        {"device": "mav1-mag2", "verdict": "interference", "angle_deg": 9.9, "interference_pct": 34.4},
    ]
    status = {"service": "compass", "vehicles": {"mav1": {"anomaly": False, "compasses": compasses}}}
    samples = {
        (f.name, tuple(sorted(s.labels.items())), s.value) for f in families("compass", status) for s in f.samples
    }
    where = (("device", "mav1-mag2"), ("service", "compass"), ("vehicle", "mav1"))
    assert ("magnet_vehicle_interference_percent", where, 34.4) in samples
    assert ("magnet_vehicle_verdict", (*where[:2], ("vehicle", "mav1"), ("verdict", "interference")), 1.0) in {
        (n, tuple(sorted(lab)), v) for n, lab, v in samples
    }
    assert ("magnet_vehicle_anomaly", (("service", "compass"), ("vehicle", "mav1")), 0.0) in samples


def test_the_grafana_dashboard_queries_only_metrics_the_services_expose():
    import json
    import re
    from pathlib import Path

    from services.common import metrics

    dashboard = json.loads((Path(__file__).resolve().parents[2] / "deploy" / "grafana-magnet.json").read_text())
    exposed = set(re.findall(r"``(magnet_\w+)``", metrics.__doc__ or ""))
    queried = {
        re.sub(r"_bucket$", "", name)
        for panel in dashboard["panels"]
        for target in panel["targets"]
        for name in re.findall(r"magnet_\w+", target["expr"])
    }
    assert queried and queried <= exposed, queried - exposed
    assert len({p["id"] for p in dashboard["panels"]}) == len(dashboard["panels"])


def test_the_compass_ros2_sides_topics_and_evictions_are_metrics():
    """Issue 32: ROS 2 topic evictions counted in the status and the metrics."""
    status = {"service": "compass", "sinks": {"ros2_topics": 256, "ros2_topics_evicted": 69}}
    samples = {(f.name, s.name, s.value) for f in families("compass", status) for s in f.samples}
    assert ("magnet_ros2_devices", "magnet_ros2_devices", 256.0) in samples
    assert ("magnet_ros2_topics_evicted", "magnet_ros2_topics_evicted_total", 69.0) in samples
