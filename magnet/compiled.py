"""The compiled kernels (``magnet/_kernels.c``, docs/cost.md), with an error that says what to do when a checkout's
install predates them."""

from __future__ import annotations

try:
    from magnet import _kernels as kernels
except ImportError as exc:  # an editable install made before the C file existed, or a build that failed
    raise ImportError(
        "magnet's compiled kernels (magnet/_kernels.c) are not built in this checkout: run "
        "`pip install -e .` again (it builds them with the C compiler; Python's headers are needed)"
    ) from exc

__all__ = ["kernels"]
