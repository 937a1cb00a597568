"""Calibration reports (``magnet report``, ``magnet fit --report``): figures people would rather look at than read."""
