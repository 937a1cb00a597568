"""Common Zenoh options of every service, the config built from them, and small shell helpers the services share.

Options: ``--config FILE.json5``, ``--mode peer|client|router``, ``--connect ENDPOINT`` (repeatable), ``--listen
ENDPOINT`` (repeatable), ``--no-multicast-scouting``, ``--prefix P``. Options given on the command line override the
file. Zenoh's default peer listens on every interface and scouts by multicast: for a local pipeline pin ``--listen
tcp/127.0.0.1:PORT`` and pass ``--no-multicast-scouting`` (``loopback_arguments`` builds exactly that).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import logging
import re
import signal
import socket
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any, Protocol, TypeVar

import zenoh

from magnet.wire import DEFAULT_PREFIX, validate_prefix
from services.common.options import add_options, check_options, from_args, one_of, option, optional

log = logging.getLogger(__name__)

T = TypeVar("T")
T_co = TypeVar("T_co", covariant=True)

MODES = ("peer", "client", "router")
OPEN_RETRY_S = 5.0
#: set in every session a service opens without a config file (a file's own settings stand). Shared memory off:
#: with it on (Zenoh 1.10's default), a process that publishes messages of a few kB or more on the same host makes a
#: 16 MB segment, and every subscriber that received from it keeps that segment mapped after the publisher is gone.
#: Measured: a bare zenoh-python subscriber grew 19 MB with each new publishing process (337 MB after 15), flat at
#: 25-32 MB with it off (docs/front-door.md, "Memory per service").
SESSION_DEFAULTS = {"transport/shared_memory/enabled": "false"}
#: the batch size of a service's raw link (bytes; Zenoh's default 65,535, the link takes the smaller of both sides'
#: for both directions). Every message Zenoh receives is a slice of the batch it came in, so a raw sample waiting in
#: the channel before the intake's pump copies it (the pump starved of CPU in a flood) keeps that whole batch alive:
#: a channel of 256 held 12 MB of 64 kB batches, 1.9 MB of 8 kB ones (``tests/system/test_raw_pinned_buffers.py``).
#: Larger raw messages arrive in fragments, joined as before.
RAW_BATCH_BYTES = 8192
RAW_LINK_DEFAULTS = {"transport/link/tx/batch_size": str(RAW_BATCH_BYTES)}


@dataclasses.dataclass(frozen=True)
class ZenohSettings:
    """The Zenoh options of a service: config file, mode (None: the file's, else ``default_mode``), endpoints to
    connect to and listen on, multicast scouting off, and the key prefix. ``default_mode`` is the service's own
    (peer, or router for ``magnet router``), not an option."""

    config: str | None = option(
        None, "--config", metavar="FILE.json5", help="a Zenoh configuration file (json5)", group="zenoh"
    )
    mode: str | None = option(
        None, "--mode", choices=MODES, check=optional(one_of(MODES)), help="session mode", group="zenoh"
    )
    connect: tuple[str, ...] = option(
        (),
        "--connect",
        repeat=True,
        metavar="ENDPOINT",
        help="endpoint to connect to, e.g. tcp/127.0.0.1:7447 (repeatable)",
        group="zenoh",
    )
    listen: tuple[str, ...] = option(
        (),
        "--listen",
        repeat=True,
        metavar="ENDPOINT",
        help="endpoint to listen on, e.g. tcp/127.0.0.1:7447 (repeatable)",
        group="zenoh",
    )
    no_multicast_scouting: bool = option(
        False, "--no-multicast-scouting", help="do not scout for peers by multicast", group="zenoh"
    )
    prefix: str = option(DEFAULT_PREFIX, "--prefix", help="key prefix", group="zenoh")
    default_mode: str = "peer"

    def __post_init__(self) -> None:
        check_options(self)
        validate_prefix(self.prefix)
        if self.default_mode not in MODES:
            raise ValueError(f"the default mode must be one of {', '.join(MODES)}, got {self.default_mode!r}")

    @classmethod
    def from_args(cls, args: argparse.Namespace) -> ZenohSettings:
        """The settings of the options ``add_zenoh_arguments`` added."""
        return from_args(cls, args, default_mode=getattr(args, "_default_mode", "peer"))


def add_zenoh_arguments(parser: argparse.ArgumentParser, *, default_mode: str = "peer") -> None:
    """The options of ``ZenohSettings`` in their "zenoh" group; ``default_mode``: the service's mode when neither
    ``--mode`` nor the config file says (shown in the help, read back by ``ZenohSettings.from_args``)."""
    add_options(parser, ZenohSettings, shown={"mode": default_mode})
    parser.set_defaults(_default_mode=default_mode)


Options = ZenohSettings | argparse.Namespace


def _settings(options: Options) -> ZenohSettings:
    return options if isinstance(options, ZenohSettings) else ZenohSettings.from_args(options)


def config_json5(options: Options) -> dict[str, str]:
    """Config path -> json5 value for every option given (what ``build_config`` inserts)."""
    settings = _settings(options)
    values = {"mode": json.dumps(settings.mode or settings.default_mode)}
    if settings.connect:
        values["connect/endpoints"] = json.dumps(list(settings.connect))
    if settings.listen:
        values["listen/endpoints"] = json.dumps(list(settings.listen))
    if settings.no_multicast_scouting:
        values["scouting/multicast/enabled"] = "false"
    return values


def build_config(options: Options, defaults: Mapping[str, str] | None = None) -> zenoh.Config:
    """A ``zenoh.Config`` from the file (if any) and the options. ValueError/OSError for a bad file or option.
    ``defaults``: config path -> json5 value that a service sets where no config file is given."""
    args = _settings(options)
    if args.config:
        path = Path(args.config)
        if not path.is_file():
            raise OSError(f"zenoh config file {path} not found")
        try:
            conf = zenoh.Config.from_file(str(path))
        except Exception as exc:  # zenoh raises ZError for any bad file
            raise ValueError(f"zenoh config file {path} is not valid: {zenoh_message(exc)}") from None
    else:
        conf = zenoh.Config()
        for path_key, value in {**SESSION_DEFAULTS, **(defaults or {})}.items():
            conf.insert_json5(path_key, value)
    for path_key, value in config_json5(args).items():
        if path_key == "mode" and args.config and not args.mode:
            continue  # the file's mode stands unless --mode is given
        try:
            conf.insert_json5(path_key, value)
        except Exception as exc:
            raise ValueError(f"zenoh option {path_key}={value} refused: {zenoh_message(exc)}") from None
    return conf


_RUST_LOCATION = re.compile(r"\s+at\s+\S+\.rs:\d+\.?")


def zenoh_message(exc: BaseException) -> str:
    """A Zenoh error's message without the Rust source locations it carries (``at /root/.cargo/...rs:447.``)."""
    return _RUST_LOCATION.sub("", str(exc)).strip()


def session_mode(options: Options) -> str:
    """The mode a session opened with these options takes (the option, else the config file's, else the default)."""
    return str(json.loads(build_config(options).get_json("mode")))


def queries_session(stack: contextlib.ExitStack, session: zenoh.Session, options: Options) -> zenoh.Session:
    """The session a service declares the queryables on that must never wait behind its samples (the calibrator's
    status). Behind a router (client mode) every message comes to ``session`` on one link, read by one task: when
    the thread that empties a subscriber's channel is starved of CPU the channel fills, that task waits on it, and a
    query behind the samples waits too. So a client gets a session of its own, a link of its own (closed by
    ``stack``, after what is declared on it later); a peer, reached directly by whoever asks on the links it listens
    on, keeps ``session``."""
    return _session_of_its_own(stack, session, options)


def raw_session(
    stack: contextlib.ExitStack, session: zenoh.Session, options: Options, defaults: Mapping[str, str] | None = None
) -> zenoh.Session:
    """The session a service declares its raw subscriber on (the calibrator's, the compass's): behind a router
    (client mode) one of its own whose link carries batches of ``RAW_BATCH_BYTES`` (``RAW_LINK_DEFAULTS`` over the
    service's ``defaults``; a ``--config`` file's own settings stand), closed by ``stack`` after what is declared on
    it later; a peer keeps ``session`` (its links, to every peer, carry the headings it sends too)."""
    return _session_of_its_own(stack, session, options, {**(defaults or {}), **RAW_LINK_DEFAULTS})


def _session_of_its_own(
    stack: contextlib.ExitStack, session: zenoh.Session, options: Options, defaults: Mapping[str, str] | None = None
) -> zenoh.Session:
    if session_mode(options) != "client":
        return session
    return stack.enter_context(open_session(options, defaults))


def open_session(options: Options, defaults: Mapping[str, str] | None = None) -> zenoh.Session:
    """Open a session from the options (``ZenohSettings``, or the parsed options of ``add_zenoh_arguments``) and the
    service's ``defaults`` (see ``build_config``); use it as a context manager so it is closed (or the process never
    exits)."""
    zenoh.try_init_log_from_env()
    deadline = time.monotonic() + OPEN_RETRY_S
    while True:
        try:
            return zenoh.open(build_config(options, defaults))
        except (ValueError, OSError):
            raise
        except Exception as exc:  # e.g. a client whose router is not up yet: retry a little, then give up
            if time.monotonic() >= deadline:
                raise OSError(f"cannot open a zenoh session: {zenoh_message(exc)}") from None
            time.sleep(0.2)


def loopback_arguments(listen_port: int | None, connect_ports: Sequence[int] = ()) -> list[str]:
    """Command-line options for a local pipeline: listen on 127.0.0.1 only, connect explicitly, no multicast."""
    options = ["--no-multicast-scouting"]
    if listen_port is not None:
        options += ["--listen", f"tcp/127.0.0.1:{listen_port}"]
    for port in connect_ports:
        options += ["--connect", f"tcp/127.0.0.1:{port}"]
    return options


def free_ports(count: int) -> list[int]:
    """``count`` distinct TCP ports free on 127.0.0.1 right now."""
    sockets, ports = [], []
    try:
        for _ in range(count):
            sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            sock.bind(("127.0.0.1", 0))
            sockets.append(sock)
            ports.append(sock.getsockname()[1])
    finally:
        for sock in sockets:
            sock.close()
    return ports


def stop_event() -> threading.Event:
    """An event set on SIGTERM or SIGINT (Ctrl-C), so a service loop can end and close its session cleanly."""
    event = threading.Event()

    def _handler(signum: int, _frame: Any) -> None:
        log.info("signal %d: stopping", signum)
        event.set()

    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, _handler)
        signal.signal(signal.SIGINT, _handler)
    return event


