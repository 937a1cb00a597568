"""Calibration reports: an emulated tumble (ellipse becomes a circle, heading error against the simulator's truth),
every real recording in data/, ``magnet fit --report``, and bad input.

The images go to ``$MAGNET_ARTEFACT_DIR/report`` (default: the system's temp folder, under ``magnet-artefacts``):
look at them.
"""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
from pathlib import Path

import numpy as np
import pytest

from magnet.calibration import FitInput, fit
from services.cli import main
from services.common.records import load_calibration
from services.report.data import build_report, load_samples

ARTEFACTS = Path(os.environ.get("MAGNET_ARTEFACT_DIR", Path(tempfile.gettempdir()) / "magnet-artefacts")) / "report"
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
LOCATION = "50.45,30.52"


def _tumble(folder: Path, count: int) -> tuple[Path, Path]:
    """``count`` samples of an emulated LSM303DLH tumbled through known hard and soft iron, and their fit: (csv,
    cal.json) in ``folder``."""
    csv, cal = folder / "tumble.csv", folder / "tumble.json"
    with open(csv, "w") as out, contextlib.redirect_stdout(out):
        assert (
            main(
                [
                    "sample",
                    "--sensor",
                    "lsm303dlh",
                    "--emulate",
                    "--trajectory",
                    "tumble",
                    "--count",
                    str(count),
                    "--hard-iron",
                    "25,-40,12",
                    "--soft-iron",
                    "1.1,0.05,0,0.05,0.9,0.02,0,0.02,1.05",
                    "--noise-ut",
                    "0.3",
                    "--date",
                    "2026-01-01",
                ]
            )
            == 0
        )
    assert main(["fit", str(csv), "--method", "ellipsoid", "--location", LOCATION, "--out", str(cal)]) == 0
    return csv, cal


@pytest.fixture(scope="module")
def tumble(tmp_path_factory):
    """3000 samples: enough for the figures the reports are checked on."""
    return _tumble(tmp_path_factory.mktemp("tumble"), 3000)


@pytest.fixture
def short_tumble(tmp_path_factory):
    """A short tumble and its (accepted) fit, for the refusals, which come before any figure is made."""
    return _tumble(tmp_path_factory.mktemp("short"), 300)


