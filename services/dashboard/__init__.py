"""``magnet dashboard``: a live web page of the fleet, with calibration control."""
