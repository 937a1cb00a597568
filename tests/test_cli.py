"""The command table: options before the command, one module imported per command, help for every command."""

import subprocess
import sys

import pytest

from services.cli import COMMANDS, main


def test_verbose_option_may_come_before_the_command(capsys):
    with pytest.raises(SystemExit) as stop:
        main(["-v", "fit", "--help"])
    assert stop.value.code == 0
    assert "--method" in capsys.readouterr().out


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_every_command_has_help(command, capsys):
    with pytest.raises(SystemExit) as stop:
        main([command, "--help"])
    assert stop.value.code == 0
    assert f"magnet {command}" in capsys.readouterr().out


@pytest.mark.integration  # a fresh interpreter (a process), so that nothing is imported already
def test_offline_commands_do_not_load_zenoh():
    code = (
        "import sys\nfrom services.cli import main\n"
        "try:\n    main(['fit', '--help'])\nexcept SystemExit:\n    pass\n"
        "print('zenoh' in sys.modules)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip().splitlines()[-1] == "False"
