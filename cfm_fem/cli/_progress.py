"""Progress bars for long work (tqdm on stderr, silent when stderr is not a terminal)."""

from __future__ import annotations

import contextlib
import sys

from tqdm import tqdm


@contextlib.contextmanager
def progress_bar(total: int, unit: str):
    """A tqdm bar; ``bar.update(n)`` advances it."""
    stream = getattr(sys.stderr, "wrapped", sys.stderr)  # the terminal, not `EscapingStream`
    bar = tqdm(total=total, unit=unit, file=stream, disable=None, dynamic_ncols=True, leave=False)
    try:
        yield bar
    finally:
        bar.close()


def note_first_compile(*kernels) -> None:
    """Say, before a bar that would sit at 0 %, that numba compiles the kernels this time."""
    from .._kernels import kernels_cached

    if not kernels_cached(*kernels):
        print(
            "cfm-fem: compiling the numerical kernels for this machine (first run after an "
            "install or upgrade: some 30 s more); later runs load them from numba's cache",
            file=sys.stderr,
        )
