"""A record applied to samples it cannot belong to (another device's hard iron, or samples in another unit) is
refused with the field it gives and exit 2, unless --force; a record of the same sensor is applied as before."""

import numpy as np
import pytest

from magnet.simulator import SimulatedDevices
from services.cli import main


@pytest.fixture(scope="module")
def csvs(tmp_path_factory):
    folder = tmp_path_factory.mktemp("plausible")
    batch = SimulatedDevices(1, rate_hz=5, seed=4, noise_ut=0.2).step(1500)
    paths = {}
    for name, scale in (("ut", 1.0), ("gauss", 0.01)):  # the same samples, in uT and in gauss
        paths[name] = folder / f"{name}.csv"
        rows = np.column_stack([batch.mag_ut[0] * scale, batch.acc_ms2[0]])
        np.savetxt(paths[name], rows, delimiter=",", header="mx,my,mz,ax,ay,az", comments="", fmt="%.6f")
    paths["cal"] = folder / "cal.json"
    assert main(["fit", str(paths["ut"]), "--method", "ellipsoid", "--out", str(paths["cal"])]) == 0
    return paths


def test_a_record_of_the_same_sensor_is_applied(csvs, capsys):
    capsys.readouterr()
    assert main(["heading", str(csvs["ut"]), "--calibration", str(csvs["cal"])]) == 0
    assert capsys.readouterr().err == ""


def test_a_record_implausible_for_the_samples_is_refused_unless_forced(csvs, capsys):
    capsys.readouterr()
    assert main(["heading", str(csvs["gauss"]), "--calibration", str(csvs["cal"])]) == 2
    captured = capsys.readouterr()
    assert captured.out == "" and "gives these samples a field of" in captured.err and "--force" in captured.err
    assert main(["heading", str(csvs["gauss"]), "--calibration", str(csvs["cal"]), "--force"]) == 0
    captured = capsys.readouterr()
    assert "warning: the calibration gives these samples" in captured.err and captured.out.startswith("heading_deg")
