"""The full disk of ``magnet bench soak``: a small tmpfs mounted under the calibrator's database (root only), filled
to its last block for a while, then freed; unmounted at the end."""

from __future__ import annotations

import contextlib
import os
import subprocess
from pathlib import Path

TMPFS_SIZE = "16m"


class FullDisk:
    """A small tmpfs under the calibrator's database when this process may mount one; ``fill`` and ``free``."""

    def __init__(self, directory: Path) -> None:
        self.directory, self.filler = directory, directory / "filler"
        self.mounted, self.why_not = False, ""
        directory.mkdir(parents=True, exist_ok=True)
        if os.geteuid() != 0:
            self.why_not = "needs root to mount a tmpfs"
            return
        done = subprocess.run(
            ["mount", "-t", "tmpfs", "-o", f"size={TMPFS_SIZE}", "tmpfs", str(directory)],
            capture_output=True,
            text=True,
        )
        self.mounted = done.returncode == 0
        self.why_not = "" if self.mounted else f"mount failed: {done.stderr.strip()}"

    def fill(self) -> int:
        """Write until the filesystem is full; the bytes written."""
        written, chunk = 0, b"\0" * (1 << 20)
        with open(self.filler, "wb") as handle, contextlib.suppress(OSError):
            while written < (1 << 30):
                handle.write(chunk)
                handle.flush()
                written += len(chunk)
        with contextlib.suppress(OSError), open(self.filler, "ab") as handle:  # the last partial block
            while True:
                handle.write(b"\0" * 4096)
                handle.flush()
        return written

    def free(self) -> None:
        self.filler.unlink(missing_ok=True)

    def unmount(self) -> None:
        if self.mounted:
            done = subprocess.run(["umount", str(self.directory)], capture_output=True)
            if done.returncode != 0:
                subprocess.run(["umount", "-l", str(self.directory)], capture_output=True)
            self.mounted = False
