"""The ``magnet`` command: one subcommand per module, imported only when that subcommand runs.

Each command module exposes ``add_arguments(parser)`` and ``run(args) -> int``. A ``ValueError`` (bad input a user can
fix) or ``OSError`` (a file or device that cannot be opened) becomes one line on stderr and exit status 2; never a
traceback.
"""

from __future__ import annotations

import argparse
import gc
import importlib
import logging
import os
import re
import sys
from typing import Any, NoReturn

#: Before numpy loads: magnet's matrices are small (a fit's design matrix at most some 10,000 x 10, the compass's 3 x 3
#: a sample), too small for OpenBLAS's threads, which only spin after each call on the other core (``magnet fit`` of
#: 300 samples 218 -> 130 ms of CPU, and 10,000 rows add 4 ms, not 17; docs/cost.md). A user's own setting wins.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

#: subcommand -> (module, one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    "fit": ("services.commands.fit", "fit a calibration to a CSV of raw samples"),
    "heading": ("services.commands.heading", "apply a calibration to a CSV and print headings"),
    "bench": ("services.bench", "benchmarks that print figures (accuracy, fit, pipeline, motion, field)"),
    "sample": ("services.commands.sample", "read a sensor (or its emulator) and print CSV"),
    "selftest": ("services.commands.selftest", "run the HMC5883L self-test"),
    "edge": ("services.edge.service", "publish raw samples of one or many devices over Zenoh"),
    "calibrator": ("services.calibrator.service", "collect, fit, gate, store and serve calibrations over Zenoh"),
    "compass": ("services.compass.service", "apply calibrations and publish headings over Zenoh"),
    "router": ("services.router", "run a Zenoh router"),
    "get": ("services.commands.remote", "query a device's calibration (or its history), a status, or the fleet"),
    "watch": ("services.commands.remote", "print headings as they are published"),
    "calibrate": ("services.commands.remote", "start, follow, commit or abort a calibration session"),
    "keys": ("services.commands.keys", "an Ed25519 key pair for signing calibrations (NAME.key, NAME.pub)"),
    "certs": ("services.commands.certs", "a site CA, certificates per role and the router/client configs (TLS, ACL)"),
    "up": ("services.commands.up", "the local pipeline: emulated devices, calibrator and compass, with a live view"),
    "dashboard": ("services.dashboard.service", "serve a live web page of the fleet (and calibration control)"),
    "report": ("services.commands.report", "draw a calibration report (HTML or PNG) from samples and a calibration"),
    "export": ("services.commands.export", "write a calibration as ArduPilot or PX4 parameters (a parameter file)"),
    "db": ("services.commands.db", "copy a site's calibrations between SQLite and PostgreSQL, or check them all"),
    "record": (
        "services.commands.record",
        "record raw, headings, calibrations and alerts as a ROS 2 bag (MCAP)",
    ),
}


def _handler(module, specific: str, generic: str):
    """The module's function named ``specific`` (e.g. ``run_get``), else the one named ``generic`` (``run``)."""
    function = getattr(module, specific, None)
    return function if function is not None else getattr(module, generic)


def _chosen_command(argv: list[str]) -> str | None:
    """The first word of argv that names a command (options such as -v may come before it)."""
    return next((word for word in argv if word in COMMANDS), None)


def _only_the_chosen(argv: list[str], chosen: str | None) -> bool:
    """Whether argparse will hand ``argv`` to the chosen command's parser without showing the others: nothing but
    -v / --verbose before the command's word (no -h, no other word the top-level parser would refuse listing the
    commands). Then only that command's parser is built: the same parse, without building a parser per command
    (milliseconds each time ``main`` runs, as the tests run it)."""
    if chosen is None:
        return False
    before = argv[: argv.index(chosen)]
    return all(re.fullmatch(r"-v+|--verbose", word) for word in before)


