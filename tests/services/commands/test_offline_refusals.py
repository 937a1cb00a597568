"""Offline input ``magnet heading`` and ``magnet fit`` must refuse with one clear line and exit 2 (input it cannot use;
1 is kept for a fit the gate rejects): a calibration marked not accepted or singular, CSV fields over 128 KiB, absurd
magnitudes, other separators or quoting, a duplicated column."""

from __future__ import annotations

import json

import numpy as np
import pytest

from magnet.model import Calibration
from services.cli import main

HEADER = "mx,my,mz,ax,ay,az"


def _rows(count=200, scale=1.0):
    rng = np.random.default_rng(0)
    mag = rng.normal(size=(count, 3))
    mag = 50 * scale * mag / np.linalg.norm(mag, axis=1, keepdims=True)
    return [f"{x:.6g},{y:.6g},{z:.6g},0,0,-9.81" for x, y, z in mag]


def _csv(tmp_path, text, name="s.csv"):
    path = tmp_path / name
    path.write_text(text)
    return str(path)


def _good_csv(tmp_path):
    return _csv(tmp_path, "\n".join([HEADER, *_rows()]) + "\n")


def _run(capsys, *argv):
    if argv[0] == "fit":
        argv = (*argv, "--method", "ellipsoid")
    code = main(list(argv))
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def _calibration_file(tmp_path, **changes):
    record = {**Calibration("ellipsoid", [1.0, 2.0, 3.0], np.diag([1.0, 1.1, 0.9])).to_dict(), **changes}
    path = tmp_path / "cal.json"
    path.write_text(json.dumps(record))
    return str(path)


def test_heading_applies_an_accepted_calibration(tmp_path, capsys):
    code, out, err = _run(capsys, "heading", _good_csv(tmp_path), "--calibration", _calibration_file(tmp_path))
    assert code == 0 and out.startswith("heading_deg,") and err == ""


def test_heading_refuses_a_calibration_marked_not_accepted(tmp_path, capsys):
    cal = _calibration_file(tmp_path, accepted=False, reason="rejected: coverage 12 %")
    code, out, err = _run(capsys, "heading", _good_csv(tmp_path), "--calibration", cal)
    assert code == 2 and out == ""
    assert "cal.json" in err and "not accepted" in err and "coverage 12 %" in err
    assert len(err.strip().splitlines()) == 1


@pytest.mark.parametrize(
    "matrix", [[[0, 0, 0]] * 3, [[1, 0, 0], [0, 1, 0], [0, 0, 0]], [[1, 2, 3], [2, 4, 6], [0, 0, 1]]]
)
def test_heading_refuses_an_all_zero_or_singular_matrix(tmp_path, capsys, matrix):
    code, out, err = _run(
        capsys, "heading", _good_csv(tmp_path), "--calibration", _calibration_file(tmp_path, matrix=matrix)
    )
    assert code == 2 and out == "" and "cal.json" in err and "matrix" in err


@pytest.mark.parametrize("command", ["heading", "fit"])
def test_a_field_over_128_kib_is_one_clear_line(tmp_path, capsys, command):
    huge = "1" * (130 * 1024)
    path = _csv(tmp_path, "\n".join([HEADER, *_rows(50), f"{huge},1,1,0,0,-9.81", *_rows(50)]) + "\n")
    code, out, err = _run(capsys, command, path)
    assert code == 2 and out == ""
    assert "line 52" in err and "128 KiB" in err and len(err.strip().splitlines()) == 1


@pytest.mark.parametrize("command", ["heading", "fit"])
@pytest.mark.parametrize("value", ["1e200", "-3e150", "1e12"])
def test_absurd_magnitudes_are_refused_before_any_maths(tmp_path, capsys, command, value):
    rows = _rows()
    rows[7] = f"{value},1,1,0,0,-9.81"
    code, out, err = _run(capsys, command, _csv(tmp_path, "\n".join([HEADER, *rows]) + "\n"))
    assert code == 2 and out == ""
    assert "row 8" in err and "mx" in err and "Eigenvalues" not in err and len(err.strip().splitlines()) == 1


def test_a_fit_of_large_but_possible_counts_still_runs(tmp_path, capsys):
    code, out, _err = _run(capsys, "fit", _csv(tmp_path, "\n".join([HEADER, *_rows(scale=1e4)]) + "\n"))
    assert code in (0, 1) and json.loads(out)["method"] == "ellipsoid"


@pytest.mark.parametrize(
    ("separator", "words"), [(";", "semicolons"), ("\t", "tabs"), ("|", "'|'")], ids=["semicolon", "tab", "bar"]
)
def test_another_separator_is_named(tmp_path, capsys, separator, words):
    text = "\n".join(line.replace(",", separator) for line in [HEADER, *_rows()]) + "\n"
    code, out, err = _run(capsys, "heading", _csv(tmp_path, text))
    assert code == 2 and out == "" and f"separated by {words}" in err and "comma" in err


def test_a_quoted_semicolon_file_is_named_too(tmp_path, capsys):
    text = "\n".join(";".join(f'"{cell}"' for cell in line.split(",")) for line in [HEADER, *_rows()]) + "\n"
    code, _out, err = _run(capsys, "heading", _csv(tmp_path, text))
    assert code == 2 and "separated by semicolons" in err


def test_a_quoted_comma_file_is_read(tmp_path, capsys):
    text = "\n".join(",".join(f'"{cell}"' for cell in line.split(",")) for line in [HEADER, *_rows()]) + "\n"
    code, out, err = _run(capsys, "heading", _csv(tmp_path, text))
    assert code == 0 and len(out.splitlines()) == 201, err


@pytest.mark.parametrize("header", ["mx,my,mz,ax,ay,az,mx", "mx,my,mz,ax,ay,az,AY"])
def test_a_duplicated_column_is_refused(tmp_path, capsys, header):
    rows = [f"{row},5" for row in _rows()]
    code, out, err = _run(capsys, "heading", _csv(tmp_path, "\n".join([header, *rows]) + "\n"))
    assert code == 2 and out == "" and "more than once" in err


def test_a_duplicated_column_that_is_not_read_is_ignored(tmp_path, capsys):
    rows = [f"{row},5,6" for row in _rows()]
    code, _out, err = _run(capsys, "heading", _csv(tmp_path, "\n".join([f"{HEADER},note,note", *rows]) + "\n"))
    assert code == 0, err
