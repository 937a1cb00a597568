"""Crafted recordings of every kind (issue 32): a ULog whose nested array formats flatten to billions of fields, an
MCAP whose chunk inflates to 1 GiB (declared, or hidden behind a small declared size), an MCAP record claiming 8 GiB,
a ``.db3`` with damaged pages and one with message rows that are not binary, a damaged DataFlash log, and flight logs
reading 3e38 uT. Each is refused with one line naming the file, within a memory ceiling of 400 MB above what the
test process already holds (``RLIMIT_AS``: an allocation past it fails instead of taking the machine) and 30 s.

The builders write the bytes by hand (ULog and MCAP records, a zstd frame of run-length blocks), so each bomb is a few
hundred bytes to 33 kB and costs nothing to make."""

from __future__ import annotations

import contextlib
import resource
import sqlite3
import struct
import time
from pathlib import Path

import numpy as np
import pytest
from logfixtures import ARDUPILOT_LOG, simulated_run, write_tlog

from services.cli import main
from services.common.inputs import read_input, rosbag_input

MEMORY_CEILING_BYTES = 400 * 1024 * 1024
SECONDS = 30.0


@contextlib.contextmanager
def memory_ceiling(extra_bytes: int = MEMORY_CEILING_BYTES):
    """Address space limited to what the process maps now plus ``extra_bytes`` (restored after)."""
    soft, hard = resource.getrlimit(resource.RLIMIT_AS)
    with open("/proc/self/statm") as statm:
        mapped = int(statm.read().split()[0]) * resource.getpagesize()
    limit = mapped + extra_bytes if hard == resource.RLIM_INFINITY else min(hard, mapped + extra_bytes)
    resource.setrlimit(resource.RLIMIT_AS, (limit, hard))
    try:
        yield
    finally:
        resource.setrlimit(resource.RLIMIT_AS, (soft, hard))


# ---- ULog ------------------------------------------------------------------------------------------------------------


def _ulog_message(kind: str, payload: bytes) -> bytes:
    return struct.pack("<HB", len(payload), ord(kind)) + payload


def ulog_nested_bomb(levels: int = 3, count: int = 255) -> bytes:
    """A ULog (about 180 bytes) whose formats nest arrays: sensor_mag flattens to count**levels fields."""
    out = b"ULog\x01\x12\x35\x01" + struct.pack("<Q", 0)
    out += _ulog_message("F", b"l0:uint8_t[%d] x;" % count)
    for k in range(1, levels):
        out += _ulog_message("F", b"l%d:l%d[%d] x;" % (k, k - 1, count))
    out += _ulog_message("F", b"sensor_mag:uint64_t timestamp;l%d[%d] y;" % (levels - 1, count))
    return out + _ulog_message("A", b"\x00\x00\x00sensor_mag")


def ulog_self_nesting() -> bytes:
    out = b"ULog\x01\x12\x35\x01" + struct.pack("<Q", 0)
    out += _ulog_message("F", b"sensor_mag:uint64_t timestamp;sensor_mag y;")
    return out + _ulog_message("A", b"\x00\x00\x00sensor_mag")


def ulog_many_subscriptions(count: int = 60, fields: int = 4000) -> bytes:
    """Formats within the limits, subscribed so often that pyulog would build 240,000 fields."""
    out = b"ULog\x01\x12\x35\x01" + struct.pack("<Q", 0)
    out += _ulog_message("F", b"sensor_mag:uint64_t timestamp;float[%d] y;" % (fields - 1))
    for k in range(count):
        out += _ulog_message("A", b"\x00" + struct.pack("<H", k) + b"sensor_mag")
    return out


def ulog_absurd_field() -> bytes:
    """A ULog whose sensor_mag reads 3e38 gauss on every sample."""
    out = b"ULog\x01\x12\x35\x01" + struct.pack("<Q", 0)
    out += _ulog_message("F", b"sensor_mag:uint64_t timestamp;uint32_t device_id;float x;float y;float z;")
    out += _ulog_message("A", b"\x00\x01\x00sensor_mag")
    for k in range(50):
        out += _ulog_message("D", struct.pack("<HQIfff", 1, 1000 * (k + 1), 0, 3e38, 1.0, 2.0))
    return out


# ---- MCAP ------------------------------------------------------------------------------------------------------------

MCAP_MAGIC = b"\x89MCAP0\r\n"


def _text(text: str) -> bytes:
    return struct.pack("<I", len(text)) + text.encode()


def _record(op: int, body: bytes, claimed: int | None = None) -> bytes:
    return bytes([op]) + struct.pack("<Q", len(body) if claimed is None else claimed) + body


