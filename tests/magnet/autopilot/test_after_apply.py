"""After ``export --apply`` (issue 27, item 7): the vehicle's own corrected field checked against what the record
predicts (magnet.autopilot.verify), and the exported file naming the sensor the values were fitted for."""

from __future__ import annotations

import numpy as np

from magnet.autopilot.params import export_parameters
from magnet.autopilot.verify import ardupilot_correction, check_after_apply
from magnet.model import Calibration

HARD_UT = np.array([25.0, -12.0, 9.0])
SOFT = np.array([[1.08, 0.03, 0.0], [0.03, 0.95, 0.02], [0.0, 0.02, 1.0]])
RECORD = Calibration("manual", HARD_UT, np.linalg.inv(SOFT), 50.0, hardware_id=466441)


def readings_mg(count: int = 400, seed: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """(the sensor's readings (N, 3) mGauss, the true fields (N, 3) uT) of a 50 uT field turned every way."""
    rng = np.random.default_rng(seed)
    field = rng.standard_normal((count, 3))
    field = 50.0 * field / np.linalg.norm(field, axis=1)[:, None]
    return (field @ SOFT.T + HARD_UT) * 10.0, field


def written(instance: int = 0) -> dict[str, float]:
    return {p.name: p.value for p in export_parameters(RECORD, "ardupilot", instance).parameters if not p.check_only}


def test_a_vehicle_that_applies_the_written_values_agrees() -> None:
    raw, truth = readings_mg()
    new = ardupilot_correction(written(), 0, 0)
    sent = np.round(new.field(raw))  # ArduPilot sends whole milligauss
    np.testing.assert_allclose(sent / 10.0, truth, atol=0.2)  # the export is right to begin with
    result = check_after_apply(RECORD, {}, written(), 0, sent)
    assert result.agrees is True and result.rms_ut is not None and result.rms_ut < 0.1, result
    assert result.summary.startswith("agrees over 400 samples of compass 0")
    assert result.size_rms_ut is not None and result.size_rms_ut < 0.1


def test_a_vehicle_that_did_not_take_them_or_held_an_older_calibration_disagrees() -> None:
    raw, _ = readings_mg()
    untouched = check_after_apply(RECORD, {}, written(), 0, raw)  # still sends the reading as it was
    assert untouched.agrees is False and untouched.size_rms_ut is not None and untouched.size_rms_ut > 10
    assert "does not apply the values" in untouched.summary
    # the vehicle held offsets before; the record was fitted on the raw reading: the written values replace the old
    before = {"COMPASS_OFS_X": 60.0, "COMPASS_OFS_Y": -40.0, "COMPASS_OFS_Z": 0.0}
    new = ardupilot_correction({**before, **written()}, 0, 0)
    replaced = check_after_apply(RECORD, before, written(), 0, np.round(new.field(raw)))
    assert replaced.agrees is False and "held a calibration before" in replaced.summary
    assert 5.0 < (replaced.rms_ut or 0) < 10.0  # the old offsets' 7.2 uT, through the record's matrix
    few = check_after_apply(RECORD, {}, written(), 0, raw[:10])
    assert few.agrees is None and "not checked" in few.summary


def test_the_export_names_its_sensor_first_and_only_when_known() -> None:
    for autopilot, name in (("ardupilot", "COMPASS_DEV_ID2"), ("px4", "CAL_MAG1_ID")):
        export = export_parameters(RECORD, autopilot, 1)
        first = export.parameters[0]
        assert (first.name, first.value, first.integer, first.check_only) == (name, 466441.0, True, True)
        assert any("I2C bus 1 address 0x1e devtype 0x07" in note for note in export.notes)
        plain = export_parameters(RECORD.replace(hardware_id=None), autopilot, 1)
        assert [p.name for p in plain.parameters] == [p.name for p in export.parameters[1:]]
