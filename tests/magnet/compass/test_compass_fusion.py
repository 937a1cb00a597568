"""The compass's per-device filter: state across batches, restarts on gaps and device restarts, bad gyroscope
samples dropped and counted, magnetic disturbances flagged without dragging the heading, never NaN."""

from __future__ import annotations

import numpy as np
import pytest
from compass_steps import NOW_NS, compass_core, heading_batches
from fusion_helpers import RATE_HZ, rotating_device

from magnet import frames, wire
from magnet.attitude import fusion
from magnet.attitude.heading import HeadingFlag, angle_difference_deg
from magnet.compass import CompassCore
from magnet.compass.filters import GYRO_LIMIT_RADS, DeviceFilters, _device_order
from magnet.earth.expected import Earth
from magnet.frames import to_magnetic_ned
from magnet.simulator import SimulatorConfig, Trajectory, simulate

BATCH = 25
PERIOD_NS = int(1e9 / RATE_HZ)


@pytest.fixture(scope="module")
def device():
    return rotating_device(seconds=60.0)


def batches(device, name="imu-1", seq0=0, t0_ns=1_000_000_000_000, gyro=True):
    gyr, acc, mag, _ = device
    t_ns = t0_ns + np.arange(len(gyr), dtype=np.int64) * PERIOD_NS
    return [
        wire.RawBatch(
            name,
            seq0 + k,
            "sim",
            t_ns[lo : lo + BATCH],
            mag[lo : lo + BATCH],
            acc[lo : lo + BATCH],
            None,
            gyr[lo : lo + BATCH] if gyro else None,
        )
        for k, lo in enumerate(range(0, len(gyr), BATCH))
    ]


def run_compass(compass: CompassCore, raw: list[wire.RawBatch]) -> list[wire.HeadingBatch]:
    out = []
    for start in range(0, len(raw), 7):  # drains of a few batches, as the loop sees them
        out += heading_batches(compass, raw[start : start + 7])
    return out


def joined(headings: list[wire.HeadingBatch], name: str) -> np.ndarray:
    return np.concatenate([getattr(h, name) for h in headings])


def test_compass_fuses_across_batches_as_one_causal_filter(device):
    gyr, acc, mag, truth = device
    compass = compass_core(Earth(declination_deg=5.0), window=1)
    out = run_compass(compass, batches(device))
    reference = fusion.fuse_causal(gyr, acc, mag, 1.0 / RATE_HZ)
    np.testing.assert_allclose(joined(out, "heading_deg"), reference.heading_deg, atol=1e-6)
    flags = joined(out, "flags")
    assert np.all(flags & HeadingFlag.FUSED)
    true_heading, pitch, _ = frames.quaternion_to_euler(truth)
    settled = (np.arange(len(gyr)) > 20 * RATE_HZ) & (np.abs(pitch) < 60)
    error = angle_difference_deg(joined(out, "heading_deg"), true_heading)[settled]
    assert np.sqrt(np.mean(error**2)) < 1.0
    quat = joined(out, "quat_wxyz")
    heading_from_quat, _, _ = frames.quaternion_to_euler(quat)
    assert np.abs(angle_difference_deg(heading_from_quat, joined(out, "true_heading_deg"))).max() < 1e-6


def test_without_gyroscope_the_tilt_heading_stays():
    device = rotating_device(seconds=5.0)
    out = run_compass(compass_core(Earth(), window=1), batches(device, gyro=False))
    assert not np.any(joined(out, "flags") & HeadingFlag.FUSED)
    assert all(h.quat_wxyz is None for h in out)  # messages of devices without a gyroscope stay as they were


def test_a_gap_in_time_or_a_device_restart_restarts_the_filter(device):
    fleet = DeviceFilters()
    raw = batches(device)

    def feed(items):
        columns = wire.RawColumns.from_batches(items)
        return fleet.update(
            columns.devices,
            columns.seqs,
            columns.bounds,
            columns.t_ns,
            columns.gyr_rads,
            columns.acc_ms2,
            columns.mag_ut,
        )

    assert feed(raw[:10]).restarts == 1  # the first batch starts the filter
    assert feed(raw[11:20]).restarts == 0  # one lost batch (0.25 s) is within the limit: it goes on
    late = [
        wire.RawBatch(b.device, b.seq, b.sensor, b.t_ns + 2_000_000_000, b.mag_ut, b.acc_ms2, None, b.gyr_rads)
        for b in raw[20:30]
    ]
    assert feed(late).restarts == 1  # two seconds missing
    rebooted = batches(device, seq0=0, t0_ns=5_000_000_000_000)
    assert feed(rebooted[:5]).restarts == 1  # seq back to 0: the device restarted
    assert feed(rebooted[:5]).restarts == 1  # the same batches again (a replay): restart, not a jump back in time


