"""Option checks shared by the commands, run before any computation or output.

An output folder that cannot be made, or a seed numba cannot take, used to surface as a traceback
(``FileExistsError``, numba's ``TypingError``) after the whole computation, sometimes with part of
the output written. Each command calls these first instead.
"""

from __future__ import annotations

import os
from pathlib import Path

from ..errors import MAX_SEED, CfmInputError, check_seed

__all__ = ["check_out_dir", "check_seed", "MAX_SEED"]


def check_out_dir(path, option: str = "--out") -> None:
    """Check that ``path`` is a folder or can be created as one; create nothing.

    Parameters
    ----------
    path : path-like
        The output folder.
    option : str
        The option that named it, for the message.

    Raises
    ------
    CfmInputError
        ``path`` (or a parent) is an existing file, or the nearest existing parent is not
        writable.
    """
    p = Path(path)
    if p.exists() and not p.is_dir():
        raise CfmInputError(
            f"{option} {str(path)!r} is an existing file; expected a folder (created if missing)"
        )
    parent = p
    while not parent.exists():
        if parent.parent == parent:
            return  # pragma: no cover - the root always exists
        parent = parent.parent
    if not parent.is_dir():
        raise CfmInputError(
            f"{option} {str(path)!r} cannot be created: {str(parent)!r} is a file, not a folder"
        )
    if not os.access(parent, os.W_OK | os.X_OK):
        raise CfmInputError(f"{option} {str(path)!r}: no permission to write in {str(parent)!r}")
