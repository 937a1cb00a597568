"""Files from outside: ``magnet heading --calibration`` (and every JSON reader through ``services.common.jsonio``) and
the sample CSV reader refuse what they cannot use with one line naming the file and exit 2, never a traceback or a
numpy warning: deep nesting, oversized files, binary input, a vanishing or huge matrix, unknown method or unit,
booleans where numbers belong."""

from __future__ import annotations

import json
import time

import numpy as np
import pytest

from magnet.calibration import Method
from magnet.model import KNOWN_METHODS, Calibration
from services.cli import main
from services.common import jsonio
from services.common.inputs import csvio

GOOD = Calibration("ellipsoid", [1.0, 2.0, 3.0], np.diag([1.0, 1.1, 0.9])).to_dict()


def _samples(tmp_path):
    rng = np.random.default_rng(0)
    mag = rng.normal(size=(100, 3))
    mag = 50 * mag / np.linalg.norm(mag, axis=1, keepdims=True)
    path = tmp_path / "s.csv"
    path.write_text("mx,my,mz,ax,ay,az\n" + "\n".join(f"{x:.5g},{y:.5g},{z:.5g},0,0,-9.81" for x, y, z in mag))
    return str(path)


def _heading(tmp_path, capsys, calibration_bytes):
    cal = tmp_path / "cal.json"
    cal.write_bytes(calibration_bytes)
    code = main(["heading", _samples(tmp_path), "--calibration", str(cal)])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def _record(**changes):
    return json.dumps({**GOOD, **changes}).encode()


@pytest.mark.parametrize(
    "content, words",
    [
        (b"[" * 100_000 + b"]" * 100_000, "nested too deeply"),
        (b"[" * 500 + b"]" * 500, "nested 500 levels deep"),
        (_record(quality={"note": [[[[[[[[[[[[[[[[[[["deep"]]]]]]]]]]]]]]]]]]]}), "nested 21 levels deep"),
        (b"\x89PNG\r\n\x1a\n\x00\x00\xff\xfe", "not a text file"),
        (b" " * (jsonio.MAX_JSON_BYTES + 1), "larger than"),
        (b"{not json", "not JSON"),
        (_record(matrix=(np.eye(3) * 1e-300).tolist()), "scales the field by 1e-300"),
        (_record(matrix=(np.eye(3) * 1e300).tolist()), "entry of 1e+300"),
        (_record(method="magic"), "method 'magic' is not one of"),
        (_record(unit="furlongs"), "unit 'furlongs' is not one of"),
        (_record(output_unit="gauss-ish"), "output_unit 'gauss-ish' is not one of"),
        (_record(matrix=[[True, False, False], [False, True, False], [False, False, True]]), "true/false"),
        (_record(matrix=[[1.0, 0, 0], [0, True, 0], [0, 0, 1.0]]), "true/false"),
        (_record(offset=[True, 0.0, 0.0]), "true/false"),
        (_record(sample_count=True), "sample_count"),
        (_record(field_strength=False), "field_strength"),
    ],
)
def test_heading_refuses_an_unusable_calibration_file_with_one_line(tmp_path, capsys, content, words):
    code, out, err = _heading(tmp_path, capsys, content)
    assert code == 2 and out == "", err
    assert "cal.json" in err and words in err, err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err and "Warning" not in err


def test_a_calibration_file_within_the_limits_is_read(tmp_path, capsys):
    code, out, err = _heading(tmp_path, capsys, _record(quality={"note": "fine", "missing_directions": ["up"]}))
    assert code == 0 and out.startswith("heading_deg,") and err == ""


def test_every_fit_method_is_a_method_a_record_may_name():
    assert {m.value for m in Method} <= KNOWN_METHODS


def test_the_depth_counts_containers_not_brackets_in_strings():
    assert jsonio.nesting_depth(json.loads('{"a": "[[[[[[[[[[[[[[[[[[[[[[[[\\"]]]", "b": [1, [2, {}]]}')) == 4
    assert jsonio.nesting_depth(5) == 0
    assert jsonio.loads_bounded('["[[[[[[[[[[[[[[[[[[[[[[[[[["]', "x") == ["[[[[[[[[[[[[[[[[[[[[[[[[[["]


@pytest.mark.parametrize("text", ['"' + "a" * 500_000, '"\\' * 200_000, '["' * 200_000, "[" * 500_000, "{" * 500_000])
def test_pathological_json_is_refused_in_linear_time(text):
    start = time.perf_counter()
    with pytest.raises(ValueError, match=r"^x: "):
        jsonio.loads_bounded(text, "x")
    assert time.perf_counter() - start < 1.0


def test_the_csv_reader_names_a_binary_or_oversized_file(tmp_path, monkeypatch):
    binary = tmp_path / "b.csv"
    binary.write_bytes(b"mx,my,mz\n\xff\xfe\x00\x01")
    with pytest.raises(ValueError, match=r"b\.csv: not a text CSV file"):
        csvio.read_samples(binary)
    monkeypatch.setattr(csvio, "MAX_CSV_BYTES", 100)
    big = tmp_path / "big.csv"
    big.write_text("mx,my,mz\n" + "1,2,3\n" * 50)
    with pytest.raises(ValueError, match=r"big\.csv: larger than"):
        csvio.read_samples(big)
