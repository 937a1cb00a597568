"""The C allocator of a service process, told to give freed memory back (glibc's ``mallopt``; elsewhere nothing).

A service receives payloads of up to a few MB (Zenoh reassembles them, the intake copies them, the decoder reads
them) and frees them at once. glibc's defaults keep such memory: after the first large block is freed it raises its
threshold for ``mmap`` to that size (so later blocks of a few MB come from heaps that shrink only from the top, and
a burst of bombs leaves them fragmented), and every thread that allocates (Zenoh's receiving threads) may get an
arena of its own, up to 8 per core. Measured on 20 payloads of 2.5 MB of empty msgpack arrays at a running compass
and calibrator (``tests/system/test_decode_bombs.py``): their RSS grew by 49 and 46 MB and stayed there with the
defaults; 24-26 MB with these settings (most of it Zenoh's own receiving buffers, which a bare Zenoh subscriber keeps
too) (docs/front-door.md, "Memory per service").

- ``M_MMAP_THRESHOLD`` fixed at ``MMAP_THRESHOLD_BYTES``: every block of 1 MiB or more is its own mapping, returned
  to the system when freed, whatever came before (a fixed value also turns the raising off);
- ``M_TRIM_THRESHOLD`` ``TRIM_THRESHOLD_BYTES``: the top of a heap is given back once that much of it is free (at
  8 MiB a compass decoding 20 bombs of empty arrays kept 51 MB; at 128 kB, 21-24 MB);
- ``M_ARENA_MAX`` ``ARENAS``: the receiving threads share arenas instead of keeping their own.

Call ``give_back_freed_memory()`` once, early, before the Zenoh session opens its threads.

A one-shot command that works through a file's arrays (``magnet fit``, ``magnet heading``) wants the opposite:
``keep_freed_memory()``. With glibc's defaults the top of the heap is given back as soon as 128 kB of it is free, and
taken again for the next array of a few hundred kB, every page of it faulted in afresh (a few us each on this
machine's virtual memory): ``magnet fit`` of 10,000 rows made 2,800 more page faults than of 300, its peak memory only
2 MB higher; ``magnet heading`` of 60,000 samples 15,000 (the floor, loadtxt and vqf, 8,700).
"""

from __future__ import annotations

import ctypes
import functools
import logging
import time
from collections.abc import Callable

log = logging.getLogger("magnet.allocator")

#: glibc's mallopt parameters (malloc.h)
M_TRIM_THRESHOLD, M_MMAP_THRESHOLD, M_ARENA_MAX = -1, -3, -8
#: 1 MiB: a payload of MBs is its own mapping, given back when freed; a drain's arrays (hundreds of kB) stay in the
#: heap, reused without page faults (at 128 kB, numpy's maths ran 40-50 % slower: `magnet bench fit`)
MMAP_THRESHOLD_BYTES = 1024 * 1024
TRIM_THRESHOLD_BYTES = 128 * 1024
ARENAS = 2
#: a one-shot command's: blocks up to 4 MiB from the heap (a fixed value: not raised to 32 MiB by a freed block, so
#: the few larger ones, a log's text or columns, are their own mappings), its top given back past 64 MiB free
KEEP_MMAP_THRESHOLD_BYTES = 4 * 1024 * 1024
KEEP_TRIM_THRESHOLD_BYTES = 64 * 1024 * 1024


def keep_freed_memory() -> bool:
    """Tell glibc's allocator to keep freed memory for the next arrays (the module docstring, last paragraph): in
    ``magnet fit`` of 10,000 rows 2,300 fewer page faults, in ``magnet heading`` of 60,000 samples 2,700 fewer, the
    same peak memory within 2 MB. False (nothing changed) where there is no glibc. Uses the symbols the process has
    loaded already (``ctypes.CDLL(None)``): no search for the C library, which runs ``ldconfig``."""
    try:
        libc = ctypes.CDLL(None)
        mallopt = getattr(libc, "mallopt", None)
    except OSError:
        mallopt = None
    if mallopt is None or not getattr(libc, "gnu_get_libc_version", None):
        return False
    settings = ((M_MMAP_THRESHOLD, KEEP_MMAP_THRESHOLD_BYTES), (M_TRIM_THRESHOLD, KEEP_TRIM_THRESHOLD_BYTES))
    return all(mallopt(ctypes.c_int(param), ctypes.c_int(value)) == 1 for param, value in settings)


