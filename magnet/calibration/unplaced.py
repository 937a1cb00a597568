"""A level device fitted with no place: what holds its vertical offset (docs/field-calibration.md, "A level device
with no place").

Level turns show the horizontal offset (the gyroscope's windows, the circle the samples draw), not the vertical one.
The WMM's dip at the place holds it; |B| alone (``--field-ut``, a calibrator's ``--location``) holds it too, through
the magnitude, for the ladder's rungs whose matrix is kept. With neither, nothing did: on fieldsim's level walks and
robot (seeds 2026-2028, 120 s) ``magnet fit`` without ``--location`` was accepted 3.4-15.3 uT off along the vertical.
So the calibration in force's vertical offset is kept, and the record says so (``VERTICAL_KEPT``), or, with nothing in
force, the fit is refused saying to give the place. Pure numpy.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from magnet.calibration.ladder import first_offset, offset_direction
from magnet.calibration.rungs import Evidence, mean_down
from magnet.model import Calibration

#: what a planar record fitted without a place says in its quality ``vertical_kept`` (and reason)
VERTICAL_KEPT = "vertical offset kept: no place given (the calibration in force's); give --location"
#: what it adds to its quality ``kept``
KEPT_ITEM = "vertical offset (no place given: the calibration in force's)"
#: ``_evidence``'s source when a calibration is in force
IN_FORCE = "the calibration in force"


def hold_vertical(ev: Evidence, source: str, planar: bool, field_known: bool) -> tuple[Evidence, str, str]:
    """(the evidence, VERTICAL_KEPT or "", the refusal or "") of a fit: unchanged unless the device is planar with
    neither the dip (``ev.vertical_ut``) nor |B| (``field_known``) known; then, with a calibration in force
    (``source``), its vertical field and |B| those the kept vertical offset gives (``_kept``), else the refusal's
    words (the offset along the mean vertical, held by nothing: give the place)."""
    if not planar or ev.vertical_ut is not None or field_known or ev.down is None:
        return ev, "", ""
    if source != IN_FORCE:
        note = ", held by neither a place (no WMM |B| or dip) nor a calibration in force"
        return ev, "", offset_direction(ev, mean_down(ev.down), note)
    return _kept(ev), VERTICAL_KEPT, ""


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
    """The record saying its vertical offset was kept, and why (quality ``vertical_kept``, ``kept``, the reason);
    unchanged when ``note`` is ""."""
    if not note:
        return record
    kept = [*record.quality.get("kept", []), KEPT_ITEM]
    quality = record.quality.with_extra(vertical_kept=note, kept=kept)
    return record.replace(quality=quality, reason=f"{record.reason}; {note}")
