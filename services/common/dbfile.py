"""Whether a database file opened by a process is still the file at its path: deleted (``rm``), replaced (another
file moved over it, a restore copied in place) or overwritten (its header no longer the format's). SQLite goes on
writing to an open file after it is deleted, so a store that does not look acknowledges rows nobody reads again."""

from __future__ import annotations

import os
from pathlib import Path

#: the first 16 bytes of every SQLite database file
SQLITE_HEADER = b"SQLite format 3\x00"

_WHAT = "restart the calibrator to open (or create) the file now at the path, or restore it from a backup"


class OpenedFile:
    """The device and inode of the file at ``path`` when it was opened (a path of ``:memory:`` is never gone)."""

    def __init__(self, path: Path, header: bytes = SQLITE_HEADER) -> None:
        self.path, self.header = path, header
        self.identity = None if str(path) == ":memory:" else self._stat()

    def _stat(self) -> tuple[int, int]:
        st = os.stat(self.path)
        return st.st_dev, st.st_ino

    def check(self) -> str | None:
        """None while the file at the path is the one opened and starts with ``header``; else
        one line saying what happened and what to do. Two system calls: a ``stat`` and a 16-byte read."""
        if self.identity is None:
            return None
        try:
            identity = self._stat()
            with open(self.path, "rb") as file:
                start = file.read(len(self.header))
        except FileNotFoundError:
            return f"calibration database {self.path} was deleted while open: nothing more is stored; {_WHAT}"
        except OSError as exc:
            return f"calibration database {self.path} cannot be checked ({exc}): nothing more is stored; {_WHAT}"
        if identity != self.identity:
            return (
                f"calibration database {self.path} was replaced by another file while open (device/inode "
                f"{self.identity} -> {identity}): nothing more is stored; {_WHAT}"
            )
        if start != self.header:
            return (
                f"calibration database {self.path} no longer starts with an SQLite header (overwritten or emptied "
                f"while open): nothing more is stored; {_WHAT}"
            )
        return None
