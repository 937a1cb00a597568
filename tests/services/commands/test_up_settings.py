"""``magnet up``'s settings are checked before anything starts: a bad option is one line on stderr and exit 2."""

import pytest

from services.cli import main
from services.commands.up import UpSettings


@pytest.mark.parametrize(
    "argv,message",
    [
        (("--rate", "0"), "--rate must be in (0, 100000] Hz, got 0.0"),
        (("--batch", "0"), "--batch must be 1..10000, got 0"),
        (("--location", "999,999"), "--location: "),
        (("--duration", "-1"), "--duration must be >= 0 seconds, got -1.0"),
        (("--devices", "0"), "--devices must be 1..10000, got 0"),
        (("--speedup", "0"), "--speedup must be in (0, 1000], got 0.0"),
        (("--interval", "0"), "--interval must be > 0 seconds"),
    ],
)
def test_bad_up_options_are_one_line_and_exit_2(capsys, tmp_path, monkeypatch, argv, message):
    monkeypatch.setenv("TMPDIR", str(tmp_path))
    monkeypatch.setattr("tempfile.tempdir", None)
    code = main(["up", *argv])
    out = capsys.readouterr()
    assert code == 2
    assert out.err.startswith("magnet up: error: ") and message in out.err, out.err
    assert len(out.err.strip().splitlines()) == 1 and "stopped unexpectedly" not in out.err
    assert list(tmp_path.iterdir()) == [], "nothing started, no temporary directory made"


def test_up_settings_from_the_defaults_are_valid():
    settings = UpSettings()
    assert settings.devices == 4 and settings.rate_hz == 50.0 and settings.location == "50.45,30.52"
