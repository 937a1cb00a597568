"""A level device fitted with no place: what holds its vertical offset (docs/field-calibration.md, "A level device
with no place").

Level turns show the horizontal offset (the gyroscope's windows, the circle the samples draw), not the vertical one.
The WMM's dip at the place holds it; |B| alone (``--field-ut``, a calibrator's ``--location``) holds it too, through
the magnitude, for the ladder's rungs whose matrix is kept. With neither, a calibration in force holds it: its
vertical offset is kept and the record says so (``VERTICAL_KEPT``). With nothing in force, only the device's own
tilts (a walk's sway, a robot's bumps) show it: the vertical field is then a free parameter, the record says so
(``VERTICAL_FROM_TILTS``), and it is judged by heading as any other. On fieldsim's level walks and robot the vertical
offset was then 3.4-15.3 uT off, yet heading near the attitudes fitted was right (tuning seeds 1-6, ``magnet fit``
and ``magnet heading`` without a place, causal: texting 1.36 deg mean against 1.26 for a sphere fit + vqf, phoning
1.07 against 0.86, robot 1.14; boats 4.99 against 11.0 with no calibration); refusing them had left every such
phone uncalibrated. Pure numpy.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from magnet.calibration.ladder import first_offset
from magnet.calibration.rungs import Evidence, mean_down
from magnet.model import Calibration

#: what a planar record fitted without a place says in its quality ``vertical_kept`` (and reason)
VERTICAL_KEPT = "vertical offset kept: no place given (the calibration in force's); give --location"
#: what it adds to its quality ``kept``
KEPT_ITEM = "vertical offset (no place given: the calibration in force's)"
#: what a planar record fitted with neither a place nor a calibration in force says in its quality
#: ``vertical_from_tilts`` (and reason): its heading holds near the attitudes it was fitted at
VERTICAL_FROM_TILTS = (
    "vertical offset from the device's own tilts alone: no place given and nothing in force; good near the attitudes "
    "fitted; give --location for the WMM's dip"
)
#: ``_evidence``'s source when a calibration is in force
IN_FORCE = "the calibration in force"


def hold_vertical(ev: Evidence, source: str, planar: bool, field_known: bool) -> tuple[Evidence, str]:
    """(the evidence, VERTICAL_KEPT, VERTICAL_FROM_TILTS or "") of a fit: unchanged unless the device is planar with
    neither the dip (``ev.vertical_ut``) nor |B| (``field_known``) known; then, with a calibration in force
    (``source``), its vertical field and |B| those the kept vertical offset gives (``_kept``), else the evidence as
    it is (the vertical field free: only the device's own tilts show the vertical offset)."""
    if not planar or ev.vertical_ut is not None or field_known or ev.down is None:
        return ev, ""
    if source != IN_FORCE:
        return ev, VERTICAL_FROM_TILTS
    return _kept(ev), VERTICAL_KEPT


def _kept(ev: Evidence) -> Evidence:
    """The evidence with the vertical field and |B| of the centre whose horizontal part is ``first_offset``'s and
    whose part along the mean down is the kept offset's, both in the kept matrix's frame: the ladder then holds the
    vertical field near it as it would near the WMM's."""
    assert ev.down is not None  # hold_vertical's caller checked
    n = mean_down(ev.down)
    centre = ev.matrix0 @ first_offset(ev)
    centre = centre + n * float(n @ (ev.matrix0 @ ev.offset0 - centre))
    b = ev.mag @ ev.matrix0.T - centre
    known = np.all(np.isfinite(ev.down), axis=1)
    vertical = float(np.median(np.einsum("ni,ni->n", ev.down[known], b[known])))
    field = float(np.median(np.linalg.norm(b, axis=1)))
    return dataclasses.replace(ev, field_ut=field, vertical_ut=vertical)


def with_vertical_kept(record: Calibration, note: str) -> Calibration:
    """The record saying where its vertical offset came from, ``hold_vertical``'s note: kept (quality
    ``vertical_kept``, and ``kept`` lists it) or from the device's tilts (quality ``vertical_from_tilts``), and the
    reason; unchanged when ``note`` is ""."""
    if not note:
        return record
    if note == VERTICAL_FROM_TILTS:
        quality = record.quality.with_extra(vertical_from_tilts=note)
    else:
        quality = record.quality.with_extra(vertical_kept=note, kept=[*record.quality.get("kept", []), KEPT_ITEM])
    return record.replace(quality=quality, reason=f"{record.reason}; {note}")
