"""Identities narrower than a role: one per edge host (the device ids it may speak for) and one per calibrator shard
(the only lease it may hold). Each becomes a certificate common name (and a password user name) and a capability
table in the router's access-control rules (``services.security.acl``).

- Edge ``NAME`` with devices ``d1, d2``: identity ``edge-NAME``; it may put ``<prefix>/<d>/raw`` (and hear of the
  subscribers of those keys and of ``<prefix>/*/raw``, without which a client publisher sends nothing), declare the
  liveliness tokens ``@alive/edge/<d>``, ``@alive/device/<d>`` and ``@alive/device/<d>/unhealthy``, and serve its
  status ``@status/edge-<d>``, for its own devices only.
- Calibrator shard ``K/N``: identity ``calibrator-K-N``; everything the calibrator role may do, but lease tokens only
  under ``@lease/calibrator/K-N/``. The plain ``calibrator`` identity holds only the lease of the whole fleet (0/1).
"""

from __future__ import annotations

import dataclasses
import json
import re
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path

from cryptography import x509
from cryptography.x509.oid import NameOID

from magnet.wire import validate_device_id
from services.security.capabilities import Can

NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,62}")
MAX_SHARDS = 64


@dataclasses.dataclass(frozen=True)
class EdgeIdentity:
    """An edge host's identity ``edge-NAME`` and the device ids it may speak for."""

    name: str
    devices: tuple[str, ...]

    def __post_init__(self) -> None:
        if not NAME.fullmatch(self.name) or self.name.endswith("-password"):
            raise ValueError(
                f"edge name {self.name!r} must be letters, digits, '.', '_' or '-' (at most 63, not ending in "
                "-password)"
            )
        if not self.devices:
            raise ValueError(f"edge {self.name} speaks for no device: give NAME=DEVICE[,DEVICE...]")
        for device in self.devices:
            validate_device_id(device)

    @property
    def identity(self) -> str:
        """Its certificate common name and password user name."""
        return f"edge-{self.name}"

    def capabilities(self) -> dict[Can, tuple[str, ...]]:
        """What it may do, as key expressions below the prefix."""
        tokens = []
        for device in self.devices:
            tokens += [f"@alive/edge/{device}", f"@alive/device/{device}", f"@alive/device/{device}/unhealthy"]
        own_raw = tuple(f"{device}/raw" for device in self.devices)
        return {
            Can.PUT: own_raw,
            # the subscribers it must hear of to send at all: those of its keys, and the services' */raw
            Can.SEE_SUBSCRIBERS: (*own_raw, "*/raw"),
            Can.TOKEN: tuple(tokens),
            Can.SERVE: tuple(f"@status/edge-{device}" for device in self.devices),
        }


def parse_edge(text: str) -> EdgeIdentity:
    """``NAME=DEVICE[,DEVICE...]`` (``--edge``); ValueError saying what is wrong."""
    name, sep, devices = text.partition("=")
    if not sep:
        raise ValueError(f"--edge {text!r}: give NAME=DEVICE[,DEVICE...], e.g. --edge barn=imu-1,imu-2")
    return EdgeIdentity(name.strip(), tuple(d.strip() for d in devices.split(",") if d.strip()))


def merge_edges(known: Iterable[EdgeIdentity], given: Iterable[EdgeIdentity]) -> list[EdgeIdentity]:
    """``known`` with ``given`` added (a name given again replaces its device list), sorted by name."""
    merged = {edge.name: edge for edge in known}
    merged.update({edge.name: edge for edge in given})
    return [merged[name] for name in sorted(merged)]


def edges_to_json(edges: Sequence[EdgeIdentity]) -> dict[str, list[str]]:
    return {edge.name: list(edge.devices) for edge in edges}


def edges_from_json(data: object) -> list[EdgeIdentity]:
    """The ``edges`` map of ``site.json`` (name -> device ids); ValueError when it is not one."""
    if not isinstance(data, Mapping) or not all(
        isinstance(v, list) and all(isinstance(d, str) for d in v) for v in data.values()
    ):
        raise ValueError("site.json: edges must map each edge name to a list of device ids")
    return [EdgeIdentity(str(name), tuple(devices)) for name, devices in data.items()]


def shard_identity(index: int, count: int) -> str:
    """The calibrator identity of shard ``index/count``."""
    return f"calibrator-{index}-{count}"


def shard_identities(count: int) -> list[tuple[str, str]]:
    """(identity, lease key below the prefix) of every shard of ``count``; none for 0 (no --shards)."""
    if not 0 <= count <= MAX_SHARDS:
        raise ValueError(f"--shards must be 0..{MAX_SHARDS}, got {count}")
    return [(shard_identity(k, count), f"@lease/calibrator/{k}-{count}/**") for k in range(count if count > 1 else 0)]


def certificate_identity(config_path: str | Path | None) -> str | None:
    """The common name of the client certificate a Zenoh config file names (``transport/link/tls/
    connect_certificate``); None without a file or a certificate, or for a config this cannot read (json5 beyond
    the ``//`` comment lines and JSON that ``magnet certs`` writes)."""
    if not config_path:
        return None
    try:
        lines = Path(config_path).read_text().splitlines()
        config = json.loads("\n".join(line for line in lines if not line.lstrip().startswith("//")))
        certificate = Path(config["transport"]["link"]["tls"]["connect_certificate"]).read_bytes()
        names = x509.load_pem_x509_certificate(certificate).subject.get_attributes_for_oid(NameOID.COMMON_NAME)
    except (OSError, ValueError, KeyError, TypeError):
        return None
    return str(names[0].value) if names else None


def check_calibrator_identity(identity: str | None, index: int, count: int) -> None:
    """ValueError when ``identity`` is a calibrator identity the router will not let hold the lease of shard
    ``index/count``: its token would be dropped, its standby would not see it, and both would act as active."""
    if identity is None or not (identity == "calibrator" or identity.startswith("calibrator-")):
        return
    expected = "calibrator" if count == 1 else shard_identity(index, count)
    if identity != expected:
        raise ValueError(
            f"--shard {index}/{count} with the certificate of {identity}, which may not hold that shard's lease (the "
            f"router would drop its lease token): give the config of {expected} (`magnet certs --shards {count}` "
            "makes one per shard)"
        )
