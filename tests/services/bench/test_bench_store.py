"""``magnet bench store`` measures a store of either kind and refuses one that already holds records."""

from __future__ import annotations

import re

import pytest

from services.bench.store import measure, run_store_benchmark


def test_the_store_bench_prints_commits_and_latencies_of_every_device_read_back():
    line = run_store_benchmark(20)
    assert re.search(r"SQLite .*20 devices: \d+ commits/s .*latest p50 [\d.]+ ms, p99 [\d.]+ ms; all_latest", line)


def test_the_store_bench_refuses_a_store_that_holds_records(tmp_path):
    measure(tmp_path / "s.sqlite3", 3)
    with pytest.raises(ValueError, match="already holds records"):
        measure(tmp_path / "s.sqlite3", 3)
