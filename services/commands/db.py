"""``magnet db``: a site's store of calibrations as a whole, for either kind (a SQLite file or
``postgresql://USER@HOST:PORT/DB``, ``services.common.stores``).

- ``magnet db copy --from A --to B``: every row of A into the empty store B, in order and in one transaction, the
  records' and changes' text byte for byte (so every signature stays as it was made); read back and compared before
  it says so. A SQLite site moves to PostgreSQL this way, and back.
- ``magnet db check --db A [--trust FILE.pub ...]``: every stored record read through the entry check, its signature
  verified (with ``--trust``: under those keys; without, signed records are counted, not verified), and each device's
  history continuous: versions rising with every row, none twice, each change's ``from_id`` the row before.
  One line per problem, then a summary; exit status 1 when there is a problem.
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import json
from collections.abc import Iterable
from pathlib import Path

from magnet import signing, wire
from services.calibrator.store import open_store
from services.common.stores import PostgresUrl, StoredRow, StoreLocation, parse_db


def add_arguments(parser: argparse.ArgumentParser) -> None:
    actions = parser.add_subparsers(dest="action", metavar="ACTION", required=True)
    copy = actions.add_parser("copy", help="copy every record (and its change) of one store into an empty one")
    copy.add_argument("--from", dest="source", required=True, type=parse_db, metavar="FILE.sqlite3|postgresql://...")
    copy.add_argument("--to", dest="target", required=True, type=parse_db, metavar="FILE.sqlite3|postgresql://...")
    check = actions.add_parser("check", help="verify every record's signature and each device's history")
    check.add_argument("--db", required=True, type=parse_db, metavar="FILE.sqlite3|postgresql://...")
    check.add_argument(
        "--trust",
        action="append",
        type=Path,
        default=[],
        metavar="FILE.pub",
        help="verify signatures under this public key (repeatable); without it, signed records are only counted",
    )


def _existing(location: StoreLocation) -> StoreLocation:
    """A store to read must exist: a SQLite file is never created by reading it."""
    if isinstance(location, Path) and not location.is_file():
        raise FileNotFoundError(f"no calibration database at {location}: give the file the calibrator wrote")
    return location


def copy(source: StoreLocation, target: StoreLocation) -> tuple[int, int]:
    """Every row of ``source`` into the empty ``target``, compared after; (rows, devices). ValueError when the
    target holds records or the copy reads back otherwise (nothing of it kept then: one transaction)."""
    with open_store(_existing(source)) as src, open_store(target) as dst:
        held = dst.count()
        if held:
            raise ValueError(
                f"{target} already holds {held} record(s): copy into an empty store (a new file or database)"
            )
        rows = list(src.rows())
        dst.load_rows(rows)
        if list(dst.rows()) != rows:
            raise ValueError(f"the copy in {target} does not read back byte for byte: check it with magnet db check")
    return len(rows), len({row.device for row in rows})


@dataclasses.dataclass
class Findings:
    """What ``check_rows`` found: counts and one line per problem."""

    rows: int = 0
    devices: int = 0
    verified: int = 0
    signed_unverified: int = 0
    unsigned: int = 0
    problems: list[str] = dataclasses.field(default_factory=list)


def _signature(record: wire.DeviceCalibration, trusted: signing.TrustedKeys, found: Findings, where: str) -> None:
    fields = record.to_record()
    if not fields.get("sig"):
        found.unsigned += 1
        if trusted.enabled:
            found.problems.append(f"{where}: unsigned, and --trust requires signed records")
        return
    if not trusted.enabled:
        found.signed_unverified += 1
        return
    try:
        trusted.verify(fields)
    except signing.SignatureError as exc:
        found.problems.append(f"{where}: signature does not verify ({exc})")
        return
    found.verified += 1


def check_rows(rows: Iterable[StoredRow], trusted: signing.TrustedKeys) -> Findings:
    """Each row through the entry check and its signature; each device's history continuous (see the module)."""
    found = Findings()
    previous: dict[str, StoredRow] = {}
    versions: dict[str, set[int]] = collections.defaultdict(set)
    for n, row in enumerate(rows, 1):
        found.rows, where = n, f"row {n} ({row.device} {row.id[:12]} version {row.version})"
        try:
            record = wire.calibration_from_record(json.loads(row.record))
        except (ValueError, RecursionError) as exc:
            found.problems.append(f"{where}: unreadable, never served ({exc})")
            continue
        if (record.device, record.id, record.version) != (row.device, row.id, row.version):
            found.problems.append(f"{where}: the record inside says {record.device} {record.id} {record.version}")
        _signature(record, trusted, found, where)
        before = previous.get(row.device)
        if row.version > 0 and row.version in versions[row.device]:
            found.problems.append(f"{where}: a second record of version {row.version}")
        elif before is not None and row.version <= before.version and row.version > 0:
            found.problems.append(f"{where}: version after {before.version} does not rise")
        from_id = _from_id(row.change)
        if from_id is not False and from_id != (before.id if before else None):
            said = before.id if before else "nothing"
            found.problems.append(f"{where}: its change comes from {from_id}, the row before is {said}")
        versions[row.device].add(row.version)
        previous[row.device] = row
    found.devices = len(previous)
    return found


def _from_id(change: str | None) -> str | bool | None:
    """The change's ``from_id`` (None: the device's first record); False where the change does not say."""
    try:
        note = json.loads(change) if change is not None else None
    except ValueError:
        return False
    if not isinstance(note, dict) or "from_id" not in note:
        return False
    value = note["from_id"]
    return value if isinstance(value, str) or value is None else False


def run(args: argparse.Namespace) -> int:
    if args.action == "copy":
        rows, devices = copy(args.source, args.target)
        print(f"copied {rows} record(s) of {devices} device(s) from {args.source} to {args.target}, byte for byte")
        return 0
    trusted = signing.TrustedKeys([signing.load_public_key(p.read_bytes(), str(p)) for p in args.trust])
    with open_store(_existing(args.db)) as store:
        found = check_rows(store.rows(), trusted)
    for line in found.problems:
        print(line)
    signatures = (
        f"{found.verified} signature(s) verified"
        if trusted.enabled
        else f"{found.signed_unverified} signed (not verified: give --trust FILE.pub)"
    )
    kind = "PostgreSQL" if isinstance(args.db, PostgresUrl) else "SQLite"
    verdict = "ok" if not found.problems else f"{len(found.problems)} problem(s)"
    print(
        f"{verdict}: {kind} {args.db}: {found.rows} record(s) of {found.devices} device(s); {signatures}, "
        f"{found.unsigned} unsigned; history continuous" + ("" if not found.problems else " except as listed")
    )
    return 0 if not found.problems else 1
