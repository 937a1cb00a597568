"""``magnet certs --out DIR``: a site CA, a v3 certificate per identity, the router's config (TLS with client
certificates, access control) and one client config per identity, ready for ``--config``.

Written to DIR (nothing existing is overwritten): ``ca.crt``/``ca.key``; ``ROLE.crt``/``ROLE.key`` for router,
edge, calibrator, compass, viewer, operator; ``router.json5``; ``ROLE.json5``. With ``--password-listen ENDPOINT``
also ``users.txt`` (the router's user:password dictionary, every identity) and ``edge-password.json5`` /
``viewer-password.json5`` (TLS to that second listener with a password, no client certificate). Keys, the
dictionary and configs holding a password are mode 0600, the rest 0644.

``--edge NAME=DEV1,DEV2`` (repeatable) issues one identity per edge host instead of the ``edge`` role: ``edge-
NAME.crt/.key/.json5`` (and ``edge-NAME-password.json5``), allowed to speak only for those devices; the list and the
shard count are kept in ``site.json``. ``--shards N`` issues ``calibrator-K-N`` identities, each allowed only its
shard's lease. ``--add`` works on an existing DIR: the CA there signs what is missing, the edges given join those of
``site.json`` (a name given again gets the new device list), existing files stay, and ``router.json5`` and
``users.txt`` are rewritten (existing passwords kept): restart the router to apply it.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import os
import secrets
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from services.security import acl, identities, pki

log = logging.getLogger("magnet.certs")

SITE = "site.json"  # the edge hosts (name -> device ids) and shards of the site, kept for --add

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
    parser.add_argument(
        "--edge",
        action="append",
        metavar="NAME=DEVICE[,DEVICE...]",
        help="an identity edge-NAME for one edge host, allowed to publish and report only for these device ids "
        "(repeatable; replaces the edge role, which speaks for any device)",
    )
    parser.add_argument(
        "--shards",
        type=int,
        metavar="N",
        help="also one calibrator identity per shard (calibrator-K-N), each allowed to hold only its shard's lease",
    )
    parser.add_argument(
        "--add",
        action="store_true",
        help="add to the site already in --out: its CA signs the identities that are missing, --edge joins "
        "site.json, router.json5 and users.txt are rewritten (passwords kept), nothing else is touched",
    )


def _targets(out: Path, roles: Sequence[str], password: bool) -> list[Path]:
    names = ["ca.crt", "ca.key", "router.json5", "router.crt", "router.key"]
    for role in roles:
        names += [f"{role}.crt", f"{role}.key", f"{role}.json5"]
    if password:
        names += ["users.txt"] + [f"{role}-password.json5" for role in acl.password_roles(roles)]
    return [out / name for name in names]


def _site(args: argparse.Namespace, out: Path) -> acl.Site:
    """The site from the options; with ``--add``, the edges and shards of ``site.json`` joined by those given (and
    the listeners and prefix it was made with, which must be given again the same)."""
    if not 1 <= args.days <= 10_000:
        raise ValueError(f"--days must be 1..10000, got {args.days}")
    given = [identities.parse_edge(text) for text in args.edge or ()]
    site = acl.Site(
        args.listen, args.password_listen, (args.files or out).absolute(), args.prefix, (), args.shards or 0
    )
    saved = _saved(out) if args.add else {}
    for name, value in _listeners(site).items():
        if name in saved and saved[name] != value:
            raise ValueError(
                f"--add: the site in {out} was made with {name} {saved[name]}, not {value}: give the same options"
            )
    known = identities.edges_from_json(saved.get("edges", {}))
    shards = site.shards if args.shards is not None else int(saved.get("shards", 0))
    return dataclasses.replace(site, edges=tuple(identities.merge_edges(known, given)), shards=shards)


def _saved(out: Path) -> dict[str, Any]:
    """What ``site.json`` in ``out`` says of the site (empty for a site made before it); ValueError without a CA."""
    missing = [name for name in ("ca.crt", "ca.key") if not (out / name).exists()]
    if missing:
        raise ValueError(f"--add needs the site made before in {out}: {', '.join(missing)} not found")
    if not (out / SITE).exists():
        return {}
    saved = json.loads((out / SITE).read_text())
    if not isinstance(saved, dict):
        raise ValueError(f"{out / SITE} is not a map: move it aside")
    return saved


def _listeners(site: acl.Site) -> dict[str, Any]:
    return {"--listen": site.listen, "--password-listen": site.password_listen, "--prefix": site.prefix}


def run(args: argparse.Namespace) -> int:
    out: Path = args.out
    site = _site(args, out)
    roles = list(site.roles)
    out.mkdir(parents=True, exist_ok=True)
    if not args.add:
        existing = [str(path) for path in _targets(out, roles, bool(args.password_listen)) if path.exists()]
        if existing:
            raise ValueError(
                f"{', '.join(existing)} already exist(s): nothing written; move them aside, choose another --out, "
                "or give --add to add identities to that site"
            )
        pki.write_issued(out, "ca", pki.make_ca())
    ca = pki.load(out / "ca.crt", out / "ca.key")
    dns, ips = args.dns or ["localhost"], args.ip or ["127.0.0.1"]
    made = []
    for role in ["router", *roles]:
        if not (out / f"{role}.crt").exists():
            issued = pki.issue(ca, role, server=role == "router", dns=dns, ips=ips, days=args.days)
            pki.write_issued(out, role, issued)
            made.append(role)
    passwords = _passwords(out, roles) if args.password_listen else {}
    saved = {"edges": identities.edges_to_json(site.edges), "shards": site.shards, **_listeners(site)}
    _replace(out / SITE, json.dumps(saved, indent=2) + "\n", pki.PUBLIC_MODE)
    _write_configs(out, site, roles, passwords)
    print(
        f"magnet certs: in {out}: new certificates for {', '.join(made) or 'none'}; router.json5 rules for "
        f"{', '.join(roles)}"
    )
    return 0


def _passwords(out: Path, roles: Sequence[str]) -> dict[str, str]:
    """A password per identity that may log in: those in ``users.txt`` kept, new ones drawn; ``users.txt`` written."""
    known: dict[str, str] = {}
    if (out / "users.txt").exists():
        for line in (out / "users.txt").read_text().splitlines():
            user, sep, password = line.partition(":")
            if sep:
                known[user] = password
    passwords = {role: known.get(role) or secrets.token_urlsafe(18) for role in roles}
    _replace(out / "users.txt", "".join(f"{r}:{p}\n" for r, p in passwords.items()), pki.PRIVATE_MODE)
    return passwords


def _write_configs(out: Path, site: acl.Site, roles: Sequence[str], passwords: dict[str, str]) -> None:
    """router.json5 (rewritten: it holds every identity's rules) and each identity's client configs (kept when
    they exist)."""
    header = HEADER.format(files=site.files, what="{what}")
    router = acl.render(acl.router_config(site), header.format(what="router: TLS, access control"))
    _replace(out / "router.json5", router, pki.PUBLIC_MODE)
    for role in roles:
        if not (out / f"{role}.json5").exists():
            _write_config(
                out / f"{role}.json5",
                acl.client_config(site, role, passwords.get(role)),
                header.format(what=f"{role}: client of the router, with its certificate"),
                secret=bool(passwords),
            )
    for role in acl.password_roles(roles) if passwords else ():
        if not (out / f"{role}-password.json5").exists():
            _write_config(
                out / f"{role}-password.json5",
                acl.client_config(site, role, passwords[role], certificate=False),
                header.format(what=f"{role}: client with a password, no certificate"),
                secret=True,
            )


def _replace(path: Path, text: str, mode: int) -> None:
    """Write ``text`` to ``path`` whole or not at all (a new file renamed over the old one)."""
    temporary = path.with_name(path.name + ".new")
    temporary.unlink(missing_ok=True)
    pki.write_file(temporary, text.encode(), mode)
    os.replace(temporary, path)


def _write_config(path: Path, config: dict, comment: str, secret: bool) -> None:
    pki.write_file(path, acl.render(config, comment).encode(), pki.PRIVATE_MODE if secret else pki.PUBLIC_MODE)
