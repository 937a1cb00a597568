"""How a calibration record's plain fields are read from a map (``magnet.model.Calibration.from_dict``): each checked,
with a ValueError naming the field and what it must be."""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

#: a sensor's hardware id is an unsigned 32-bit number (``Calibration.hardware_id``)
MAX_HARDWARE_ID = (1 << 32) - 1


def text(data: Mapping[str, Any], name: str, default: str) -> str:
    value = data.get(name, default)
    if value is None:
        return default
    if not isinstance(value, str):
        raise ValueError(f"calibration field {name} must be a string, got {type(value).__name__}")
    return value


def known(data: Mapping[str, Any], name: str, default: str, known: frozenset[str]) -> str:
    """A text field that must be one of ``known``; ValueError naming them otherwise."""
    value = text(data, name, default)
    if value not in known:
        shown = value if len(value) <= 40 else value[:40] + "..."
        raise ValueError(f"calibration field {name} {shown!r} is not one of {', '.join(sorted(known))}")
    return value


def number(data: Mapping[str, Any], name: str) -> float:
    value = data.get(name)
    value = 0 if value is None else value  # not ``or 0``: false would pass as 0
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value < 0:
        raise ValueError(f"calibration field {name} must be a finite number >= 0, got {value!r}")
    return float(value)


def hardware_id(data: Mapping[str, Any]) -> int | None:
    """The optional ``hardware_id`` (absent, null or 0: not known)."""
    value = data.get("hardware_id")
    if value is None or value == 0:
        return None
    if isinstance(value, bool) or not isinstance(value, int) or not 0 < value <= MAX_HARDWARE_ID:
        raise ValueError(f"calibration field hardware_id must be a whole number 1..{MAX_HARDWARE_ID}, got {value!r}")
    return int(value)


def flag(data: Mapping[str, Any], name: str) -> bool:
    value = data.get(name, True)
    if not isinstance(value, bool):
        raise ValueError(f"calibration field {name} must be true or false, got {value!r}")
    return value
