"""``Fusion.update_rows`` (one compiled call, ``magnet._kernels.fuse_rows``: the field's watch, the flagged samples'
field left out, the turn gate and vqf) against the same steps written out with the Python pieces they replace
(``FieldWatch.update``, ``np.where``, ``run_gated``), on random samples with field disturbances, cut into random runs
of a drain at random places."""

from __future__ import annotations

import numpy as np
import pytest

from magnet.attitude.fusion import Fusion
from magnet.attitude.turn_gate import run_gated


def _samples(rng: np.random.Generator, count: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """gyr, acc, field (count, 3) in vqf's frame: a device held nearly still, the field disturbed twice."""
    gyr = rng.normal(0.0, 0.005, (count, 3))
    acc = rng.normal(0.0, 0.4, (count, 3)) + [0.0, 0.0, 9.81]
    field = rng.normal(0.0, 0.3, (count, 3)) + [0.0, 20.0, -40.0]
    field[1500:1600] += [25.0, -10.0, 5.0]  # after the watch's 5 s of learning at 200 and 100 Hz
    field[2000:2030] *= 1.4
    return gyr, acc, field


def _plain(
    fusion: Fusion, gyr: np.ndarray, acc: np.ndarray, field: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """What update_vqf_frame did before, step by step: quaternions (n, 4), disturbed (n,), the watch's flags (n,)."""
    assert fusion.watch is not None and fusion.turn_gate is not None
    watched = fusion.watch.update(field, gyr)
    if watched.any():
        field = np.ascontiguousarray(np.where(watched[:, None], 0.0, field))
    out = run_gated(fusion.turn_gate, fusion._filter, None, (gyr, acc, field), watched)
    return np.asarray(out["quat9D"]), np.asarray(out["magDistDetected"], dtype=bool) | watched, watched


@pytest.mark.parametrize("period_s", [0.01, 0.005])
def test_update_rows_is_the_watch_the_gate_and_vqf_written_out(period_s):
    rng = np.random.default_rng(11)
    count = 2400
    gyr, acc, field = _samples(rng, count)
    compiled, plain = Fusion(period_s), Fusion(period_s)
    quat, disturbed = np.full((count + 7, 4), np.nan), np.zeros(count + 7, dtype=bool)
    # the drain holds 7 rows of another device in front: the rows are addressed within the whole drain
    inputs = tuple(np.ascontiguousarray(np.vstack([np.ones((7, 3)), x])) for x in (gyr, acc, field))
    want_q, want_d, watched, start = [], [], 0, 0
    while start < count:
        stop = min(start + int(rng.integers(1, 160)), count)
        compiled.update_rows(inputs, 7 + start, 7 + stop, quat, disturbed)
        q, d, w = _plain(plain, gyr[start:stop], acc[start:stop], field[start:stop])
        watched += int(w.sum())
        want_q.append(q)
        want_d.append(d)
        start = stop
    want_d_all = np.concatenate(want_d)
    assert 20 < watched < count // 4  # the watch left some samples' field out (zero rows for vqf), not most
    np.testing.assert_array_equal(quat[7:], np.concatenate(want_q))
    np.testing.assert_array_equal(disturbed[7:], want_d_all)
    assert np.isnan(quat[:7]).all() and not disturbed[:7].any()  # the other device's rows untouched
    assert compiled.samples == count
    np.testing.assert_array_equal(compiled.watch.state, plain.watch.state)
    np.testing.assert_array_equal(compiled.turn_gate.state, plain.turn_gate.state)


def test_update_rows_refuses_rows_outside_the_drain():
    fusion = Fusion(0.01)
    rng = np.random.default_rng(3)
    inputs = _samples(rng, 50)
    quat, disturbed = np.empty((50, 4)), np.zeros(50, dtype=bool)
    fusion.update_rows(inputs, 0, 10, quat, disturbed)  # the first batch runs the plain companion's way
    with pytest.raises(ValueError, match="not within"):
        fusion.update_rows(inputs, 40, 60, quat, disturbed)
    with pytest.raises(ValueError, match="disturbed"):
        fusion.update_rows(inputs, 10, 20, quat, np.zeros(49, dtype=bool))
