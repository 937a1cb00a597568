"""Hardware ids through ``magnet edge --mavlink``, the calibrator and the compass (issue 27, item 5), against the
pymavlink stand-in (tests/mav_vehicle.py): its two compasses are calibrated, each record naming its sensor's
COMPASS_DEV_ID; then it reboots without its first compass, so the second comes in as instance 0 (``mav1-mag0``).
The first compass's record is not applied to it: counted and named in the compass's status, and the calibrator makes
the second sensor a record of its own."""

from __future__ import annotations

import time

import numpy as np
import pytest
import zenoh
from helpers import connect_args, free_ports, listen_args, liveliness_keys, magnet_json, wait_for
from motion_pipeline import PREFIX, Pipeline, _client_config
from test_edge_mavlink import DATE, LOCATION, RawBatches, vehicle

from magnet import wire

pytestmark = pytest.mark.integration

FIRST, SECOND = 466441, 131874  # tests/mav_vehicle.py SENSOR_IDS[0], [1]
REBOOT_S = 30.0


def status(name: str, port: int) -> dict:
    code, lines = magnet_json("get", "status", name, "--no-multicast-scouting", *connect_args(port))
    assert code == 0, lines
    return lines[0]


def test_a_compass_missing_at_boot_does_not_move_its_calibration_onto_another_sensor(procs, tmp_path):
    pipeline = Pipeline(procs, tmp_path, [], ["--location", LOCATION, "--date", DATE])
    udp, edge_port = free_ports(2)
    edge_args = ["--mavlink", f"udpin:127.0.0.1:{udp}", "--batch", "25"]
    procs.start(
        "edge", "edge", *edge_args, *listen_args(edge_port), *connect_args(pipeline.cal_port, pipeline.comp_port)
    )
    wait_for(lambda: "magnet/@alive/edge/dev" in liveliness_keys(edge_port), 20, "the edge")
    raws = RawBatches()
    with (
        pipeline.calibrations() as records,
        pipeline.headings() as headings,
        zenoh.open(_client_config(edge_port)) as s,
    ):
        s.declare_subscriber(wire.key(PREFIX, "*", wire.Kind.RAW), raws.on_sample)
        time.sleep(0.5)
        started = time.monotonic()
        args = ["--rate", "50", "--samples", "1000", "--duration", "100", "--reboot-at", str(REBOOT_S)]
        stand_in = vehicle(tmp_path, udp, *args, "--missing", "0", "--truth", str(tmp_path / "truth.npz"))
        first = {
            d: wait_for(lambda d=d: records.in_force(d), REBOOT_S - 5, f"a calibration of {d} before the reboot")
            for d in ("mav1-mag0", "mav1-mag1")
        }
        assert (first["mav1-mag0"]["hardware_id"], first["mav1-mag1"]["hardware_id"]) == (FIRST, SECOND)
        assert time.monotonic() - started < REBOOT_S, "calibrated too late for the test to mean anything"
        held = wait_for(
            lambda: status("compass", pipeline.comp_port)["hardware_mismatched"].get("mav1-mag0"),
            REBOOT_S + 20,
            "the compass to hold mav1-mag0's record back from the second sensor",
        )
        assert held == {"record": FIRST, "sensor": SECOND}
        assert status("compass", pipeline.comp_port)["hardware_mismatches"] > 0
        assert "its calibration was made for sensor 466441 but the samples come from sensor 131874" in procs.log(
            "compass"
        )
        second = wait_for(
            lambda: (r := records.in_force("mav1-mag0")) and r["hardware_id"] == SECOND and r,
            40,
            "a record of the second sensor for mav1-mag0",
        )
        # the compass applies the new record a moment after the calibrator publishes it: stop the vehicle only then
        wait_for(
            lambda: any(b.calibration_id == second["id"] for b in headings.batches("mav1-mag0")),
            20,
            "a heading of mav1-mag0 corrected with the second sensor's record",
        )
        edge = status("edge-dev", edge_port)
        stand_in.terminate()
        assert stand_in.wait(timeout=20) == 0
    assert edge["reads"]["hardware_ids"]["mav1-mag0"] == SECOND, edge
    np.testing.assert_allclose(second["offset"], [-8.0, 30.0, -14.0], atol=1.5)  # the second compass's hard iron
    # before the vehicle's first HEARTBEAT (which names whom to ask) samples go without an id; then never again
    ids = [raws.by_device["mav1-mag0"][seq].hardware_id for seq in sorted(raws.by_device["mav1-mag0"])]
    known = next(k for k, i in enumerate(ids) if i)
    assert set(ids[known:]) == {FIRST, SECOND} and known <= 3, ids[:10]
    assert ids[known:] == sorted(ids[known:], key=lambda i: i == SECOND), "the first sensor's, then the second's"
    # no heading of the second sensor's samples was corrected with the first sensor's record
    wrong = right = 0
    for batch in headings.batches("mav1-mag0"):
        raw = raws.by_device["mav1-mag0"].get(batch.seq)
        if raw is None:
            continue
        if raw.hardware_id == SECOND:
            wrong += batch.calibration_id == first["mav1-mag0"]["id"]
            right += batch.calibration_id == second["id"]
    assert wrong == 0 and right > 0, (wrong, right)
    sensors = np.load(tmp_path / "truth.npz")["sensors"]
    assert set(sensors.tolist()) == {FIRST, SECOND}
