"""Files the commands write with ``--out`` are ordinary files (0666 less the umask: 0644 under umask 022), readable
by the people the umask lets read them; only private keys are 0600."""

from __future__ import annotations

import os
import stat

import pytest

from services.cli import main
from services.common.records import write_atomically

RECORDING = "data/ck_explorer_acc_mag_log.csv"


def _mode(path):
    return stat.S_IMODE(os.stat(path).st_mode)


@pytest.fixture(params=[0o022, 0o027])
def umask(request):
    old = os.umask(request.param)
    yield request.param
    os.umask(old)


def test_write_atomically_makes_an_ordinary_file(tmp_path, umask):
    path = tmp_path / "cal.json"
    write_atomically(path, "{}\n")
    assert _mode(path) == 0o666 & ~umask and path.read_text() == "{}\n"
    write_atomically(path, "{ }\n")  # replacing it keeps the same mode
    assert _mode(path) == 0o666 & ~umask and not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


def test_fit_and_keys_write_their_files_with_the_modes_they_need(tmp_path, umask, capsys):
    from helpers import REPO_ROOT

    cal = tmp_path / "cal.json"
    data = str(REPO_ROOT / RECORDING)
    assert main(["fit", data, "--method", "minmax", "--unit", "gauss", "--out", str(cal)]) == 0
    assert main(["keys", "--out", str(tmp_path / "keys"), "--name", "site"]) == 0
    capsys.readouterr()
    assert _mode(cal) == 0o666 & ~umask
    assert _mode(tmp_path / "keys" / "site.key") == 0o600
    assert _mode(tmp_path / "keys" / "site.pub") == 0o644


@pytest.mark.integration  # draws a figure: seconds
def test_fit_report_writes_its_report_with_the_mode_of_an_ordinary_file(tmp_path, umask, capsys):
    from helpers import REPO_ROOT

    cal, report = tmp_path / "cal.json", tmp_path / "report.html"
    data = str(REPO_ROOT / RECORDING)
    assert main(["fit", data, "--method", "minmax", "--unit", "gauss", "--out", str(cal), "--report", str(report)]) == 0
    capsys.readouterr()
    assert _mode(cal) == 0o666 & ~umask == _mode(report)
