"""The first heading's take compiled (magnet._kernels.first_take, behind ``FirstHeading.judge``) against the same
maths written plainly in numpy here (the implementation it replaced): random fields of the Earth's strength, doors,
zero rows and other scales, cut into random batches, judged and restarted alike, sample for sample."""

from __future__ import annotations

import numpy as np
import pytest

from magnet.attitude import fusion
from magnet.compass.first_heading import (
    AWAY,
    CALM,
    CALM_S,
    EARLY_S,
    JUDGED,
    LEFT,
    MAX_SHARE,
    MIN_JUDGED_S,
    SEEN_AWAY,
    SEEN_STRENGTH,
    TOL_PCT,
    FirstHeading,
)


class PlainTake:
    """The take written plainly in numpy (as it was before it was compiled): ``start`` at each (re)start of a
    filter's magnetic side, ``judge`` on the samples fed to it; ``left`` samples of the take remain."""

    def __init__(self) -> None:
        self.period_s = 0.0
        self.left = self.size = self.judged = self.away = self.calm = 0
        self.seen_away = self.seen_strength = False
        self.calm_needed = self.early = 1

    def start(self, filt: fusion.Fusion, again: bool = False) -> None:
        """A (re)start of the filter's magnetic side: the next tauMag seconds of samples are judged, where vqf takes
        its first heading from them (not where a record's heading came from the device's history: its ``kMagInit``
        is off then, ``magnet.attitude.causal_drift``); ``again``: the take begun again after a door (once only)."""
        self.period_s = filt.period_s
        taking = float(filt._filter.state["kMagInit"]) != 0.0
        self.left = self.size = max(1, round(filt.figures().tau_mag_s / self.period_s)) if taking else 0
        self.judged = self.away = self.calm = 0
        self.seen_away = self.seen_strength = False
        self.calm_needed = max(1, round(CALM_S / self.period_s))
        self.early = 0 if again else round(EARLY_S / self.period_s)

    def judge(
        self, fields: np.ndarray, expected_ut: np.ndarray, lo: int, hi: int
    ) -> tuple[np.ndarray | None, int | None]:
        """(left out, restart) for samples lo .. hi of fields (S, 3) uT (zero rows: no field) against expected_ut (S,)
        uT (NaN or 0 where unknown; one device's samples of one step, so one value: the first's is taken): those (n =
        hi - lo,) bool away from the strength, their rows zeroed in ``fields`` (in place), or None when none is (the
        usual case: the take is over); and the index (from lo) where the take starts again (the filter's magnetic
        side restarted there, the rest judged after ``start``), or None."""
        field = fields[lo:hi]
        if self.left <= 0 or len(field) == 0:
            return None, None
        take = min(self.left, len(field))
        strength = float(expected_ut[lo])
        if not strength > 0.0:  # NaN or 0: no strength to judge by
            self.left -= take
            return None, None
        norm2 = np.einsum("ij,ij->i", field[:take], field[:take])
        known = norm2 > 0.0
        low, high = ((1.0 - TOL_PCT / 100.0) * strength) ** 2, ((1.0 + TOL_PCT / 100.0) * strength) ** 2
        away = known & ((norm2 < low) | (norm2 > high))
        any_away = bool(away.any())
        may_restart = self.seen_away or (any_away and self.size - self.left < self.early)  # an early away, or now
        restart = self._calm_again(known, away) if may_restart else None
        end = take if restart is None else restart
        self.left -= end
        self.judged += int(np.count_nonzero(known[:end]))
        if not any_away:
            self.seen_strength = self.seen_strength or bool(known[:end].any())
            return None, restart
        self.away += int(np.count_nonzero(away[:end]))
        if self.judged * self.period_s >= MIN_JUDGED_S and self.away > MAX_SHARE * self.judged:
            self.left = 0  # the strength is in question: nothing more left out until the next start
            return None, None
        # left out once the field has shown the strength: a field never near it leaves vqf's take as it was
        seen = self.seen_strength | np.logical_or.accumulate(known[:end] & ~away[:end])
        self.seen_strength = bool(seen[-1]) if end else self.seen_strength
        if not (away[:end] & seen).any():
            return None, restart
        out = np.zeros(len(field), dtype=bool)
        out[:end] = away[:end] & seen
        field[out] = 0.0
        return out, restart

    def _calm_again(self, known: np.ndarray, away: np.ndarray) -> int | None:
        """The index (into known (m,) bool) of the sample that ends ``CALM_S`` of known samples within the strength
        after one away from it (in this batch or carried over), one away having come within ``EARLY_S`` of the take's
        start; or None. The calm run and whether one was away early are carried to the next batch."""
        index = np.flatnonzero(known)
        if index.size == 0:
            return None
        flagged = away[index]
        position = np.arange(index.size)
        last_away = np.maximum.accumulate(np.where(flagged, position, -1 - self.calm))
        early = flagged & (index + (self.size - self.left) < self.early)
        seen = self.seen_away | np.logical_or.accumulate(early)
        ready = np.flatnonzero(seen & (position - last_away >= self.calm_needed))
        if ready.size:
            return int(index[ready[0]])
        self.calm = int(position[-1] - last_away[-1])
        self.seen_away = bool(seen[-1])
        return None