def test_bad_gyroscope_samples_are_dropped_counted_and_never_published_as_nan(device):
    raw = batches(device)[:40]
    nan_batch, saturated_batch = raw[10], raw[20]
    nan_gyr = nan_batch.gyr_rads.copy()
    nan_gyr[3:6] = np.nan
    sat_gyr = saturated_batch.gyr_rads.copy()
    sat_gyr[7, 2] = GYRO_LIMIT_RADS * 1.0005
    raw[10] = wire.RawBatch(
        nan_batch.device, nan_batch.seq, "sim", nan_batch.t_ns, nan_batch.mag_ut, nan_batch.acc_ms2, None, nan_gyr
    )
    raw[20] = wire.RawBatch(
        saturated_batch.device,
        saturated_batch.seq,
        "sim",
        saturated_batch.t_ns,
        saturated_batch.mag_ut,
        saturated_batch.acc_ms2,
        None,
        sat_gyr,
    )
    compass = compass_core(Earth(), window=1)
    out = run_compass(compass, raw)
    for name in ("heading_deg", "true_heading_deg", "pitch_deg", "roll_deg"):
        assert np.all(np.isfinite(joined(out, name))), name
    dropped = compass.status("compass").dropped
    assert dropped["raw:gyro-non-finite"] == 3 and dropped["raw:gyro-saturated"] == 1
    flags = out[10].flags
    assert not np.any(flags[3:6] & HeadingFlag.FUSED) and np.all(flags[6:] & HeadingFlag.FUSED)
    assert compass.filters.devices["imu-1"].restarts == 2  # the start, and after the saturated sample


def test_a_magnetic_disturbance_is_flagged_and_does_not_drag_the_heading(device):
    gyr, acc, mag, truth = device
    disturbed = mag.copy()
    window = slice(int(30 * RATE_HZ), int(40 * RATE_HZ))
    # a magnet under the device for ten seconds: |B| and dip change beyond vqf's thresholds (10 %, 10 deg). One that
    # kept both and only turned the field would be undetectable by any check of |B| and dip.
    disturbed[window] += np.array([0.0, 0.0, 30.0])
    out = run_compass(compass_core(Earth(), window=1), batches((gyr, acc, disturbed, truth)))
    flags = joined(out, "flags")
    assert np.mean(flags[window] & HeadingFlag.FIELD_DISTURBED > 0) > 0.9
    true_heading, pitch, _ = frames.quaternion_to_euler(truth)
    heading = joined(out, "heading_deg")
    level = np.abs(pitch) < 60
    error = np.abs(angle_difference_deg(heading, true_heading))[window][level[window]]
    raw_tilt = np.abs(
        angle_difference_deg(
            joined(
                run_compass(compass_core(Earth(), window=1), batches((gyr, acc, disturbed, truth), gyro=False)),
                "heading_deg",
            ),
            true_heading,
        )
    )[window][level[window]]
    assert error.max() < 3.0 < 20.0 < raw_tilt.max()


def test_compass_encodes_the_fused_quaternion_on_the_wire(device):
    compass = compass_core(Earth(), window=1)
    raw = batches(device)[:8]
    columns = wire.RawColumns.from_batches(raw)
    payloads = compass.encode(columns, compass.step(columns, NOW_NS))
    decoded = [wire.decode_heading(p) for p in payloads]
    assert all(h.quat_wxyz is not None and h.quat_wxyz.shape == (BATCH, 4) for h in decoded)
    assert np.all(joined(decoded, "flags") & HeadingFlag.FUSED)


def test_fleet_state_is_bounded(device):
    fleet = DeviceFilters(max_devices=3)
    first = batches(device)[0]
    for k in range(5):
        columns = wire.RawColumns.from_batches(
            [wire.RawBatch(f"d{k}", 0, "sim", first.t_ns, first.mag_ut, first.acc_ms2, None, first.gyr_rads)]
        )
        fleet.update(
            columns.devices,
            columns.seqs,
            columns.bounds,
            columns.t_ns,
            columns.gyr_rads,
            columns.acc_ms2,
            columns.mag_ut,
        )
    assert list(fleet.devices) == ["d2", "d3", "d4"]


