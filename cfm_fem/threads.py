"""Run GIL-releasing work (nogil numba kernels, VTK writers) on a pool of threads."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numba
import numpy as np


def map_blocks(work, n: int, block: int) -> tuple:
    """``work(i0, i1)`` for each block [i0, i1) of range(n); each returns a tuple of arrays,
    and the blocks' arrays are concatenated in block order (axis 0).

    The blocks run on ``numba.get_num_threads()`` threads; ``work`` must release the GIL
    (a ``nogil`` kernel) for them to run at once. A numba ``prange`` would do the same, but a
    parallel function compiles its callees' code again on first use, which for the sweep's
    kernel tree costs ~7 s per fresh install.

    Parameters
    ----------
    work : callable (int, int) -> tuple of ndarray
    n : int
        Number of items.
    block : int
        Items per call: large enough that a call's overhead (~10 us) does not show.
    """
    bounds = [(i, min(i + block, n)) for i in range(0, n, block)] or [(0, 0)]  # n = 0: one
    # empty call, so the caller still gets results of the right shapes
    parts = map_threads(lambda b: work(*b), bounds)
    return tuple(np.concatenate(arrays) for arrays in zip(*parts, strict=True))


def map_threads(func, items, threads: int | None = None) -> list:
    """``[func(x) for x in items]``, on up to ``threads`` threads (default
    ``numba.get_num_threads()``); results in the order of ``items``. The first exception
    raised by ``func`` propagates once the running calls have ended."""
    items = list(items)
    threads = min(numba.get_num_threads() if threads is None else threads, len(items))
    if threads <= 1:
        return [func(x) for x in items]
    with ThreadPoolExecutor(threads) as pool:
        return list(pool.map(func, items))


def map_threads_widening(func, items, start: int, threads: int, widen) -> list:
    """`map_threads` on ``threads`` threads of which only ``start`` run ``func`` at once until
    the future ``widen`` is done (finished, failed or cancelled), then all of them.

    For work that shares the cores with another task for a while (the report's figures beside
    the map writers): the other task's core is taken up as soon as it is free.

    Parameters
    ----------
    func : callable
    items : iterable
    start : int
        Calls at once while ``widen`` runs (at least 1).
    threads : int
        Calls at once after it.
    widen : concurrent.futures.Future
    """
    import threading

    items = list(items)
    threads = min(threads, len(items))
    start = max(1, min(start, threads))
    if threads <= start:
        return map_threads(func, items, start)
    gate = threading.Semaphore(start)
    widen.add_done_callback(lambda _: gate.release(threads - start))

    def gated(x):
        with gate:
            return func(x)

    with ThreadPoolExecutor(threads) as pool:
        return list(pool.map(gated, items))


#: Share of the available memory one run may plan to use: the rest stays for the operating
#: system, the interpreter and the arrays an estimate leaves out.
MEMORY_SHARE = 0.8


def available_memory() -> int | None:
    """Bytes of memory available to a new allocation (Linux ``MemAvailable``; else the free
    physical pages), or None when the system does not say."""
    try:
        with open("/proc/meminfo", encoding="ascii") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        import os

        return int(os.sysconf("SC_AVPHYS_PAGES")) * int(os.sysconf("SC_PAGE_SIZE"))
    except (AttributeError, OSError, ValueError):
        return None


def gigabytes(nbytes: float) -> str:
    """``nbytes`` for a message: ``'3.2 GB'``, ``'5,000 GB'``, ``'120 MB'``."""
    if nbytes < 1e9:
        return f"{nbytes / 1e6:.3g} MB"
    gb = nbytes / 1e9
    return f"{gb:.3g} GB" if gb < 100 else f"{gb:,.0f} GB" if gb < 1e9 else f"{gb:.2g} GB"


def check_memory(what: str, count: float, per_unit: float, unit: str, fixed: float = 0.0,
                 available: int | None = None) -> None:  # fmt: skip
    """Refuse, before allocating, work whose arrays need more memory than is available.

    The estimate is ``fixed + count * per_unit`` bytes: the arrays the work holds at once.

    Parameters
    ----------
    what : str
        The work and the option that sizes it, for the message (``'sweep --trials'``).
    count : float
        The size the option asks for (trials, grid points, rows).
    per_unit : float
        Bytes per unit of ``count``.
    unit : str
        The unit's name, plural (``'trials'``).
    fixed : float, optional
        Bytes needed whatever ``count`` is.
    available : int, optional
        Bytes available; default `available_memory`.

    Raises
    ------
    CfmInputError
        The estimate exceeds `MEMORY_SHARE` of the available memory; the message gives both
        sizes and the largest ``count`` that fits.
    """
    from .errors import CfmInputError

    free = available_memory() if available is None else available
    nbytes = float(fixed) + float(count) * float(per_unit)
    if free is None or not nbytes > MEMORY_SHARE * free:
        return
    most = int(max(MEMORY_SHARE * free - fixed, 0.0) // per_unit) if per_unit > 0 else 0
    fits = f"at most about {most:,} {unit} fit" if most > 0 else f"not even one of the {unit} fits"
    raise CfmInputError(
        f"{what}: {count:,.0f} {unit} need about {gigabytes(nbytes)} of memory at once; "
        f"{gigabytes(free)} is available, of which this run plans on "
        f"{100 * MEMORY_SHARE:.0f} %: {fits}"
    )


#: Fewest seconds one core needs for one unit of Monte Carlo work (a field or position
#: evaluation at one point in one trial): no kernel of cfm_fem comes near it, so a run this
#: floor puts beyond `MAX_RUN_SECONDS` cannot end in any useful time.
MIN_SECONDS_PER_EVALUATION = 1e-9
#: Longest run a command starts: a week.
MAX_RUN_SECONDS = 7 * 86400.0


def _duration(seconds: float) -> str:
    """``seconds`` for a message: ``'3.2 days'``, ``'41 years'``."""
    days = seconds / 86400.0
    return f"{days:.2g} days" if days < 365 else f"{days / 365.25:,.3g} years"


def check_run_time(what: str, count: float, evaluations_per_unit: float, unit: str,
                   cores: int | None = None) -> None:  # fmt: skip
    """Refuse, before starting, Monte Carlo work that no machine ends within a week.

    The estimate is a lower bound: ``count * evaluations_per_unit`` evaluations at
    `MIN_SECONDS_PER_EVALUATION` each, spread over ``cores`` (default: numba's threads). Work
    within the bound starts and shows its progress with the time left.

    Parameters
    ----------
    what : str
        The work and the option that sizes it, for the message (``'tolerance --check'``).
    count : float
        The size the option asks for (trials).
    evaluations_per_unit : float
        Point evaluations per unit of ``count`` (scan points times passes).
    unit : str
        The unit's name, plural (``'trials'``).
    cores : int, optional

    Raises
    ------
    CfmInputError
        The lower bound exceeds `MAX_RUN_SECONDS`; the message gives it and the largest
        ``count`` within the bound.
    """
    from .errors import CfmInputError

    cores = max(int(numba.get_num_threads() if cores is None else cores), 1)
    per_unit = float(evaluations_per_unit) * MIN_SECONDS_PER_EVALUATION / cores
    seconds = float(count) * per_unit
    if not seconds > MAX_RUN_SECONDS:
        return
    most = int(MAX_RUN_SECONDS // per_unit) if per_unit > 0 else 0
    raise CfmInputError(
        f"{what}: {count:,.0f} {unit} of {evaluations_per_unit:,.0f} point evaluations each "
        f"would take at least {_duration(seconds)} on {cores} core(s), even at "
        f"{MIN_SECONDS_PER_EVALUATION * 1e9:g} ns an evaluation; at most about {most:,} {unit} "
        "end within a week"
    )


#: Seconds of work after which `paced` compares the run's pace with its size.
PACE_CHECK_SECONDS = 2.0


def paced(what: str, total: float, unit: str, progress=None, after: float = PACE_CHECK_SECONDS):
    """A progress callback that refuses the run once its pace shows it cannot end in a week.

    After ``after`` seconds of work the time per unit done so far, times ``total``, estimates
    the run's length; beyond `MAX_RUN_SECONDS` the next call raises. It checks once, so a
    later pass over the same units (counted again) costs nothing. Outputs are written after
    the work, so a refusal leaves nothing half-written.

    Parameters
    ----------
    what : str
        The work and the option that sizes it, for the message (``'--budget-trials'``).
    total : float
        Units the run will do.
    unit : str
        The unit's name, plural.
    progress : callable(int), optional
        Called with each count, after the check.
    after : float, s

    Returns
    -------
    callable(int)
    """
    import threading
    import time

    from .errors import CfmInputError

    state = {"done": 0, "start": time.monotonic(), "checked": False}
    lock = threading.Lock()

    def update(n: int = 1) -> None:
        with lock:
            state["done"] += n
            elapsed = time.monotonic() - state["start"]
            if not state["checked"] and elapsed >= after and state["done"] > 0:
                state["checked"] = True
                estimate = elapsed / state["done"] * float(total)
                if estimate > MAX_RUN_SECONDS:
                    most = int(MAX_RUN_SECONDS / elapsed * state["done"])
                    raise CfmInputError(
                        f"{what}: {float(total):,.0f} {unit} would take about "
                        f"{_duration(estimate)} at this run's pace ({state['done']:,} in "
                        f"{elapsed:.1f} s); at most about {most:,} {unit} end within a week"
                    )
        if progress is not None:
            progress(n)

    return update
