"""ROS 2 recordings (rosbag2: a bag directory, or its ``.mcap`` or ``.db3`` file) as offline input, read with
rosbags: the ``sensor_msgs/msg/MagneticField`` samples of one topic (``--topic``, or the only such topic), joined with
the ``sensor_msgs/msg/Imu`` samples of the same stamp (the sibling ``.../imu`` topic, or the only Imu topic) and
converted to magnet's frame (``magnet.ros2.frames.from_ros``): mx,my,mz in uT (so ``--unit ut``), ax,ay,az m/s^2,
gx,gy,gz rad/s, t_s from the header stamps. Messages that do not decode are skipped and counted in the note.

A recording is untrusted: before rosbags opens an MCAP file, its records are walked and one claiming more bytes than
the file holds is refused; a chunk is decompressed only up to the size it declares, which may be at most
``MAX_CHUNK_BYTES`` and at most ``MAX_CHUNK_RATIO`` times its compressed size (``MIN_CHUNK_ALLOWANCE`` at least),
and one reading decompresses at most ``DECOMPRESSED_PER_FILE_BYTE`` times the recording's size
(``MIN_DECOMPRESSED_BYTES`` at least). Whatever rosbags or SQLite raise for a damaged file (``apsw.CorruptError``,
a message row that is not binary) is one ``ValueError`` naming the file."""

from __future__ import annotations

import contextlib
import contextvars
import struct
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import lz4.frame  # type: ignore[import-untyped]
import numpy as np
from rosbags.rosbag2 import Reader, storage_mcap

from magnet.ros2 import messages
from magnet.ros2.frames import from_ros
from services.common.inputs.csvio import SampleTable

PAIR_TOLERANCE_NS = 20_000_000
#: the largest chunk decompressed (rosbag2 writes chunks of about 1 MB; a larger message gets a chunk of its own)
MAX_CHUNK_BYTES = 64 * 1024 * 1024
#: a chunk may inflate to at most this many times its compressed size (sensor messages compress a few times) ...
MAX_CHUNK_RATIO = 256
#: ... or to this, whatever its compressed size
MIN_CHUNK_ALLOWANCE = 64 * 1024
#: bytes decompressed in all by one reading: this many times the recording's size ...
DECOMPRESSED_PER_FILE_BYTE = 64
#: ... or this, whichever is larger
MIN_DECOMPRESSED_BYTES = 256 * 1024 * 1024
#: records rosbags may parse out of decompressed chunks in one reading (every pass counted: it scans a bag without
#: an index three times): one per this many bytes of the recording (a real message compresses to 30-80 bytes) ...
FILE_BYTES_PER_RECORD = 4
#: ... or this many, whichever is larger (rosbags takes 1.5-3 us a record: a few seconds)
MIN_RECORDS = 2_000_000
MCAP_MAGIC = b"\x89MCAP0\r\n"
_FOOTER = 0x02


class ChunkRefusedError(Exception):
    """A chunk of an MCAP file beyond the limits (its words name the chunk, not the file)."""


#: what one reading may still decompress: [bytes, records, the records allowed] (set by ``read_rosbag``; None
#: outside a reading: rosbags' own limits)
_BUDGET: contextvars.ContextVar[list[int] | None] = contextvars.ContextVar("mcap_budget", default=None)


def _allowed(size: int, compressed: int) -> None:
    """ChunkRefusedError when a chunk of ``compressed`` bytes declaring ``size`` decompressed is beyond the limits."""
    limit = min(MAX_CHUNK_BYTES, max(MIN_CHUNK_ALLOWANCE, MAX_CHUNK_RATIO * compressed))
    if size > limit:
        raise ChunkRefusedError(
            f"a chunk of {compressed} bytes declares {size} bytes decompressed, more than the {limit} allowed "
            f"(at most {MAX_CHUNK_BYTES} bytes and {MAX_CHUNK_RATIO} times its size): a damaged or crafted file"
        )
    budget = _BUDGET.get()
    if budget is not None:
        if size > budget[0]:
            raise ChunkRefusedError(f"its chunks decompress to more than {DECOMPRESSED_PER_FILE_BYTE} times its size")
        budget[0] -= size


def _count_records(chunk: bytes | bytearray) -> None:
    """Charge the records of a decompressed ``chunk`` to the reading's budget (ChunkRefusedError past it): a chunk
    within every size limit may still hold millions of records of 9 bytes, each a step of rosbags' Python parser."""
    budget = _BUDGET.get()
    if budget is None:
        return
    left, position, end = budget[1], 0, len(chunk) - 9
    length = struct.Struct("<Q").unpack_from
    while position <= end and left >= 0:
        position += 9 + length(chunk, position + 1)[0]
        left -= 1
    if left < 0:
        raise ChunkRefusedError(
            f"its chunks hold more than {budget[2]} records (at most one per {FILE_BYTES_PER_RECORD} bytes of the "
            f"recording, or {MIN_RECORDS}): a damaged or crafted file"
        )
    budget[1] = left


