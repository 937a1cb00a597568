"""``magnet certs --out DIR``: a site CA, a v3 certificate per role, the router's config (TLS with client
certificates, access control) and one client config per role, ready for ``--config``.

Written to DIR (nothing existing is overwritten): ``ca.crt``/``ca.key``; ``ROLE.crt``/``ROLE.key`` for router,
edge, calibrator, compass, viewer, operator; ``router.json5``; ``ROLE.json5``. With ``--password-listen ENDPOINT``
also ``users.txt`` (the router's user:password dictionary, every role) and ``edge-password.json5`` /
``viewer-password.json5`` (TLS to that second listener with a password, no client certificate). Keys, the
dictionary and configs holding a password are mode 0600, the rest 0644.
"""

from __future__ import annotations

import argparse
import logging
import secrets
from pathlib import Path

from services.security import acl, pki

log = logging.getLogger("magnet.certs")

HEADER = "magnet {what}, written by `magnet certs`.\nCertificates, keys and passwords are read from {files}."


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", type=Path, required=True, help="directory to write into (created if missing)")
    parser.add_argument(
        "--listen",
        default="tls/127.0.0.1:7447",
        help="the router's TLS endpoint with client certificates (default tls/127.0.0.1:7447)",
    )
    parser.add_argument(
        "--password-listen",
        metavar="ENDPOINT",
        help="a second TLS endpoint without client certificates, for user/password clients "
        "(edge, viewer), e.g. tls/127.0.0.1:7448; every client then also needs its password",
    )
    parser.add_argument(
        "--dns",
        action="append",
        metavar="NAME",
        help="host name clients dial the router by, for the certificates (repeatable; default localhost)",
    )
    parser.add_argument(
        "--ip",
        action="append",
        metavar="ADDRESS",
        help="IP address clients dial the router by (repeatable; default 127.0.0.1)",
    )
    parser.add_argument(
        "--files",
        type=Path,
        help="directory the configs name for the certificate files, where they will be installed (default: --out)",
    )
    parser.add_argument("--prefix", default="magnet", help="key prefix the access-control rules cover (default magnet)")
    parser.add_argument("--days", type=int, default=825, help="validity of the role certificates (default 825)")


def _targets(out: Path, password: bool) -> list[Path]:
    names = ["ca.crt", "ca.key", "router.json5"]
    for role in ["router", *acl.ROLES]:
        names += [f"{role}.crt", f"{role}.key"] + ([f"{role}.json5"] if role != "router" else [])
    if password:
        names += ["users.txt"] + [f"{role}-password.json5" for role in acl.PASSWORD_ROLES]
    return [out / name for name in names]


def run(args: argparse.Namespace) -> int:
    if not 1 <= args.days <= 10_000:
        raise ValueError(f"--days must be 1..10000, got {args.days}")
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    existing = [str(path) for path in _targets(out, bool(args.password_listen)) if path.exists()]
    if existing:
        raise ValueError(
            f"{', '.join(existing)} already exist(s): nothing written; move them aside or choose another --out"
        )
    site = acl.Site(args.listen, args.password_listen, (args.files or out).absolute(), args.prefix)
    dns, ips = args.dns or ["localhost"], args.ip or ["127.0.0.1"]
    ca = pki.make_ca()
    pki.write_issued(out, "ca", ca)
    for role in ["router", *acl.ROLES]:
        pki.write_issued(out, role, pki.issue(ca, role, server=role == "router", dns=dns, ips=ips, days=args.days))
    passwords = {role: secrets.token_urlsafe(18) for role in acl.ROLES} if args.password_listen else {}
    if passwords:
        dictionary = "".join(f"{role}:{password}\n" for role, password in passwords.items())
        pki.write_file(out / "users.txt", dictionary.encode(), pki.PRIVATE_MODE)
    header = HEADER.format(files=site.files, what="{what}")
    _write_config(
        out / "router.json5", acl.router_config(site), header.format(what="router: TLS, access control"), secret=False
    )
    for role in acl.ROLES:
        _write_config(
            out / f"{role}.json5",
            acl.client_config(site, role, passwords.get(role)),
            header.format(what=f"{role}: client of the router, with its certificate"),
            secret=bool(passwords),
        )
    for role in acl.PASSWORD_ROLES if passwords else ():
        _write_config(
            out / f"{role}-password.json5",
            acl.client_config(site, role, passwords[role], certificate=False),
            header.format(what=f"{role}: client with a password, no certificate"),
            secret=True,
        )
    print(f"magnet certs: CA, certificates and configs for router, {', '.join(acl.ROLES)} written to {out}")
    return 0


def _write_config(path: Path, config: dict, comment: str, secret: bool) -> None:
    pki.write_file(path, acl.render(config, comment).encode(), pki.PRIVATE_MODE if secret else pki.PUBLIC_MODE)
