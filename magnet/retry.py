"""One retry policy and one health record, for everything that is tried, can fail and is tried again.

Two levels use them: an I2C transfer (``magnet.drivers.base.I2CDevice``: a few quick retries of a glitch, then the
read fails) and the read loop above the driver (``magnet.edge.readloop.ReadLoop``: a failing sensor is read again after
a wait that doubles up to a cap, so a dead bus costs about one attempt per ``max_s``). Each level holds one
``RetryPolicy`` (how long to wait, when to give up, when to call it unhealthy) and one ``Health`` (what happened).

Pure: the waits are returned, never slept here; the caller sleeps with its injected ``sleep``.
"""

from __future__ import annotations

import dataclasses
import errno
from typing import Any


@dataclasses.dataclass(frozen=True)
class RetryPolicy:
    """Bounded exponential backoff. Seconds throughout; counts are failures in a row.

    After the n-th failure in a row the caller waits ``initial_s * factor**(n-1)``, capped at ``max_s``; after
    ``give_up_after`` failures in a row it gives up (None: never, until stopped); after ``unhealthy_after`` the
    thing is unhealthy, and its next success makes it healthy again. ``poll_s`` and ``max_polls`` are for a sensor
    that has nothing new yet (the read loop): polled again after ``poll_s``, ``max_polls`` polls in a row count as
    one failure. The defaults are an I2C transfer's (``TRANSFER_RETRY``).
    """

    initial_s: float = 0.002
    max_s: float = 0.05
    factor: float = 2.0
    give_up_after: int | None = 4
    unhealthy_after: int = 3
    poll_s: float = 0.0005
    max_polls: int = 200

    def __post_init__(self) -> None:
        if not 0 <= self.initial_s <= self.max_s:
            raise ValueError(f"retry needs 0 <= initial_s <= max_s, got {self.initial_s} and {self.max_s}")
        if self.factor < 1:
            raise ValueError(f"retry factor must be >= 1, got {self.factor}")
        if self.unhealthy_after < 1 or self.max_polls < 1 or self.poll_s < 0:
            raise ValueError("unhealthy_after and max_polls must be >= 1 and poll_s >= 0")
        if self.give_up_after is not None and self.give_up_after < 1:
            raise ValueError(f"give_up_after must be >= 1 or None, got {self.give_up_after}")

    def delay_s(self, failures: int) -> float:
        """Seconds to wait after the ``failures``-th failure in a row (1-based)."""
        exponent = min(max(failures - 1, 0), 64)
        return float(min(self.max_s, self.initial_s * self.factor**exponent))

    def gives_up(self, failures: int) -> bool:
        """True when ``failures`` in a row are as many as the policy tries."""
        return self.give_up_after is not None and failures >= self.give_up_after


#: an I2C transfer: 4 tries, waits of 2, 4, 8 ms between them
TRANSFER_RETRY = RetryPolicy()
#: a read loop that never gives up: waits of 10 ms, 20 ms, ... up to 1 s between failed reads
READ_BACKOFF = RetryPolicy(initial_s=0.01, max_s=1.0, give_up_after=None)


def cause_of(exc: OSError) -> str:
    """The name a failure is counted under: the errno's name (``EIO``), else the exception's type."""
    code = exc.errno
    return errno.errorcode.get(code, f"errno {code}") if code else type(exc).__name__


@dataclasses.dataclass
class Health:
    """What happened to one thing that is tried (mutable: its user counts as it goes; read it from anywhere for a
    status reply).

    attempts: tries; samples: successes (good transfers, usable readings); errors: failed tries, by cause in
    ``errors_by_cause``; retries: failed tries tried again at once (a transfer); consecutive_failures: failures
    since the last success; healthy: per the policy's ``unhealthy_after``; last_error: the last failure's message;
    waited_s: seconds of backoff slept; not_ready, overflows: readings with nothing new or saturated (the read loop).
    """

    attempts: int = 0
    samples: int = 0
    errors: int = 0
    retries: int = 0
    not_ready: int = 0
    overflows: int = 0
    consecutive_failures: int = 0
    healthy: bool = True
    last_error: str = ""
    waited_s: float = 0.0
    errors_by_cause: dict[str, int] = dataclasses.field(default_factory=dict)

    def failed(self, cause: str, message: str, policy: RetryPolicy) -> bool:
        """Count one failed try; True when it turned the thing unhealthy."""
        self.errors += 1
        self.errors_by_cause[cause] = self.errors_by_cause.get(cause, 0) + 1
        self.consecutive_failures += 1
        self.last_error = message
        if self.healthy and self.consecutive_failures >= policy.unhealthy_after:
            self.healthy = False
            return True
        return False

    def succeeded(self) -> bool:
        """Count one success; True when it made the thing healthy again."""
        self.samples += 1
        self.consecutive_failures = 0
        if self.healthy:
            return False
        self.healthy = True
        return True

    def as_dict(self) -> dict[str, Any]:
        out = dataclasses.asdict(self)
        out["waited_s"] = round(self.waited_s, 3)
        return out
