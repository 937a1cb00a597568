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
from services.common.options import add_options, check_options, from_args, option
from services.common.router_stats import open_counting
from services.common.zenoh_session import ZenohSettings, add_zenoh_arguments, stop_event

log = logging.getLogger("magnet.router")

#: Safe by default: serving other hosts is an explicit choice (--listen or --config).
DEFAULT_LISTEN = "tcp/127.0.0.1:7447"


@dataclasses.dataclass(frozen=True)
class RouterSettings:
    """The router's name (liveliness token) and Zenoh options; ``loopback_default``: it listens on DEFAULT_LISTEN
    because neither --listen nor --config was given."""

    name: str = option("router", "--name", help="name for its liveliness token")
    zenoh: ZenohSettings = ZenohSettings(listen=(DEFAULT_LISTEN,), default_mode="router")
    loopback_default: bool = False

    def __post_init__(self) -> None:
        check_options(self)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_options(parser, RouterSettings)
    add_zenoh_arguments(parser, default_mode="router")


def settings_from_args(args: argparse.Namespace) -> RouterSettings:
    zenoh = ZenohSettings.from_args(args)
    default = not zenoh.listen and not zenoh.config
    if default:
        zenoh = dataclasses.replace(zenoh, listen=(DEFAULT_LISTEN,))
    return from_args(RouterSettings, args, zenoh=zenoh, loopback_default=default)


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
    token_key = wire.liveliness_key(settings.zenoh.prefix, "router", settings.name)
    # denied messages counted, status answered (services.common.router_stats)
    with open_counting(settings.zenoh, settings.name) as session, session.liveliness().declare_token(token_key):
        log.info(
            "router %s up (zid %s), listening on %s",
            settings.name,
            session.zid(),
            ", ".join(settings.zenoh.listen) or "the config's endpoints",
        )
        while not stop.wait(0.5):
            pass
    return 0
