"""Hardware ids through the calibrator and the compass (issue 27, item 5): a record names the sensor its samples came
from; when a device's batches come from another sensor (a compass missing at boot gave its instance away) the record
is not applied to them, counted and said in the compass's status, and the calibrator makes the new sensor a record of
its own instead of fitting on a mixture."""

from __future__ import annotations

import numpy as np
import pytest
from compass_steps import heading_batches
from memory_store import MemoryStore
from test_calibrator_core import Clocks, Published, _core

from magnet import wire
from magnet.compass import CompassCore
from magnet.model import Calibration
from magnet.simulator import SensorErrors, SimulatorConfig, simulate

FIRST, SECOND = 466441, 131874  # an external I2C compass and an internal SPI one (ArduPilot ids)
SOFT = np.array([[1.1, 0.04, 0.0], [0.04, 0.9, 0.02], [0.0, 0.02, 1.0]])


def run(hard: tuple[float, float, float], seed: int):
    return simulate(SimulatorConfig(count=3000, seed=seed, errors=SensorErrors(hard, SOFT, noise_ut=0.3)))


def raw_batches(sim, sensor: int, device: str = "mav1-mag0", batch: int = 50, seq0: int = 0) -> list[wire.RawBatch]:
    out = []
    for k, start in enumerate(range(0, len(sim.t_s), batch)):
        part = slice(start, start + batch)
        t_ns = (sim.t_s[part] * 1e9).astype(np.int64) + 1_000_000_000 * (seq0 + 1)
        out.append(
            wire.RawBatch(device, seq0 + k, "mavlink", t_ns, sim.mag_ut[part], sim.acc_ms2[part], hardware_id=sensor)
        )
    return out


def test_every_record_names_its_sensor_and_a_new_sensor_gets_its_own_record() -> None:
    store, clocks, published = MemoryStore(), Clocks(), Published()
    core = _core(store, clocks, published)
    for batch in raw_batches(run((30.0, -12.0, 8.0), 0), FIRST):
        core.on_raw("magnet/mav1-mag0/raw", wire.encode_raw(batch), "magnet")
    first = core.records.get("mav1-mag0")
    assert first is not None and first.calibration.hardware_id == FIRST
    np.testing.assert_allclose(first.calibration.offset, [30.0, -12.0, 8.0], atol=1.0)
    # the next boot: instance 0 is the other compass, with its own hard iron
    for batch in raw_batches(run((-8.0, 25.0, -14.0), 1), SECOND, seq0=100):
        core.on_raw("magnet/mav1-mag0/raw", wire.encode_raw(batch), "magnet")
    second = core.records.get("mav1-mag0")
    assert second is not None and second.version == 2 and second.calibration.hardware_id == SECOND
    np.testing.assert_allclose(second.calibration.offset, [-8.0, 25.0, -14.0], atol=1.0)
    assert core.sensors.changes == 1
    # both records kept: the first sensor's calibration is in the history, not lost or moved
    assert sorted(r.calibration.hardware_id for r, _ in store.history_changes("mav1-mag0")) == [SECOND, FIRST]
    # the boot after, the first compass is there again: its record comes back at once, nothing fitted
    fits = core.fitter.fits
    for batch in raw_batches(run((30.0, -12.0, 8.0), 4), FIRST, seq0=200)[:3]:
        core.on_raw("magnet/mav1-mag0/raw", wire.encode_raw(batch), "magnet")
    back = core.records.get("mav1-mag0")
    assert back is not None and back.version == 3 and back.id == first.id and core.fitter.fits == fits
    [(_, change), *_] = store.history_changes("mav1-mag0")
    assert change is not None and (change["action"], change["to_id"]) == ("sensor-back", first.id)
    assert core.sensors.back == 1 and "mav1-mag0" not in core.collections
    status = core.status("c").to_dict()
    assert (status["sensor_changes"], status["sensors_back"]) == (2, 1)


def test_the_compass_applies_a_record_only_to_batches_of_its_sensor_and_says_so() -> None:
    compass = CompassCore()
    cal = Calibration("ellipsoid", np.array([30.0, -12.0, 8.0]), np.eye(3), 50.0, hardware_id=FIRST)
    record = wire.DeviceCalibration("mav1-mag0", 1, cal, version=1)
    assert compass.accept_calibration(wire.pack(record.to_record()), "magnet/mav1-mag0/calibration", "magnet")
    sim = run((30.0, -12.0, 8.0), 2)
    own, other, unknown = (raw_batches(sim, sensor)[:2] for sensor in (FIRST, SECOND, 0))
    assert [h.calibration_id for h in heading_batches(compass, own)] == [record.id] * 2
    assert compass.status("c").hardware_mismatches == 0
    out = heading_batches(compass, other)
    assert [h.calibration_id for h in out] == ["", ""], "not applied to another sensor"
    status = compass.status("c").to_dict()
    assert status["hardware_mismatches"] == 2
    assert status["hardware_mismatched"] == {"mav1-mag0": {"record": FIRST, "sensor": SECOND}}
    # a batch without an id (an edge that does not know it) is corrected as before
    assert [h.calibration_id for h in heading_batches(compass, unknown)] == [record.id] * 2
    assert compass.status("c").hardware_mismatched != {}, "an unknown sensor does not say the right one is back"
    heading_batches(compass, raw_batches(sim, FIRST, seq0=10)[:1])
    assert compass.status("c").hardware_mismatched == {}
    # a record without an id (made before ids, or off a bus without them) applies to any sensor: old records work
    plain = wire.DeviceCalibration("mav1-mag0", 2, cal.replace(hardware_id=None), version=2)
    compass.accept_calibration(wire.pack(plain.to_record()), "magnet/mav1-mag0/calibration", "magnet")
    assert [h.calibration_id for h in heading_batches(compass, other)] == [plain.id] * 2


def test_old_records_read_and_keep_their_ids() -> None:
    old = {"method": "ellipsoid", "offset": [1.0, 2.0, 3.0], "matrix": np.eye(3).tolist()}
    cal = Calibration.from_dict(old)
    assert cal.hardware_id is None and "hardware_id" not in cal.to_dict()
    assert cal.content_id == Calibration.from_dict({**old, "hardware_id": None}).content_id
    named = Calibration.from_dict({**old, "hardware_id": FIRST})
    assert named.hardware_id == FIRST and named.to_dict()["hardware_id"] == FIRST
    assert named.content_id != cal.content_id  # one sensor's record is not another's
    for bad in (-1, 1.5, True, 1 << 40, "466441"):
        with pytest.raises(ValueError, match="hardware_id"):
            Calibration.from_dict({**old, "hardware_id": bad})
