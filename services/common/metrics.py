"""Prometheus metrics of a service (``--metrics HOST:PORT``; ``prometheus-client``).

Each service exposes its own counters at ``http://HOST:PORT/metrics`` in the Prometheus text format. The counters
are the ones it already keeps for its status answer, read when the endpoint is scraped (nothing extra on the hot
path), plus one latency histogram fed where the time is measured:

| metric | type | labels | what |
|---|---|---|---|
| ``magnet_samples_received_total`` | counter | service | samples taken in (edge: published) |
| ``magnet_batches_received_total`` | counter | service | messages taken in |
| ``magnet_dropped_total`` | counter | service, cause | messages dropped, by cause |
| ``magnet_headings_published_total`` | counter | service | heading messages put (compass) |
| ``magnet_calibrations_total`` | counter | service, result | fits accepted / rejected / stored (calibrator) |
| ``magnet_devices`` | gauge | service, state | devices known, by calibration state where the service knows it |
| ``magnet_alerts_open`` | gauge | service, kind | open drift alerts, by cause |
| ``magnet_latency_seconds`` | histogram | service | compass: sample to heading put; dashboard: sample to arrival |
| ``magnet_read_errors_total`` | counter | service | sensor read errors (edge) |
| ``magnet_healthy`` | gauge | service | 1 when the sensor reads (edge) |
| ``magnet_vehicle_verdict`` | gauge | service, vehicle, device, verdict | 1: its verdict (compass; docs/vehicles.md) |
| ``magnet_vehicle_angle_degrees`` | gauge | service, vehicle, device | median angle to the reference compass |
| ``magnet_vehicle_interference_percent`` | gauge | service, vehicle, device | motors' field, % of the Earth's |
| ``magnet_vehicle_residual_ut`` | gauge | service, vehicle, device | what is left against the reference (uT RMS) |
| ``magnet_vehicle_anomaly`` | gauge | service, vehicle | 1: all compasses agree, |B| is off the WMM (local anomaly) |

The status of a service is read from the server's thread while the service runs: a reading that races with the
service (a dictionary changing size) is retried, and a scrape never stops the service.
"""

from __future__ import annotations

import argparse
import logging
from collections.abc import Callable, Iterator, Mapping
from typing import Any

log = logging.getLogger("magnet.metrics")

LATENCY_BUCKETS_S = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0)
Status = Callable[[], Mapping[str, Any]]


def add_metrics_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--metrics",
        metavar="HOST:PORT",
        help="serve Prometheus metrics at http://HOST:PORT/metrics (e.g. 127.0.0.1:9464; default: none)",
    )


def parse_address(text: str) -> tuple[str, int]:
    """HOST:PORT (IPv6 in brackets) -> (host, port); ValueError naming --metrics."""
    host, sep, port = text.rpartition(":")
    host = host[1:-1] if host.startswith("[") and host.endswith("]") else host
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise ValueError(f"--metrics must be HOST:PORT (e.g. 127.0.0.1:9464), got {text!r}")
    return host, int(port)


class ServiceMetrics:
    """One service's registry: counters read from ``status()`` at scrape time, and the latency histogram."""

    def __init__(self, service: str, status: Status) -> None:
        from prometheus_client import CollectorRegistry, Histogram

        self.service, self.status = service, status
        self.registry = CollectorRegistry(auto_describe=False)
        self.latency = Histogram(
            "magnet_latency_seconds",
            "compass: age of the newest sample of a drain when its headings left; dashboard: age of a heading on "
            "arrival",
            ["service"],
            buckets=LATENCY_BUCKETS_S,
            registry=self.registry,
        ).labels(service)
        self.registry.register(self)
        self.server: Any = None

    def serve(self, address: str) -> None:
        """Serve at ``address`` (``services.common.metrics_http``: bounded connections, each with a timeout)."""
        from services.common.metrics_http import MetricsServer

        host, port = parse_address(address)
        self.server = MetricsServer(host, port, self.registry)
        log.info("%s metrics at http://%s:%d/metrics", self.service, host, self.server.port)

    def close(self) -> None:
        if self.server is not None:
            self.server.close()
            self.server = None

    def _read(self) -> Mapping[str, Any]:
        for _ in range(5):
            try:
                return dict(self.status())
            except RuntimeError:  # a dictionary changed size under us: read again
                continue
        return {}

    def collect(self) -> Iterator[Any]:
        return iter(families(self.service, self._read()))


