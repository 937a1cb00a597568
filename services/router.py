"""``magnet router``: a Zenoh session in router mode (stands in for zenohd, which no reachable registry provides).

Peers and clients connect to it (``--connect tcp/HOST:7447``); without ``--listen`` or ``--config`` it listens on
127.0.0.1:7447 only; with ``--config`` it takes a full router config (TLS,
user/password authentication, access control: see ``deploy/``). It holds no storage: calibrations live in the
calibrator's SQLite behind its queryables.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging

from magnet import wire
from services.common.router_stats import open_counting
from services.common.zenoh_session import ZenohSettings, add_zenoh_arguments, stop_event

log = logging.getLogger("magnet.router")

#: Safe by default: serving other hosts is an explicit choice (--listen or --config).
DEFAULT_LISTEN = "tcp/127.0.0.1:7447"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--name", default="router", help="name for its liveliness token")
    add_zenoh_arguments(parser, default_mode="router")


@dataclasses.dataclass(frozen=True)
class RouterSettings:
    """The router's name (liveliness token) and Zenoh options; ``loopback_default``: it listens on DEFAULT_LISTEN
    because neither --listen nor --config was given."""

    name: str = "router"
    zenoh: ZenohSettings = ZenohSettings(listen=(DEFAULT_LISTEN,), default_mode="router")
    loopback_default: bool = False


def settings_from_args(args: argparse.Namespace) -> RouterSettings:
    zenoh = ZenohSettings.from_args(args)
    default = not zenoh.listen and not zenoh.config
    if default:
        zenoh = dataclasses.replace(zenoh, listen=(DEFAULT_LISTEN,))
    return RouterSettings(args.name, zenoh, default)


def run_router(args: argparse.Namespace) -> int:
    """``magnet router``: the settings from the options, then ``run``."""
    return run(settings_from_args(args))


def run(settings: RouterSettings) -> int:
    if settings.loopback_default:
        log.warning(
            "router listens on %s only: give --listen tcp/<interface address>:7447 (or a config from "
            "deploy/) to serve other hosts",
            DEFAULT_LISTEN,
        )
    stop = stop_event()
    with open_counting(settings.zenoh, settings.name) as session:  # denied messages counted, status answered
        token = session.liveliness().declare_token(wire.liveliness_key(settings.zenoh.prefix, "router", settings.name))
        log.info(
            "router %s up (zid %s), listening on %s",
            settings.name,
            session.zid(),
            ", ".join(settings.zenoh.listen) or "the config's endpoints",
        )
        while not stop.wait(0.5):
            pass
        token.undeclare()
    return 0
