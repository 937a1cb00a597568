"""The calibration record: the model's formula, JSON round trip, stable ids and clear refusals."""

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from magnet.frames import quaternion_to_matrix
from magnet.model import MAX_CONDITION, Calibration, Quality, check_plausible

finite = st.floats(-1e3, 1e3, allow_nan=False, allow_infinity=False)


# arrays of the same fixed shapes each time, 27 floats drawn one by one (the cost): 25 examples
@settings(max_examples=25, deadline=None)
@given(
    offset=arrays(float, 3, elements=finite),
    matrix=arrays(float, (3, 3), elements=finite),
    raw=arrays(float, (5, 3), elements=finite),
)
def test_apply_is_matrix_times_raw_minus_offset(offset, matrix, raw):
    cal = Calibration(method="ellipsoid", offset=offset, matrix=matrix)
    expected = np.array([matrix @ (r - offset) for r in raw])
    assert np.allclose(cal.apply(raw), expected)


@settings(max_examples=25, deadline=None)
@given(
    offset=arrays(float, 3, elements=finite),
    scales=arrays(float, 3, elements=st.floats(0.4, 3.0)),
    q=arrays(float, 4, elements=st.floats(0.1, 1.0)),
)
def test_plausible_records_survive_json(offset, scales, q):
    cal = Calibration(method="ellipsoid", offset=offset, matrix=quaternion_to_matrix(q) @ np.diag(scales))
    again = Calibration.from_dict(json.loads(json.dumps(cal.to_dict())))
    assert np.array_equal(again.offset, cal.offset) and np.array_equal(again.matrix, cal.matrix)
    assert again.content_id == cal.content_id


def test_content_id_is_stable_for_identical_coefficients_and_changes_with_them():
    a = Calibration(method="sphere", offset=[1, 2, 3], matrix=np.eye(3), quality={"x": 1})
    b = Calibration(method="sphere", offset=[1, 2, 3], matrix=np.eye(3), quality={"x": 2})
    c = Calibration(method="sphere", offset=[1, 2, 3.001], matrix=np.eye(3))
    assert a.content_id == b.content_id != c.content_id


@pytest.mark.parametrize(
    "data, words",
    [
        ({"offset": [0, 0, 0]}, "missing matrix"),
        ({"matrix": np.eye(3).tolist()}, "missing offset"),
        ({"offset": [0, 0], "matrix": np.eye(3).tolist()}, "offset must be 3 numbers"),
        ({"offset": [0, 0, float("nan")], "matrix": np.eye(3).tolist()}, "non-finite"),
        ({"offset": [0, 0, 0], "matrix": [[1, 0], [0, 1]]}, "3x3"),
        ([1, 2, 3], "JSON object"),
    ],
)
def test_from_dict_refuses_bad_records_with_a_message(data, words):
    with pytest.raises(ValueError, match=words):
        Calibration.from_dict(data)


def test_quality_with_numpy_values_is_json_able():
    cal = Calibration(
        method="x",
        offset=np.zeros(3),
        matrix=np.eye(3),
        quality={"a": np.float64(1.5), "b": np.arange(3), "c": float("nan"), "d": np.bool_(True)},
    )
    text = json.dumps(cal.to_dict())
    assert json.loads(text)["quality"] == {"a": 1.5, "b": [0, 1, 2], "c": None, "d": True}


_PLAIN = {"offset": [1.0, 2.0, 3.0], "matrix": np.eye(3).tolist()}


@pytest.mark.parametrize(
    "changes, words",
    [
        ({"matrix": [[1, 0, 0], [0, 1, 0], [0, 0, 0]]}, "condition number inf"),
        ({"matrix": np.diag([1.0, 1.0, 1e-3]).tolist()}, "condition number 1e\\+03"),
        ({"matrix": np.diag([-1.0, 1.0, 1.0]).tolist()}, "negative determinant"),
        ({"matrix": (-np.eye(3)).tolist()}, "negative determinant"),
        ({"offset": [1e4, 0, 0]}, "offset 1e\\+04 ut exceeds 5000"),
        ({"offset": [60, 0, 0], "unit": "gauss", "output_unit": "gauss"}, "exceeds 50 gauss"),
        ({"matrix": (1e9 * np.eye(3)).tolist()}, "scales the field by 1e\\+09"),
        ({"matrix": (1e-3 * np.eye(3)).tolist()}, "scales the field by 0.001"),
        ({"unit": "gauss"}, "scales the field by 0.01"),  # gauss read as uT: 100 times too small
        ({"matrix": (1e9 * np.eye(3)).tolist(), "unit": "counts"}, "beyond 1/1e\\+06"),
        ({"offset": [1e8, 0, 0], "unit": "counts"}, "exceeds"),
        ({"accepted": "yes"}, "true or false"),
        ({"method": 5}, "must be a string"),
        ({"field_strength": -1}, "finite number >= 0"),
        ({"quality": {"coverage": "most"}}, "coverage must be a number"),
        ({"quality": [1, 2]}, "map of figures"),
    ],
)
def test_from_dict_refuses_implausible_records(changes, words):
    with pytest.raises(ValueError, match=words):
        Calibration.from_dict({**_PLAIN, **changes})


def test_nanotesla_offsets_are_judged_in_microtesla():
    cal = Calibration.from_dict(
        {**_PLAIN, "matrix": (1e-3 * np.eye(3)).tolist(), "offset": [40_000.0, 0, 0], "unit": "nt"}
    )  # 40 uT of hard iron
    assert cal.offset[0] == 40_000.0
    assert check_plausible(cal) is cal
    assert MAX_CONDITION >= 5  # every fit the gate accepts (axis ratio <= 5) passes the entry check


def test_quality_round_trips_through_its_map_and_keeps_extra_figures():
    quality = Quality(
        geometry="sphere",
        residual_rms_ut=0.4,
        coverage=0.9,
        cells_hit=90,
        cell_count=100,
        missing_directions=("point the nose (x) down",),
        scatter_condition=float("inf"),
        extra={"note": "z left uncorrected"},
    )
    data = json.loads(json.dumps(quality.to_dict()))
    assert data["scatter_condition"] is None and data["note"] == "z left uncorrected" and data["dip_spread_deg"] is None
    again = Quality.from_dict(data)
    assert again.coverage == 0.9 and again.cells_hit == 90 and again.missing_directions == quality.missing_directions
    assert again["note"] == "z left uncorrected" and again.get("radius", 7) == 7 and again.to_dict() == data
    assert Quality().to_dict() == {} and Quality(extra={"selftest": {"ok": True}}).to_dict() == {
        "selftest": {"ok": True}
    }