def zstd_zeros(size: int, block: int = 128 * 1024) -> bytes:
    """A zstd frame of ``size`` zero bytes made of run-length blocks of ``block`` bytes (at most 128 KiB): 4 bytes a
    block."""
    out = bytearray(b"\x28\xb5\x2f\xfd\x00\x38")  # magic, no content size, window 128 KiB
    count = size // block
    for k in range(count):
        out += (int(k == count - 1) | 1 << 1 | block << 3).to_bytes(3, "little") + b"\x00"
    return bytes(out)


def mcap_bomb(
    declared: int, inflated: int, record_claim: int | None = None, chunks: int = 1, block: int = 128 * 1024
) -> bytes:
    """An MCAP with one channel and ``chunks`` zstd chunks declaring ``declared`` bytes that inflate to ``inflated``
    zero bytes each (records of opcode 0 and no content: 9 bytes a record)."""
    out = MCAP_MAGIC + _record(0x01, _text("ros2") + _text(""))
    out += _record(0x04, struct.pack("<HH", 1, 0) + _text("/mag") + _text("cdr") + struct.pack("<I", 0))
    data = zstd_zeros(inflated, block)
    chunk = struct.pack("<QQQI", 0, 1, declared, 0) + _text("zstd") + struct.pack("<Q", len(data)) + data
    out += _record(0x06, chunk, record_claim) * chunks
    return out + _record(0x0F, struct.pack("<I", 0)) + _record(0x02, struct.pack("<QQI", 0, 0, 0)) + MCAP_MAGIC


# ---- rosbag2 .db3 ----------------------------------------------------------------------------------------------------


def small_db3(directory: Path) -> Path:
    from rosbags.rosbag2 import StoragePlugin

    from tests.services.edge.test_ros2_recordings import write_bag

    rng = np.random.default_rng(1)
    mag = rng.normal(size=(200, 3))
    write_bag(directory / "bag", 0.5 * mag / np.linalg.norm(mag, axis=1, keepdims=True), np.tile([0, 0, 1.0], (200, 1)),
              storage=StoragePlugin.SQLITE3)  # fmt: skip
    return directory / "bag" / "bag.db3"


def db3_damaged(directory: Path) -> Path:
    """A bag whose rosbags can open (its tables, topics and counts intact) but some message rows continue on
    overflow pages whose chain is broken: SQLite finds the damage only when the rows are read."""
    path = small_db3(directory)
    with contextlib.closing(sqlite3.connect(path)) as db:
        with db:
            db.execute("UPDATE messages SET data = data || zeroblob(12000) WHERE id % 50 = 7")
        pages = db.execute("SELECT pageno FROM dbstat WHERE name = 'messages' AND pagetype = 'overflow'").fetchall()
        page_bytes = db.execute("PRAGMA page_size").fetchone()[0]
    content = bytearray(path.read_bytes())
    for (page,) in pages:
        offset = (page - 1) * page_bytes
        if content[offset : offset + 4] != bytes(4):  # not the last of its chain: point it past the file
            content[offset : offset + 4] = b"\xff\xff\xff\x00"
    path.write_bytes(bytes(content))
    return path


def db3_not_binary(directory: Path, value: object) -> Path:
    path = small_db3(directory)
    with contextlib.closing(sqlite3.connect(path)) as db, db:
        db.execute("UPDATE messages SET data = ?", (value,))
    return path


# ---- the tests -------------------------------------------------------------------------------------------------------


def _refused(path: Path, words: str) -> str:
    """The reader's one error for ``path``, read under the memory ceiling and within SECONDS."""
    start = time.perf_counter()
    with memory_ceiling(), pytest.raises(ValueError) as refused:
        read_input(path)
    assert time.perf_counter() - start < SECONDS
    message = str(refused.value)
    assert message.startswith(str(path)) and words in message and "\n" not in message, message
    return message


@pytest.mark.parametrize(
    "content, words",
    [
        (ulog_nested_bomb(), "flattens to more than 4096 fields"),
        (ulog_nested_bomb(levels=2, count=300), "flattens to more than 4096 fields"),
        (ulog_self_nesting(), "nests more than 16 levels"),
        (ulog_many_subscriptions(), "subscriptions flatten to more than 200000 fields"),
    ],
    ids=["nested-3x255", "nested-2x300", "self", "subscriptions"],
)
def test_a_crafted_ulog_is_refused_before_pyulog_flattens_it(tmp_path, content, words):
    path = tmp_path / "bomb.ulg"
    path.write_bytes(content)
    assert len(content) < 1100
    _refused(path, words)


