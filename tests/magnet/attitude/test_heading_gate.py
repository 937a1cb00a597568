"""magnet.attitude.heading_gate: field samples at odds with vqf's heading left out while the device did not turn (a
slow turn of the field, a parked car passed), against the simulator's truth and the plain maths."""

import math

import numpy as np
import pytest
import vqf

from magnet import frames
from magnet.attitude import fusion
from magnet.attitude.heading_gate import HeadingGate, HeadingGateSettings
from services.bench import field_runs

PERIOD_S = 0.02


def walk(name, seconds, seed):
    run = field_runs.field_run(field_runs.MOTIONS[name], seed, field_runs.FieldSettings(seconds=seconds))
    return run, run.errors.true_calibration().apply(run.mag_ut)


def turn_about_vertical(run, field, angle_rad):
    """The field (N, 3) turned about the true vertical by angle_rad (N,): |B| and the dip kept."""
    down = frames.quaternion_to_matrix(run.quat_wxyz)[:, 2, :]
    c, s = np.cos(angle_rad)[:, None], np.sin(angle_rad)[:, None]
    along = np.sum(down * field, axis=1, keepdims=True) * down
    return field * c + np.cross(down, field) * s + along * (1.0 - c)


def turned_field(run, field, start, stop, degrees):
    """The field turned about the vertical by up to ``degrees`` (a sine squared) from sample start to stop: |B| and
    the dip kept, as a parked car passed on the way nearly does until its peak."""
    angle = np.zeros(len(field))
    angle[start:stop] = np.radians(degrees) * np.sin(np.linspace(0.0, np.pi, stop - start)) ** 2
    return turn_about_vertical(run, field, angle)


def turned_for_good(run, field, start, ramp, degrees):
    """The field turned by ``degrees`` from sample ``start`` on (reached over ``ramp`` samples) and left so."""
    angle = np.zeros(len(field))
    angle[start:] = np.radians(degrees) * np.minimum(1.0, np.arange(len(field) - start) / ramp)
    return turn_about_vertical(run, field, angle)


def test_a_slow_turn_of_the_field_moves_the_heading_less_with_the_gate():
    """A turn of the field by 25 deg over 3 s and back (|B| and dip kept: what the watch's steps miss in a swinging
    hand), on straight stretches of walks with the true calibration: how far it moves the causal heading from the
    same filter's on the undisturbed field, over the turn and 6 s after."""
    moved = {False: [], True: []}
    for name, seed in (("walk-texting", 1), ("walk-texting", 2), ("walk-hand", 2)):
        run, field = walk(name, 60.0, seed)
        truth = field_runs.magnetic_truth(run)
        for gate in (False, True):
            calm = fusion.fuse_causal(run.gyr_rads, run.acc_ms2, field, PERIOD_S, heading_gate=gate)
            calm_deg = field_runs.heading_error_deg(calm.quat_wxyz, truth)
            for degrees in (-25.0, 25.0):
                turned = turned_field(run, field, 2000, 2300, degrees)
                fused = fusion.fuse_causal(run.gyr_rads, run.acc_ms2, turned, PERIOD_S, heading_gate=gate)
                moved_deg = field_runs.heading_error_deg(fused.quat_wxyz, truth) - calm_deg
                moved[gate].append(float(np.sqrt(np.mean(moved_deg[2000:2600] ** 2))))
    without, with_gate = np.mean(moved[False]), np.mean(moved[True])
    assert without > 1.0  # the watch and vqf's own rejection let it through: measured 1.36 deg
    assert with_gate < 0.6 * without  # measured 0.58


def test_the_answers_do_not_depend_on_how_the_samples_are_batched():
    run, field = walk("walk-hand", 30.0, 2)
    field = turned_field(run, field, 800, 1100, 30.0)
    answers = []
    for size in (7, 25, 100):
        filter_ = fusion.Fusion(PERIOD_S)
        parts = [
            filter_.update(run.gyr_rads[i : i + size], run.acc_ms2[i : i + size], field[i : i + size])
            for i in range(0, len(field), size)
        ]
        answers.append((np.concatenate([p.quat_wxyz for p in parts]), np.concatenate([p.mag_disturbed for p in parts])))
    for quat, flags in answers[1:]:  # to the last bits: without AVX-512 numpy's SIMD tails differ by batch length
        np.testing.assert_allclose(quat, answers[0][0], rtol=0.0, atol=1e-12)
        np.testing.assert_array_equal(flags, answers[0][1])


