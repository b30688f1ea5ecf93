"""Command line: ``cfm-fem <command> ...``.

Parsing, progress, messages and exit codes live here only.

Each subcommand is a module in this package with ``NAME``, ``HELP``, ``add_args(parser)`` and
``run(args) -> int``; add it to ``_COMMANDS`` below. A command module imports the numerics
(numba, scipy, pyvista, ...) inside the functions that run, not at the top: ``--help`` and
option errors then answer in ~0.2 s instead of ~1 s.
"""

from __future__ import annotations

import argparse
import atexit
import contextlib
import errno
import importlib
import os
import re
import shlex
import shutil
import sys
import threading
import warnings
from pathlib import Path

from .. import __version__
from ..errors import CfmInputError, CfmInputWarning, interrupted, printable

__all__ = ["main", "run"]

#: Subcommand modules, in the order ``--help`` lists them.
_COMMANDS = [
    "sweep",
    "design",
    "kinematics",
    "tolerance",
    "coupled",
    "quality",
    "fig4",
    "compare",
    "diagnose",
    "synth",
]

EXIT_OK = 0
EXIT_FAILURE = 1
EXIT_BAD_INPUT = 2


class _Parser(argparse.ArgumentParser):
    """argparse that raises instead of exiting, so ``main`` keeps control of the exit code.

    Every ``type=float`` option takes finite numbers only (`cfm_fem.cli._checks.finite_float`):
    ``--reversal-um inf`` or ``--drift-um-per-s nan`` stop at the option, naming it.

    A value that starts with a minus sign and a digit (``--z -100,0,100``, ``--up -10:50:10``)
    is a value, not an option: argparse's own test takes only a plain number such as ``-100``
    for one, and answered "expected one argument". No option of cfm-fem looks like a number.
    """

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self._negative_number_matcher = re.compile(r"^-\.?\d")
        from ._checks import finite_float, plain_int

        self.register("type", float, finite_float)  # every type=float option: finite only
        self.register("type", int, plain_int)  # every type=int option: ASCII digits only

    def error(self, message):
        # ``main`` prints "cfm-fem: error: " before it: a subcommand's parser adds only its name
        # ("sweep: argument --trials: ..."), the top one nothing (it printed "cfm-fem: error:
        # cfm-fem: unrecognized arguments: -x")
        _, _, command = self.prog.partition(" ")
        raise CfmInputError(f"{command}: {message}" if command else message)


