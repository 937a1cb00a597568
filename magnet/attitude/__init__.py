"""Attitude and heading from the inertial sensors and the calibrated field: the vqf filter (``fusion``), the
velocity-aided filter (``aided_fusion``, ``aiding``), the gyroscope bias filter of an aided vehicle
(``gyro_bias``), the magnetometer's delay behind the gyroscope (``mag_delay``) and tilt-compensated heading
(``heading``). Pure numpy (and vqf)."""
