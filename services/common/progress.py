"""A progress bar through the named steps of a slow command (``rich``), on stderr and only when it is a terminal:
pipes, files and CI logs get nothing from it.

    with steps(["reading samples", "fitting"]) as step:
        step("reading samples"); ...
        step("fitting"); ...
"""

from __future__ import annotations

import contextlib
import sys
from collections.abc import Callable, Iterator, Sequence


@contextlib.contextmanager
def steps(names: Sequence[str], enabled: bool | None = None) -> Iterator[Callable[[str], None]]:
    """A callable that marks the start of the next step (by its name); the bar goes when the block ends."""
    if enabled is None:
        enabled = sys.stderr.isatty()
    if not enabled:
        yield lambda name: None
        return
    from rich.console import Console
    from rich.progress import BarColumn, Progress, SpinnerColumn, TextColumn, TimeElapsedColumn

    progress = Progress(
        SpinnerColumn(),
        TextColumn("{task.description:<28}"),
        BarColumn(),
        TextColumn("{task.completed}/{task.total}"),
        TimeElapsedColumn(),
        console=Console(stderr=True, force_terminal=True),  # only reached on a terminal, or when asked
        transient=True,
    )
    task = progress.add_task(names[0] if names else "", total=len(names))
    begun: list[str] = []

    def step(name: str) -> None:
        if begun:
            progress.advance(task)
        begun.append(name)
        progress.update(task, description=name)

    with progress:
        yield step
