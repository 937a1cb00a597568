"""``heading_sigma_deg`` on the wire (issue 27): an optional per-sample array after the others, in both versions;
a message without it reads as before, and a reader that does not know it (a map read by key) reads a message with it
as before."""

import itertools

import msgpack
import numpy as np
import pytest

from magnet import wire

VERSIONS = (1, 2)


def _batch(sigma, quat=True):
    n = len(sigma) if sigma is not None else 3
    q = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1)) if quat else None
    zeros = np.zeros(n)
    return wire.HeadingBatch(
        "dev",
        4,
        np.arange(n, dtype=np.int64) + 10**18,
        zeros + 10,
        zeros + 12,
        zeros,
        zeros,
        np.ones((n, 3)),
        2.0,
        "cal",
        np.zeros(n, dtype=np.int64),
        q,
        None if sigma is None else np.asarray(sigma, dtype=float),
    )


@pytest.mark.parametrize("version", VERSIONS)
@pytest.mark.parametrize("quat", [True, False])
def test_sigma_round_trips_with_and_without_quaternions(version, quat):
    sigma = [0.25, 1.5, 42.0]
    payload = wire.encode_heading(_batch(sigma, quat), version=version)
    back = wire.decode_heading(payload)
    np.testing.assert_allclose(back.heading_sigma_deg, sigma, rtol=1e-6)
    assert (back.quat_wxyz is not None) == quat
    # the same bytes msgpack itself gives for the map (the v 2 encoder joins pieces by hand)
    message = msgpack.unpackb(payload, raw=False)
    assert list(message)[-1] == "heading_sigma_deg"
    assert msgpack.packb(message, use_bin_type=True) == payload


@pytest.mark.parametrize("version", VERSIONS)
def test_a_message_without_sigma_reads_as_before(version):
    back = wire.decode_heading(wire.encode_heading(_batch(None), version=version))
    assert back.heading_sigma_deg is None
    np.testing.assert_allclose(back.heading_deg, 10.0)


def test_an_old_reader_reads_a_message_with_sigma():
    """What a reader that predates the field does: take the keys it knows and leave the rest."""
    message = msgpack.unpackb(wire.encode_heading(_batch([1.0, 2.0, 3.0])), raw=False)
    old = {key: value for key, value in message.items() if key != "heading_sigma_deg"}
    assert set(message) - set(old) == {"heading_sigma_deg"}
    back = wire.decode_heading(msgpack.packb(old, use_bin_type=True))
    assert back.heading_sigma_deg is None and len(back) == 3


def test_a_batch_with_a_sigma_that_is_not_finite_carries_none_and_negative_is_refused():
    columns = wire.RawColumns.from_batches(
        [
            wire.RawBatch("a", 1, "s", np.arange(2, dtype=np.int64), np.ones((2, 3))),
            wire.RawBatch("b", 1, "s", np.arange(2, dtype=np.int64), np.ones((2, 3))),
        ]
    )
    z = np.zeros(4)
    payloads = wire.encode_headings(
        columns, z, z, z, z, np.ones((4, 3)), z.astype(int), 0.0, ["", ""], None, np.array([1.0, np.nan, 2.0, 3.0])
    )
    assert wire.decode_heading(payloads[0]).heading_sigma_deg is None
    np.testing.assert_allclose(wire.decode_heading(payloads[1]).heading_sigma_deg, [2.0, 3.0])
    message = msgpack.unpackb(payloads[1], raw=False)
    message["heading_sigma_deg"] = [-1.0, 2.0]
    with pytest.raises(wire.WireError):
        wire.decode_heading(msgpack.packb(message, use_bin_type=True))


def test_per_batch_finiteness_is_the_plain_check_of_each_batch():
    """The encoders' per-batch 'all finite' (sigma, quaternions) in one pass over the drain, on random drains with
    empty batches, NaN and infinities anywhere, is each batch's own ``.all()``."""
    from magnet.wire import headings

    rng = np.random.default_rng(28)
    for _ in range(200):
        sizes = rng.integers(0, 6, size=rng.integers(1, 8))
        bounds = np.concatenate(([0], np.cumsum(sizes))).tolist()
        total = bounds[-1]
        sigma = rng.normal(size=total)
        quat = rng.normal(size=(total, 4))
        for values in (sigma, quat):
            spots = rng.random(values.shape) < rng.choice([0.0, 0.05, 0.5])
            values[spots] = rng.choice([np.nan, np.inf, -np.inf], size=int(spots.sum()))
        finite_rows = np.isfinite(quat).all(axis=1)
        assert headings._sigmas_ok(sigma, bounds) == [
            bool(np.isfinite(sigma[a:b]).all()) for a, b in itertools.pairwise(bounds)
        ]
        assert headings._quaternions_ok(quat, bounds) == [
            bool(finite_rows[a:b].all()) for a, b in itertools.pairwise(bounds)
        ]
        assert all(type(v) is bool for v in headings._sigmas_ok(sigma, bounds))
