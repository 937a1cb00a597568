"""Figures of merit of a calibration and the gate that accepts or refuses it (docs/design.md, "Quality").

Pure numpy. Every figure is computed on the corrected field ``calibration.apply(raw)``:

- residual: RMS over the samples of ``|B| - F``, where F is the expected magnitude (the record's ``field_strength``,
  or the mean ``|B|`` when that is 0); in uT when the output unit converts to uT, and in % of F. For the ``circle``
  geometry (a level turn, ``minmax2d``) the horizontal magnitude ``sqrt(Bx^2 + By^2)`` is judged instead of ``|B|``.
- coverage: the fraction of ~100 equal-area cells of the unit sphere (a Fibonacci lattice of cell centres; a sample
  belongs to its nearest centre) that hold at least one corrected field direction, and the empty cells named as the
  attitude a person should add. For the circle geometry: the fraction of 36 ten-degree heading sectors.
- radius: the fitted radius in uT (when the raw unit converts to uT) against the expected field (WMM), as a ratio.
- conditioning: ``soft_iron_condition`` = largest / smallest singular value of the correction matrix;
  ``scatter_condition`` = sqrt(largest / smallest eigenvalue) of the raw samples' covariance (the ratio of the
  widest to the thinnest spread of the cloud: ~1-3 for a tumbled sensor, large when the samples lie in a plane).
- dip spread: standard deviation, in degrees, of the angle between the corrected field and gravity (needs acc).
- held-out residual: the same residual for samples the fit did not see (the caller fits on one part, scores here).
- disturbed samples (``field_disturbance``): |B| or dip away from the expected, or a change of the field the
  gyroscope's rotation does not explain; such samples are left out of a fit and of the compass's filter.
"""

from magnet.quality.coverage import (
    CELL_COUNT,
    HEADING_SECTORS,
    MAX_ADVICE,
    Coverage,
    coverage,
    fibonacci_centres,
    heading_coverage,
)
from magnet.quality.disturbance import DisturbanceSettings, FieldDisturbance, field_disturbance
from magnet.quality.figures import Geometry, assess, dip_spread_deg, matrix_condition, scatter_condition
from magnet.quality.gate import GateThresholds, for_travel, gate
from magnet.units import ut_per_unit

__all__ = [
    "CELL_COUNT",
    "HEADING_SECTORS",
    "MAX_ADVICE",
    "Coverage",
    "DisturbanceSettings",
    "FieldDisturbance",
    "GateThresholds",
    "Geometry",
    "assess",
    "coverage",
    "dip_spread_deg",
    "fibonacci_centres",
    "field_disturbance",
    "for_travel",
    "gate",
    "heading_coverage",
    "matrix_condition",
    "scatter_condition",
    "ut_per_unit",
]
