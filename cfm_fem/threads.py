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
