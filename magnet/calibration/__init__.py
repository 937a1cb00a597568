"""Fitting a calibration B = A (u - b) to raw magnetometer samples (docs/design.md, "The calibration model").

Every method returns the same record (``magnet.model.Calibration``): ``offset`` b in the raw unit and ``matrix`` A
mapping raw units to the output unit. Each method first finds a *shape*: an offset b, a matrix S and a radius r (raw
unit) such that |S (u - b)| ~ r for the whole sphere (or the level circle); ``fitting._finish`` then scales S to the
output unit:

- ``field_ut`` given (3D methods): A = S * field_ut / r, output uT, |B| = field_ut;
- else the raw unit converts to uT (ut, gauss, nt): A = S * (uT per unit), output uT, |B| = r in uT;
- else (counts): A = S, output in the raw unit, |B| = r.

Methods (``Method``), each in its module:

- ``minmax2d``, ``minmax``, ``sphere``: closed-form fits (``closed_form.py``);
- ``ellipsoid``: algebraic fit refined by Levenberg-Marquardt, spikes left out (``ellipsoid.py``);
- ``ellipsoid+align``: the ellipsoid, then the magnetometer-accelerometer rotation (``alignment.py``);
- ``turntable``: ``turntable.py`` (needs the mounting and table angle of every sample: ``TurntableSetup``);
- ``gyro-ellipsoid``: the ellipsoid held to the gyroscope's turns, and the magnetometer's delay
  (``gyro_ellipsoid.py``).

``auto`` (``choose.py``) is a choice, not a method: gyro-ellipsoid or ellipsoid, whichever the gate finds better; the
record names the method that made it.

Every method is fitted from one input, ``FitInput`` (``fit_input.py``: samples, times, gyroscope, accelerometer,
place and the fit's options). ``base.py`` holds the method names, the error and the input checks; ``fitting.py`` the
method table ``METHODS`` (one ``MethodSpec`` per method: its fit, geometry and held-out fit) and the entry points
``fit_shape`` and ``fit`` (quality figures, held-out residual and gate). A new method: a ``Method`` member, a
function ``FitInput -> Shape`` and one line in ``METHODS``.
"""

from __future__ import annotations

from magnet.calibration.alignment import MAX_ALIGN_CONDITION, MIN_GRAVITY_SPREAD, align_rotation
from magnet.calibration.base import (
    HOLDOUT_BLOCK,
    HOLDOUT_BLOCK_S,
    HOLDOUT_EVERY,
    MAX_SCATTER_FOR_3D,
    MIN_SAMPLES,
    FitError,
    Method,
    Shape,
)
from magnet.calibration.choose import AUTO, CHOICES, fit_auto, fit_choice, parse_choice
from magnet.calibration.ellipsoid import GROSS_OUTLIER_FACTOR, MAX_OUTLIER_FRACTION, OUTLIER_SIGMAS
from magnet.calibration.fit_input import FitInput, TurntableSetup
from magnet.calibration.fitting import METHODS, MethodSpec, fit, fit_shape

__all__ = [
    "AUTO",
    "CHOICES",
    "GROSS_OUTLIER_FACTOR",
    "HOLDOUT_BLOCK",
    "HOLDOUT_BLOCK_S",
    "HOLDOUT_EVERY",
    "MAX_ALIGN_CONDITION",
    "MAX_OUTLIER_FRACTION",
    "MAX_SCATTER_FOR_3D",
    "METHODS",
    "MIN_GRAVITY_SPREAD",
    "MIN_SAMPLES",
    "OUTLIER_SIGMAS",
    "FitError",
    "FitInput",
    "Method",
    "MethodSpec",
    "Shape",
    "TurntableSetup",
    "align_rotation",
    "fit",
    "fit_auto",
    "fit_choice",
    "fit_shape",
    "parse_choice",
]
