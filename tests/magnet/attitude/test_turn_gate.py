"""magnet.attitude.turn_gate: the accelerometer fed a window late and left out where the course turned (in a gait),
or levelled there (in a swinging hand), so that a walker's or runner's corners are not taken for gravity leaning
(against the simulator's truth and the plain maths)."""

import numpy as np
import pytest
import vqf

from magnet import frames
from magnet.attitude import fusion
from magnet.attitude.turn_gate import TurnGate, TurnSettings
from magnet.simulator import SimulatorConfig, Trajectory, simulate
from services.bench import field_runs

PERIOD_S = 0.02


def about_z(rate_rads, seconds):
    """Body rates (n, 3): turning about the Earth's vertical (a level device) at ``rate_rads`` for ``seconds``."""
    gyr = np.zeros((round(seconds / PERIOD_S), 3))
    gyr[:, 2] = rate_rads
    return gyr


def stepping(count, step_hz=2.5, bounce_ms2=4.0):
    """Specific force (count, 3) of a level device whose holder steps: gravity plus a bounce at the step rate, and a
    marker in x (which sample came in)."""
    t = np.arange(count) * PERIOD_S
    acc = np.zeros((count, 3))
    acc[:, 2] = 9.81 + bounce_ms2 * np.sin(2.0 * np.pi * step_hz * t)
    acc[:, 0] = np.arange(count) * 0.01
    return acc


LEVEL = np.array([1.0, 0.0, 0.0, 0.0])


def fed_in_batches(gate, gyr, acc, bias=None, size=25):
    bias = np.zeros(3) if bias is None else bias
    parts = [gate.update(gyr[i : i + size], acc[i : i + size], LEVEL, bias) for i in range(0, len(gyr), size)]
    return np.vstack([fed for fed, _ in parts]), np.concatenate([gated for _, gated in parts])


def test_in_a_gait_the_accelerometer_comes_a_window_late_and_is_left_out_in_turns():
    gate = TurnGate(PERIOD_S, TurnSettings(window_s=1.0, turn_deg=15.0))
    still, turn = about_z(0.0, 4.0), about_z(np.radians(90.0), 1.0)  # a 90 deg corner in one second
    gyr = np.vstack([still, turn, still])
    acc = stepping(len(gyr))
    fed, gated = fed_in_batches(gate, gyr, acc)
    late = gate.width - 1  # the delay: the longest stride judged (1.35 s), 67 samples
    assert late == 67 and gate.stride == 40  # the steps' bounce repeats every 20 samples; a stride is two steps
    # gaits are judged at the start of each 0.5 s block on the 2 s (gait_s) before: the first 2 s as they come, then
    # the sample of 67 earlier
    assert np.allclose(fed[:100], acc[:100])
    assert np.allclose(fed[100:200], acc[100 - late : 200 - late])
    # the samples fed the corner's specific force (200..249, 67 later) are left out; none on the straights far off
    assert gated[200 + late : 250 + late].all()
    assert not gated[: 175 + late].any() and not gated[275 + late :].any()
    assert np.all(fed[gated] == 0.0)
    assert np.allclose(fed[275 + late :], acc[275:-late])  # after it, in the same axes again


def test_a_batch_reaching_past_its_block_is_refused():
    gate = TurnGate(PERIOD_S)
    gate.update(about_z(0.0, 0.2), stepping(10), LEVEL, np.zeros(3))
    assert gate.left_in_block() == 15
    with pytest.raises(ValueError, match="within its block"):
        gate.update(about_z(0.0, 0.4), stepping(20), LEVEL, np.zeros(3))


def test_without_steps_the_accelerometer_is_fed_as_it_comes():
    gate = TurnGate(PERIOD_S)
    gyr = np.vstack([about_z(0.0, 4.0), about_z(np.radians(90.0), 1.0), about_z(0.0, 2.0)])
    acc = stepping(len(gyr), bounce_ms2=0.5)  # a vehicle's vibration, not a holder's steps
    fed, gated = fed_in_batches(gate, gyr, acc)
    assert not gated.any() and np.array_equal(fed, acc)


def test_the_late_specific_force_is_turned_into_the_present_axes():
    gate = TurnGate(PERIOD_S, TurnSettings(window_s=1.0, turn_deg=1e6))  # never gated
    gyr = about_z(np.radians(30.0), 4.0) + [0.01, -0.02, 0.0]  # turning, with a bias that vqf knows
    acc = stepping(len(gyr)) + np.random.default_rng(3).normal(0.0, 0.5, (len(gyr), 3))
    fed, gated = fed_in_batches(gate, gyr, acc, np.array([0.01, -0.02, 0.0]))
    angle = np.radians(30.0) * (gate.width - 1) * PERIOD_S  # turned since the sample fed (67 samples back)
    c, s = np.cos(angle), np.sin(angle)
    late = acc[100 - (gate.width - 1) : -(gate.width - 1)]
    turned = np.column_stack([c * late[:, 0] + s * late[:, 1], -s * late[:, 0] + c * late[:, 1], late[:, 2]])
    assert not gated.any()
    assert np.allclose(fed[100:], turned, atol=1e-9)


