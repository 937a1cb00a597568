"""Shards: a stable, documented hash splits any fleet into N disjoint shards that cover it."""

import hashlib

import pytest

from magnet.shard import Shard, shard_of


def test_the_hash_is_the_documented_one_and_stable():
    for device in ("imu-1", "b-000", "ü-7"):
        expected = int.from_bytes(hashlib.sha256(device.encode()).digest()[:8], "big") % 7
        assert shard_of(device, 7) == expected
    assert [shard_of(d, 2) for d in ("imu-1", "b-000", "b-001")] == [0, 0, 1]  # fixed: the split never moves


@pytest.mark.parametrize("count", [1, 2, 3, 8])
def test_shards_are_disjoint_cover_the_fleet_and_balanced(count):
    devices = [f"dev-{i:04d}" for i in range(4000)]
    owners = [[k for k in range(count) if Shard(k, count).owns(d)] for d in devices]
    assert all(len(o) == 1 for o in owners)
    sizes = [sum(o == [k] for o in owners) for k in range(count)]
    assert min(sizes) > 0.85 * len(devices) / count


@pytest.mark.parametrize("text", ["2/2", "-1/2", "1", "a/b", "0/0", "", "1/2/3"])
def test_bad_shard_specs_are_refused(text):
    with pytest.raises(ValueError, match="K/N"):
        Shard.parse(text)


def test_parse():
    assert Shard.parse("1/4") == Shard(1, 4) and str(Shard.parse(" 0 / 2 ")) == "0/2" and Shard().everything
