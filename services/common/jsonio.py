"""Reading JSON from files and requests within a size and a nesting depth (docs/front-door.md, "Decoding limits").

Every JSON the commands and services read from outside (a calibration record, a request body) goes through
``read_json`` or ``loads_bounded``: a file larger than its limit, a text that is not UTF-8, nesting deeper than the
limit (the parser's own ``RecursionError``, a thousand levels down, is caught too) and a text that is not JSON are
each one ``ValueError`` naming the file (or request) and what is wrong. Everything here is linear in the size.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

#: a calibration record is about 1 KiB; a request body a few dozen bytes
MAX_JSON_BYTES = 1024 * 1024
#: a record nests 3 deep (record -> matrix -> row, record -> quality -> figure list); room for a few more
MAX_JSON_DEPTH = 16


def nesting_depth(value: Any) -> int:
    """How deep the lists and dicts of a parsed JSON value nest (a scalar: 0), walked without recursion."""
    deepest, stack = 0, [(value, 1)]
    while stack:
        item, depth = stack.pop()
        children = item.values() if isinstance(item, dict) else item if isinstance(item, list) else None
        if children is not None:
            deepest = max(deepest, depth)
            stack.extend((child, depth + 1) for child in children)
    return deepest


def loads_bounded(text: str | bytes, where: str, max_depth: int = MAX_JSON_DEPTH) -> Any:
    """The value of a JSON text; ValueError ``"<where>: ..."`` when it is not UTF-8, nests deeper than
    ``max_depth`` or is not JSON."""
    if isinstance(text, bytes):
        try:
            text = text.decode("utf-8-sig")
        except UnicodeDecodeError as exc:
            raise ValueError(f"{where}: not a text file (not UTF-8 at byte {exc.start})") from None
    try:
        value = json.loads(text)
    except json.JSONDecodeError as exc:
        raise ValueError(f"{where}: not JSON ({exc.msg} at line {exc.lineno})") from None
    except RecursionError:  # the parser's own guard, hundreds of levels down
        raise ValueError(f"{where}: JSON nested too deeply (more than {max_depth} levels)") from None
    depth = nesting_depth(value)
    if depth > max_depth:
        raise ValueError(f"{where}: JSON nested {depth} levels deep, more than {max_depth}")
    return value


def read_json(path: str | Path, max_bytes: int = MAX_JSON_BYTES, max_depth: int = MAX_JSON_DEPTH) -> Any:
    """The JSON value in the file at ``path``; ValueError naming the file when it cannot be read, is larger than
    ``max_bytes``, is not UTF-8 text, nests deeper than ``max_depth`` or is not JSON."""
    try:
        with open(path, "rb") as handle:
            data = handle.read(max_bytes + 1)
    except OSError as exc:
        raise ValueError(f"{path}: cannot read it: {exc.strerror or exc}") from None
    if len(data) > max_bytes:
        raise ValueError(f"{path}: larger than {max_bytes} bytes, too large for a JSON record")
    return loads_bounded(data, str(path), max_depth)
