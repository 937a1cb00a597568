"""What each role may do on the router, as Zenoh 1.10 access-control rules, and the router and client configs.

A role is described by what it does (publishes, subscribes, serves queryables, asks queries, declares liveliness
tokens, watches liveliness); each capability becomes the messages the router must let through, in the right flow:
``ingress`` is what the role sends to the router, ``egress`` what the router forwards to the role. For example a
subscriber needs ``declare_subscriber`` in and ``put`` out; a publisher needs ``put`` in and the subscribers'
declarations out (a client publisher only sends when it knows of a subscriber). Everything else is denied
(``default_permission: deny``), and Zenoh drops denied messages silently.

Subjects: the certificate common name of each role (mTLS listener); with ``password_roles`` also the user names of
those roles (the password listener, TLS without client certificates).
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

from services.security.capabilities import Can
from services.security.identities import EdgeIdentity, shard_identities

#: key expressions below the prefix
RAW, CAL, HISTORY, PROGRESS, CALIBRATE, HEADING = (
    "*/raw",
    "*/calibration",
    "*/calibration/history",
    "*/calibration/progress",
    "*/calibrate",
    "*/heading",
)
STATUS, ALIVE, LEASE = "@status/*", "@alive/**", "@lease/**"
WHOLE_FLEET_LEASE = "@lease/calibrator/0-1/**"  # the plain calibrator identity: shard 0/1 only
ALERT, FLEET = "*/alert", "@fleet"  # drift alerts (compass), the fleet query (calibrator)

_VIEW: dict[Can, tuple[str, ...]] = {
    Can.SUBSCRIBE: (HEADING, CAL, PROGRESS, RAW, ALERT),
    Can.ASK: (CAL, HISTORY, STATUS, FLEET, ALERT),
    Can.WATCH: (ALIVE,),
}

#: role -> capability -> key expressions (below the prefix). The role is the certificate's common name.
ROLES: dict[str, dict[Can, tuple[str, ...]]] = {
    # any device (a trial site): `magnet certs --edge NAME=IDS` issues per-host identities instead (identities.py)
    "edge": {
        Can.PUBLISH: (RAW,),
        Can.TOKEN: ("@alive/edge/*", "@alive/device/*", "@alive/device/*/unhealthy"),
        Can.SERVE: ("@status/edge-$*",),
    },
    "calibrator": {
        Can.SUBSCRIBE: (RAW, ALERT),
        Can.PUBLISH: (CAL, PROGRESS),
        Can.ASK: (ALERT,),
        Can.SERVE: (CAL, HISTORY, CALIBRATE, STATUS, FLEET),
        Can.TOKEN: ("@alive/calibrator/*", WHOLE_FLEET_LEASE),
        Can.WATCH: (WHOLE_FLEET_LEASE,),
    },
    "compass": {
        Can.SUBSCRIBE: (RAW, CAL),
        Can.PUBLISH: (HEADING, ALERT),
        Can.ASK: (CAL,),
        Can.SERVE: (STATUS, ALERT),
        Can.TOKEN: ("@alive/compass/*",),
    },
    "viewer": _VIEW,
    "operator": {**_VIEW, Can.ASK: (CAL, HISTORY, STATUS, CALIBRATE, FLEET, ALERT)},
}

#: roles that may authenticate with a user name and password instead of a certificate (devices that cannot hold one,
#: read-only viewers); the others always need their certificate
PASSWORD_ROLES = ("edge", "viewer")


Roles = Mapping[str, Mapping[Can, Sequence[str]]]


def site_roles(edges: Sequence[EdgeIdentity] = (), shards: int = 0) -> dict[str, Mapping[Can, Sequence[str]]]:
    """Every identity of a site and what it may do: the roles of ``ROLES``; with ``edges``, one identity per edge
    host instead of the ``edge`` role that speaks for any device; with ``shards`` > 1, one calibrator identity per
    shard that may hold only its shard's lease."""
    roles: dict[str, Mapping[Can, Sequence[str]]] = dict(ROLES)
    if edges:
        del roles["edge"]
        roles.update({edge.identity: edge.capabilities() for edge in edges})
    for identity, lease in shard_identities(shards):
        roles[identity] = {
            **ROLES["calibrator"],
            Can.TOKEN: ("@alive/calibrator/*", lease),
            Can.WATCH: (lease,),
        }
    return roles


def role_rules(prefix: str, role: str, capabilities: Mapping[Can, Sequence[str]]) -> list[dict[str, Any]]:
    """The allow rules of one identity: per flow, its messages on its key expressions under ``prefix``."""
    grants: dict[tuple[str, str], list[str]] = {}
    for can, keys in capabilities.items():
        for flow_message in can.value:
            for key in keys:
                if f"{prefix}/{key}" not in grants.setdefault(flow_message, []):
                    grants[flow_message].append(f"{prefix}/{key}")
    merged: dict[tuple[str, tuple[str, ...]], list[str]] = {}  # messages of one flow on the same keys: one rule
    for (flow, message), granted in grants.items():
        merged.setdefault((flow, tuple(granted)), []).append(message)
    return [
        {
            "id": f"{role}-{flow}-{'+'.join(messages)}",
            "permission": "allow",
            "flows": [flow],
            "messages": messages,
            "key_exprs": list(rule_keys),
        }
        for (flow, rule_keys), messages in merged.items()
    ]


def rules(prefix: str, roles: Roles = ROLES) -> list[dict[str, Any]]:
    """One allow rule per identity, flow and message kind, on the identity's key expressions under ``prefix``."""
    return [rule for role, capabilities in roles.items() for rule in role_rules(prefix, role, capabilities)]