def _bounded(decompressor: Callable[[], Any]) -> Callable[[bytes, int], bytes]:
    """A decompressor for rosbags' table that writes no more than the chunk's declared size (ChunkRefusedError when the
    data holds more, or the declared size is beyond the limits)."""

    def decompress(data: bytes, size: int) -> bytes:
        _allowed(size, len(data))
        out, rest = bytearray(), data
        while rest and len(out) <= size:
            frame = decompressor()
            out += frame.decompress(rest, max_length=size + 1 - len(out))
            if not frame.eof:
                break
            rest = frame.unused_data
        if len(out) > size:
            raise ChunkRefusedError(f"a chunk inflates beyond the {size} bytes it declares: a damaged or crafted file")
        _count_records(out)
        return bytes(out)

    return decompress


_ZSTD = storage_mcap.zstd  # type: ignore[attr-defined]  # the zstd module rosbags uses (compression or backports)
storage_mcap.DECOMPRESSORS.update(
    {"zstd": _bounded(_ZSTD.ZstdDecompressor), "lz4": _bounded(lz4.frame.LZ4FrameDecompressor)}
)


def check_mcap(path: Path) -> None:
    """Walk the records of the MCAP file at ``path``; ValueError naming the file and the offset for a record that
    claims more bytes than the file holds after it. Reads 9 bytes a record (a chunk is one record)."""
    size = path.stat().st_size
    with open(path, "rb") as handle:
        if handle.read(8) != MCAP_MAGIC:
            return  # rosbags says what is wrong with it
        position = 8
        while position + 9 <= size - len(MCAP_MAGIC):
            handle.seek(position)
            op, length = struct.unpack("<BQ", handle.read(9))
            left = size - len(MCAP_MAGIC) - position - 9
            if length > left:
                raise ValueError(
                    f"{path}: the record at byte {position} (opcode 0x{op:02x}) claims {length} bytes, but the file "
                    f"holds {max(left, 0)} after it: cut short, damaged or crafted"
                )
            if op == _FOOTER:
                return
            position += 9 + length


def _mcap_files(path: Path) -> list[Path]:
    return sorted(path.glob("*.mcap")) if path.is_dir() else [path] if path.suffix.lower() == ".mcap" else []


def _size(path: Path) -> int:
    return sum(f.stat().st_size for f in path.iterdir() if f.is_file()) if path.is_dir() else path.stat().st_size


