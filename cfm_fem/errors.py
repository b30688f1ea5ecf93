"""The one exception family of cfm_fem and the warning category for recoverable input issues."""

from __future__ import annotations

import re

__all__ = [
    "CfmInputError",
    "CfmInputWarning",
    "interrupted",
    "location",
    "MAX_SEED",
    "check_seed",
    "one_line",
    "printable",
    "shown",
]

#: Control characters (C0 but tab and line feed, DEL, C1) and the bidirectional overrides that
#: reorder what a terminal shows: file contents and names quoted in messages escape them.
_CONTROLS = re.compile("[\x00-\x08\x0b-\x1f\x7f-\x9f\u202a-\u202e\u2066-\u2069]")


def printable(text) -> str:
    """``text`` with control characters and ANSI escape sequences made visible (``\\x1b``),
    so that what a file holds cannot move the cursor, recolour or clear a terminal."""
    return _CONTROLS.sub(lambda m: f"\\x{ord(m[0]):02x}" if ord(m[0]) < 256
                         else f"\\u{ord(m[0]):04x}", str(text))  # fmt: skip


def one_line(text) -> str:
    """``text`` made `printable` and kept on one line: line feeds, carriage returns and tabs
    (in a file name, say) written as ``\\n``, ``\\r``, ``\\t``. Every `CfmInputError` message
    is one line, so a message stays one line on a terminal and in a log."""
    return printable(text).replace("\n", "\\n").replace("\r", "\\r").replace("\t", "\\t")


def shown(token: str, limit: int = 60) -> str:
    """A token from a file, quoted for a message: escaped (`printable`) and cut to ``limit``
    characters."""
    s = printable(token)
    return f"'{s[:limit]}...'" if len(s) > limit else f"'{s}'"


#: Seeds go to numpy's SeedSequence and to numba kernels as int64: [0, MAX_SEED).
MAX_SEED = 2**63


def location(file=None, line=None) -> str:
    """Format ``file:line`` (either part optional) for messages."""
    if file is None:
        return "" if line is None else f"line {line}"
    if not str(file).strip() or str(file) != str(file).strip():  # blanks a reader cannot see
        file = repr(str(file))
    return f"{file}" if line is None else f"{file}:{line}"


class CfmInputError(ValueError):
    """Bad input: a file, an argument or a bench description the tool cannot use.

    The message reads ``"<file>:<line>: <what>"``; ``what`` names the column (if any) and what was
    expected, for example ``"column 'Bx' must be a number; found 'abc'"``.

    Parameters
    ----------
    what : str
        What is wrong and what was expected.
    file : str or path-like, optional
        The file the problem is in.
    line : int, optional
        1-based line number in ``file``.
    column : str, optional
        Column name, kept as an attribute for programs and tests (name it in ``what`` too).
    """

    def __init__(self, what: str, *, file=None, line: int | None = None, column: str | None = None):
        what = one_line(what)
        self.what = what
        self.file = None if file is None else one_line(file)
        self.line = line
        self.column = column
        loc = location(self.file, line)
        super().__init__(f"{loc}: {what}" if loc else what)


class CfmInputWarning(UserWarning):
    """Input that is usable but suspicious (wrong node count in a header, placeholder rows, ...)."""


def check_seed(seed, option: str = "--seed") -> None:
    """Check that ``seed`` is an integer in [0, MAX_SEED) (numba kernels take it as int64).

    The one seed rule of the command line (`cfm_fem.cli._checks`) and of the Python API
    (`cfm_fem.workflows.sweep.problem`): both give the same message.

    Parameters
    ----------
    seed : int
    option : str
        The option (or parameter) that gave the seed, for the message.

    Raises
    ------
    CfmInputError
        The seed is not an integer (a bool, a float, a string), is negative or is too large.
    """
    import numbers

    if isinstance(seed, bool) or not isinstance(seed, numbers.Integral):
        raise CfmInputError(f"{option} must be an integer in [0, 2**63); got {seed!r}")
    if not 0 <= int(seed) < MAX_SEED:
        raise CfmInputError(f"{option} must be in [0, 2**63); got {seed}")


def interrupted(exc) -> bool:
    """True for Ctrl-C, also when numba reports it as a SystemError raised from it."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, KeyboardInterrupt):
            return True
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return False
