"""Opening input files: regular files only, never a FIFO, socket or device.

A FIFO given as a field map or a bench file would block the reader forever (nothing writes to
it) and a device such as ``/dev/zero`` never ends; both are refused before a byte is read.
"""

from __future__ import annotations

import os
import stat

from ..errors import CfmInputError

__all__ = ["open_regular", "check_regular"]

_KINDS = (
    (stat.S_ISDIR, "a folder"),
    (stat.S_ISFIFO, "a FIFO (named pipe)"),
    (stat.S_ISSOCK, "a socket"),
    (stat.S_ISCHR, "a character device"),
    (stat.S_ISBLK, "a block device"),
)


def _kind(mode: int) -> str:
    return next((name for test, name in _KINDS if test(mode)), "not a regular file")


def open_regular(path, what: str = "a file", reading: str = "the file"):
    """Open ``path`` for reading in binary mode if it is a regular file (links followed).

    The file is opened without blocking (a FIFO would wait for a writer) and checked on the
    open descriptor, so what is checked is what is read.

    Parameters
    ----------
    path : path-like
    what : str
        What the file should be, for the message (``"a field map"``).
    reading : str
        How the message names the file in "cannot read ...".

    Returns
    -------
    io.BufferedReader

    Raises
    ------
    CfmInputError
        The file cannot be opened, or it is a folder, a FIFO, a socket or a device.
    """
    if os.fspath(path) in ("", b""):
        raise CfmInputError(f"an empty file name; expected {what}", file=path)
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
    except OSError as exc:
        raise CfmInputError(f"cannot read {reading}: {exc.strerror or exc}", file=path) from None
    try:
        mode = os.fstat(fd).st_mode
        if not stat.S_ISREG(mode):
            raise CfmInputError(f"this is {_kind(mode)}; expected {what}", file=path)
        return os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise


def check_regular(path, what: str = "a file") -> None:
    """Refuse ``path`` unless it is a regular file (for readers that open it themselves, such
    as meshio's); see `open_regular`."""
    open_regular(path, what).close()
