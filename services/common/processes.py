"""``stop_processes``: end child processes politely, then firmly: SIGTERM to each still running, SIGKILL to any that
has not ended ``timeout_s`` later. Shared by ``magnet up``, ``magnet bench soak`` and the tests' process helpers."""

from __future__ import annotations

import subprocess
from collections.abc import Iterable
from typing import Any

#: seconds a process has to end after SIGTERM before it is killed
STOP_TIMEOUT_S = 5.0


def stop_processes(procs: Iterable[subprocess.Popen[Any]], timeout_s: float = STOP_TIMEOUT_S) -> None:
    """Terminate every process of ``procs`` still running, wait up to ``timeout_s`` for each, kill the rest."""
    procs = list(procs)
    for proc in procs:
        if proc.poll() is None:
            proc.terminate()
    for proc in procs:
        try:
            proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
