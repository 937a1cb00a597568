"""Messages the router's access control denies, counted, and the router's status (``<prefix>/@status/<name>``).

Zenoh drops a message its access-control rules deny without a word to the sender or the receiver. Its own counter
of such drops (a drop reason "access control" in its statistics, read from the admin space
``@/<zid>/router/metrics``) exists only in Zenoh builds with the ``stats`` feature, and the eclipse-zenoh wheel is
built without it: its metrics hold the build's version and nothing else (docs/front-door.md, "Messages the router
denies"). What every build has is the access-control module's trace log: one line per message it judges,
``<zid> on <subject> is unauthorized to Put (ingress) on <key>`` (or ``Using cached result: <zid> is unauthorized
...`` once the key's verdict is cached). So the router:

- turns that log on for the access-control module only (``RUST_LOG`` gets ``ACL_TARGET=trace``; nothing else of
  Zenoh's is logged that was not before) before its session starts Zenoh's logging;
- reads Zenoh's log (Zenoh writes it to file descriptor 1) through a pipe on a thread of its own: the access-control
  lines are counted (``AclDenials``) and swallowed, every other line goes on to the real standard output;
- answers ``<prefix>/@status/<name>`` with ``acl_denied`` (denied messages since it started), ``acl_denied_by``
  (per message kind and direction, e.g. ``Put (ingress)``) and ``acl_denied_keys`` (per key, the most recent
  ``MAX_KEYS``; a flood of keys cannot grow it).

With no access-control rules Zenoh logs nothing of the kind and this costs nothing; with rules every judged message
is a line: about 5 us of router CPU per message (3 formatting it in Zenoh, 2 reading it here; measured in
docs/front-door.md).
"""

from __future__ import annotations

import contextlib
import os
import re
import threading
from collections.abc import Iterator, MutableMapping
from typing import Any

import zenoh

from magnet import wire
from magnet.bounded import Recent
from services.common.zenoh_session import ZenohSettings, open_session

#: the Rust module whose trace log judges every message
ACL_TARGET = "zenoh::net::routing::interceptor::access_control"
#: keys remembered with their count at most
MAX_KEYS = 256
_DENIED = re.compile(
    r"(?:Using cached result: )?[0-9a-f]+ (?:on \S+ )?is unauthorized to (?P<kind>.+?) \((?P<flow>ingress|egress)\)"
    r" on (?P<key>\S+)"
)
_ANSI = re.compile(r"\x1b\[[0-9;]*m")
_READ_BYTES = 1 << 16


class AclDenials:
    """Counts of denied messages from Zenoh's access-control log lines (``feed``); thread-safe."""

    def __init__(self, max_keys: int = MAX_KEYS) -> None:
        self.total = 0
        self.by_kind: dict[str, int] = {}
        self.by_key: MutableMapping[str, int] = Recent(max_keys)
        self._lock = threading.Lock()

    def feed(self, line: str) -> bool:
        """Count ``line`` when it says a message was denied; True when it is an access-control line at all (which
        the caller swallows), False for any other line."""
        if ACL_TARGET not in line:
            return False
        if "unauthorized" not in line:  # an allowed message: most lines, no more work
            return True
        found = _DENIED.search(_ANSI.sub("", line))
        if found is not None:
            kind = f"{found['kind']} ({found['flow']})"
            with self._lock:
                self.total += 1
                self.by_kind[kind] = self.by_kind.get(kind, 0) + 1
                self.by_key[found["key"]] = self.by_key.get(found["key"], 0) + 1
        return True

    def to_dict(self) -> dict[str, Any]:
        with self._lock:
            return {"acl_denied": self.total, "acl_denied_by": dict(self.by_kind), "acl_denied_keys": dict(self.by_key)}


def log_filter(current: str | None) -> str:
    """``RUST_LOG`` with the access-control module at trace: added to the directives given, else alone (``off``
    for the rest, as without RUST_LOG Zenoh logs nothing)."""
    return f"{current},{ACL_TARGET}=trace" if current else f"off,{ACL_TARGET}=trace"


def _forward(read_fd: int, out_fd: int, denials: AclDenials) -> None:
    """Read lines from ``read_fd`` until it closes: count and swallow the access-control ones, write the rest to
    ``out_fd``."""
    pending = b""
    target, denied = ACL_TARGET.encode(), b"unauthorized"
    while chunk := os.read(read_fd, _READ_BYTES):
        lines = (pending + chunk).split(b"\n")
        pending = lines.pop()
        kept = []
        for line in lines:  # most lines are allowed messages: two byte searches each, nothing decoded
            if target not in line:
                kept.append(line)
            elif denied in line:
                denials.feed(line.decode("utf-8", "replace"))
        if kept:
            os.write(out_fd, b"\n".join(kept) + b"\n")
    if pending and not denials.feed(pending.decode("utf-8", "replace")):
        os.write(out_fd, pending)


def capture_zenoh_log(denials: AclDenials) -> None:
    """Turn on Zenoh's access-control log and count it (see the module's docstring). Call it before the first Zenoh
    session of the process opens (Zenoh reads ``RUST_LOG`` once). Standard output becomes a pipe read by a daemon
    thread that passes every other line on."""
    os.environ["RUST_LOG"] = log_filter(os.environ.get("RUST_LOG"))
    read_fd, write_fd = os.pipe()
    out_fd = os.dup(1)
    os.dup2(write_fd, 1)
    os.close(write_fd)
    threading.Thread(target=_forward, args=(read_fd, out_fd, denials), name="zenoh-log", daemon=True).start()


@contextlib.contextmanager
def open_counting(options: ZenohSettings, name: str) -> Iterator[zenoh.Session]:
    """The router's session (``open_session``) with its denied messages counted and its status answered on
    ``<prefix>/@status/<name>``: ``{"name", "role": "router", "zid", "acl_denied", "acl_denied_by",
    "acl_denied_keys"}``."""
    denials = AclDenials()
    capture_zenoh_log(denials)
    with open_session(options) as session:
        status_key = wire.status_key(options.prefix, name)
        zid = str(session.zid())

        def answer(query: zenoh.Query) -> None:
            query.reply(status_key, wire.pack({"name": name, "role": "router", "zid": zid, **denials.to_dict()}))

        with session.declare_queryable(status_key, answer):
            yield session
