"""Key expressions: ``<prefix>/<device>/<kind>`` with the device id as one key chunk, and the one key check.

``validate_device_id`` is the only check of a device id (keys, messages and queries all use it); ``check_key`` the
only check that a message arrived on the key of its own device.
"""

from __future__ import annotations

import enum
from typing import Any

from magnet.wire.errors import WireError

DEFAULT_PREFIX = "magnet"
MAX_DEVICE_ID_CHARS = 128
_FORBIDDEN_ID_CHARS = frozenset("/*$?#")
_FORBIDDEN_PREFIX_CHARS = frozenset("*$?#")
#: device ids already found valid (each validated once while it is here), emptied when it holds ``_VALID_IDS_CAP``:
#: at 100,000 kept for good, a flood's new ids stayed alive in every service (five floods of 20,000 ids: +1.3 MB of
#: live strings a flood, about 10 MB in all, and the memory pools they pinned; docs/front-door.md). Emptied, a fleet
#: of 10,000 real devices validates each id again once per 6,000 new ones
_VALID_IDS: set[str] = set()
_VALID_IDS_CAP = 16_384


class Kind(enum.Enum):
    """What a key carries: the key suffix after ``<prefix>/<device>/``."""

    RAW = "raw"
    CALIBRATION = "calibration"
    HISTORY = "calibration/history"
    PROGRESS = "calibration/progress"
    CALIBRATE = "calibrate"
    HEADING = "heading"
    ALERT = "alert"


def validate_device_id(device: Any) -> str:
    """Return ``device`` if it is a usable single key chunk, else raise ValueError saying why."""
    if type(device) is str and device in _VALID_IDS:
        return device
    if not isinstance(device, str) or not device:
        raise ValueError("a device id must be a non-empty string")
    bad = sorted(set(device) & _FORBIDDEN_ID_CHARS)
    if bad:
        raise ValueError(f"device id {device!r} contains {' '.join(bad)}: ids may not contain / * $ ? #")
    if len(device) > MAX_DEVICE_ID_CHARS or not device.isprintable() or device.strip() != device:
        raise ValueError(
            f"device id {device!r} must be printable, without surrounding spaces, at most {MAX_DEVICE_ID_CHARS} chars"
        )
    if len(_VALID_IDS) >= _VALID_IDS_CAP:
        _VALID_IDS.clear()  # frees its table too: a flood's ids are not kept, the fleet's come back in one message
    _VALID_IDS.add(device)
    return device


def message_device(message: Any) -> str:
    """The ``device`` field of a decoded message map; WireError ``bad-device`` when it is not a valid id."""
    try:
        return validate_device_id(message.get("device"))
    except ValueError as exc:
        raise WireError("bad-device", str(exc)) from None


def validate_prefix(prefix: str) -> str:
    """Return ``prefix`` (one or more key chunks, no wildcards) or raise ValueError."""
    if not isinstance(prefix, str) or not prefix or prefix.startswith("/") or prefix.endswith("/") or "//" in prefix:
        raise ValueError(f"key prefix {prefix!r} must be non-empty chunks separated by single '/'")
    bad = sorted(set(prefix) & _FORBIDDEN_PREFIX_CHARS)
    if bad:
        raise ValueError(f"key prefix {prefix!r} contains {' '.join(bad)}: no wildcards or special characters")
    return prefix


def key(prefix: str, device: str, kind: Kind) -> str:
    """``<prefix>/<device>/<kind>``; ``device`` may be ``*`` to match every device."""
    if device != "*":
        validate_device_id(device)
    return f"{prefix}/{device}/{kind.value}"


def device_from_key(prefix: str, key_expr: str, kind: Kind) -> str:
    """The device chunk of ``<prefix>/<device>/<kind>``; WireError if the key has another shape."""
    head, tail = f"{prefix}/", f"/{kind.value}"
    if not (key_expr.startswith(head) and key_expr.endswith(tail)):
        raise WireError("bad-key", f"key {key_expr!r} is not {head}<device>{tail}")
    device = key_expr[len(head) : -len(tail)]
    try:
        return validate_device_id(device)
    except ValueError as exc:
        raise WireError("bad-key", str(exc)) from None


def key_mismatch(key_expr: str, device: str) -> WireError:
    """The error for a message whose device is not the one its key names."""
    return WireError("key-mismatch", f"key {key_expr} carries device {device}")


def check_key(prefix: str, key_expr: str, kind: Kind, device: str) -> None:
    """WireError unless ``key_expr`` is ``<prefix>/<device>/<kind>`` for the message's own ``device``."""
    if device_from_key(prefix, key_expr, kind) != device:
        raise key_mismatch(key_expr, device)


def status_key(prefix: str, service: str) -> str:
    """Queryable key of a service's counters: ``<prefix>/@status/<service>``."""
    return f"{prefix}/@status/{service}"


def vehicle_key(prefix: str, vehicle: str) -> str:
    """Queryable key of a vehicle's compasses compared (the compass answers): ``<prefix>/@vehicle/<vehicle>``."""
    return f"{prefix}/@vehicle/{vehicle}"


def liveliness_key(prefix: str, role: str, name: str) -> str:
    """Liveliness token key: ``<prefix>/@alive/<role>/<name>`` (role: edge, device, calibrator, compass, router)."""
    return f"{prefix}/@alive/{role}/{name}"
