"""Progress bars for long work (tqdm on stderr, silent when stderr is not a terminal)."""

from __future__ import annotations

import contextlib
import sys

from tqdm import tqdm


@contextlib.contextmanager
def progress_bar(total: int, unit: str):
    """A tqdm bar; ``bar.update(n)`` advances it."""
    bar = tqdm(
        total=total, unit=unit, file=sys.stderr, disable=None, dynamic_ncols=True, leave=False
    )
    try:
        yield bar
    finally:
        bar.close()