def give_back_freed_memory() -> bool:
    """Set glibc's allocator as the docstring says; False (and nothing changed) where there is no glibc."""
    import ctypes.util  # subprocess and shutil: only where a service starts

    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name) if name else None
        mallopt = getattr(libc, "mallopt", None)
    except OSError:
        mallopt = None
    if mallopt is None or not getattr(libc, "gnu_get_libc_version", None):
        return False
    settings = (
        (M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES),
        (M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES),
        (M_ARENA_MAX, ARENAS),
    )
    done = all(mallopt(ctypes.c_int(param), ctypes.c_int(value)) == 1 for param, value in settings)
    if not done:
        log.debug("mallopt refused a setting; the allocator keeps its defaults for it")
    return done


def give_back_now() -> bool:
    """Give the free memory at the top and in the middle of every heap back to the system now (glibc's
    ``malloc_trim(0)``; a few ms for a heap of hundreds of MB); False where there is no glibc. For a process whose
    bursts leave its heaps fragmented beyond what ``M_TRIM_THRESHOLD`` gives back (the dashboard after floods)."""
    trim = _malloc_trim()
    if trim is None:
        return False
    trim(ctypes.c_size_t(0))
    return True


@functools.cache
def _malloc_trim() -> Callable[[ctypes.c_size_t], int] | None:
    """glibc's ``malloc_trim`` from the symbols the process has loaded (looked up once: ``find_library`` took 1-22 ms
    a call, more than the trim)."""
    try:
        libc = ctypes.CDLL(None)
    except OSError:
        return None
    trim = getattr(libc, "malloc_trim", None)
    return trim if trim is not None and getattr(libc, "gnu_get_libc_version", None) else None


class BurstTrim:
    """When to give the freed heap back (``give_back_now``) in a service loop: every ``every_s``, and while a burst
    lasts (a step that took ``busy_messages`` or more) at most every ``busy_every_s``, once more after it. A flood's
    drains leave the heap's middle freed but kept (decoded batches, numpy's columns, Zenoh's buffers, between blocks
    that stay), which only a trim gives back. ``trim`` and ``clock`` are injected for tests."""

    def __init__(
        self,
        busy_messages: int,
        every_s: float = 10.0,
        busy_every_s: float = 1.0,
        trim: Callable[[], bool] = give_back_now,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if busy_messages < 1 or not 0 < busy_every_s <= every_s:
            raise ValueError(
                f"a burst is at least 1 message and its trims at most as far apart as the period, got busy_messages "
                f"{busy_messages}, busy_every_s {busy_every_s}, every_s {every_s}"
            )
        self.busy_messages, self.every_s, self.busy_every_s = busy_messages, every_s, busy_every_s
        self.trim, self.clock = trim, clock
        self.trimmed_s, self.busy, self.trims = clock(), False, 0  # busy: a burst came since the last trim

    def after_step(self, taken: int, burst: bool = False) -> bool:
        """Call after each step with the messages it took (``burst``: the step saw a burst by another measure, large
        payloads refused by their size); whether it trimmed now."""
        self.busy = self.busy or burst or taken >= self.busy_messages
        now = self.clock()
        since_s = now - self.trimmed_s
        if since_s < self.every_s and not (self.busy and since_s >= self.busy_every_s):
            return False
        self.trimmed_s, self.busy = now, False
        self.trims += 1
        self.trim()
        return True
