"""``magnet db copy`` moves a site between SQLite and PostgreSQL with every row byte for byte (signatures untouched);
``magnet db check`` verifies every record's signature and each device's history, and names what is wrong."""

from __future__ import annotations

import dataclasses
import json
import sqlite3
import time
from pathlib import Path

import pytest
from memory_store import record_of

from magnet import signing
from services.calibrator.store import open_store
from services.cli import main
from services.common.stores import StoredRow, parse_db


def new_site_signer(tmp_path: Path) -> tuple[signing.Signer, Path]:
    """A signer and its public key written to ``site.pub``."""
    private_pem, public_pem = signing.new_key_pair()
    (tmp_path / "site.pub").write_bytes(public_pem)
    return signing.Signer(signing.load_private_key(private_pem)), tmp_path / "site.pub"


def fill_site(location: str, devices: int, records: int, signer: signing.Signer) -> None:
    """``devices`` devices with ``records`` signed records each (versions 1, 2, ...), every change naming the record
    before it, stored in one transaction as the calibrator would have stored them one by one."""
    rows = []
    for d in range(devices):
        device, before = f"dev-{d:04d}", None
        for n in range(records):
            made = record_of(device, n + 1, float(n + 1), created_ns=1_700_000_000_000_000_000 + n)
            fields = signer.sign(made.to_record())
            record = dataclasses.replace(made, sig=fields["sig"], key_id=fields["key_id"])
            text = json.dumps(record.to_record(), sort_keys=True, allow_nan=False)
            change = json.dumps({"action": "auto", "by": "", "from_id": before}, sort_keys=True)
            rows.append(StoredRow(device, record.id, record.created_ns, record.version, text, change))
            before = record.id
    with open_store(parse_db(location)) as store:
        store.load_rows(rows)


@pytest.fixture
def site(tmp_path):
    """A SQLite site of 20 devices with 3 signed records each, and the public key file that verifies them."""
    signer, pub = new_site_signer(tmp_path)
    fill_site(str(tmp_path / "site.sqlite3"), 20, 3, signer)
    return tmp_path / "site.sqlite3", pub


def test_copy_moves_every_row_byte_for_byte_and_check_finds_it_whole(site, tmp_path, capsys):
    path, pub = site
    assert main(["db", "copy", "--from", str(path), "--to", str(tmp_path / "moved.sqlite3")]) == 0
    assert "copied 60 record(s) of 20 device(s)" in capsys.readouterr().out
    with open_store(path) as a, open_store(tmp_path / "moved.sqlite3") as b:
        assert list(a.rows()) == list(b.rows())
    assert main(["db", "check", "--db", str(tmp_path / "moved.sqlite3"), "--trust", str(pub)]) == 0
    assert capsys.readouterr().out.startswith("ok: SQLite")
    assert main(["db", "copy", "--from", str(path), "--to", str(tmp_path / "moved.sqlite3")]) == 2
    assert "already holds 60 record(s): copy into an empty store" in capsys.readouterr().err
    assert main(["db", "check", "--db", str(tmp_path / "nothing.sqlite3")]) == 2
    assert not (tmp_path / "nothing.sqlite3").exists(), "checking never creates a store"


def test_check_names_a_changed_record_a_repeated_version_and_a_broken_history(site, capsys):
    path, pub = site
    with sqlite3.connect(path) as db:  # what a hand in the file would do
        db.execute(
            "UPDATE calibrations SET record = replace(record, '\"version\": 2', '\"version\": 2 ') WHERE seq = 2"
        )
        db.execute("UPDATE calibrations SET record = replace(record, '1.0', '1.5') WHERE seq = 4")
        db.execute("DROP INDEX calibrations_version_per_device")
        db.execute("UPDATE calibrations SET version = 2 WHERE seq = 9")
        db.execute("DELETE FROM calibrations WHERE seq = 11")
    assert main(["db", "check", "--db", str(path), "--trust", str(pub)]) == 1
    out = capsys.readouterr().out.splitlines()
    assert any("dev-0001" in line and "signature does not verify" in line for line in out), out
    assert any("dev-0002" in line and "a second record of version 2" in line for line in out), out
    assert any("dev-0003" in line and "its change comes from" in line for line in out), out
    assert out[-1].startswith(f"{len(out) - 1} problem(s): SQLite")


@pytest.mark.integration
def test_a_thousand_device_site_moves_to_postgresql_and_back_byte_for_byte(tmp_path, postgres_url, capsys):
    signer, pub = new_site_signer(tmp_path)
    fill_site(str(tmp_path / "site.sqlite3"), 1000, 2, signer)
    started = time.perf_counter()
    assert main(["db", "copy", "--from", str(tmp_path / "site.sqlite3"), "--to", postgres_url]) == 0
    there = time.perf_counter()
    assert main(["db", "copy", "--from", postgres_url, "--to", str(tmp_path / "back.sqlite3")]) == 0
    back = time.perf_counter()
    assert main(["db", "check", "--db", postgres_url, "--trust", str(pub)]) == 0
    out = capsys.readouterr().out
    assert "ok: PostgreSQL" in out and "2000 record(s) of 1000 device(s); 2000 signature(s) verified" in out
    print(f"db copy of 1000 devices x 2 records: to PostgreSQL {there - started:.2f} s, back {back - there:.2f} s")
    with open_store(tmp_path / "site.sqlite3") as a, open_store(tmp_path / "back.sqlite3") as b:
        assert list(a.rows()) == list(b.rows())
