"""Shards: N compass or calibrator processes split a fleet by device id, with nothing shared but Zenoh.

A device belongs to shard ``shard_of(device, N)``: the first 8 bytes of the SHA-256 of its id (UTF-8), read as a
big-endian unsigned integer, modulo N. The hash is stable across processes, machines, Python versions and restarts
(unlike Python's ``hash``), so every process started with ``--shard K/N`` (K in 0 .. N-1) takes the same devices:

    int.from_bytes(hashlib.sha256(device.encode("utf-8")).digest()[:8], "big") % N

Every shard receives every message on the keys it subscribes to (Zenoh routes by key, not by hash) and drops the
other shards' devices by their key before decoding anything.
"""

from __future__ import annotations

import dataclasses
import functools
import re

_SPEC = re.compile(r"^\s*(\d+)\s*/\s*(\d+)\s*$")
MAX_SHARDS = 10_000


@functools.lru_cache(maxsize=200_000)
def _hash64(device: str) -> int:
    import hashlib  # on the first hash (a sharded compass), not on every import: OpenSSL's hashes take ms to load

    return int.from_bytes(hashlib.sha256(device.encode("utf-8")).digest()[:8], "big")


def shard_of(device: str, count: int) -> int:
    """The shard (0 .. count-1) of ``device`` among ``count``."""
    if count < 1:
        raise ValueError(f"a fleet is split into at least 1 shard, got {count}")
    return _hash64(device) % count


@dataclasses.dataclass(frozen=True)
class Shard:
    """Shard ``index`` of ``count`` (0 <= index < count); ``Shard()`` (0 of 1) takes every device."""

    index: int = 0
    count: int = 1

    def __post_init__(self) -> None:
        if not 1 <= self.count <= MAX_SHARDS or not 0 <= self.index < self.count:
            raise ValueError(f"--shard K/N needs 1 <= N <= {MAX_SHARDS} and 0 <= K < N, got {self.index}/{self.count}")

    @classmethod
    def parse(cls, text: str) -> Shard:
        """``"K/N"`` (e.g. ``"0/2"``, ``"1/2"``); ValueError saying what is expected."""
        match = _SPEC.match(text or "")
        if match is None:
            raise ValueError(f"--shard must be K/N (e.g. 0/2: the first of two shards), got {text!r}")
        return cls(int(match.group(1)), int(match.group(2)))

    @property
    def everything(self) -> bool:
        return self.count == 1

    def owns(self, device: str) -> bool:
        """Whether ``device`` belongs to this shard."""
        return self.count == 1 or _hash64(device) % self.count == self.index

    def __str__(self) -> str:
        return f"{self.index}/{self.count}"


#: the one shard of an unsharded service: every device
EVERY_DEVICE = Shard()
