"""Whether a compass still sees a calibrator (``CalibratorPresence``): the liveliness tokens of the calibrators that
are alive. When every calibrator is gone (stopped, crashed, their hosts lost), the compass keeps applying the records
in force it holds, exactly as before, and says so in its status (``state`` "gone", since when). No zenoh inside: the
service feeds ``on_token`` with the tokens that appear and go away; times are ns since the epoch, injected.
"""

from __future__ import annotations

import dataclasses

#: the states a compass reports: no calibrator seen yet, at least one alive, every one gone
UNSEEN, PRESENT, GONE = "unseen", "present", "gone"


@dataclasses.dataclass
class CalibratorPresence:
    """The calibrators alive (their token keys) and since when none is (ns since the epoch; None while one is or
    before any was seen)."""

    alive: set[str] = dataclasses.field(default_factory=set)
    seen: bool = False
    gone_since_ns: int | None = None

    @property
    def state(self) -> str:
        return PRESENT if self.alive else GONE if self.seen else UNSEEN

    def on_token(self, key: str, alive: bool, now_ns: int) -> bool:
        """A calibrator's token appeared (``alive``) or went away at ``now_ns``; True when the state changed."""
        before = self.state
        if alive:
            self.alive.add(key)
            self.seen, self.gone_since_ns = True, None
        else:
            self.alive.discard(key)
            if self.seen and not self.alive and self.gone_since_ns is None:
                self.gone_since_ns = now_ns
        return self.state != before