def test_a_turn_held_longer_than_max_hold_gets_the_accelerometer_back():
    gate = TurnGate(PERIOD_S, TurnSettings(window_s=1.0, turn_deg=15.0, max_hold_s=2.0))
    gyr = about_z(np.radians(60.0), 10.0)  # a walker circling: never a straight
    _, gated = fed_in_batches(gate, gyr, stepping(len(gyr)))
    assert gated.sum() == round(2.0 / PERIOD_S)
    assert not gated[-100:].any()


def test_settings_refuse_what_is_not_a_positive_number():
    with pytest.raises(ValueError, match="turn_deg"):
        TurnSettings(turn_deg=0.0)
    with pytest.raises(ValueError, match="step_s"):
        TurnSettings(step_s=(0.7, 0.3))


def tilt_errors_deg(run, turn_gate):
    filter_ = fusion.Fusion(PERIOD_S, turn_gate=turn_gate)
    parts = [
        filter_.update(run.gyr_rads[i : i + 25], run.acc_ms2[i : i + 25], run.true_field_ut[i : i + 25]).quat_wxyz
        for i in range(0, len(run.t_s), 25)
    ]
    down = frames.quaternion_to_matrix(np.concatenate(parts))[:, 2, :]
    down_true = frames.quaternion_to_matrix(run.quat_wxyz)[:, 2, :]
    errors = np.degrees(np.arccos(np.clip(np.sum(down * down_true, axis=1), -1.0, 1.0)))[500:]
    return float(np.sqrt(np.mean(errors**2)))


def test_a_runners_corners_bend_the_tilt_less_with_the_gate():
    # the true field: what is left is the fusion's tilt, which the corners' centripetal acceleration bends
    ratios = []
    for seed in (1, 2, 3, 4):  # one run (simulated once: the most of the time) through both filters
        run = field_runs.field_run(field_runs.MOTIONS["running"], seed, field_runs.FieldSettings(seconds=80.0))
        plain, gated = tilt_errors_deg(run, False), tilt_errors_deg(run, True)
        assert plain > 2.0  # the corners do bend the plain filter (2.4 to 4.0 deg RMS)
        assert gated < 0.9 * plain
        ratios.append(gated / plain)
    assert np.mean(ratios) < 0.75  # 0.68 when measured (0.51 to 0.78)


def test_a_swinging_hands_corners_bend_the_tilt_less_with_the_swing_levelled():
    # a hand is no gait (its |specific force| does not repeat at a step's lag), but its rates swing: the corners'
    # horizontal acceleration is taken out of the stride's mean rather than samples left out
    run = field_runs.field_run(field_runs.MOTIONS["walk-hand"], 2, field_runs.FieldSettings(seconds=30.0))
    tilt = {}
    for name, settings in (("plain", TurnSettings(swing_sd_rads=1e9)), ("levelled", TurnSettings())):
        filter_ = fusion.Fusion(PERIOD_S, watch=False)
        filter_.turn_gate = TurnGate(PERIOD_S, settings, filter_.params)  # the swing never found, or as it comes
        quat = filter_.update(run.gyr_rads, run.acc_ms2, run.true_field_ut).quat_wxyz
        down, down_true = (frames.quaternion_to_matrix(q)[500:, 2, :] for q in (quat, run.quat_wxyz))
        errors = np.degrees(np.arccos(np.clip(np.sum(down * down_true, axis=1), -1.0, 1.0)))
        tilt[name] = float(np.sqrt(np.mean(errors**2)))
    assert filter_.turn_gate.in_swing
    assert tilt["plain"] > 1.0  # the corners bend it: 1.18 deg RMS when measured
    assert tilt["levelled"] < 0.6 * tilt["plain"]  # 0.60


def test_a_runners_arm_levelled_leaves_no_standing_heading_error():
    """A runner's corners cut out of the accelerometer (a gait's gaps, as before 4 Dec: the swing's upper bound at 4
    rad/s) leave pieces of the arm's swing, which lean the tilt along the course and turn the heading by a standing
    error; levelled as a swing's, they do not. The true field and the gyroscope's true bias taken off: what is left
    is the tilt."""
    run = field_runs.field_run(field_runs.MOTIONS["running"], 1, field_runs.FieldSettings(seconds=90.0))
    gyr = run.gyr_rads - np.mean(run.gyr_rads - run.true_gyr_rads, axis=0)
    truth = field_runs.magnetic_truth(run)
    mean_deg = {}
    for name, settings in (("gaps", TurnSettings(swing_max_rads=4.0)), ("levelled", TurnSettings())):
        filter_ = fusion.Fusion(PERIOD_S, watch=False)
        filter_.turn_gate = TurnGate(PERIOD_S, settings, filter_.params)
        quat = filter_.update(gyr, run.acc_ms2, run.true_field_ut).quat_wxyz
        mean_deg[name] = float(np.mean(field_runs.heading_error_deg(quat, truth)[1000:]))
    assert abs(mean_deg["gaps"]) > 2.0  # 3.0 deg when measured
    assert abs(mean_deg["levelled"]) < 0.25 * abs(mean_deg["gaps"])  # -0.55