def test_a_field_that_stays_turned_is_taken_after_max_reject_s():
    """A heading that went wrong (or a field turned for good) is not held off for ever: 20 s after the field turned
    by 30 deg for good, the gated filter follows it as the plain one does."""
    run, field = walk("walk-texting", 60.0, 1)
    field = turned_for_good(run, field, 1000, 100, 30.0)
    truth = field_runs.magnetic_truth(run)
    late = slice(1000 + int(20.0 / PERIOD_S), None)
    means = []
    for gate in (True, False):
        fused = fusion.fuse_causal(run.gyr_rads, run.acc_ms2, field, PERIOD_S, watch=False, heading_gate=gate)
        means.append(np.mean(field_runs.heading_error_deg(fused.quat_wxyz, truth)[late]))
        if gate:
            assert np.asarray(fused.mag_disturbed)[1000:1500].any()  # it was left out at first
    assert abs(means[1]) > 20.0
    assert abs(means[0] - means[1]) < 0.2 * abs(means[1])  # measured 2.2 of 22.7 deg


def test_settings_refuse_what_is_not_a_positive_number():
    for bad in ({"floor_deg": 0.0}, {"relative": -1.0}, {"tau_s": float("nan")}, {"percent": 120.0}):
        with pytest.raises(ValueError, match="HeadingGateSettings"):
            HeadingGateSettings(**bad)


def plain_gate(settings, period_s, pieces):
    """The gate in plain Python (the module docstring, sample by sample), over ``pieces``: (gyr, field, start, bias,
    delta, init) per piece, each within a block: the fed fields and flags."""
    block = max(1, round(0.5 / period_s))
    width = max(1, round(settings.turn_s / period_s))
    floor, turn = math.radians(settings.floor_deg), math.radians(settings.turn_deg)
    hold_n, max_run = round(settings.hold_s / period_s), round(settings.max_reject_s / period_s)
    weight = -math.expm1(-period_s / settings.smooth_s)
    st = {"n": 0, "att": np.array([1.0, 0, 0, 0]), "bias": np.zeros(3), "delta": 0.0, "init": 0.0, "level": 0.0,
          "seen": 0.0, "hold": 0.0, "run": 0.0, "accepting": False, "over": False, "turned": 0.0,
          "smoothed": np.nan}  # fmt: skip
    ring, pending = np.zeros(width), np.full(block, np.nan)
    fed_all, flags_all = [], []
    for gyr, field, start, bias, delta, init in pieces:
        for i in range(len(gyr)):
            g = st["n"]
            if g % block == 0:
                st.update(att=np.asarray(start, float), bias=np.asarray(bias, float), delta=delta, init=init)
                if init != 0.0:
                    st.update(level=0.0, seen=0.0, run=0.0, hold=0.0, accepting=False, over=False, smoothed=np.nan)
            r = gyr[i] - st["bias"]
            norm = np.linalg.norm(r)
            half = norm * period_s / 2.0
            step = np.r_[math.cos(half), r * (math.sin(half) / norm if norm > 0 else 0.0)]
            att = frames.quaternion_multiply(st["att"][None], step[None])[0]
            st["att"] = att / np.linalg.norm(att)
            rot = frames.quaternion_to_matrix(st["att"][None])[0]
            st["turned"] += (rot @ r)[2] * period_s
            back = min(g, width)
            turned = max([abs(st["turned"] - ring[(g - m) % width]) for m in range(1, back + 1)], default=0.0)
            ring[g % width] = st["turned"]
            v = field[i]
            innovation = np.nan
            if np.any(v != 0.0):
                earth = rot @ v
                now = math.remainder(math.atan2(earth[0], earth[1]) - st["delta"], 2.0 * math.pi)
                was = st["smoothed"]
                if not np.isnan(was):
                    now = math.remainder(was + weight * math.remainder(now - was, 2.0 * math.pi), 2.0 * math.pi)
                innovation = st["smoothed"] = now
            limit = max(floor, settings.relative * st["level"])
            ready = st["init"] == 0.0 and st["seen"] * period_s >= settings.learn_s and st["level"] > 0.0
            over = bool(np.isfinite(innovation) and abs(innovation) > limit)
            st["over"] |= over
            raw = ready and over and turned <= turn and not st["accepting"]
            flagged = raw or (bool(np.isfinite(innovation)) and st["hold"] > 0)
            if raw:
                st["hold"] = float(hold_n)
            elif flagged:
                st["hold"] -= 1.0
            st["run"] = st["run"] + 1.0 if flagged else 0.0
            if st["run"] > max_run:
                flagged = False
                st.update(run=0.0, hold=0.0, accepting=True)
            pending[g % block] = np.nan if flagged else abs(innovation)
            flags_all.append(flagged)
            fed_all.append(np.zeros(3) if flagged else v)
            st["n"] += 1
            if st["n"] % block == 0:
                finite = pending[np.isfinite(pending)]
                pending[:] = np.nan
                if st["accepting"] and not st["over"]:
                    st["accepting"] = False
                st["over"] = False
                if finite.size and st["init"] == 0.0 and not st["accepting"]:
                    st["seen"] += finite.size
                    alpha = max(-math.expm1(-block * period_s / settings.tau_s), block / st["seen"])
                    st["level"] += min(alpha, 1.0) * (np.percentile(finite, settings.percent) - st["level"])
    return np.array(fed_all), np.array(flags_all)