def subjects(password_roles: Sequence[str], roles: Roles = ROLES) -> list[dict[str, Any]]:
    out = [{"id": f"{role}-certificate", "cert_common_names": [role]} for role in roles]
    return out + [{"id": f"{role}-password", "usernames": [role]} for role in password_roles if role in roles]


def policies(prefix: str, password_roles: Sequence[str], roles: Roles = ROLES) -> list[dict[str, Any]]:
    return [
        {
            "id": role,
            "rules": [rule["id"] for rule in role_rules(prefix, role, capabilities)],
            "subjects": [f"{role}-certificate"] + ([f"{role}-password"] if role in password_roles else []),
        }
        for role, capabilities in roles.items()
    ]


def access_control(prefix: str, password_roles: Sequence[str] = (), roles: Roles = ROLES) -> dict[str, Any]:
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": rules(prefix, roles),
        "subjects": subjects(password_roles, roles),
        "policies": policies(prefix, password_roles, roles),
    }


def password_roles(roles: Iterable[str]) -> list[str]:
    """The identities that may log in with a password: ``PASSWORD_ROLES`` and every edge host."""
    return [role for role in roles if role in PASSWORD_ROLES or role.startswith("edge-")]


@dataclasses.dataclass(frozen=True)
class Site:
    """Where the router listens and where the configs find the files.

    ``listen``: the mTLS endpoint (``tls/HOST:PORT``); ``password_listen``: a second TLS endpoint without client
    certificates where users authenticate with a password (None: no passwords at all); ``files``: the directory
    the configs name for certificates, keys and the password dictionary (where they will be installed)."""

    listen: str
    password_listen: str | None
    files: Path
    prefix: str = "magnet"
    edges: tuple[EdgeIdentity, ...] = ()  # one identity per edge host (none: the edge role, any device)
    shards: int = 0  # > 1: one calibrator identity per shard

    @property
    def roles(self) -> dict[str, Mapping[Can, Sequence[str]]]:
        return site_roles(self.edges, self.shards)

    def __post_init__(self) -> None:
        for endpoint in (self.listen, self.password_listen):
            if endpoint is not None and not endpoint.startswith("tls/"):
                raise ValueError(f"endpoint {endpoint!r} must be a TLS endpoint: tls/HOST:PORT")


def router_config(site: Site) -> dict[str, Any]:
    """The router's config: mTLS listener (+ password listener), access control, no scouting."""
    endpoints = [site.listen] + ([f"{site.password_listen}#enable_mtls=false"] if site.password_listen else [])
    transport: dict[str, Any] = {
        "link": {
            "tls": {
                "root_ca_certificate": str(site.files / "ca.crt"),
                "listen_certificate": str(site.files / "router.crt"),
                "listen_private_key": str(site.files / "router.key"),
                "enable_mtls": True,
            }
        }
    }
    if site.password_listen:
        transport["auth"] = {"usrpwd": {"dictionary_file": str(site.files / "users.txt")}}
    return {
        "mode": "router",
        "listen": {"endpoints": endpoints},
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
        "transport": transport,
        "access_control": access_control(
            site.prefix, password_roles(site.roles) if site.password_listen else (), site.roles
        ),
    }


def client_config(site: Site, role: str, password: str | None, certificate: bool = True) -> dict[str, Any]:
    """A client config for ``role``: with its certificate on the mTLS listener, or (``certificate=False``) with
    only the CA and its password on the password listener. ``password`` is required when the site has passwords."""
    tls: dict[str, Any] = {"root_ca_certificate": str(site.files / "ca.crt")}
    if certificate:
        tls.update(
            connect_certificate=str(site.files / f"{role}.crt"),
            connect_private_key=str(site.files / f"{role}.key"),
            enable_mtls=True,
        )
    endpoint = site.listen if certificate else site.password_listen
    config: dict[str, Any] = {
        "mode": "client",
        "connect": {"endpoints": [endpoint]},
        "scouting": {"multicast": {"enabled": False}},
        "transport": {"link": {"tls": tls}},
    }
    if password is not None:
        config["transport"]["auth"] = {"usrpwd": {"user": role, "password": password}}
    return config


def render(config: dict[str, Any], comment: str) -> str:
    """json5 text: ``//`` comment lines, then the config as JSON (valid json5), one short object per line."""
    lines = [f"// {line}" if line else "//" for line in comment.splitlines()]
    return "\n".join(lines) + "\n" + _compact(config, 0) + "\n"


def _compact(value: Any, depth: int, width: int = 118) -> str:
    """JSON of ``value``: on one line when it fits in ``width`` columns or is an object of plain values (a rule, a
    subject), else one member per line."""
    flat = json.dumps(value)
    leaf = isinstance(value, dict) and not any(
        isinstance(v, dict) or (isinstance(v, list) and any(isinstance(item, (dict, list)) for item in v))
        for v in value.values()
    )
    if len(flat) + 2 * depth <= width or leaf or not isinstance(value, (dict, list)) or not value:
        return flat
    pad, inner = "  " * depth, "  " * (depth + 1)
    if isinstance(value, dict):
        members = [f"{inner}{json.dumps(k)}: {_compact(v, depth + 1)}" for k, v in value.items()]
        return "{\n" + ",\n".join(members) + f"\n{pad}}}"
    return "[\n" + ",\n".join(inner + _compact(v, depth + 1) for v in value) + f"\n{pad}]"