def option_type(func, option: str):
    """``func`` as an argparse ``type=``, keeping the message of its `CfmInputError`.

    argparse turns a ValueError (CfmInputError is one) from ``type=`` into its own "invalid
    <func> value"; only ArgumentTypeError keeps the text. argparse prefixes "argument
    <option>: ", so a leading "<option> " of the message is dropped."""

    def convert(text):
        try:
            return func(text)
        except CfmInputError as exc:
            msg = str(exc)
            raise argparse.ArgumentTypeError(msg.removeprefix(option + " ")) from None

    convert.__name__ = func.__name__
    return convert


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="cfm-fem",
        description="Field-mapping uncertainty of Hall-probe benches from FEM field maps.",
    )
    parser.add_argument("--version", action="version", version=f"cfm-fem {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    for name in _COMMANDS:
        mod = importlib.import_module(f".{name}", __name__)
        p = sub.add_parser(mod.NAME, help=mod.HELP, description=mod.__doc__)
        mod.add_args(p)
        p.set_defaults(_run=mod.run)
    return parser


def _show_warning(message, category, filename, lineno, file=None, line=None):
    from tqdm import tqdm  # above a progress bar that is running, not into its line

    tqdm.write(f"warning: {message}", file=sys.stderr)


class EscapingStream:
    """A text stream that writes through `cfm_fem.errors.printable`: column names, tokens
    and file names a run prints (notes, warnings, summaries) cannot reach the terminal as
    control characters or ANSI escapes. Line feeds, tabs and carriage returns pass. The
    stream wrapped is ``wrapped`` (progress bars draw on it)."""

    def __init__(self, stream):
        self.wrapped = stream

    def write(self, text):
        return self.wrapped.write(printable(text).replace("\\x0d", "\r"))

    def __getattr__(self, name):
        return getattr(self.wrapped, name)


def _disk_full(exc) -> OSError | None:
    """The "no space left" (or quota) error in ``exc``'s chain, if there is one."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, OSError) and exc.errno in (errno.ENOSPC, errno.EDQUOT):
            return exc
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return None


def _entries(out) -> set | None:
    """Names in the output folder ``out`` before a run; None if it does not exist (yet)."""
    try:
        return {p.name for p in Path(out).iterdir()} if out is not None else None
    except OSError:
        return None


def _remove_new(out, before) -> int:
    """Remove what a run added to ``out`` (all of it if the run made the folder); bytes freed."""
    if out is None or not Path(out).is_dir():
        return 0
    new = [p for p in Path(out).iterdir() if before is None or p.name not in before]
    size = sum(f.stat().st_size for p in new for f in ([p] if p.is_file() else p.rglob("*"))
               if f.is_file() and not f.is_symlink())  # fmt: skip
    for p in new:
        if p.is_dir() and not p.is_symlink():
            shutil.rmtree(p, ignore_errors=True)
        else:
            with contextlib.suppress(OSError):
                p.unlink()
    if before is None:
        with contextlib.suppress(OSError):
            Path(out).rmdir()
    return size


def _disk_full_message(full: OSError, out, freed: int) -> str:
    from ..io._atomic import mb

    where = Path(full.filename).parent if full.filename else Path(out or ".")
    existing = next((p for p in (where, *where.parents) if p.exists()), Path("."))
    try:
        free = mb(shutil.disk_usage(existing).free)
    except OSError:
        free = "an unknown amount"
    return (
        f"{where}: the disk is full ({full.strerror or full}); the {mb(freed)} this run had "
        f"written there were removed, and it needs more than the {free} now free: free some "
        "space or write to another folder"
    )


def main(argv=None) -> int:
    """Run the command line with ``argv`` (default ``sys.argv[1:]``); return the exit code.

    0 on success, 2 on bad input (message on stderr, no traceback, no output written), 1 when
    interrupted.
    """
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser()
    old_show = warnings.showwarning
    warnings.showwarning = _show_warning
    streams = sys.stdout, sys.stderr
    sys.stdout, sys.stderr = EscapingStream(sys.stdout), EscapingStream(sys.stderr)
    out = before = None
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("always", CfmInputWarning)
            warnings.showwarning = _show_warning
            args = parser.parse_args(argv)
            if not getattr(args, "command", None):
                parser.print_help()
                return EXIT_BAD_INPUT
            args.command_line = "cfm-fem " + " ".join(shlex.quote(a) for a in argv)
            out = getattr(args, "out", None)
            before = _entries(out)
            from .._numba_cache import NOTE

            if NOTE:
                print(f"cfm-fem: note: {NOTE}", file=sys.stderr)
            return int(args._run(args) or EXIT_OK)
    except CfmInputError as exc:
        print(f"cfm-fem: error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except (KeyboardInterrupt, SystemError) as exc:
        if not interrupted(exc):
            raise
        print(
            "cfm-fem: interrupted; completed outputs are kept, nothing half-written",
            file=sys.stderr,
        )
        return EXIT_FAILURE
    except Exception as exc:  # a full disk, wherever it is met: clean up and say so
        full = _disk_full(exc)
        if full is None:
            raise
        freed = _remove_new(out, before)
        print(f"cfm-fem: error: {_disk_full_message(full, out, freed)}", file=sys.stderr)
        return EXIT_BAD_INPUT
    finally:
        warnings.showwarning = old_show
        sys.stdout, sys.stderr = streams


def run() -> None:
    """The ``cfm-fem`` program: `main` with ``sys.argv``, then the process ends with its code.

    When the command is done and no other thread of the process runs, the exit handlers run,
    the standard streams are flushed and the process ends there, without taking its modules
    apart one by one (about half a second once numba, scipy and matplotlib are loaded). An
    exception leaves by the interpreter's own exit, with its traceback.
    """
    code = main()
    if threading.active_count() == 1:
        atexit._run_exitfuncs()
        for stream in (sys.stdout, sys.stderr):
            with contextlib.suppress(Exception):  # a closed pipe: nothing more to say there
                stream.flush()
        os._exit(code)
    sys.exit(code)


if __name__ == "__main__":  # pragma: no cover
    run()