def test_the_compiled_gate_is_the_plain_maths():
    """vqf run beside the gate on a walk whose field turns slowly twice (once for good: the acceptance), its
    6D attitude, bias, delta and kMagInit taken at each block's start; batches of 10 (pieces cut at blocks)."""
    run, field = walk("walk-texting", 40.0, 1)
    field = turned_for_good(run, turned_field(run, field, 800, 1100, 40.0), 1200, 50, 40.0)
    gyr, acc, mag = (fusion.to_vqf_frame(x) for x in (run.gyr_rads, run.acc_ms2, field))
    settings = HeadingGateSettings()
    gate, filter_ = HeadingGate(PERIOD_S, settings), vqf.VQF(PERIOD_S)
    pieces, fed_all, flags_all = [], [], []
    start = bias = None
    delta = init = 0.0
    i = 0
    while i < len(gyr):
        size = min(10, gate.block - gate.samples % gate.block)
        part = slice(i, i + size)
        if gate.samples % gate.block == 0:
            start, bias = np.asarray(filter_.getQuat6D()), np.asarray(filter_.getBiasEstimate()[0])
            delta, init = float(filter_.getDelta()), float(filter_.state["kMagInit"])
        fed, flags = gate.update(gyr[part], mag[part], start, bias, delta, init)
        pieces.append((gyr[part], mag[part], start, bias, delta, init))
        fed_all.append(fed)
        flags_all.append(flags)
        filter_.updateBatch(np.ascontiguousarray(gyr[part]), np.ascontiguousarray(acc[part]), fed)
        i += size
    fed_plain, flags_plain = plain_gate(settings, PERIOD_S, pieces)
    flags = np.concatenate(flags_all)
    np.testing.assert_array_equal(flags, flags_plain)
    np.testing.assert_allclose(np.concatenate(fed_all), fed_plain, rtol=0, atol=0)
    assert not flags[:800].any()  # not while vqf takes its first heading, nor before its level is learnt
    assert flags[800:1100].any()  # the turn that came and went: left out
    assert flags[1200:1500].sum() == 250  # the turn for good: left out for max_reject_s, then taken
    assert not flags[1500:].any()


def test_beside_the_turn_gate_in_one_compiled_call_the_answers_are_the_piece_by_piece_ones_to_the_bit():
    """``gated_run`` hands the turn gate's per-sample turns to the heading gate (one sqrt, cos and sin a sample):
    vqf's quaternions and flags the same bits as the two gates and vqf's ``updateBatch`` called piece by piece (each
    gate computing its own turns), batches of 1 to 150 samples, on the walk whose field turns twice."""
    from magnet.attitude.turn_gate import TurnGate, run_gated

    run, field = walk("walk-texting", 40.0, 1)
    field = turned_for_good(run, turned_field(run, field, 800, 1100, 40.0), 1200, 50, 40.0)
    gyr, acc, mag = (np.ascontiguousarray(fusion.to_vqf_frame(x)) for x in (run.gyr_rads, run.acc_ms2, field))
    answers = []
    for compiled in (True, False):
        gate, filter_ = TurnGate(PERIOD_S), vqf.VQF(PERIOD_S)
        gate.heading = HeadingGate(PERIOD_S)
        rng, parts, start = np.random.default_rng(7), [], 0
        while start < len(gyr):
            rows = slice(start, min(start + int(rng.integers(1, 151)), len(gyr)))
            piece = None if compiled else (lambda g, a, f, _w, v=filter_: v.updateBatch(g, a, f))
            out = run_gated(
                gate, filter_, piece, (gyr[rows], acc[rows], mag[rows]), np.zeros(rows.stop - rows.start, bool)
            )
            parts.append((np.asarray(out["quat9D"]), np.asarray(out["magDistDetected"], dtype=bool)))
            start = rows.stop
        answers.append([np.concatenate([p[k] for p in parts]) for k in range(2)])
    np.testing.assert_array_equal(answers[0][0], answers[1][0])
    np.testing.assert_array_equal(answers[0][1], answers[1][1])
    assert answers[0][1][800:1100].any()  # the heading gate was at work
