"""Physical simulator of a magnetometer + accelerometer + gyroscope moved through known attitudes in the Earth's field.

Truth. The Earth's field comes from WMM2025 (``magnet.earth.geomag``) at a place and date, as a north-east-down (NED)
vector B_ned in uT. An attitude trajectory gives, per sample, the magnetic heading K of the body x axis (clockwise from
magnetic north), pitch and roll (Z-Y-X Euler angles, ``magnet.frames``) and the body-to-NED quaternion; the true heading
is K + declination. Still trajectories keep the device at rest at every sample (the accelerometer reads gravity only);
moving ones add linear acceleration:

    B_body = R^T B_ned,      f_body = R^T (a_lin - g_ned),      R = Rz(true heading) Ry(pitch) Rx(roll)

and the gyroscope reads the body rate that carries the attitude from one sample to the next.

Sensor model (docs/design.md, "Sensors and the simulator"). M is the magnetometer's orientation in the body
(= accelerometer) frame, from the small angles ``misalignment_deg`` (roll, pitch, yaw); S the soft-iron / gain /
cross-axis matrix; h the hard iron:

    mag_measured = S @ M^T @ B_body * (1 + tempco * (T - 25 C)) + h(T) + noise (+ occasional spikes)
    acc_measured = f_body + noise
    gyr_measured = w_body + gyro bias(T) + noise

so the exact correction (at 25 C) is B_body = M @ S^-1 @ (mag - h) (``SensorErrors.true_calibration``).

Modules, by idea:
- ``errors``: ``SensorErrors``, the errors of one sensor.
- ``trajectories``: ``Trajectory`` (every name) and the still trajectories (spin, turntable, tumble, tenface).
- ``motion``: the moving trajectories (multirotor, car, figure8, fast-tumble) with linear acceleration (``plan``:
  eased steps, tones and plans of segments they are made of).
- ``paths``, ``walks``, ``ground``: motions along a path: a person walking or running with a phone (pocket, swinging
  hand, texting, phoning, running) with its gait; a boat and a ground robot that only yaw (``models``: every moving
  model by name).
- ``disturbances``: objects passed on the way (steel doors, parked cars) and a mid-run hard-iron change.
- ``run``: ``SimulatorConfig``, ``SimulatedRun``, ``simulate``, ``SensorStream`` (one device, any trajectory).
- ``devices``: ``SimulatedDevices``, many tumbling devices at once.
- ``motors``: ``Motors``, a vehicle's throttle, battery current and the field they add (``SimulatorConfig.motors``).

Everything is deterministic from ``seed``.
"""

from magnet.simulator.devices import DevicesBatch, SimulatedDevices
from magnet.simulator.disturbances import Disturbances, HardIronChange
from magnet.simulator.errors import REFERENCE_TEMPERATURE_C, SensorErrors
from magnet.simulator.models import MODELS
from magnet.simulator.motion import CarModel, FastTumbleModel, Figure8Model, MotionModel, MultirotorModel
from magnet.simulator.motors import Motors
from magnet.simulator.run import (
    DEFAULT_DATE,
    DEFAULT_LAT_DEG,
    DEFAULT_LOCATION,
    DEFAULT_LON_DEG,
    SensorStream,
    SimulatedRun,
    SimulatorConfig,
    simulate,
)
from magnet.simulator.trajectories import (
    GOLDEN_RATIO_MINOR,
    MOVING_TRAJECTORIES,
    PATH_TRAJECTORIES,
    PLANAR_TRAJECTORIES,
    TENFACE_STATIONS,
    TUMBLE_CYCLES,
    TUMBLE_PITCH_AMPLITUDE_DEG,
    TURNTABLE_ANGLES_DEG,
    TURNTABLE_ROLL_DEG,
    TURNTABLE_STEP_DEG,
    VEHICLE_TRAJECTORIES,
    WALKING_TRAJECTORIES,
    Trajectory,
)

__all__ = [
    "DEFAULT_DATE",
    "DEFAULT_LAT_DEG",
    "DEFAULT_LOCATION",
    "DEFAULT_LON_DEG",
    "GOLDEN_RATIO_MINOR",
    "MODELS",
    "MOVING_TRAJECTORIES",
    "PATH_TRAJECTORIES",
    "PLANAR_TRAJECTORIES",
    "REFERENCE_TEMPERATURE_C",
    "TENFACE_STATIONS",
    "TUMBLE_CYCLES",
    "TUMBLE_PITCH_AMPLITUDE_DEG",
    "TURNTABLE_ANGLES_DEG",
    "TURNTABLE_ROLL_DEG",
    "TURNTABLE_STEP_DEG",
    "VEHICLE_TRAJECTORIES",
    "WALKING_TRAJECTORIES",
    "CarModel",
    "DevicesBatch",
    "Disturbances",
    "FastTumbleModel",
    "Figure8Model",
    "HardIronChange",
    "MotionModel",
    "Motors",
    "MultirotorModel",
    "SensorErrors",
    "SensorStream",
    "SimulatedDevices",
    "SimulatedRun",
    "SimulatorConfig",
    "Trajectory",
    "simulate",
]
