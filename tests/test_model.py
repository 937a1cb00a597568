"""The calibration record: the model's formula, JSON round trip, stable ids and clear refusals."""

import json

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st
from hypothesis.extra.numpy import arrays

from magnet.model import Calibration

finite = st.floats(-1e3, 1e3, allow_nan=False, allow_infinity=False)


@settings(max_examples=50, deadline=None)
@given(offset=arrays(float, 3, elements=finite), matrix=arrays(float, (3, 3), elements=finite),
       raw=arrays(float, (5, 3), elements=finite))
def test_apply_is_matrix_times_raw_minus_offset_and_survives_json(offset, matrix, raw):
    cal = Calibration(method="ellipsoid", offset=offset, matrix=matrix)
    expected = np.array([matrix @ (r - offset) for r in raw])
    assert np.allclose(cal.apply(raw), expected)
    again = Calibration.from_dict(json.loads(json.dumps(cal.to_dict())))
    assert np.array_equal(again.offset, cal.offset) and np.array_equal(again.matrix, cal.matrix)
    assert again.content_id == cal.content_id


def test_content_id_is_stable_for_identical_coefficients_and_changes_with_them():
    a = Calibration(method="sphere", offset=[1, 2, 3], matrix=np.eye(3), quality={"x": 1})
    b = Calibration(method="sphere", offset=[1, 2, 3], matrix=np.eye(3), quality={"x": 2})
    c = Calibration(method="sphere", offset=[1, 2, 3.001], matrix=np.eye(3))
    assert a.content_id == b.content_id != c.content_id


@pytest.mark.parametrize("data, words", [
    ({"offset": [0, 0, 0]}, "missing matrix"),
    ({"matrix": np.eye(3).tolist()}, "missing offset"),
    ({"offset": [0, 0], "matrix": np.eye(3).tolist()}, "offset must be 3 numbers"),
    ({"offset": [0, 0, float("nan")], "matrix": np.eye(3).tolist()}, "non-finite"),
    ({"offset": [0, 0, 0], "matrix": [[1, 0], [0, 1]]}, "3x3"),
    ([1, 2, 3], "JSON object"),
])
def test_from_dict_refuses_bad_records_with_a_message(data, words):
    with pytest.raises(ValueError, match=words):
        Calibration.from_dict(data)


def test_quality_with_numpy_values_is_json_able():
    cal = Calibration(method="x", offset=np.zeros(3), matrix=np.eye(3),
                      quality={"a": np.float64(1.5), "b": np.arange(3), "c": float("nan"), "d": np.bool_(True)})
    text = json.dumps(cal.to_dict())
    assert json.loads(text)["quality"] == {"a": 1.5, "b": [0, 1, 2], "c": None, "d": True}
