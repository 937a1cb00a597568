"""Which device a key expression names, and whether it is this compass's (its shard's): each answer remembered for
the keys seen most recently, so that a drain of thousands of messages parses few keys. Pure."""

from __future__ import annotations

from magnet import wire
from magnet.bounded import Recent
from magnet.shard import EVERY_DEVICE, Shard

#: key expressions remembered at most (beyond: the least recently seen forgotten, and parsed again when seen)
MAX_KEYS = 200_000


class DeviceKeys:
    """The device of ``<prefix>/<device>/<kind>`` keys and whether ``shard`` owns it."""

    def __init__(self, shard: Shard = EVERY_DEVICE, max_keys: int = MAX_KEYS) -> None:
        self.shard = shard
        self._devices: Recent[str, str] = Recent(max_keys)
        self._mine: Recent[str, bool] = Recent(max_keys)

    def device(self, key_expr: str, prefix: str, kind: wire.Kind = wire.Kind.RAW) -> str | None:
        """The device a raw key names, or None when the key is not one."""
        device = self._devices.get(key_expr)
        if device is None:
            try:
                device = wire.device_from_key(prefix, key_expr, kind)
            except wire.WireError:
                return None
            self._devices[key_expr] = device
        return device

    def mine(self, key_expr: str, prefix: str, kind: wire.Kind = wire.Kind.RAW) -> bool:
        """Whether the device of ``key_expr`` belongs to this compass's shard (a malformed key: True, so that it is
        decoded, refused and counted)."""
        if self.shard.everything:
            return True
        owned = self._mine.get(key_expr)
        if owned is None:
            try:
                owned = self.shard.owns(wire.device_from_key(prefix, key_expr, kind))
            except wire.WireError:
                return True
            self._mine[key_expr] = owned
        return owned
