"""The edge's sources send the gyroscope where there is one: a moving simulated trajectory, a gyroscope chip."""

import numpy as np
import pytest

from magnet import simulator as sim
from services.common.sim_options import SimulatorSettings
from services.edge.settings import EdgeSettings
from services.edge.sources import make_source


def _batch(sensor, trajectory, **kw):
    settings = EdgeSettings(
        device="g1",
        sensor=sensor,
        emulate=True,
        rate_hz=100.0,
        batch=20,
        simulator=SimulatorSettings(seed=3, trajectory=sim.Trajectory(trajectory)),
        **kw,
    )
    (batch,) = make_source(settings).take(0, 10**9, lambda: False)
    return batch


def test_a_moving_simulated_device_sends_its_gyroscope():
    batch = _batch("sim", "multirotor")
    truth = sim.simulate(sim.SimulatorConfig(trajectory="multirotor", count=20, rate_hz=100.0, seed=3))
    np.testing.assert_allclose(batch.gyr_rads, truth.gyr_rads)
    assert _batch("sim", "tumble").gyr_rads is None  # still trajectories keep today's messages


def test_a_moving_simulated_device_sends_its_gnss_velocity():
    settings = EdgeSettings(
        device="g1",
        sensor="sim",
        emulate=True,
        rate_hz=100.0,
        batch=30,
        simulator=SimulatorSettings(seed=3, trajectory=sim.Trajectory("car")),
    )
    (batch,) = make_source(settings).take(0, 10**9, lambda: False)
    truth = sim.simulate(sim.SimulatorConfig(trajectory="car", count=30, rate_hz=100.0, seed=3))
    np.testing.assert_array_equal(batch.vel_ned_ms, truth.vel_ned_ms)  # NaN before the first fix, then held
    assert np.isnan(batch.vel_ned_ms[:10]).all() and np.isfinite(batch.vel_ned_ms[10:]).all()
    assert _batch("sim", "tumble").vel_ned_ms is None


@pytest.mark.parametrize("sensor", ["icm20948", "mpu6050+qmc5883l"])
def test_a_gyroscope_chip_sends_its_rates(sensor):
    batch = _batch(sensor, "car")
    assert batch.gyr_rads.shape == (20, 3) and np.all(np.isfinite(batch.gyr_rads))
    assert _batch("hmc5883l", "car").gyr_rads is None


@pytest.mark.parametrize(
    "sensor,trajectory,extra",
    [("sim", "car", {}), ("icm20948", "tumble", {}), ("sim", "tumble", {"devices": 3, "gyro": True})],
)
def test_speedup_is_refused_where_a_gyroscope_is_simulated(sensor, trajectory, extra):
    """The wire times keep --rate: sped-up motion would rotate more per sample than its rates say."""

    def settings(speedup):
        return EdgeSettings(
            device="g1",
            sensor=sensor,
            emulate=True,
            speedup=speedup,
            simulator=SimulatorSettings(trajectory=sim.Trajectory(trajectory)),
            **extra,
        )

    with pytest.raises(ValueError, match="--speedup needs a simulation without a gyroscope"):
        settings(4.0)
    assert settings(1.0).simulated_gyroscope  # at the simulated pace it runs


def test_speedup_stays_for_still_simulations_without_a_gyroscope():
    assert _batch("sim", "tumble", speedup=4.0).gyr_rads is None
    assert _batch("lsm303dlh", "tumble", speedup=4.0).gyr_rads is None


def test_a_replayed_recording_carries_its_velocity_columns(tmp_path):
    from services.edge.sources import read_recording

    path = tmp_path / "rec.csv"
    path.write_text("t_s,mx,my,mz,vn,ve,vd\n0,20,0,40,,,\n0.01,20,0,40,nan,nan,nan\n0.02,20,0,40,1.5,-2,0.1\n")
    recording = read_recording(path)
    assert np.isnan(recording.vel_ned_ms[:2]).all()
    np.testing.assert_allclose(recording.vel_ned_ms[2], [1.5, -2.0, 0.1])
    path.write_text("t_s,mx,my,mz,vn,ve\n0,20,0,40,1,2\n")
    with pytest.raises(ValueError, match="vn,ve,vd"):
        read_recording(path)
