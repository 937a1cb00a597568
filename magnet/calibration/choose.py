"""``auto``: the choice between gyro-ellipsoid and ellipsoid, made by the fits themselves (docs/gyro-calibration.md,
"Choosing the method").

``auto`` is a choice, not a method: ``magnet fit --method`` and the calibrator's ``--method`` and sessions accept it,
the record always names the method that made it (``Method``; a stored or published record never says "auto").

The rule (``fit_auto``):

- no gyroscope (or no sample period): the ellipsoid fit, nothing else;
- with one: both gyro-ellipsoid and ellipsoid are fitted and gated exactly as ``fit`` does for each; a fit that
  cannot be computed (``FitError``) counts as refused, with its message as the reason;
- only one accepted: that one;
- both accepted: the one whose field is more constant in the earth frame on the held-out samples (quality
  ``holdout_consistency_deg``, deg, lower is better: the figure the gate judges heading by, computed on the same
  held-out rows for both and with the magnetometer delay a gyro-ellipsoid record carries). Without it (no
  accelerometer) the lower held-out |B| residual (``holdout_rms_pct``); a tie or no figure at all: gyro-ellipsoid;
- neither accepted (or, without a gyroscope, the ellipsoid refused): the field ladder
  (``magnet.calibration.field``): the model the motion identifies (offset, offset+scale, planar or a full
  ellipsoid), judged by held-out heading consistency; its record when accepted (quality ``auto_other`` names the
  sphere's method it replaced, ``auto_refused`` every one);
- none accepted: the refusal of gyro-ellipsoid (ellipsoid's when gyro-ellipsoid could not be computed), its
  reason naming both methods' reasons; FitError (both messages) when neither could be computed.

Before any of it, the samples in a disturbed field are left out (``magnet.calibration.disturbed``): judged with the
calibration in force, else from the raw field and then once more with the first choice's correction, the choice
being made again when that finds more.

The chosen record's quality carries ``auto_other``: the other method, whether it was accepted, its held-out
consistency (deg or None) and, when it could not be computed, why (``error``); its reason ends with the choice.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from magnet.calibration import disturbed
from magnet.calibration.base import FitError, Method
from magnet.calibration.fit_input import FitInput
from magnet.calibration.fitting import fit
from magnet.model import Calibration

#: the choice that is not a method
AUTO = "auto"
#: what ``magnet fit --method`` and the calibrator accept: auto, then every method
CHOICES: tuple[str, ...] = (AUTO, *(m.value for m in Method))
#: the methods auto chooses between, the preferred first
CANDIDATES = (Method.GYRO_ELLIPSOID, Method.ELLIPSOID)


def parse_choice(value: Method | str) -> str:
    """ "auto" or a method's name, normalised; ValueError naming the choices."""
    if isinstance(value, Method):
        return value.value
    text = str(value).strip().lower()
    if text == AUTO:
        return AUTO
    try:
        return Method.parse(text).value
    except ValueError:
        raise ValueError(f"unknown calibration method {value!r}: use one of {', '.join(CHOICES)}") from None


def fit_choice(data: FitInput, choice: Method | str) -> Calibration:
    """``fit_auto`` for "auto", else ``fit`` with that method, its disturbed samples left out as ``fit_auto``
    leaves them (``magnet.calibration.disturbed``: once more with the first fit's correction)."""
    chosen = parse_choice(choice)
    if chosen == AUTO:
        return fit_auto(data)
    if chosen == Method.TURNTABLE.value:
        return fit(data, chosen)
    return disturbed.fit_undisturbed(data, lambda undisturbed: fit(undisturbed, chosen))


def fit_auto(data: FitInput) -> Calibration:
    """The better of gyro-ellipsoid and ellipsoid for ``data`` (the rule: the module docstring), its disturbed
    samples left out. Raises FitError when no calibration can be computed by either."""
    return disturbed.fit_undisturbed(data, _fit_auto)


def _fit_auto(data: FitInput) -> Calibration:
    if not data.has_gyroscope:
        plain = data.replace(gyr_rads=None, period_s=None)
        try:
            sphere: Calibration | FitError = fit(plain, Method.ELLIPSOID)
        except FitError as exc:
            sphere = exc
        if isinstance(sphere, Calibration) and sphere.accepted:
            return sphere
        return _field_fallback(plain, {Method.ELLIPSOID: sphere})
    results: dict[Method, Calibration | FitError] = {}
    for method in CANDIDATES:
        try:
            results[method] = fit(data, method)
        except FitError as exc:
            results[method] = exc
    records = {method: result for method, result in results.items() if isinstance(result, Calibration)}
    if not any(record.accepted for record in records.values()):
        return _field_fallback(data, results)
    chosen = _choose(records)
    other = Method.ELLIPSOID if chosen is Method.GYRO_ELLIPSOID else Method.GYRO_ELLIPSOID
    return _mark(records[chosen], other, results)


