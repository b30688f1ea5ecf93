"""Option checks shared by the commands, run before any computation or output.

An output folder that cannot be made, or a seed numba cannot take, would otherwise surface as a
traceback (``FileExistsError``, numba's ``TypingError``) after the whole computation, sometimes
with part of the output written. Each command calls these first.
"""

from __future__ import annotations

import os
from decimal import Decimal, InvalidOperation
from pathlib import Path

from ..errors import MAX_SEED, CfmInputError, check_seed
from . import option_type

__all__ = ["check_out_dir", "check_seed", "MAX_SEED", "MAX_TRIALS", "trial_count_type"]

#: Largest trial count taken (int64, as the kernels count trials); far beyond any run's time.
MAX_TRIALS = 2**63 - 1


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


def trial_count_type(option: str = "--trials"):
    """argparse ``type=`` of a trial count: a whole number, also written with an exponent.

    ``1e6`` and ``2.5e5`` are whole numbers as the help texts write them ("default 1e6");
    ``1.5`` is refused. The range (at least 20, ...) is each command's own check.
    """

    def trial_count(text: str) -> int:
        try:
            value = Decimal(text.strip())  # exact: 2.5e5 is 250000, 1.0000001e6 is not whole
        except InvalidOperation:
            value = None
        if value is None or not value.is_finite() or value != value.to_integral_value():
            raise CfmInputError(
                f"{option} must be a whole number of trials, such as 2000 or 1e6; got {text!r}"
            )
        if abs(value) > MAX_TRIALS:
            raise CfmInputError(f"{option} must be at most {MAX_TRIALS:.3g}; got {text!r}")
        return int(value)

    return option_type(trial_count, option)
