"""One writer per device among the calibrators of a shard, a lease held through Zenoh liveliness tokens (``Lease``);
which devices a calibrator serves is ``magnet.calibrator.keys.ShardKeys``.

Every calibrator declares the liveliness token ``<prefix>/@lease/calibrator/<K>-<N>/<started_ns>/<name>`` (its shard
``K/N``, its start time in ns since the epoch and its ``--name``) and watches the tokens of its shard. Among the live
ones, the oldest (smallest ``(started_ns, name)``) is active: it alone collects, fits, stores, publishes and answers
for the shard's devices. The others stand by (they answer only their own status) and the next oldest takes over when
the active one's token goes away (it stopped, crashed or lost its link): it reads the records in force back from the
shared store and carries on. A calibrator that starts later never takes the lease from one already running, so
sessions in progress are not cut short by a new standby.

No zenoh inside: the service feeds ``on_token`` with the keys of the tokens that appear (alive) or go away.
"""

from __future__ import annotations

import dataclasses
import logging

from magnet.shard import Shard

log = logging.getLogger("magnet.calibrator")

ROLE = "calibrator"


def shard_chunk(shard: Shard) -> str:
    """The shard as one key chunk: ``K-N``."""
    return f"{shard.index}-{shard.count}"


def lease_prefix(prefix: str, shard: Shard) -> str:
    """The key under which the calibrators of ``shard`` declare their tokens."""
    return f"{prefix}/@lease/{ROLE}/{shard_chunk(shard)}"


@dataclasses.dataclass(frozen=True, order=True)
class Member:
    """A calibrator holding a token: ordered by start time (ns since the epoch), then name."""

    started_ns: int
    name: str

    def __post_init__(self) -> None:
        if self.started_ns < 0 or not self.name or any(c in self.name for c in "/*$?#"):
            raise ValueError(f"a calibrator name is one key chunk without / * $ ? #, got {self.name!r}")

    def __str__(self) -> str:
        return f"{self.name} (started at {self.started_ns} ns)"


class Lease:
    """The live calibrators of one shard, as this calibrator (``me``) sees them; ``active`` when ``me`` is the
    oldest."""

    def __init__(self, prefix: str, shard: Shard, me: Member) -> None:
        self.prefix, self.shard, self.me = prefix, shard, me
        self.members: set[Member] = {me}
        self.takeovers = 0  # times this calibrator became active after standing by

    @property
    def key(self) -> str:
        """This calibrator's token key."""
        return f"{lease_prefix(self.prefix, self.shard)}/{self.me.started_ns}/{self.me.name}"

    @property
    def watch_key(self) -> str:
        """The key expression of every token of this shard."""
        return f"{lease_prefix(self.prefix, self.shard)}/*/*"

    @property
    def holder(self) -> Member:
        return min(self.members)

    @property
    def active(self) -> bool:
        return self.holder == self.me

    def member(self, key_expr: str) -> Member | None:
        """The member a token key names; None for a key of another shard or a malformed one."""
        head, _, rest = key_expr.partition(lease_prefix(self.prefix, self.shard) + "/")
        started, _, name = rest.partition("/")
        if head or not started.isdigit() or not name:
            return None
        try:
            return Member(int(started), name)
        except ValueError:
            return None

    def on_token(self, key_expr: str, alive: bool) -> bool | None:
        """A token appeared (``alive``) or went away. Returns the new ``active`` when it changed, else None."""
        member = self.member(key_expr)
        if member is None or member == self.me:
            return None  # this calibrator holds its own token until it stops
        was = self.active
        if alive:
            self.members.add(member)
        else:
            self.members.discard(member)
        if self.active == was:
            return None
        if self.active:
            self.takeovers += 1
            log.warning("lease of shard %s: %s takes over (the active calibrator went away)", self.shard, self.me)
        else:
            log.warning("lease of shard %s: %s stands by; %s is active", self.shard, self.me, self.holder)
        return self.active

    def state(self) -> str:
        return "active" if self.active else "standby"