def test_the_swing_is_a_swinging_hand_not_a_pocket_texting_or_a_vehicle():
    settings = field_runs.FieldSettings(seconds=8.0)
    for motion, swings in (
        ("walk-hand", True),
        ("running", True),  # a runner's arm (4.6-6.9 rad/s): a swing since 4 Dec
        ("walk-pocket", False),
        ("walk-texting", False),
        ("robot", False),
    ):
        run = field_runs.field_run(field_runs.MOTIONS[motion], 1, settings)
        gate = TurnGate(PERIOD_S)
        seen = []
        for i in range(0, len(run.t_s), 25):
            gate.update(fusion.to_vqf_frame(run.gyr_rads[i : i + 25]), fusion.to_vqf_frame(run.acc_ms2[i : i + 25]),
                        LEVEL, np.zeros(3))  # fmt: skip
            seen.append(gate.in_swing)
        assert all(seen[4:]) if swings else not any(seen), motion  # judged from 2 s of rates on


def test_a_runners_attitude_does_not_depend_on_how_the_samples_are_cut_into_batches():
    run = simulate(SimulatorConfig(trajectory=Trajectory.RUNNING, rate_hz=50.0, count=1500, seed=1))
    whole = fusion.Fusion(PERIOD_S).update(run.gyr_rads, run.acc_ms2, run.true_field_ut).quat_wxyz
    parts = fusion.Fusion(PERIOD_S)
    pieces = [
        parts.update(run.gyr_rads[s : s + 7], run.acc_ms2[s : s + 7], run.true_field_ut[s : s + 7]).quat_wxyz
        for s in range(0, 1500, 7)
    ]
    assert parts.turn_gate is not None and (parts.turn_gate.in_gait or parts.turn_gate.in_swing)  # the gate at work
    np.testing.assert_allclose(np.vstack(pieces), whole, atol=1e-9)


def test_without_the_field_the_answer_is_vqfs_own_6d_attitude():
    """Until a field reaches the filter the heading is the gyroscope's, whose error is that of vqf's bias about the
    vertical, not the tilt's: the answer is plain vqf's 6D attitude (the gyroscope alone as any filter has it,
    whatever the gate does to the tilt beside it), batch by batch; from the first field sample on, the gated
    filter's."""
    run = field_runs.field_run(field_runs.MOTIONS["running"], 1, field_runs.FieldSettings(seconds=30.0))
    gyr, acc = fusion.to_vqf_frame(run.gyr_rads), fusion.to_vqf_frame(run.acc_ms2)
    plain = frames.ned_enu_attitude(np.asarray(vqf.VQF(PERIOD_S).updateBatch(gyr, acc)["quat6D"]))
    gated = fusion.Fusion(PERIOD_S)
    alone = np.vstack(
        [gated.update(run.gyr_rads[s : s + 25], run.acc_ms2[s : s + 25]).quat_wxyz for s in range(0, 1500, 25)]
    )
    assert gated.turn_gate is not None and (gated.turn_gate.in_gait or gated.turn_gate.in_swing)  # at work beside it
    np.testing.assert_allclose(alone, plain, atol=1e-12)
    # a field left out everywhere (zero rows: no calibration, or the watch) is no field either
    blind = fusion.Fusion(PERIOD_S).update(run.gyr_rads, run.acc_ms2, np.zeros_like(run.mag_ut)).quat_wxyz
    np.testing.assert_allclose(blind, plain, atol=1e-12)
    # the field from sample 1000 on: plain vqf's answer before it, the gated filter's after (its tilt kept right)
    field = np.where(np.arange(1500)[:, None] >= 1000, run.true_field_ut, 0.0)
    late = fusion.Fusion(PERIOD_S)
    mixed = np.vstack([late.update(run.gyr_rads[s : s + 7], run.acc_ms2[s : s + 7], field[s : s + 7]).quat_wxyz
                       for s in range(0, 1500, 7)])  # fmt: skip
    np.testing.assert_allclose(mixed[:1000], plain[:1000], atol=1e-12)
    assert late.turn_gate is not None and late.turn_gate.alone is not None and late.turn_gate.alone.done
    whole = fusion.Fusion(PERIOD_S, turn_gate=True).update(run.gyr_rads, run.acc_ms2, field).quat_wxyz
    np.testing.assert_allclose(mixed, whole, atol=1e-9)
    assert np.max(np.abs(mixed[1000:] - plain[1000:])) > 1e-3