def test_an_mcap_chunk_declaring_1_gib_is_refused_before_decompressing(tmp_path):
    path = tmp_path / "bomb.mcap"
    path.write_bytes(mcap_bomb(1 << 30, 1 << 30))
    assert path.stat().st_size < 34_000
    _refused(path, "declares 1073741824 bytes decompressed")


def test_an_mcap_chunk_inflating_beyond_its_declared_size_stops_there(tmp_path):
    path = tmp_path / "liar.mcap"
    path.write_bytes(mcap_bomb(16384, 1 << 30))
    _refused(path, "inflates beyond the 16384 bytes it declares")


def test_an_mcap_record_claiming_8_gib_is_named(tmp_path):
    path = tmp_path / "huge.mcap"
    path.write_bytes(mcap_bomb(16384, 16384, record_claim=8 << 30))
    _refused(path, "(opcode 0x06) claims 8589934592 bytes, but the file holds")


def test_one_reading_decompresses_a_bounded_total(tmp_path, monkeypatch):
    monkeypatch.setattr(rosbag_input, "MIN_DECOMPRESSED_BYTES", 10_000)
    path = tmp_path / "b.mcap"
    path.write_bytes(mcap_bomb(16384, 16384))
    _refused(path, "decompress to more than 64 times its size")


def test_chunks_of_millions_of_tiny_records_are_refused_by_their_count(tmp_path, monkeypatch):
    """Chunks within every size limit that inflate to records of 9 bytes: a 1 MB file of them held 30 million
    records, which rosbags parsed one by one in Python (46-56 s, then the decompression budget refused it). The records
    of every chunk decompressed are counted against one budget per reading (at the real limits: 2.7 s)."""
    monkeypatch.setattr(rosbag_input, "MIN_RECORDS", 20_000)
    path = tmp_path / "tiny.mcap"
    path.write_bytes(mcap_bomb(65_520, 65_520, chunks=4, block=8_190))  # 7,280 records a chunk
    _refused(path, "its chunks hold more than 20000 records")
    path.write_bytes(mcap_bomb(65_520, 65_520, chunks=2, block=8_190))  # within: read, then no topic found
    with pytest.raises(ValueError, match="pick the MagneticField topic"):
        read_input(path)


def test_a_db3_with_damaged_pages_is_one_line(tmp_path):
    _refused(db3_damaged(tmp_path), "not a rosbag2 recording rosbags can read")


@pytest.mark.parametrize("value", ["text", 10**12, 1.5], ids=["text", "huge-int", "float"])
def test_db3_message_rows_that_are_not_binary_are_skipped(tmp_path, value):
    _refused(db3_not_binary(tmp_path, value), "holds no MagneticField message that decodes")


def test_a_damaged_dataflash_log_is_one_line_without_bad_header_lines(tmp_path, capfd):
    content = bytearray(ARDUPILOT_LOG.read_bytes())
    content[20_000:50_000] = bytes(30_000)  # a hole: pymavlink's indexer prints a line for each bad byte
    path = tmp_path / "holed.bin"
    path.write_bytes(bytes(content))
    assert main(["fit", str(path)]) == 2
    out, err = capfd.readouterr()
    assert out == "" and "bad header" not in err and len(err.splitlines()) <= 2, err[:500]


def test_flight_logs_refuse_an_absurd_field(tmp_path):
    path = tmp_path / "absurd.ulg"
    path.write_bytes(ulog_absurd_field())
    _refused(path, "magnetometer sample 1 (t=0.001 s) reads 3e+40, beyond +-1e+09")
    tlog = tmp_path / "absurd.tlog"
    from pymavlink import mavutil

    log = mavutil.mavlogfile(str(tlog), write=True, source_system=7)
    for k in range(200):
        stamp = struct.pack(">Q", 1_700_000_000_000_000 + k * 20_000)
        log.write(
            stamp + log.mav.highres_imu_encode(k * 20_000, 0, 0, -9.8, 0, 0, 0, 3e38, 0, 0, 0, 0, 0, 0, 0).pack(log.mav)
        )
    log.close()
    _refused(tlog, "magnetometer sample 1")


def test_the_readers_keep_numbers_not_message_objects(tmp_path):
    """A telemetry log's samples are kept as numbers: reading 600 samples (about 1,900 messages kept) traces under
    0.8 MB (a pymavlink message object kept per message was about 1 kB: 2.4 MB)."""
    import tracemalloc

    run = simulated_run(count=600)
    path = tmp_path / "t.tlog"
    write_tlog(path, run)
    read_input(path)  # imports and caches warm
    tracemalloc.start()
    read_input(path)
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    assert peak < 800_000, peak
