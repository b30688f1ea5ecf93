"""Compile the adaptive sweep kernel in other processes while this one reads and fits the map.

On the first run after an install numba compiles every kernel a sweep uses. The harmonic fit's
kernel is needed at once, the sweep's only after the fit: `start` compiles the sweep's in
child processes (beside the fit's compilation) into numba's on-disk cache, and `wait`, called
just before the kernel's first use, waits for them, so that this one then loads the compiled
code. One child compiles the kernel for the argument types the sweep passes (`model_arrays`);
the other compiles its per-node statistics (`_node_estimates` and its callees) meanwhile,
which the first loads from the cache when it comes to them instead of compiling them itself.
On later runs `start` loads the cached kernel on a thread while the map is read.
"""

from __future__ import annotations

import contextlib
import subprocess
import sys
import threading

import numpy as np

from ... import _kernels

__all__ = ["start", "wait", "compile_now", "compile_estimates", "model_arrays"]

_pending: list = []


def start() -> bool:
    """Start compiling `harmonic_cv_sweep` in child processes unless numba's cache holds it;
    True if they were started. If the cache holds it, start loading it on a thread instead
    (about half a second of linking, beside the map's reading and meshing); False."""
    if _pending:
        return False
    if _kernels.kernels_cached(_kernels.harmonic_cv_sweep):
        loader = threading.Thread(target=_load_quietly, name="cfm_fem kernel loader")
        loader.start()
        _pending.append(loader)
        return False
    for name in ("compile_now", "compile_estimates"):
        code = f"from cfm_fem.workflows.sweep.compile_ahead import {name}; {name}()"
        _pending.append(
            subprocess.Popen(
                [sys.executable, "-c", code], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
            )
        )
    return True


def wait() -> None:
    """Wait for the processes or the thread `start` began, if any (the processes compile into
    the cache this process then reads; if they failed, the first call compiles here as it
    would have anyway)."""
    while _pending:
        task = _pending.pop()
        if isinstance(task, threading.Thread):
            task.join()
        else:
            task.wait()


def _load_quietly() -> None:
    """`compile_now` on the loader thread; a failure there is left to the kernel's own first
    call, which meets it again and reports it where the sweep runs."""
    with contextlib.suppress(Exception):  # not this thread's to report
        compile_now()


def model_arrays(coords, coef, degree, scale, reach_mm, gmat, exps) -> tuple:
    """The ``model`` argument of the harmonic kernels, every array C-contiguous and writable,
    so that its numba types are those `compile_now` compiles for."""

    def c(a, dtype):
        a = np.ascontiguousarray(a, dtype=dtype)
        return a if a.flags.writeable else a.copy()

    return (
        c(coords, np.float64), c(coef, np.float64), c(degree, np.int64), c(scale, np.float64),
        c(reach_mm, np.float64), c(gmat, np.float64), c(exps, np.int64),
    )  # fmt: skip


def compile_now() -> None:
    """Call `harmonic_cv_sweep` (and `harmonic_cv_buffers`) once on a one-node model: numba
    compiles them into its cache."""
    from ...models.harmonic_basis import field_basis, monomial_exponents
    from ...models.sweep import ADAPTIVE_PLAN

    gmat = field_basis()
    model = model_arrays(
        np.zeros((1, 3)), np.zeros((1, gmat.shape[2])), np.ones(1), np.ones(1), np.ones(1),
        gmat, monomial_exponents(),
    )  # fmt: skip
    nodes = np.zeros(1, dtype=np.int64)
    buffers = _kernels.harmonic_cv_buffers(2, 0.95, ADAPTIVE_PLAN)
    _kernels.harmonic_cv_sweep(
        nodes, nodes.copy(), model, np.ones(3), np.array([0.0, 0.01]), 0, 0.95, ADAPTIVE_PLAN,
        buffers,
    )  # fmt: skip


def compile_estimates(n_up: int = 2, p: float = 0.95) -> None:
    """Compile `harmonic_cv_sweep`'s per-node statistics (`_node_estimates`) into numba's cache
    for the argument types the kernel passes them (C-contiguous writable float64 arrays, int64
    counts, the work arrays of `_buffers` as tuples), without running them."""
    import numba

    from ..._kernels import harmonic_cv

    size = 4
    work = tuple(np.empty(size) for _ in range(4))
    x_win = (np.empty((2, 4, size), dtype=np.int64), np.empty((4, 2), dtype=np.int64))
    args = (
        np.int64(size), p, np.ones(n_up), np.empty(4), 1.0, np.empty((n_up, 4, size)),
        np.empty((4, size)), work, np.empty((4, 6)), np.empty((2, 4, size)), x_win,
        np.empty((1, n_up, 4, 6))[0], np.empty(2), np.int64(0), np.int64(3),
    )  # fmt: skip
    harmonic_cv._node_estimates.compile(tuple(numba.typeof(a) for a in args))
