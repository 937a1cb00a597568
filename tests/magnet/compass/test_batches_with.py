"""``batches_with``: per batch, whether any of its samples is set, written plainly beside it (empty batches too)."""

from __future__ import annotations

import itertools

import numpy as np

from magnet.compass.tilt import batches_with


def test_per_batch_any_is_the_plain_loop_with_empty_batches():
    rng = np.random.default_rng(7)
    for _ in range(200):
        counts = rng.integers(0, 5, int(rng.integers(1, 8)))
        mask = rng.random(int(counts.sum())) < rng.random() * 0.5
        bounds = np.concatenate([[0], np.cumsum(counts)])
        plain = [bool(mask[lo:hi].any()) for lo, hi in itertools.pairwise(bounds)]
        assert batches_with(mask, counts) == plain
