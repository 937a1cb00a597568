"""Which devices a calibrator serves: the devices of its shard (``ShardKeys``), read from the raw keys and remembered
per key. Whether it holds the lease of its shard is the service's (``services.calibrator.lease``)."""

from __future__ import annotations

from magnet import wire
from magnet.bounded import Recent
from magnet.shard import Shard

#: raw keys whose shard is remembered at most (the least recently seen forgotten first)
MAX_SHARD_KEYS = 200_000


class ShardKeys:
    """Whether a raw key names a device of ``shard``, remembered per key for the last ``limit`` keys seen."""

    def __init__(self, shard: Shard, limit: int = MAX_SHARD_KEYS) -> None:
        self.shard = shard
        self.owned: Recent[str, bool] = Recent(limit)

    def owns(self, key_expr: str, prefix: str) -> bool:
        """Whether the device of ``key_expr`` (``<prefix>/<device>/raw``) is of this shard; a malformed key: True,
        to be refused and counted by the decoder."""
        if self.shard.everything:
            return True
        owned = self.owned.get(key_expr)
        if owned is None:
            try:
                owned = self.shard.owns(wire.device_from_key(prefix, key_expr, wire.Kind.RAW))
            except wire.WireError:
                return True
            self.owned[key_expr] = owned
        return owned
