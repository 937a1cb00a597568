"""The heading's uncertainty on ROS 2, read back by a peer nobody here wrote (zenoh-ros2-sdk, its own process): the
Imu's ``orientation_covariance`` holds the heading's sigma squared as its yaw term (rad^2, element 8) and the tilt's
on elements 0 and 4; the MagneticField's covariance the calibration's residual squared (T^2) on its diagonal; the
``/diagnostics`` status says the sigma. Each against magnet's own heading message of the same sample."""

from __future__ import annotations

import math
import threading
import time

import numpy as np
import pytest
import zenoh
from helpers import free_ports, wait_for
from test_ros2_compass import DEVICE, sdk, stamp_ns, start_compass_and_fleet

from magnet import wire
from magnet.model import Calibration, Quality
from magnet.ros2.names import ros_name_of_device

pytestmark = pytest.mark.integration

RESIDUAL_UT = 0.4


def _client(port: int) -> zenoh.Config:
    conf = zenoh.Config()
    conf.insert_json5("connect/endpoints", f'["tcp/127.0.0.1:{port}"]')
    conf.insert_json5("scouting/multicast/enabled", "false")
    return conf


def _watch(port: int, stop: threading.Event, into: dict[int, tuple[float, str]]) -> None:
    """magnet's own headings of the device by sample time: (heading sigma deg, calibration id); and a calibration
    put in force for it (identity, residual ``RESIDUAL_UT``) every second until one is seen applied."""
    calibration = Calibration("ellipsoid", np.zeros(3), np.eye(3), quality=Quality(residual_rms_ut=RESIDUAL_UT))
    payload = wire.encode_calibration(DEVICE, calibration, time.time_ns())
    with zenoh.open(_client(port)) as session:
        sub = session.declare_subscriber(f"magnet/{DEVICE}/heading", zenoh.handlers.FifoChannel(4096))
        last_put = 0.0
        while not stop.is_set():
            if time.monotonic() - last_put > 1.0 and not any(cal for _, cal in list(into.values())[-5:]):
                session.put(wire.key("magnet", DEVICE, wire.Kind.CALIBRATION), payload)
                last_put = time.monotonic()
            sample = sub.try_recv()
            if sample is None:
                stop.wait(0.01)
                continue
            h = wire.decode_heading(sample.payload.to_bytes())
            assert h.heading_sigma_deg is not None, "a heading message without heading_sigma_deg"
            for t, sigma in zip(h.t_ns.tolist(), h.heading_sigma_deg.tolist()):
                into[t] = (sigma, h.calibration_id)


def test_a_ros2_peer_reads_the_heading_sigma_and_the_fields_covariance(procs):
    comp_port, edge_port = free_ports(2)
    start_compass_and_fleet(procs, comp_port, edge_port)
    headings: dict[int, tuple[float, str]] = {}
    stop = threading.Event()
    watcher = threading.Thread(target=_watch, args=(comp_port, stop, headings), daemon=True)
    watcher.start()
    try:
        wait_for(lambda: sum(1 for _, cal in list(headings.values())[-20:] if cal) >= 20, 40, "the calibration")
        name = ros_name_of_device(DEVICE)
        imus = sdk(comp_port, "subscribe", f"/magnet/{name}/imu", "sensor_msgs/msg/Imu", "20", "20")
        mags = sdk(comp_port, "subscribe", f"/magnet/{name}/mag", "sensor_msgs/msg/MagneticField", "20", "20")
        diagnostics = sdk(comp_port, "subscribe", "/diagnostics", "diagnostic_msgs/msg/DiagnosticArray", "1", "15")
        wait_for(lambda: all(stamp_ns(m) in headings for m in imus + mags), 10, "the headings of those samples")
    finally:
        stop.set()
        watcher.join(timeout=10)
    assert len(imus) == 20 and len(mags) == 20
    for msg in imus:
        sigma_deg, _ = headings[stamp_ns(msg)]
        cov = np.asarray(msg["orientation_covariance"], dtype=float).reshape(3, 3)
        # the heading message carries the sigma as float32
        assert cov[2, 2] == pytest.approx(math.radians(sigma_deg) ** 2, rel=1e-5)
        assert 0 < cov[0, 0] == cov[1, 1] < 1 and cov[0, 0] < math.pi**2
        assert not (cov - np.diag(np.diag(cov))).any()
    for msg in mags:
        cov = np.asarray(msg["magnetic_field_covariance"], dtype=float).reshape(3, 3)
        if headings[stamp_ns(msg)][1]:  # calibrated then
            np.testing.assert_allclose(cov, np.eye(3) * (RESIDUAL_UT * 1e-6) ** 2, rtol=1e-12)
    assert any(headings[stamp_ns(m)][1] for m in mags)
    (status,) = diagnostics[0]["status"]
    values = {v["key"]: v["value"] for v in status["values"]}
    assert float(values["heading_sigma_deg"]) > 0, values
    assert procs.alive("compass"), procs.log("compass")[-2000:]
