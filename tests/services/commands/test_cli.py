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


@pytest.mark.parametrize(
    "argv, says",
    [
        (["fit", "--method", "bogus", "x.csv"], "argument --method: invalid choice: 'bogus'"),
        (["fit"], "the following arguments are required: FILE.csv"),
        (["bogus"], "argument COMMAND: invalid choice: 'bogus'"),
    ],
)
def test_a_wrong_option_value_is_one_line_not_a_page_of_usage(argv, says, capsys):
    with pytest.raises(SystemExit) as stop:
        main(argv)
    assert stop.value.code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and says in err and "usage:" not in err
    assert "--help" in err  # where to read the usage


@pytest.mark.parametrize("command, keeps", [("fit", True), ("heading", True), ("export", False), ("keys", False)])
def test_the_array_commands_tell_the_allocator_to_keep_freed_memory(command, keeps, monkeypatch):
    import services.common.allocator as allocator

    calls = []
    monkeypatch.setattr(allocator, "keep_freed_memory", lambda: calls.append(command) or True)
    with pytest.raises(SystemExit):
        main([command, "--help"])
    assert calls == ([command] if keeps else [])


def test_keep_freed_memory_is_set_on_glibc_and_nothing_elsewhere():
    import platform

    from services.common.allocator import keep_freed_memory

    assert keep_freed_memory() == (platform.libc_ver()[0] == "glibc")


@pytest.mark.parametrize("command, settles", [("heading", True), ("fit", True), ("export", False)])
def test_an_array_command_run_as_the_process_loads_without_collections_then_freezes(command, settles, monkeypatch):
    import gc

    import services.cli as cli

    seen = []
    real_build = cli.build_parser

    def build(argv):  # what the collector is doing while the command's module loads
        seen.append(gc.isenabled())
        return real_build(argv)

    monkeypatch.setattr(cli, "build_parser", build)
    monkeypatch.setattr(sys, "argv", ["magnet", command, "--help"])
    gc.unfreeze()
    try:
        with pytest.raises(SystemExit):
            main()  # the process's own command line
        assert seen == [not settles] and gc.isenabled()
        assert (gc.get_freeze_count() > 0) == settles
        gc.unfreeze()
        with pytest.raises(SystemExit):
            main([command, "--help"])  # called with its arguments (as here): the collector left alone
        assert seen[-1] and gc.get_freeze_count() == 0
    finally:
        gc.unfreeze()
        gc.enable()