def test_devices_interleaved_in_one_drain_fuse_as_each_alone(device):
    """A drain holds several batches of each device, interleaved: each device's filter sees its own batches in
    order (joined into one vqf call per run), exactly as when each device is fed alone."""
    one, two = batches(device, "imu-1")[:12], batches(device, "imu-2", t0_ns=2_000_000_000_000)[:12]
    mixed = [b for pair in zip(one, two) for b in pair]
    together = heading_batches(compass_core(Earth(), window=1), mixed)
    alone = heading_batches(compass_core(), one) + heading_batches(compass_core(), two)
    by_device = {name: joined([h for h in together if h.device == name], "heading_deg") for name in ("imu-1", "imu-2")}
    np.testing.assert_array_equal(by_device["imu-1"], joined(alone[:12], "heading_deg"))
    np.testing.assert_array_equal(by_device["imu-2"], joined(alone[12:], "heading_deg"))
    assert np.all(joined(together, "flags") & HeadingFlag.FUSED)


def test_compass_aids_with_the_velocity_its_batches_carry_as_magnet_heading_does():
    """One place for velocity aiding: the compass's per-device filter gives what ``fuse_causal`` gives with the
    same velocity turned to magnetic north by the compass's declination, and the car's heading comes back."""
    run = simulate(SimulatorConfig(trajectory=Trajectory.CAR, rate_hz=RATE_HZ, count=int(20 * RATE_HZ), seed=3))
    declination = run.earth.declination_deg
    t_ns = 1_000_000_000_000 + np.arange(len(run.t_s), dtype=np.int64) * PERIOD_NS
    raw = [
        wire.RawBatch(
            "car-1",
            k,
            "sim",
            t_ns[lo : lo + BATCH],
            run.mag_ut[lo : lo + BATCH],
            run.acc_ms2[lo : lo + BATCH],
            None,
            run.gyr_rads[lo : lo + BATCH],
            vel_ned_ms=run.vel_ned_ms[lo : lo + BATCH],
        )
        for k, lo in enumerate(range(0, len(run.t_s), BATCH))
    ]
    out = run_compass(compass_core(Earth(declination_deg=declination), window=1), raw)
    vel = to_magnetic_ned(run.vel_ned_ms, declination)
    reference = fusion.fuse_causal(run.gyr_rads, run.acc_ms2, run.mag_ut, 1.0 / RATE_HZ, None, t_ns * 1e-9, vel)
    # the same code; the compass's batches of 25 cut the filter's pieces at other samples, so the products of the
    # carried-forward attitudes round differently (1e-16), which the aided vehicle's drift filter keeps at 1e-4 deg
    np.testing.assert_allclose(joined(out, "heading_deg"), reference.heading_deg, atol=1e-3)
    plain = fusion.fuse_causal(run.gyr_rads, run.acc_ms2, run.mag_ut, 1.0 / RATE_HZ)
    scored = run.t_s > 10.0
    aided_error = angle_difference_deg(joined(out, "heading_deg"), run.magnetic_heading_deg)[scored]
    plain_error = angle_difference_deg(plain.heading_deg, run.magnetic_heading_deg)[scored]
    assert np.sqrt(np.mean(aided_error**2)) < np.sqrt(np.mean(plain_error**2)) / 2


def test_the_drains_order_is_none_where_each_devices_samples_already_follow_each_other():
    """No permutation (and so no copies of the drain) where the stable sort by device would leave every sample in
    place; otherwise the permutation groups each device's samples, in their order, batches without a gyroscope last."""
    sizes = np.array([2, 3, 0, 1])
    assert _device_order({"a": [0, 1], "b": [3]}, sizes) is None  # a, a, (empty), b
    assert _device_order({"a": [0, 1, 3]}, sizes) is None
    assert _device_order({"a": [0]}, np.array([2, 1, 0])) is None  # the batch without a gyroscope already last
    assert _device_order({"a": [0, 3], "b": [1]}, sizes).tolist() == [0, 1, 5, 2, 3, 4]
    assert _device_order({"a": [1]}, np.array([2, 1])).tolist() == [2, 0, 1]  # no gyroscope first: moved last