def _walk(rng: np.random.Generator, n: int, strength_ut: float, early: int) -> np.ndarray:
    """(n, 3) uT: the Earth's field in random directions with doors (1.3-2.5x), dips (0.4-0.8x) and runs of zero rows
    (no field), half of them within ``early`` samples of the start; one walk in five at another scale throughout."""
    scale = np.full(n, strength_ut * rng.uniform(0.95, 1.05))
    if rng.random() < 0.2:
        scale *= rng.choice([0.5, 1.6])
    for _ in range(rng.integers(1, 6)):
        lo = int(rng.integers(0, n if rng.random() < 0.5 else early))
        scale[lo : lo + int(rng.integers(1, 300))] *= rng.choice([rng.uniform(1.3, 2.5), rng.uniform(0.4, 0.8), 0.0])
    direction = rng.normal(size=(n, 3))
    return direction / np.linalg.norm(direction, axis=1, keepdims=True) * scale[:, None]


@pytest.mark.parametrize("seed", range(40))
def test_the_compiled_take_judges_as_the_plain_one(seed):
    rng = np.random.default_rng(seed)
    period_s = float(rng.choice([0.002, 0.01, 0.02]))
    n, strength = int(rng.integers(200, 2500)), float(rng.uniform(25.0, 65.0))
    fields = _walk(rng, n, strength, round(EARLY_S / period_s))
    expected = np.full(n, strength if rng.random() > 0.1 else np.nan)
    f = fusion.Fusion(period_s)
    compiled, plain = FirstHeading(), PlainTake()
    compiled.start(f), plain.start(f)
    mine, theirs = fields.copy(), fields.copy()
    lo = 0
    while lo < n:
        hi = min(n, lo + int(rng.integers(1, 400)))
        out_c, again_c = compiled.judge(mine, expected, lo, hi)
        out_p, again_p = plain.judge(theirs, expected, lo, hi)
        assert again_c == again_p
        assert (out_c is None) == (out_p is None)
        if out_c is not None:
            assert np.array_equal(out_c, out_p)
        numbers = [compiled.state[k] for k in (LEFT, JUDGED, AWAY, SEEN_STRENGTH)]
        assert numbers == [plain.left, plain.judged, plain.away, plain.seen_strength]
        if again_p is None and (plain.seen_away or plain.calm):
            assert compiled.state[CALM] == plain.calm and compiled.state[SEEN_AWAY] == plain.seen_away
        lo = hi if again_p is None else lo + again_p
        if again_p is not None:
            compiled.start(f, again=True), plain.start(f, again=True)
        elif rng.random() < 0.02:  # a record in force: the magnetic side restarted
            compiled.start(f), plain.start(f)
    assert np.array_equal(mine, theirs), "the same rows zeroed"
