"""``--db``: a SQLite file or a PostgreSQL URL, any other scheme refused; both stores refuse a second record of one
version of a device (a constraint, not only the lease) and hand out and take in their rows byte for byte."""

from __future__ import annotations

import contextlib
from pathlib import Path

import pytest
from memory_store import record_of

from services.calibrator.settings import ServiceSettings
from services.calibrator.store import open_store
from services.common.stores import PostgresUrl, StoredRow, parse_db


def test_db_is_a_sqlite_file_or_a_postgresql_url_and_nothing_else():
    assert parse_db("calibrations.sqlite3") == Path("calibrations.sqlite3")
    assert parse_db("/var/lib/magnet/c.db") == Path("/var/lib/magnet/c.db")
    url = "postgresql://magnet@db.example:5432/site"
    assert parse_db(url) == PostgresUrl(url) and parse_db("postgres://h/site") == PostgresUrl("postgres://h/site")
    for wrong in ("mysql://root@h/db", "sqlite:///c.db", "https://h/db", "postgresql:"):
        with pytest.raises(ValueError, match=r"give .*postgresql://USER@HOST:PORT/DB"):
            parse_db(wrong)
    assert ServiceSettings().db_path.suffix == ".db", "SQLite stays the default"


def test_a_password_in_the_url_never_reaches_a_log_line():
    url = PostgresUrl("postgresql://magnet:s3cret@db.example:5432/site")
    assert "s3cret" not in str(url) and str(url) == "postgresql://magnet:***@db.example:5432/site"


def test_an_unreachable_server_is_one_line_naming_it_without_its_password(tmp_path):
    from helpers import free_ports

    (port,) = free_ports(1)
    with pytest.raises(OSError, match=rf"127.0.0.1:{port}/site .*check that the server runs") as refused:
        open_store(parse_db(f"postgresql://magnet:pw@127.0.0.1:{port}/site"))
    assert "pw@" not in str(refused.value) and "\n" not in str(refused.value)


def _stores(request: pytest.FixtureRequest, name: str) -> tuple[str, str]:
    """Two locations of ``name``'s kind."""
    if name == "sqlite":
        tmp: Path = request.getfixturevalue("tmp_path")
        return str(tmp / "a.sqlite3"), str(tmp / "b.sqlite3")
    server = request.getfixturevalue("postgres")
    return server.new_database(), server.new_database()


KINDS = [pytest.param("sqlite"), pytest.param("postgresql", marks=pytest.mark.integration)]


@pytest.mark.parametrize("name", KINDS)
def test_versions_are_unique_per_device_and_rows_move_byte_for_byte(name, request):
    first, second = _stores(request, name)
    with contextlib.closing(open_store(parse_db(first))) as store:
        store.append("d", lambda v: record_of("d", v, 1.0), {"action": "auto", "by": "ä"})
        store.append("d", lambda v: record_of("d", v, 2.0))
        with pytest.raises(OSError, match="calibration database"):
            store.append("d", lambda v: record_of("d", 2, 3.0), {"action": "auto"})  # version 2 again
        assert [r.version for r in store.history("d")] == [2, 1], "nothing of the refused record is stored"
        rows = list(store.rows())
    assert [(r.device, r.version, r.change) for r in rows] == [
        ("d", 1, '{"action": "auto", "by": "\\u00e4"}'),
        ("d", 2, None),
    ]
    with contextlib.closing(open_store(parse_db(second))) as other:
        assert other.load_rows(rows) == 2 and other.count() == 2
        assert list(other.rows()) == rows
        with pytest.raises(OSError):
            other.load_rows([StoredRow("e", "x", 1, 1, rows[0].record), rows[0]])  # the second: version 1 of d again
        assert other.count() == 2, "a refused load stores nothing"


def test_the_deploy_units_command_is_one_magnet_accepts_with_a_postgresql_store():
    import re
    import shlex

    from helpers import REPO_ROOT

    from services.cli import build_parser

    unit = (REPO_ROOT / "deploy" / "postgresql" / "magnet-calibrator.service").read_text()
    line = next(line for line in unit.splitlines() if line.startswith("ExecStart="))
    program, *argv = shlex.split(line.removeprefix("ExecStart="))
    assert program == "/opt/magnet/.venv/bin/magnet" and not re.search(r"%[^%]", line)
    args = build_parser(argv).parse_args(argv)
    db = parse_db(args.db)  # what the settings make of the option's text
    assert isinstance(db, PostgresUrl) and "target_session_attrs=read-write" in db.url
