"""The Earth's field and where a device is: the World Magnetic Model (``geomag``), a place (``location``), what
the model expects at a place on a day (``expected``) and each device's place (``places``). Used by the compass, the
calibrator, the dashboard and the simulator alike. Pure."""
