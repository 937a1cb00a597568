"""Autopilots: MAVLink messages in magnet's units (``mavlink``) and a vehicle's stream as raw batches
(``mavlink_stream``), the conventions shared with the flight-log readers (``conventions``) and a record as
autopilot parameters (``params``). Pure: no sockets, no pymavlink import."""
