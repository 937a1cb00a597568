"""``magnet router``: a Zenoh session in router mode (stands in for zenohd, which no reachable registry provides).

Peers and clients connect to it (``--connect tcp/HOST:7447``); without ``--listen`` or ``--config`` it listens on
127.0.0.1:7447 only; with ``--config`` it takes a full router config (TLS,
user/password authentication, access control: see ``deploy/``). It holds no storage: calibrations live in the
calibrator's SQLite behind its queryables.
"""

from __future__ import annotations

import argparse
import logging

from magnet import wire
from services.common.zenoh_session import add_zenoh_arguments, open_session, stop_event

log = logging.getLogger("magnet.router")

#: Safe by default: serving other hosts is an explicit choice (--listen or --config).
DEFAULT_LISTEN = "tcp/127.0.0.1:7447"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--name", default="router", help="name for its liveliness token")
    add_zenoh_arguments(parser, default_mode="router")


def run(args: argparse.Namespace) -> int:
    if not args.listen and not args.config:
        args.listen = [DEFAULT_LISTEN]
        log.warning("router listens on %s only: give --listen tcp/<interface address>:7447 (or a config from "
                    "deploy/) to serve other hosts", DEFAULT_LISTEN)
    stop = stop_event()
    with open_session(args) as session:
        token = session.liveliness().declare_token(wire.liveliness_key(args.prefix, "router", args.name))
        log.info("router %s up (zid %s), listening on %s", args.name, session.zid(), ", ".join(args.listen) or
                 "the config's endpoints")
        while not stop.wait(0.5):
            pass
        token.undeclare()
    return 0