def payload_bytes(sample_or_query: zenoh.Sample | zenoh.Query | zenoh.ReplyError) -> bytes:
    """The payload of a zenoh Sample, Query (b"" when it has none) or error reply as bytes."""
    payload = sample_or_query.payload
    return b"" if payload is None else payload.to_bytes()


def matching(publisher: zenoh.Publisher) -> bool:
    """Whether a subscriber matches ``publisher`` now (zenoh 1.10's stub says ``matching_status`` is a bool; it is a
    ``MatchingStatus`` with ``.matching``)."""
    return bool(publisher.matching_status.matching)  # type: ignore[attr-defined]


class Receiver(Protocol[T_co]):
    """What a zenoh channel gives without blocking: a ``Subscriber``, ``Queryable`` or ``Handler`` (of a ``get``)."""

    def try_recv(self) -> T_co | None: ...


class Channel(Protocol[T_co]):
    """A zenoh channel read by a thread of its own: ``recv`` waits (without the GIL), ``try_recv`` does not."""

    def recv(self) -> T_co: ...

    def try_recv(self) -> T_co | None: ...


def pump(
    channel: Channel[T],
    closed: type[BaseException],
    handle: Callable[[list[T]], object],
    batch: int,
    rest_s: float = 0.0,
    rest: Callable[[float], None] = time.sleep,
) -> None:
    """Hand what arrives on ``channel`` to ``handle`` a batch at a time until the channel closes (``closed`` raised:
    the subscriber was undeclared); the intakes' thread (``services.calibrator.intake``, ``services.compass.intake``).
    ``recv`` waits for the first sample without the GIL and ``try_recv`` takes what else waits, up to ``batch``, so
    Zenoh's buffers are let go of at once and the GIL changes hands once per batch. After a batch under ``batch`` / 8
    it rests ``rest_s`` (0: never) so that the next one is larger."""
    while True:
        try:
            items = [channel.recv()]
            while len(items) < batch and (more := channel.try_recv()) is not None:
                items.append(more)
        except closed:
            return
        handle(items)
        small = len(items) < batch // 8
        del items  # Zenoh's samples are not held while resting or waiting
        if small and rest_s > 0:
            rest(rest_s)


def drain(handler: Receiver[T], limit: int) -> list[T]:
    """Up to ``limit`` items a zenoh handler holds now (an empty, closed channel gives none)."""
    items: list[T] = []
    while len(items) < limit:
        try:
            item = handler.try_recv()
        except zenoh.ZError:  # closed: a finished query's replies
            break
        if item is None:
            break
        items.append(item)
    return items
