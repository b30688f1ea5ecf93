"""Progress of long work on stderr: a tqdm bar on a terminal, plain lines in a log file."""

from __future__ import annotations

import contextlib
import sys
import threading
import time

from tqdm import tqdm

#: Seconds between two progress lines when stderr is not a terminal.
LOG_INTERVAL_S = 5.0


class LogProgress:
    """What a tqdm bar offers the commands (``update``, ``total``, ``refresh``, ``write``,
    ``close``), written as a plain line at most every ``interval`` seconds: a log file gets
    ``cfm-fem: 20,000 / 46,051 nodes (43 %), 12 s, about 16 s left`` and no carriage
    returns. Nothing is
    written for work that ends within the first interval.
    """

    def __init__(self, total: int | None, unit: str, file, interval: float = LOG_INTERVAL_S):
        self.total, self.unit, self.file, self.interval = total, unit, file, interval
        self.n = 0
        self._start = self._last = time.monotonic()
        self._said = None  # (n, total) of the last line written
        self._lock = threading.Lock()  # chunks may finish on worker threads

    def _line(self, now: float) -> str:
        done = f"{self.n:,}"
        if self.total:
            done += f" / {self.total:,} {self.unit} ({100.0 * self.n / self.total:.0f} %)"
        else:
            done += f" {self.unit}"
        elapsed = now - self._start
        line = f"cfm-fem: {done}, {elapsed:.0f} s"
        if self.total and 0 < self.n < self.total:
            line += f", about {_left(elapsed / self.n * (self.total - self.n))} left"
        return line

    def update(self, n: int = 1) -> None:
        with self._lock:
            self.n += n
            now = time.monotonic()
            if now - self._last >= self.interval:
                self._last, self._said = now, (self.n, self.total)
                print(self._line(now), file=self.file, flush=True)

    def refresh(self) -> None:
        """Nothing to redraw: the next line shows a changed ``total``."""

    def write(self, text: str, file=None) -> None:
        print(text, file=self.file if file is None else file, flush=True)

    def close(self) -> None:
        with self._lock:
            # a series of lines ends with the final count, unless its last line gave it
            if self._said is not None and self._said != (self.n, self.total):
                print(self._line(time.monotonic()), file=self.file, flush=True)
            self._said = None


def _left(seconds: float) -> str:
    """A remaining time for a progress line: ``'40 s'``, ``'12 min'``, ``'3.5 h'``."""
    if seconds < 120:
        return f"{seconds:.0f} s"
    if seconds < 7200:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.1f} h" if seconds < 172800 else f"{seconds / 86400:.1f} days"


def _is_terminal(stream) -> bool:
    try:
        return stream.isatty()
    except (AttributeError, ValueError):
        return False


@contextlib.contextmanager
def progress_bar(total: int | None, unit: str, interval: float = LOG_INTERVAL_S):
    """A progress display on stderr; ``bar.update(n)`` advances it.

    A tqdm bar when stderr is a terminal, else `LogProgress` lines every ``interval`` s.
    """
    stream = getattr(sys.stderr, "wrapped", sys.stderr)  # the terminal, not `EscapingStream`
    if _is_terminal(stream):
        bar = tqdm(total=total, unit=unit, file=stream, dynamic_ncols=True, leave=False)
    else:
        bar = LogProgress(total, unit, stream, interval)
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


def announcer(bar, command: str):
    """The ``on_start`` callback the workflows call once their inputs are checked: it prints
    ``cfm-fem <command>: <line>`` on stderr above ``bar`` and sets the bar's total (and unit)
    to the work the workflow counts; a ``line`` None sets the total only."""

    def on_start(line: str | None, total: int | None = None, unit: str | None = None) -> None:
        if line is not None:
            bar.write(f"cfm-fem {command}: {line}", file=sys.stderr)
        if unit is not None:
            bar.unit = unit
        if total is not None:
            bar.total = total
            bar.refresh()

    return on_start
