"""Option checks shared by the commands, run before any computation or output.

An output folder that cannot be made, or a seed numba cannot take, would otherwise surface as a
traceback (``FileExistsError``, numba's ``TypingError``) after the whole computation, sometimes
with part of the output written. Each command calls these first.
"""

from __future__ import annotations

import math
import os
from decimal import Decimal, InvalidOperation
from pathlib import Path

from ..errors import MAX_SEED, CfmInputError, check_seed
from . import option_type

__all__ = [
    "check_out_dir",
    "check_seed",
    "finite_float",
    "MAX_SEED",
    "MAX_TRIALS",
    "number_list",
    "trial_count_type",
]

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
    if not str(path).strip():  # Path("") is the current folder: outputs would land there
        raise CfmInputError(
            f"{option} is empty; expected the name of an output folder (created if missing)"
        )
    try:
        _check_out_dir(Path(path), path, option)
    except OSError as exc:  # a name too long, a loop of links, ...: what stat() met
        raise CfmInputError(
            f"{option} {str(path)!r} cannot be used: {exc.strerror or exc}; expected a folder "
            "name the file system takes"
        ) from None


def _check_out_dir(p: Path, path, option: str) -> None:
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


def _float(text: str) -> float:
    """``float(text)`` of plain ASCII number text: Python's float also takes digit separators
    (``1_000``) and other scripts' digits, which the file readers refuse, so options do too."""
    if not str(text).isascii() or "_" in str(text):
        raise ValueError(text)
    return float(text)


def finite_float(text: str) -> float:
    """argparse ``type=`` of every ``type=float`` option (`cfm_fem.cli._Parser` registers it):
    a finite number. ``nan``, ``inf`` and numbers beyond the float range (``1e999``) are
    refused, so no option carries a non-finite value into the numerics."""
    import argparse
    import math

    try:
        value = _float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a number; got {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be a finite number; got {text!r}")
    return value


finite_float.__name__ = "float"


def plain_int(text: str) -> int:
    """argparse ``type=`` of every ``type=int`` option (`cfm_fem.cli._Parser` registers it): a
    whole number in ASCII digits; Python's int also takes ``1_000`` and other scripts' digits."""
    import argparse

    if not str(text).isascii() or "_" in str(text):
        raise argparse.ArgumentTypeError(f"must be a whole number; got {text!r}")
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a whole number; got {text!r}") from None


plain_int.__name__ = "int"


def number_list(text: str, option: str, count=None, what: str = "numbers") -> list[float]:
    """The comma-separated finite numbers of an option (``--z 0,50``, ``--magnet-offset 1,0``).

    Parameters
    ----------
    text : str
        The option's value.
    option : str
        The option, for the message.
    count : int or tuple of int, optional
        The number (or the numbers) of values allowed; any number when None.
    what : str
        What the values are, for the message (``'numbers in mm'``).

    Raises
    ------
    CfmInputError
        A value that is not a number or not finite, or the wrong count; the message names
        ``option``.
    """
    counts = (count,) if isinstance(count, int) else count
    want = (
        f"{' or '.join(map(str, counts))} comma-separated finite {what}"
        if counts
        else f"comma-separated finite {what}"
    )
    try:
        values = [_float(v) for v in str(text).split(",")]
    except ValueError:
        values = None
    if values is None or (counts and len(values) not in counts):
        raise CfmInputError(f"{option} must be {want}; got {text!r}")
    bad = [v for v in values if not math.isfinite(v)]
    if bad:
        raise CfmInputError(f"{option} must be {want}; got {text!r} ({bad[0]:g} is not finite)")
    return values
