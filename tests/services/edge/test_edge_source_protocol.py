"""Every kind of source ``magnet edge`` can open has the one ``Source`` shape, and the settings' kind picks it through
the one dispatch table (``services.edge.sources.SOURCES``)."""

from __future__ import annotations

import itertools
import time
from pathlib import Path

import pytest
from helpers import free_ports

from magnet import wire
from services.common.ros2_options import Ros2Settings
from services.edge.settings import EdgeSettings, SourceKind
from services.edge.source import Source
from services.edge.sources import SOURCES, make_source

FAST = {"rate_hz": 1000.0, "batch": 5}


def _settings(kind: SourceKind, tmp_path: Path) -> EdgeSettings:
    """Settings of each kind, as the options would give them."""
    if kind is SourceKind.MAVLINK:
        [port] = free_ports(1)
        return EdgeSettings(mavlink=f"udpin:127.0.0.1:{port}", **FAST)
    if kind is SourceKind.REPLAY:
        path = tmp_path / "r.csv"
        path.write_text("t_s,mx,my,mz\n" + "".join(f"{k / 1000},20,0,40\n" for k in range(12)))
        return EdgeSettings(replay=path, speed=1000.0, **FAST)
    by_kind = {
        SourceKind.ROS2: {"ros2": Ros2Settings(True), "mag_topic": "/robot/mag"},
        SourceKind.FLEET: {"emulate": True, "devices": 3},
        SourceKind.SIMULATOR: {"emulate": True},
        SourceKind.CHIP: {"emulate": True, "sensor": "icm20948"},
    }
    return EdgeSettings(**by_kind[kind], **FAST)


def test_the_table_opens_every_kind_of_source() -> None:
    assert set(SOURCES) == set(SourceKind)


@pytest.mark.parametrize("kind", list(SourceKind))
def test_every_kind_of_source_has_the_one_shape(kind: SourceKind, tmp_path: Path) -> None:
    settings = _settings(kind, tmp_path)
    assert settings.source_kind is kind
    source = make_source(settings)
    try:
        assert isinstance(source, Source) and isinstance(source, SOURCES[kind])  # type: ignore[arg-type]
        assert all(isinstance(device, str) for device in source.ids)
        status = source.status()
        assert status is None or {"healthy", "attempts", "errors", "last_error"} <= set(status)
        # a ROS 2 source without a session, or a MAVLink one with nobody sending, never fills a batch: asked for a
        # moment only; the others fill their two at once (the deadline is only their bound)
        deadline = time.monotonic() + (0.05 if kind in (SourceKind.ROS2, SourceKind.MAVLINK) else 0.2)
        steps = list(itertools.islice(source.batches(lambda: time.monotonic() > deadline), 2))
        for step in steps:
            assert all(isinstance(batch, wire.RawBatch) for batch in step)
        if kind in (SourceKind.FLEET, SourceKind.SIMULATOR, SourceKind.CHIP, SourceKind.REPLAY):
            assert [len(step) for step in steps] == [len(source.ids)] * 2 and steps[1][0].seq == 1
    finally:
        source.close()


def test_a_chip_tells_the_edge_when_its_health_changes(monkeypatch: pytest.MonkeyPatch) -> None:
    """A chip on a dead (emulated) bus turns unhealthy through the events the edge attaches (its backoff between
    attempts not slept: what is counted is the same)."""
    slept: list[float] = []
    monkeypatch.setattr(time, "sleep", slept.append)  # the source takes time.sleep when it is made

    class Events:
        def __init__(self) -> None:
            self.changes: list[bool] = []

        def on_health(self, healthy: bool, error: str) -> None:
            self.changes.append(healthy)

        def device_seen(self, device: str) -> None:
            raise AssertionError("one chip, one device")

        def device_health(self, device: str, healthy: bool) -> None:
            raise AssertionError("one chip: on_health")

    source = make_source(EdgeSettings(sensor="hmc5883l", emulate=True, emulate_faults=1.0, **FAST))
    events = Events()
    source.attach(None, events)  # type: ignore[arg-type]  # a chip declares nothing on the session
    calls = itertools.count()
    assert list(source.batches(lambda: next(calls) > 8)) in ([], [[]])
    status = source.status()
    assert status is not None and not status["healthy"] and status["errors"] >= 3 and events.changes == [False]
    assert slept  # it did back off
