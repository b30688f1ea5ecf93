"""Numba options of every kernel, set once, and a check of numba's on-disk cache."""

from __future__ import annotations

from .._numba_cache import CACHE

#: One place for numba options. ``cache`` keeps compile time out of repeated runs.
JIT = dict(nogil=True, cache=CACHE, fastmath=False, error_model="numpy")


PJIT = dict(JIT, parallel=True)


#: Multiply-adds fused where the hardware has them: for loops whose results only need to agree
#: with their twins to rounding (same bits on a given machine, whatever the threads).
FJIT = dict(JIT, fastmath={"contract"})


def kernels_cached(*kernels) -> bool:
    """Whether numba's on-disk cache holds compiled code of each of ``kernels`` for this source.

    False means the next call compiles (tens of seconds for the sweep kernels); the commands
    say so before starting. Reads numba's cache index (a private API): if that fails, True.
    """
    try:
        return all(len(k._cache._cache_file._load_index()) > 0 for k in kernels)
    except Exception:  # another numba version: say nothing rather than something wrong
        return True


#: Reductions may be reassociated (vectorised); the order is fixed by the compiled code.
RJIT = dict(JIT, fastmath={"reassoc"})

#: Both: loops that compute values and sum them in one pass.
SJIT = dict(JIT, fastmath={"contract", "reassoc"})
