"""The Earth's field and where on it: the World Magnetic Model (``geomag``), a place (``location``) and what the
model expects at a place on a day (``expected``). Used by the compass, the calibrator, the dashboard and the
simulator alike (each device's place among a fleet's: ``magnet.fleet``). Pure."""
