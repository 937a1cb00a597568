"""Shared test fixtures: where the repository's recordings live (``data/``), and processes stopped after a test."""

from __future__ import annotations

import gc
from collections.abc import Iterator
from pathlib import Path

import pytest
from helpers import Processes
from postgres_server import PostgresServer, start_postgres

REPO_ROOT = Path(__file__).resolve().parents[1]
DATA_DIR = REPO_ROOT / "data"


@pytest.hookimpl(wrapper=True)
def pytest_collection(session: pytest.Session) -> Iterator[None]:
    """Collecting imports every module the tests use and builds the tests: objects that live to the end of the run.
    The garbage collector would walk all of them again at each of its full collections (a dozen while collecting,
    then one every few seconds): it rests while they are made, and afterwards they are moved out of its sight
    (``gc.freeze``), so its collections see only what the tests themselves make."""
    gc.disable()
    try:
        return (yield)
    finally:
        gc.enable()
        gc.collect()
        gc.freeze()


#: packages that pytest would rewrite only because they ship a pytest plugin (every module of such a distribution is
#: marked): their own internal asserts gain nothing from rewritten messages, and rewriting parses and recompiles them
#: from source at every run (about 1.3 s of the unit suite's collection where bytecode is not written). Their plugin
#: modules (``_hypothesis_pytestplugin``, ``anyio.pytest_plugin`` is tiny) stay as pytest loads them; the tests' own
#: asserts are rewritten as before.
LIBRARIES_NOT_REWRITTEN = ("hypothesis", "anyio")


def pytest_configure(config: pytest.Config) -> None:
    """Runs before any test module is imported (so before hypothesis or anyio is): unmarks those libraries."""
    marked = getattr(config.pluginmanager.rewrite_hook, "_must_rewrite", None)
    if isinstance(marked, set):  # pytest's rewrite hook (absent with --assert=plain): a private set, hence the check
        marked.difference_update(LIBRARIES_NOT_REWRITTEN)


@pytest.fixture(scope="session")
def datasets_dir() -> Path:
    if not DATA_DIR.is_dir():
        pytest.fail(f"recordings not found at {DATA_DIR}: the repository's data/ folder is missing")
    return DATA_DIR


@pytest.fixture
def procs(tmp_path: Path) -> Iterator[Processes]:
    """``magnet`` processes for one test (logs in tmp_path), all stopped when the test ends."""
    processes = Processes(tmp_path)
    yield processes
    processes.stop_all()


@pytest.fixture(scope="session")
def postgres() -> Iterator[PostgresServer]:
    """A PostgreSQL server started once for the session (``postgres_server``): initdb, loopback port, stopped at
    the end. Tests that use it are marked integration."""
    yield from start_postgres()


@pytest.fixture
def postgres_url(postgres: PostgresServer) -> str:
    """A new, empty database on the session's server: its URL."""
    return postgres.new_database()
