"""The cheaper held-out fit of the iterative methods is the same fit: started from the fit of every sample and
stopped at HOLDOUT_TOLERANCE, it lands where a cold fit of the training samples to the full tolerance lands, and the
figures the gate judges do not move."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from magnet.calibration import FitInput, Method, fit
from magnet.calibration import fitting as fitting_module
from magnet.calibration.ellipsoid import ellipsoid
from services.bench.fit import synthetic_tumble


@pytest.mark.parametrize("seed", [0, 1])
def test_the_warm_started_holdout_fit_matches_a_cold_one(seed):
    raw, _ = synthetic_tumble(4000, seed)
    test = fitting_module._holdout_mask(len(raw))
    whole = ellipsoid(raw, None, False)
    cold = ellipsoid(raw[~test], None, False)
    warm = ellipsoid(raw[~test], None, False, whole, fitting_module.HOLDOUT_TOLERANCE)
    assert np.abs(warm.offset - cold.offset).max() < 1e-3  # uT, against 0.3 uT of noise
    assert np.abs(warm.matrix - cold.matrix).max() < 1e-6


@pytest.mark.parametrize("method", [Method.ELLIPSOID, Method.ELLIPSOID_ALIGN])
def test_quality_figures_and_verdict_are_those_of_the_cold_holdout_fit(method, monkeypatch):
    raw, acc = synthetic_tumble(4000, 3)
    quick = fit(FitInput(raw, acc=acc), method)
    cold = dataclasses.replace(fitting_module.METHODS[method], held_out=None)
    monkeypatch.setitem(fitting_module.METHODS, method, cold)  # every held-out fit from a cold start
    slow = fit(FitInput(raw, acc=acc), method)
    assert quick.accepted == slow.accepted and quick.reason == slow.reason
    a, b = quick.quality.to_dict(), slow.quality.to_dict()
    assert a.keys() == b.keys()
    for key, value in a.items():
        if isinstance(value, float):
            assert value == pytest.approx(b[key], rel=1e-5, abs=1e-6), key
        else:
            assert value == b[key], key