def _field_fallback(data: FitInput, results: dict[Method, Calibration | FitError]) -> Calibration:
    """The field ladder's record when the sphere's methods (``results``) were refused: accepted, it is returned
    with ``auto_other`` and ``auto_refused`` naming them; refused or impossible, the sphere's refusal as before (its
    reason ends with the ladder's), FitError when nothing could be computed. The ladder's modules are imported
    here, where they are first needed."""
    from magnet.calibration import field

    try:
        ladder: Calibration | FitError = field.fit_field(field.FieldInput.of(data), gate_thresholds=data.gate)
    except FitError as exc:
        ladder = exc
    if isinstance(ladder, Calibration) and ladder.accepted:
        summary = [
            {"method": method.value, "accepted": False, "reason": _reason(result)[:300]}
            for method, result in results.items()
        ]
        quality = ladder.quality.with_extra(auto_other=summary[0], auto_refused=summary)
        why = "chosen by auto: the sphere's fits were refused"
        return ladder.replace(quality=quality, reason=f"{ladder.reason}; {why}")
    records = {method: result for method, result in results.items() if isinstance(result, Calibration)}
    why = f"; the field ladder refused: {_reason(ladder)}"
    if not records:
        raise FitError(_all_reasons(results) + why)
    if len(results) == 1:
        only = next(iter(records.values()))
        return only.replace(reason=only.reason + why)
    chosen = _choose(records)
    other = Method.ELLIPSOID if chosen is Method.GYRO_ELLIPSOID else Method.GYRO_ELLIPSOID
    marked = _mark(records[chosen], other, results)
    return marked.replace(reason=marked.reason + why)


def _all_reasons(results: dict[Method, Calibration | FitError]) -> str:
    if len(results) == len(CANDIDATES):
        return _both_reasons(results)
    return "; ".join(f"{method.value} refused: {_reason(result)}" for method, result in results.items())


def _choose(records: dict[Method, Calibration]) -> Method:
    """The chosen method among those whose fit could be computed, by the rule of the module docstring."""
    accepted = [method for method in CANDIDATES if method in records and records[method].accepted]
    if len(accepted) == len(CANDIDATES):
        gyro, ellipsoid = records[Method.GYRO_ELLIPSOID], records[Method.ELLIPSOID]
        return Method.ELLIPSOID if _better(ellipsoid, gyro) else Method.GYRO_ELLIPSOID
    if accepted:
        return accepted[0]
    return next(method for method in CANDIDATES if method in records)


def _better(candidate: Calibration, than: Calibration) -> bool:
    """Whether ``candidate`` is strictly better than ``than`` by held-out consistency, else held-out residual."""
    for key in ("holdout_consistency_deg", "holdout_rms_pct"):
        mine, theirs = _figure(candidate, key), _figure(than, key)
        if mine is not None and theirs is not None:
            return mine < theirs
    return False


def _figure(calibration: Calibration, key: str) -> float | None:
    value = calibration.quality.get(key)
    return None if value is None or not np.isfinite(float(value)) else float(value)


def _reason(result: Calibration | FitError) -> str:
    return str(result) if isinstance(result, FitError) else result.reason


def _both_reasons(results: dict[Method, Calibration | FitError]) -> str:
    return "auto: " + " | ".join(f"{method.value} refused: {_reason(results[method])}" for method in CANDIDATES)


def _mark(chosen: Calibration, other_method: Method, results: dict[Method, Calibration | FitError]) -> Calibration:
    """The chosen record, its quality saying what the other scored, its reason saying how it was chosen."""
    other = results[other_method]
    accepted = isinstance(other, Calibration) and other.accepted
    summary: dict[str, Any] = {"method": other_method.value, "accepted": accepted}
    if isinstance(other, FitError):
        summary["holdout_consistency_deg"], summary["error"] = None, str(other)
    else:
        summary["holdout_consistency_deg"] = _figure(other, "holdout_consistency_deg")
    quality = chosen.quality.with_extra(auto_other=summary)
    if not chosen.accepted:
        return chosen.replace(quality=quality, reason=_both_reasons(results))
    mine, theirs = _figure(chosen, "holdout_consistency_deg"), summary["holdout_consistency_deg"]
    scores = f" (held-out consistency {mine:.2f} deg vs {theirs:.2f} deg)" if mine is not None and theirs else ""
    why = "the better of the two accepted" if accepted else f"{other_method.value} was refused"
    return chosen.replace(quality=quality, reason=f"{chosen.reason}; chosen by auto: {why}{scores}")