#: a value that starts with a minus and a digit, alone or as a list (``-33.87,151.21``, ``-25,40,12``, ``-1e-3``): a
#: value, not an option (argparse knows only single numbers, so ``--location -33.87,151.21`` was refused)
NEGATIVE_VALUE = re.compile(r"^-\.?\d[\d.eE+-]*(,[-+]?\.?\d[\d.eE+-]*)*$")


class OneLineParser(argparse.ArgumentParser):
    """An argument parser whose refusal is the one line that matters (``magnet fit: error: argument --method: ...``)
    and where to read more, not a page of usage before it: the usage is what ``--help`` is for. Exit status 2, as
    argparse's own refusal. A word like ``-33.87,151.21`` is a value (``NEGATIVE_VALUE``); the commands' parsers
    inherit this class (``add_subparsers``)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._negative_number_matcher = NEGATIVE_VALUE

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message} (see '{self.prog} --help')\n")


def build_parser(argv: list[str]) -> argparse.ArgumentParser:
    parser = OneLineParser(prog="magnet", description="Magnetometer calibration and compass service.")
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more logging (-vv for debug)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    chosen = _chosen_command(argv)
    only = _only_the_chosen(argv, chosen)
    for name, (module_name, help_text) in COMMANDS.items():
        if only and name != chosen:
            continue
        child = sub.add_parser(name, help=help_text, description=help_text)
        if name == chosen:  # only the chosen command's module is imported, so `magnet fit` never loads zenoh
            _handler(importlib.import_module(module_name), f"add_{name}_arguments", "add_arguments")(child)
        child.set_defaults(_module=module_name, _name=name)
    return parser


#: the long-running processes, which receive messages of MBs from the network and must give that memory back (a
#: one-shot command such as ``fit`` keeps glibc's defaults, which suit numpy's large temporary arrays)
SERVICES = frozenset({"edge", "calibrator", "compass", "router", "dashboard", "up"})
#: the one-shot commands that work through a file's arrays: glibc told to keep freed memory for the next array (not
#: to give the heap's top back and fault it in again: services/common/allocator.py, ``keep_freed_memory``). Run as a
#: process's own command, Python's cycle collector is off while their modules load (numpy's, vqf's, magnet's: some
#: 100,000 objects that live until the process ends, which each collection walked again) and those objects are
#: frozen out of every later collection (``gc.freeze``): ``magnet heading`` of 60,000 samples 1.800e9 -> 1.753e9
#: instructions, CPU 0.220 -> 0.204 s (docs/cost.md). Not when ``main`` is called with its arguments (the tests):
#: there the objects alive are not the process's for good.
ARRAY_COMMANDS = frozenset({"fit", "heading"})


def main(argv: list[str] | None = None) -> int:
    own_process = argv is None  # the process's own command line, not a call from a test or another program
    argv = list(sys.argv[1:] if argv is None else argv)
    one_shot = _chosen_command(argv) in ARRAY_COMMANDS
    if one_shot:
        from services.common.allocator import keep_freed_memory  # ctypes, which numpy loads anyway

        keep_freed_memory()
    if one_shot and own_process:
        gc.disable()  # no collections while the command's modules load: see ARRAY_COMMANDS
    try:
        args = build_parser(argv).parse_args(argv)
    finally:
        if one_shot and own_process:
            gc.freeze()
            gc.enable()
    level = [logging.WARNING, logging.INFO, logging.DEBUG][min(args.verbose, 2)]
    logging.basicConfig(level=level, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    if args._name in SERVICES:  # before any Zenoh thread allocates: see services/common/allocator.py
        from services.common.allocator import give_back_freed_memory  # ctypes: only where a service starts

        give_back_freed_memory()
    module = importlib.import_module(args._module)
    runner = _handler(module, f"run_{args._name}", "run")
    try:
        return int(runner(args) or 0)
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:  # the reader went away (`magnet heading ... | head`): stop quietly, as Unix tools do
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    except (ValueError, OSError) as exc:
        print(f"magnet {args._name}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
