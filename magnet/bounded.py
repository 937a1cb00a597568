"""A map with a bound on its size that forgets the least recently seen key first (per-device state of services).

Pure; no clock: "recently seen" is the order of ``touch`` and insertion.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable, Iterator, MutableMapping
from typing import TypeVar, overload

K = TypeVar("K")
V = TypeVar("V")
T = TypeVar("T")


class Recent(MutableMapping[K, V]):
    """At most ``limit`` entries; inserting beyond it evicts the least recently seen one (for which ``keep(value)`` is
    not true), counted in ``evicted`` and handed to ``on_evict(key, value)`` (to release what it holds).
    ``touch(key)`` marks a key as just seen; ``get`` does not."""

    def __init__(
        self,
        limit: int,
        keep: Callable[[V], bool] | None = None,
        on_evict: Callable[[K, V], None] | None = None,
    ) -> None:
        if isinstance(limit, bool) or not isinstance(limit, int) or limit < 1:
            raise ValueError(f"a bound must be a whole number >= 1, got {limit!r}")
        self.limit, self.keep, self.on_evict = limit, keep, on_evict
        self.evicted = 0
        self._items: OrderedDict[K, V] = OrderedDict()

    def __len__(self) -> int:
        return len(self._items)

    def __contains__(self, key: object) -> bool:
        return key in self._items

    def __iter__(self) -> Iterator[K]:
        return iter(self._items)

    def __getitem__(self, key: K) -> V:
        return self._items[key]

    @overload
    def get(self, key: K, /) -> V | None: ...
    @overload
    def get(self, key: K, default: V | T, /) -> V | T: ...
    def get(self, key: K, default: object = None, /) -> object:
        """The value of ``key`` (not marked as seen), else ``default``: a plain dict lookup, no exception raised."""
        return self._items.get(key, default)

    def clear(self) -> None:
        """Forget every entry (not counted as evicted)."""
        self._items.clear()

    def touch(self, key: K) -> None:
        if key in self._items:
            self._items.move_to_end(key)

    def __setitem__(self, key: K, value: V) -> None:
        self._items[key] = value
        self._items.move_to_end(key)
        while len(self._items) > self.limit and self._evict_one():
            pass

    def setdefault(self, key: K, value: V) -> V:
        if key not in self._items:
            self[key] = value
        return self._items.get(key, value)

    def __delitem__(self, key: K) -> None:
        del self._items[key]

    def _evict_one(self) -> bool:
        """Drop the least recently seen entry that may go; False when every entry must stay."""
        for key, value in self._items.items():
            if self.keep is None or not self.keep(value):
                del self._items[key]
                self.evicted += 1
                if self.on_evict is not None:
                    self.on_evict(key, value)
                return True
        return False


class Graded(Recent[K, V]):
    """A ``Recent`` that evicts newcomers first: a key is on probation until it has been seen (``touch``)
    ``promote_after`` times since it was inserted; inserting beyond the bound evicts the least recently seen key on
    probation, and only when none is (or none may go) the least recently seen of all. A flood of keys seen once each
    (new device ids of one message each) then churns among themselves and never pushes out a key seen again and
    again (a real device). Both orders are kept in ``OrderedDict``s: eviction stays O(1) as long as keys may go."""

    def __init__(
        self,
        limit: int,
        promote_after: int,
        keep: Callable[[V], bool] | None = None,
        on_evict: Callable[[K, V], None] | None = None,
    ) -> None:
        super().__init__(limit, keep, on_evict)
        if isinstance(promote_after, bool) or not isinstance(promote_after, int) or promote_after < 1:
            raise ValueError(f"promote_after must be a whole number >= 1, got {promote_after!r}")
        self.promote_after = promote_after
        self._probation: OrderedDict[K, int] = OrderedDict()  # key -> times seen since inserted

    def touch(self, key: K) -> None:
        super().touch(key)
        seen = self._probation.get(key)
        if seen is not None:
            if seen + 1 >= self.promote_after:
                del self._probation[key]
            else:
                self._probation[key] = seen + 1
                self._probation.move_to_end(key)

    def __setitem__(self, key: K, value: V) -> None:
        if key not in self._items:
            self._probation[key] = 0
        super().__setitem__(key, value)

    def __delitem__(self, key: K) -> None:
        super().__delitem__(key)
        self._probation.pop(key, None)

    def clear(self) -> None:
        super().clear()
        self._probation.clear()

    def _evict_one(self) -> bool:
        newest = next(reversed(self._items))  # the key being inserted: never its own victim
        for key in self._probation:
            value = self._items[key]
            if key != newest and (self.keep is None or not self.keep(value)):
                self._drop(key, value)
                return True
        for key, value in self._items.items():
            if self.keep is None or not self.keep(value):
                self._drop(key, value)
                return True
        return False

    def _drop(self, key: K, value: V) -> None:
        del self._items[key]
        self._probation.pop(key, None)
        self.evicted += 1
        if self.on_evict is not None:
            self.on_evict(key, value)