@pytest.mark.integration  # draws a figure: seconds
def test_report_of_an_emulated_tumble_shows_the_ellipse_become_a_circle(tumble):
    csv, cal = tumble
    ARTEFACTS.mkdir(parents=True, exist_ok=True)
    out = ARTEFACTS / "tumble.png"
    assert (
        main(
            [
                "report",
                str(csv),
                "--calibration",
                str(cal),
                "--location",
                LOCATION,
                "--date",
                "2026-01-01",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    assert out.read_bytes()[:8] == PNG_MAGIC and out.stat().st_size > 50_000
    from services.common.records import load_calibration

    data = build_report(load_samples(csv, None), load_calibration(str(cal)), declination_deg=None)
    assert data.spread_before_pct > 15 and data.spread_after_pct < 1.0  # offset ellipsoid -> centred sphere
    assert data.accepted and data.headings is not None
    assert data.headings.raw_rms_deg > 20 and data.headings.rms_deg < 2.0
    assert "taken from the data" in data.headings.note


@pytest.mark.integration  # draws a figure: seconds
def test_fit_report_writes_the_same_report_for_the_fit_it_made(tumble, tmp_path):
    csv, _ = tumble
    page = tmp_path / "fit.html"
    assert (
        main(
            [
                "fit",
                str(csv),
                "--method",
                "ellipsoid",
                "--location",
                LOCATION,
                "--report",
                str(page),
                "--out",
                str(tmp_path / "cal.json"),
            ]
        )
        == 0
    )
    text = page.read_text()
    record = json.loads((tmp_path / "cal.json").read_text())
    assert "data:image/png;base64," in text and "ellipsoid calibration" in text
    assert record["reason"] in text and f"{record['quality']['residual_rms_ut']:.3f} uT" in text


@pytest.mark.integration  # draws a figure: seconds
def test_a_pdf_report_is_on_a4_with_its_record_and_the_gate_in_its_metadata(tumble, capsys):
    csv, cal = tumble
    ARTEFACTS.mkdir(parents=True, exist_ok=True)
    out = ARTEFACTS / "tumble.pdf"
    assert main(["report", str(csv), "--calibration", str(cal), "--location", LOCATION, "--out", str(out)]) == 0
    assert capsys.readouterr().err == ""  # no progress bar without a terminal
    pdf = out.read_bytes()
    assert pdf.startswith(b"%PDF-") and pdf.rstrip().endswith(b"%%EOF") and b"/Count 2" in pdf
    assert b"/Title (magnet report: tumble.csv)" in pdf and b"/Subject (verdict: accepted; method: ellipsoid" in pdf
    assert pdf.count(b"/MediaBox [ 0 0 595.44 841.68 ]") == 2  # A4 (8.27 x 11.69 in), both pages
    record = json.loads(cal.read_text())
    from services.report.data import build_report, load_samples
    from services.report.render import summary_lines

    rows = dict(summary_lines(build_report(load_samples(csv, "ut"), load_calibration(str(cal)), None, None), "now"))
    assert rows["calibration id"] == load_calibration(str(cal)).content_id and rows["report made"] == "now"
    assert rows["offset b"].startswith(f"{record['offset'][0]:+.4f}") and rows["method"] == "ellipsoid"
    letter = ARTEFACTS / "tumble-letter.pdf"
    assert main(["report", str(csv), "--calibration", str(cal), "--paper", "letter", "--out", str(letter)]) == 0
    assert letter.read_bytes().count(b"/MediaBox [ 0 0 612 792 ]") == 2


@pytest.mark.integration  # draws a figure: seconds
def test_a_rejected_fit_still_gets_its_report_and_the_reason(tmp_path, capsys):
    rng = np.random.default_rng(3)
    directions = rng.normal(size=(4000, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    cap = directions[directions[:, 2] > 0.4][:400]  # one side of the sphere only: the gate refuses the coverage
    mag = 50 * cap + [10, -5, 20] + rng.normal(0, 0.2, cap.shape)
    csv = tmp_path / "turn.csv"
    np.savetxt(csv, mag, delimiter=",", header="mx,my,mz", comments="", fmt="%.4f")
    page = tmp_path / "turn.png"
    status = main(["fit", str(csv), "--method", "sphere", "--report", str(page), "--out", str(tmp_path / "c.json")])
    assert status == 1 and "coverage" in capsys.readouterr().err
    assert page.read_bytes()[:8] == PNG_MAGIC and not (tmp_path / "c.json").exists()


def test_bad_report_requests_say_what_is_wrong(short_tumble, tmp_path, capsys):
    csv, cal = short_tumble
    assert main(["report", str(csv), "--calibration", str(cal), "--out", str(tmp_path / "r.svg")]) == 2
    assert "must end in .png, .html, .pdf" in capsys.readouterr().err
    assert (
        main(["report", str(csv), "--calibration", str(cal), "--unit", "gauss", "--out", str(tmp_path / "r.png")]) == 2
    )
    assert "give --unit ut" in capsys.readouterr().err
    assert not list(tmp_path.iterdir())


RECORDINGS = {  # file -> (unit, method, fit every n-th sample)
    "ck_explorer_acc_mag_log.csv": ("gauss", "ellipsoid", 1),
    "qmc5883l_tomisuarez2_filtered.csv": ("counts", "ellipsoid", 1),
    "broad_01_undisturbed_slow_rotation_A.npz": ("ut", "ellipsoid", 10),
    "broad_06_undisturbed_fast_rotation_A.npz": ("ut", "ellipsoid", 10),
}


@pytest.mark.integration
@pytest.mark.parametrize("name", sorted(RECORDINGS))
def test_report_of_each_real_recording(datasets_dir, name):
    from services.report.render import html_page, write  # matplotlib: imported here, not for the unit tests

    unit, method, step = RECORDINGS[name]
    samples = load_samples(datasets_dir / name, unit)
    calibration = fit(
        FitInput(samples.raw[::step], acc=None if samples.acc is None else samples.acc[::step], unit=unit), method
    )
    data = build_report(samples, calibration)
    assert data.spread_after_pct < data.spread_before_pct
    assert 0.3 < data.quality["coverage"] <= 1.0  # the gate figures are in the report
    ARTEFACTS.mkdir(parents=True, exist_ok=True)
    write(ARTEFACTS / f"{Path(name).stem}.png", data)
    assert (ARTEFACTS / f"{Path(name).stem}.png").read_bytes()[:8] == PNG_MAGIC
    assert name in html_page(data)


def _npz(path: Path, rows: int, data_rows: int, compress: bool = True) -> Path:
    """An .npz whose mag_ut.npy header claims ``rows`` x 3 float64 and holds ``data_rows`` x 3 of zeros."""
    import zipfile

    method = zipfile.ZIP_DEFLATED if compress else zipfile.ZIP_STORED
    with (
        zipfile.ZipFile(path, "w", compression=method) as archive,
        archive.open("mag_ut.npy", "w", force_zip64=True) as member,
    ):
        header = np.lib.format.header_data_from_array_1_0(np.zeros((1, 3)))
        header["shape"] = (rows, 3)
        np.lib.format.write_array_header_1_0(member, header)
        for lo in range(0, data_rows, 1 << 18):
            member.write(bytes(24 * min(1 << 18, data_rows - lo)))
    return path


def test_an_npz_claiming_or_inflating_to_more_rows_than_allowed_is_refused_before_it_is_read(tmp_path, monkeypatch):
    """Issue 32's front door for `magnet report`'s .npz: a header claiming 10^10 rows was a 224 GiB allocation and a
    traceback; a 2 MB file inflating to 2 GiB of zeros took 8.2 GB and 68 s, then a traceback. Now the arrays'
    headers are read first (at the real limit, 2,000,000 rows: 70 MB, 2.4 s as a command)."""
    import services.report.data as report_data

    monkeypatch.setattr(report_data, "MAX_NPZ_SAMPLES", 1000)
    claims = _npz(tmp_path / "claims.npz", 10**10, 10)
    with pytest.raises(ValueError, match=r"mag_ut.npy claims 10000000000 rows \(its zip entry holds 368 bytes"):
        load_samples(claims, None)
    with pytest.raises(ValueError, match=r"mag_ut\.npy claims 5000 rows"):
        load_samples(_npz(tmp_path / "inflates.npz", 5000, 5000), None)
    with pytest.raises(ValueError, match="claims 900 rows"):  # a header claiming more than the entry holds
        load_samples(_npz(tmp_path / "short.npz", 900, 10), None)
    (tmp_path / "not.npz").write_bytes(b"PK\x03\x04 not a zip")
    with pytest.raises(ValueError, match=r"not an \.npz recording numpy can read"):
        load_samples(tmp_path / "not.npz", None)
    assert load_samples(_npz(tmp_path / "fine.npz", 900, 900), None).raw.shape == (900, 3)


def test_the_coverage_map_finds_its_cells_a_block_of_samples_at_a_time(monkeypatch):
    """The sphere's map took the nearest of 100 cells for every sample at once: 800 bytes a sample (6.8 GB for a
    48 MB CSV of 8 million samples). Blocks of HIT_ROWS give the same cells."""
    from matplotlib.figure import Figure

    from services.report import render

    rng = np.random.default_rng(5)
    field = rng.normal(size=(5000, 3)) * np.array([1.0, 1.0, 0.1])  # a band around the equator: some cells missed

    def cells(rows: int) -> str:
        monkeypatch.setattr(render, "HIT_ROWS", rows)
        fig = Figure()
        data = type("D", (), {"calibrated": field, "quality": {}})()
        render._coverage(fig, fig.add_gridspec(1, 1)[0, 0], data)
        return fig.axes[0].get_legend().get_texts()[0].get_text()

    assert cells(10**9) == cells(777) and cells(777).startswith("covered (")