def families(service: str, status: Mapping[str, Any]) -> list[Any]:
    """The metric families of one service's status map (the keys its status answer uses)."""
    from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily

    out: list[Any] = []

    def counter(name: str, text: str, value: Any) -> None:
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            family = CounterMetricFamily(name, text, labels=["service"])
            family.add_metric([service], float(value))
            out.append(family)

    counter(
        "magnet_samples_received",
        "samples taken in (edge: published)",
        status.get("received_samples", status.get("published_samples")),
    )
    counter(
        "magnet_batches_received",
        "messages taken in (edge: published)",
        status.get("received_batches", status.get("published_batches", status.get("messages"))),
    )
    if status.get("service") == "compass":
        counter("magnet_headings_published", "heading messages put", status.get("published_batches"))
    counter("magnet_read_errors", "sensor read errors", status.get("read_errors"))
    dropped = CounterMetricFamily("magnet_dropped", "messages dropped, by cause", labels=["service", "cause"])
    for cause, count in sorted((status.get("dropped") or {}).items()):
        dropped.add_metric([service, str(cause)], float(count))
    out.append(dropped)
    results = CounterMetricFamily("magnet_calibrations", "fits by result", labels=["service", "result"])
    for result in ("accepted", "rejected", "stored"):
        if isinstance(status.get(result), int):
            results.add_metric([service, result], float(status[result]))
    out.append(results)
    devices = GaugeMetricFamily("magnet_devices", "devices known, by calibration state", labels=["service", "state"])
    known = status.get("devices")
    for state, count in sorted(known.items()) if isinstance(known, Mapping) else [("all", known)]:
        if isinstance(count, int):
            devices.add_metric([service, str(state)], float(count))
    out.append(devices)
    alerts = GaugeMetricFamily("magnet_alerts_open", "open drift alerts, by cause", labels=["service", "kind"])
    for kind, count in sorted((status.get("alerts_open") or {}).items()):
        alerts.add_metric([service, str(kind)], float(count))
    out.append(alerts)
    if isinstance(status.get("healthy"), bool):
        healthy = GaugeMetricFamily("magnet_healthy", "1 when the sensor reads", labels=["service"])
        healthy.add_metric([service], float(status["healthy"]))
        out.append(healthy)
    out += ros2_families(service, status.get("sinks"))
    vehicles = status.get("vehicles")
    if isinstance(vehicles, Mapping) and vehicles:
        out += vehicle_families(service, vehicles)
    return out


def ros2_families(service: str, sinks: Any) -> list[Any]:
    """The compass's ROS 2 side (``services.compass.ros2``, status ``sinks``): devices with topics, evictions."""
    from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily

    if not isinstance(sinks, Mapping) or "ros2_topics" not in sinks:
        return []
    topics = GaugeMetricFamily("magnet_ros2_devices", "devices with ROS 2 topics", labels=["service"])
    topics.add_metric([service], float(sinks["ros2_topics"]))
    evicted = CounterMetricFamily(
        "magnet_ros2_topics_evicted", "devices whose ROS 2 topics went to a new device", labels=["service"]
    )
    evicted.add_metric([service], float(sinks.get("ros2_topics_evicted", 0)))
    return [topics, evicted]


#: per compass of a vehicle: metric name, help, the report's key
VEHICLE_GAUGES = (
    ("magnet_vehicle_angle_degrees", "median angle to the vehicle's reference compass", "angle_deg"),
    ("magnet_vehicle_interference_percent", "motors' field at full throttle, % of the Earth's", "interference_pct"),
    ("magnet_vehicle_residual_ut", "what is left against the reference compass, uT RMS", "residual_ut"),
)


def vehicle_families(service: str, vehicles: Mapping[str, Any]) -> list[Any]:
    """Gauges of the compass's vehicle reports (``magnet.vehicle.VehicleReport.to_dict`` per vehicle)."""
    from prometheus_client.core import GaugeMetricFamily

    labels = ["service", "vehicle", "device"]
    verdict = GaugeMetricFamily("magnet_vehicle_verdict", "1: the compass's verdict", labels=[*labels, "verdict"])
    gauges = {key: GaugeMetricFamily(name, text, labels=labels) for name, text, key in VEHICLE_GAUGES}
    anomaly = GaugeMetricFamily("magnet_vehicle_anomaly", "1: a local anomaly", labels=["service", "vehicle"])
    for vehicle, report in sorted(vehicles.items()):
        anomaly.add_metric([service, vehicle], float(bool(report.get("anomaly"))))
        for compass in report.get("compasses") or []:
            device = str(compass.get("device"))
            verdict.add_metric([service, vehicle, device, str(compass.get("verdict"))], 1.0)
            for key, family in gauges.items():
                value = compass.get(key)
                if isinstance(value, (int, float)) and not isinstance(value, bool):
                    family.add_metric([service, vehicle, device], float(value))
    return [verdict, *gauges.values(), anomaly]


#: the metrics of this process, when --metrics was given (one service per process)
_CURRENT: ServiceMetrics | None = None


def start(address: str | None, service: str, status: Status) -> ServiceMetrics | None:
    """Serve ``service``'s metrics at ``address`` (None: no metrics); the process's one endpoint."""
    global _CURRENT
    if address is None:
        return None
    _CURRENT = ServiceMetrics(service, status)
    _CURRENT.serve(address)
    return _CURRENT


def observe_latency(seconds: float) -> None:
    """Feed the latency histogram of this process's metrics (nothing without --metrics)."""
    if _CURRENT is not None:
        _CURRENT.latency.observe(max(0.0, seconds))
