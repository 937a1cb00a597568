"""services.cli: OpenBLAS's threads limited to one before numpy loads, unless the user chose (docs/cost.md)."""

from __future__ import annotations

import importlib
import os

import pytest

import services.cli


@pytest.mark.parametrize(("given", "expected"), [(None, "1"), ("3", "3")])
def test_the_command_line_keeps_openblas_to_one_thread_unless_told(
    monkeypatch: pytest.MonkeyPatch, given: str | None, expected: str
) -> None:
    if given is None:
        monkeypatch.delenv("OPENBLAS_NUM_THREADS", raising=False)
    else:
        monkeypatch.setenv("OPENBLAS_NUM_THREADS", given)
    importlib.reload(services.cli)
    assert os.environ["OPENBLAS_NUM_THREADS"] == expected
