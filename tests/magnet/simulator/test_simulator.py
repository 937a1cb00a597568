"""The physical simulator: truth consistency, seed 000's turntable equations, trajectories, errors, streams, fleet."""

import numpy as np
import pytest

from magnet import simulator as sim
from magnet.attitude import heading as hd
from magnet.frames import euler_to_matrix, ned_to_body, rotation_angle_deg

DATE = "2026-03-01"


def errors(**kw):
    rng = np.random.default_rng(42)
    return sim.SensorErrors.random(rng, 50.0, **kw)


def run(trajectory="tumble", count=2000, **kw):
    return sim.simulate(sim.SimulatorConfig(trajectory=trajectory, count=count, date=DATE, **kw))


def test_same_seed_same_data_other_seed_other_data():
    e = errors(noise_ut=0.3, acc_noise_ms2=0.05, spike_probability=0.01, spike_ut=30.0)
    a, b = run(errors=e, seed=7), run(errors=e, seed=7)
    c = run(errors=e, seed=8)
    for name in ("mag_ut", "acc_ms2", "heading_deg", "pitch_deg", "roll_deg"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    assert not np.allclose(a.mag_ut, c.mag_ut)


@pytest.mark.parametrize("trajectory", [t for t in sim.Trajectory if not t.moving])
def test_truth_is_consistent_with_the_measurements(trajectory):
    e = errors(misalignment_deg=4.0)
    r = run(trajectory, count=520, errors=e)
    earth = r.earth
    # the field in the body frame is the WMM field rotated by the true attitude
    rotation = euler_to_matrix(r.heading_deg, r.pitch_deg, r.roll_deg)
    np.testing.assert_allclose(ned_to_body(rotation, np.array(earth.ned_ut)), r.true_field_ut, atol=1e-9)
    np.testing.assert_allclose(ned_to_body(rotation, np.array([0, 0, -9.80665])), r.acc_ms2, atol=1e-9)
    # the true errors invert the measurement exactly (no noise, 25 C)
    corrected = e.true_calibration().apply(r.mag_ut)
    np.testing.assert_allclose(corrected, r.true_field_ut, atol=1e-9)
    # and the heading computed from them is the true heading (away from the vertical, where it is undefined)
    ok = np.abs(r.pitch_deg) < 89.0
    magnetic = hd.tilt_compensated_heading_deg(corrected, r.acc_ms2)
    true = hd.true_heading_deg(magnetic, earth.declination_deg)
    assert np.abs(hd.angle_difference_deg(true, r.heading_deg))[ok].max() < 1e-7
    assert np.abs(hd.angle_difference_deg(r.heading_deg - earth.declination_deg, r.magnetic_heading_deg)).max() < 1e-9
    pitch, roll = hd.pitch_roll_deg(r.acc_ms2)
    np.testing.assert_allclose(pitch[ok], r.pitch_deg[ok], atol=1e-7)
    assert np.abs(hd.angle_difference_deg(roll, r.roll_deg))[ok].max() < 1e-7


def test_raw_field_is_distorted_as_the_model_says():
    e = errors(misalignment_deg=5.0)
    r = run(errors=e)
    np.testing.assert_allclose(
        r.mag_ut, r.true_field_ut @ (e.soft_iron @ e.misalignment_matrix.T).T + e.hard_iron_ut, atol=1e-9
    )
    # misalignment only rotates: undoing soft and hard iron leaves the field rotated by exactly 5 deg
    in_mag_frame = (r.mag_ut - e.hard_iron_ut) @ np.linalg.inv(e.soft_iron).T
    cos = np.sum(in_mag_frame * r.true_field_ut, axis=1) / np.linalg.norm(r.true_field_ut, axis=1) ** 2
    assert np.degrees(np.arccos(np.clip(cos, -1, 1))).max() == pytest.approx(5.0, abs=1e-6)
    assert rotation_angle_deg(e.misalignment_matrix) == pytest.approx(5.0)


def test_random_errors_respect_their_bounds():
    rng = np.random.default_rng(5)
    for _ in range(50):
        e = sim.SensorErrors.random(rng, 50.0, hard_iron_max_ratio=3.0, soft_iron_max=0.2)
        assert np.linalg.norm(e.hard_iron_ut) <= 150.0
        np.testing.assert_allclose(e.soft_iron, e.soft_iron.T, atol=1e-12)
        eig = np.linalg.eigvalsh(e.soft_iron)
        assert eig.min() >= 0.8 - 1e-9 and eig.max() <= 1.2 + 1e-9


def test_turntable_reproduces_seed_000_equations_exactly():
    per_step = 5
    r = run("turntable", count=26 * per_step)
    h, v_up = r.earth.horizontal_ut, -r.earth.down_ut  # Bv is the UP component: negative in the north
    assert v_up < 0
    k = np.radians(r.table_deg)
    a, b = r.mounting == "a", r.mounting == "b"
    assert a.sum() == b.sum() == 13 * per_step and np.all(a[: 13 * per_step])
    np.testing.assert_allclose(
        r.true_field_ut[a], np.column_stack([h * np.cos(k[a]), h * np.sin(k[a]), np.full(a.sum(), v_up)]), atol=1e-12
    )
    np.testing.assert_allclose(
        r.true_field_ut[b], np.column_stack([h * np.cos(k[b]), np.full(b.sum(), -v_up), h * np.sin(k[b])]), atol=1e-12
    )
    assert sorted(set(r.table_deg.tolist())) == list(range(0, 361, 30))
    assert np.all(np.bincount((r.table_deg[a] // 30).astype(int)) == per_step)
    # a: z up (upside down), b: y down (right side down); magnetic heading = table angle
    assert np.all(r.roll_deg[a] == 180.0) and np.all(r.roll_deg[b] == 90.0) and np.all(r.pitch_deg == 0.0)
    np.testing.assert_allclose(r.magnetic_heading_deg, np.mod(r.table_deg, 360.0), atol=1e-9)


def test_turntable_closed_form_recovers_the_simulated_errors():
    from magnet.calibration.turntable import fit_turntable

    e = errors()
    r = run("turntable", count=26 * 3, errors=e)
    cal = fit_turntable(
        r.mag_ut, r.mounting, r.table_deg, r.earth.horizontal_ut, -r.earth.down_ut, unit="ut", field_unit="ut"
    )
    np.testing.assert_allclose(cal.offset, e.hard_iron_ut, atol=1e-9)
    np.testing.assert_allclose(np.linalg.inv(cal.matrix), e.soft_iron, atol=1e-9)


def test_spin_is_one_level_turn():
    r = run("spin", count=360)
    assert np.all(r.pitch_deg == 0) and np.all(r.roll_deg == 0)
    np.testing.assert_allclose(r.magnetic_heading_deg, np.arange(360.0))


def test_tenface_visits_ten_stations_each_with_a_full_turn():
    r = run("tenface", count=1000)
    stations = sorted(set(zip(r.pitch_deg.tolist(), r.roll_deg.tolist())))
    assert len(stations) == 10
    for pitch, roll in stations:
        at = (r.pitch_deg == pitch) & (r.roll_deg == roll)
        assert at.sum() == 100
        assert np.ptp(r.magnetic_heading_deg[at]) > 350
    down = -r.acc_ms2 / 9.80665
    for axis in range(3):  # each body axis pointed straight down and straight up
        assert down[:, axis].max() > 0.999 and down[:, axis].min() < -0.999


def _sphere_cells_hit(directions, cells=100):
    i = np.arange(cells) + 0.5
    z = 1 - 2 * i / cells
    phi = np.pi * (1 + 5**0.5) * i
    centres = np.column_stack([np.sqrt(1 - z * z) * np.cos(phi), np.sqrt(1 - z * z) * np.sin(phi), z])
    unit = directions / np.linalg.norm(directions, axis=1, keepdims=True)
    nearest = np.argmax(unit @ centres.T, axis=1)
    return np.unique(nearest).size / cells


def test_tumble_is_smooth_and_covers_the_sphere():
    r = run("tumble", count=3000)
    assert _sphere_cells_hit(r.true_field_ut) == 1.0
    assert _sphere_cells_hit(r.acc_ms2) >= 0.98  # gravity: all but the caps within 5 deg of the x axis
    rotation = euler_to_matrix(r.heading_deg, r.pitch_deg, r.roll_deg)
    step = rotation_angle_deg(np.einsum("nji,njk->nik", rotation[:-1], rotation[1:]))
    assert step.max() < 5.0  # degrees per sample at 50 Hz: smooth, no jumps


def test_noise_spikes_and_temperature_drift():
    e = sim.SensorErrors(
        noise_ut=0.3,
        acc_noise_ms2=0.05,
        spike_probability=0.02,
        spike_ut=40.0,
        gain_tempco_per_k=-0.001,
        temperature_c=25.0,
        temperature_ramp_k_per_s=0.5,
    )
    r = run("spin", count=5000, errors=e, rate_hz=100.0)
    error = r.mag_ut - r.true_field_ut * e.gain(r.t_s)[:, None]
    spike = np.linalg.norm(error, axis=1) > 20
    assert 0.01 < spike.mean() < 0.03
    assert np.linalg.norm(error[spike], axis=1) == pytest.approx(40.0, abs=3.0)
    assert np.std(error[~spike]) == pytest.approx(0.3, rel=0.05)
    assert np.std(
        r.acc_ms2 - ned_to_body(euler_to_matrix(r.heading_deg, 0, 0), np.array([0, 0, -9.80665]))
    ) == pytest.approx(0.05, rel=0.05)
    # the last second is 24.5 K warmer: gain 2.45 % lower
    assert r.temperature_c[-1] == pytest.approx(25.0 + 0.5 * 49.99)
    ratio = np.linalg.norm(r.mag_ut[-100:][~spike[-100:]], axis=1).mean() / r.earth.total_ut
    assert ratio == pytest.approx(1 - 0.001 * 24.5, abs=0.005)


def test_sensor_stream_matches_simulate_and_keeps_going():
    e = errors(noise_ut=0.3, spike_probability=0.05, spike_ut=10.0, acc_noise_ms2=0.01)
    config = sim.SimulatorConfig(trajectory="spin", count=300, date=DATE, errors=e, seed=3)
    whole = sim.simulate(config)
    stream = sim.SensorStream(config)
    samples = [stream.measure() for _ in range(700)]
    mag = np.array([m for m, _ in samples])
    acc = np.array([a for _, a in samples])
    np.testing.assert_allclose(mag[:300], whole.mag_ut, atol=1e-12)
    np.testing.assert_allclose(acc[:300], whole.acc_ms2, atol=1e-12)
    assert stream.last_truth["heading_deg"] == pytest.approx(whole.heading_deg[699 % 300])
    assert stream.last_truth["t_s"] == pytest.approx(699 / config.rate_hz)
    assert not np.allclose(mag[300:600], whole.mag_ut)  # fresh noise on the next lap
    np.testing.assert_allclose(mag[300:600], whole.mag_ut, atol=15.0)


@pytest.mark.parametrize(
    "bad",
    [
        dict(trajectory="loop"),
        dict(rate_hz=0),
        dict(count=0),
        dict(trajectory="turntable", count=20),
        dict(errors="none"),
    ],
)
def test_bad_config_is_refused(bad):
    with pytest.raises(ValueError):
        sim.SimulatorConfig(**{"date": DATE, **bad})


@pytest.mark.parametrize(
    "bad",
    [
        dict(hard_iron_ut=(1, 2)),
        dict(soft_iron=np.zeros((3, 3))),
        dict(noise_ut=-1),
        dict(spike_probability=2),
        dict(misalignment_deg=(0, np.nan, 0)),
    ],
)
def test_bad_errors_are_refused(bad):
    with pytest.raises(ValueError):
        sim.SensorErrors(**bad)


def test_bad_place_or_date_is_refused_when_simulating():
    with pytest.raises(ValueError, match="life span"):
        sim.simulate(sim.SimulatorConfig(date="2035-01-01"))


def test_fleet_shapes_truth_and_determinism():
    fleet = sim.SimulatedDevices(20, rate_hz=100.0, seed=1, date=DATE, noise_ut=0.0, acc_noise_ms2=0.0)
    first, second = fleet.step(30), fleet.step(30)
    assert first.mag_ut.shape == first.acc_ms2.shape == (20, 30, 3)
    assert first.heading_deg.shape == first.pitch_deg.shape == first.roll_deg.shape == (20, 30)
    np.testing.assert_array_equal(np.concatenate([first.t_ns, second.t_ns]), np.arange(60) * 10_000_000)
    assert len({tuple(np.round(e.hard_iron_ut, 6)) for e in fleet.errors}) == 20
    earth = fleet.earth
    for d in (0, 7, 19):
        corrected = fleet.errors[d].true_calibration().apply(second.mag_ut[d])
        magnetic = hd.tilt_compensated_heading_deg(corrected, second.acc_ms2[d])
        err = hd.angle_difference_deg(hd.true_heading_deg(magnetic, earth.declination_deg), second.heading_deg[d])
        assert np.abs(err).max() < 1e-7
        np.testing.assert_allclose(np.linalg.norm(corrected, axis=1), earth.total_ut, rtol=1e-9)
        pitch, _ = hd.pitch_roll_deg(second.acc_ms2[d])
        np.testing.assert_allclose(pitch, second.pitch_deg[d], atol=1e-7)
    # the same seed gives the same fleet, stepping in other chunk sizes gives the same truth
    again = sim.SimulatedDevices(20, rate_hz=100.0, seed=1, date=DATE, noise_ut=0.0, acc_noise_ms2=0.0).step(60)
    np.testing.assert_allclose(again.mag_ut, np.concatenate([first.mag_ut, second.mag_ut], axis=1), atol=1e-12)


def test_fleet_devices_tumble_over_the_sphere_and_noise_is_as_asked():
    fleet = sim.SimulatedDevices(10, rate_hz=50.0, seed=2, date=DATE, noise_ut=0.3)
    batch = fleet.step(6000)  # two minutes
    hit = [_sphere_cells_hit(fleet.errors[d].true_calibration().apply(batch.mag_ut[d])) for d in range(10)]
    assert np.mean(hit) >= 0.97 and np.min(hit) >= 0.9
    clean = sim.SimulatedDevices(10, rate_hz=50.0, seed=2, date=DATE, noise_ut=0.0, acc_noise_ms2=0.0).step(6000)
    assert np.std(batch.mag_ut - clean.mag_ut) == pytest.approx(0.3, rel=0.05)


def test_fleet_bad_arguments():
    with pytest.raises(ValueError):
        sim.SimulatedDevices(0, date=DATE)
    with pytest.raises(ValueError):
        sim.SimulatedDevices(2, date=DATE).step(0)
