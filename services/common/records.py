"""Calibration records in files: ``load_calibration`` (a record as ``magnet fit`` writes it, validated) and
``write_atomically`` (a file replaced whole or not at all); shared by ``magnet fit``, ``heading``, ``report`` and
``export``."""

from __future__ import annotations

import os
from pathlib import Path

from magnet.model import Calibration
from services.common.jsonio import read_json


def load_calibration(path: str) -> Calibration:
    """A record as ``magnet fit`` writes it, from a JSON file (read within ``jsonio``'s size and depth limits);
    ValueError naming the file."""
    data = read_json(path)
    try:
        return Calibration.from_dict(data)
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from None


def _umask() -> int:
    """The process's file creation mask (read by setting it and putting it back)."""
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def write_atomically(path: Path, text: str) -> None:
    """Replace ``path`` with ``text`` so that a crash leaves either the old file or the new one, never half."""
    directory = path.parent if str(path.parent) else Path(".")
    import tempfile  # (random, hashlib): only when a record is written

    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=directory)
    try:
        os.fchmod(fd, 0o666 & ~_umask())  # as an ordinary new file (0644 under umask 022), not mkstemp's 0600
        with os.fdopen(fd, "w") as handle:
            handle.write(text)
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