@contextlib.contextmanager
def _budget(path: Path) -> Iterator[None]:
    size = _size(path)
    records = max(MIN_RECORDS, size // FILE_BYTES_PER_RECORD)
    token = _BUDGET.set([max(MIN_DECOMPRESSED_BYTES, DECOMPRESSED_PER_FILE_BYTE * size), records, records])
    try:
        yield
    finally:
        _BUDGET.reset(token)


def _topics(reader: Any, ros_type: str) -> list[str]:
    return sorted({c.topic for c in reader.connections if c.msgtype == ros_type})


def _mag_topic(path: Path, reader: Any, asked: str | None) -> str:
    mags = _topics(reader, messages.MAGNETIC_FIELD)
    if asked is not None:
        if asked not in mags:
            raise ValueError(
                f"{path}: no {messages.MAGNETIC_FIELD} topic {asked!r}; it has {', '.join(mags) or 'none'}"
            )
        return asked
    if len(mags) != 1:
        listed = ", ".join(mags) or "none"
        raise ValueError(f"{path}: pick the MagneticField topic with --topic (the recording has: {listed})")
    return mags[0]


def _imu_topic(reader: Any, mag_topic: str) -> str | None:
    imus = _topics(reader, messages.IMU)
    sibling = mag_topic.rsplit("/", 1)[0] + "/imu"
    if sibling in imus:
        return sibling
    return imus[0] if len(imus) == 1 else None


def _read(reader: Any, topic: str, decode: Any) -> tuple[list[Any], int]:
    conns = [c for c in reader.connections if c.topic == topic]
    out, bad = [], 0
    for _, _, data in reader.messages(connections=conns):
        if not isinstance(data, bytes | bytearray | memoryview):  # a .db3 row may hold any SQLite value
            bad += 1
            continue
        try:
            out.append(decode(bytes(data)))
        except ValueError:
            bad += 1
    return out, bad


def _join(mag_t: np.ndarray, imus: list[messages.ImuSample]) -> tuple[np.ndarray | None, np.ndarray | None]:
    """Per field sample, the acceleration and rates (FLU) of the Imu sample nearest in time (20 ms at most); None
    when any field sample has none."""
    usable = [i for i in imus if i.acc_ms2 is not None]
    if not usable or not len(mag_t):
        return None, None
    usable.sort(key=lambda i: i.t_ns)
    imu_t = np.array([i.t_ns for i in usable], dtype=np.int64)
    right = np.clip(np.searchsorted(imu_t, mag_t), 1, len(imu_t) - 1) if len(imu_t) > 1 else np.zeros_like(mag_t)
    left = np.maximum(right - 1, 0)
    nearest = np.where(np.abs(imu_t[left] - mag_t) <= np.abs(imu_t[right] - mag_t), left, right)
    if (np.abs(imu_t[nearest] - mag_t) > PAIR_TOLERANCE_NS).any():
        return None, None
    acc = np.array([usable[k].acc_ms2 for k in nearest])
    gyros = [usable[k].gyr_rads for k in nearest]
    gyr = None if any(g is None for g in gyros) else np.array(gyros)
    return acc, gyr


def _unreadable(path: Path, exc: BaseException) -> ValueError:
    """The one error of a recording rosbags (or SQLite) cannot read."""
    words = str(exc) or "no detail given"
    if isinstance(exc, ChunkRefusedError):
        return ValueError(f"{path}: {words}")
    return ValueError(f"{path}: not a rosbag2 recording rosbags can read ({type(exc).__name__}: {words})")


def _messages(path: Path, topic: str | None) -> tuple[str, str | None, list[Any], list[Any], int, int]:
    """(field topic, Imu topic, field samples, Imu samples, undecodable of each) of a rosbag2 recording."""
    for mcap in _mcap_files(path):
        check_mcap(mcap)
    with _budget(path):
        try:
            reader = Reader(path)
            reader.open()
        except Exception as exc:  # rosbags raises its own errors for files it cannot read
            raise _unreadable(path, exc) from None
        try:
            mag_topic = _mag_topic(path, reader, topic)
            mags, bad_mag = _read(reader, mag_topic, messages.decode_magnetic_field)
            imu_topic = _imu_topic(reader, mag_topic)
            imus, bad_imu = _read(reader, imu_topic, messages.decode_imu) if imu_topic else ([], 0)
        except ValueError:
            raise
        except Exception as exc:  # a damaged file: rosbags' ReaderError, apsw.CorruptError, a refused chunk ...
            raise _unreadable(path, exc) from None
        finally:
            with contextlib.suppress(Exception):
                reader.close()
    return mag_topic, imu_topic, mags, imus, bad_mag, bad_imu


def read_rosbag(path: Path, topic: str | None) -> SampleTable:
    """The samples of a rosbag2 recording; ValueError naming the file and what to do."""
    mag_topic, imu_topic, mags, imus, bad_mag, bad_imu = _messages(path, topic)
    if not mags:
        raise ValueError(f"{path}: topic {mag_topic} holds no MagneticField message that decodes")
    t_ns = np.array([m.t_ns for m in mags], dtype=np.int64)
    acc, gyr = _join(t_ns, imus)
    field = np.array([m.field_t for m in mags])
    mag_ut, acc_frd, gyr_frd = from_ros(field, acc if acc is not None else np.zeros_like(field), gyr)
    columns: dict[str, list[str] | np.ndarray] = {"t_s": t_ns / 1e9}
    for names, values in ((("mx", "my", "mz"), mag_ut), (("ax", "ay", "az"), acc_frd), (("gx", "gy", "gz"), gyr_frd)):
        if values is not None and (names[0] == "mx" or acc is not None):
            columns.update({name: values[:, k] for k, name in enumerate(names)})
    note = f"{len(mags)} samples of {_source_words(mag_topic, imu_topic, acc)} (uT, converted from ROS 2's FLU tesla)"
    if bad_mag or bad_imu:
        note += f"; skipped {bad_mag} MagneticField and {bad_imu} Imu messages that do not decode"
    return SampleTable(str(path), mag_ut, acc_frd if acc is not None else None, columns, note=note)


def _source_words(mag_topic: str, imu_topic: str | None, acc: np.ndarray | None) -> str:
    """Where the samples came from, in words."""
    if imu_topic is None:
        return f"{mag_topic} (no Imu topic)"
    return f"{mag_topic} with {imu_topic}" + ("" if acc is not None else " (not paired in time: no acceleration)")
