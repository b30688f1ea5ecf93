"""Numba options of every kernel, set once, and a check of numba's on-disk cache."""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

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


#: Beside numba's cache of the kernels: a digest of every kernel source it was written for.
DIGEST_FILE = "cfm_fem_kernels.sha256"


def drop_stale_cache(cache_dir, sources) -> bool:
    """Delete numba's cached kernels in ``cache_dir`` unless they were written for these
    ``sources`` (paths of the kernel modules); True if it deleted any.

    numba checks each cached kernel against its own source file only. A kernel that calls,
    and so compiles in, a function of another module keeps that function's old code when
    only the other module changes, as in a checkout updated in place (an upgrade by pip
    replaces every file). A digest of all the sources, kept in the cache folder, catches it:
    on a change the folder's kernels are compiled anew, once.
    """
    import numba

    h = hashlib.sha256(numba.__version__.encode())
    for path in sorted(Path(p) for p in sources):
        h.update(path.name.encode())
        h.update(path.read_bytes())
    digest = h.hexdigest()
    folder = Path(cache_dir)
    stamp = folder / DIGEST_FILE
    try:
        if stamp.read_text() == digest:
            return False
    except OSError:
        pass
    try:  # a first run: the folder numba is about to fill gets the digest too
        folder.mkdir(parents=True, exist_ok=True)
    except OSError:  # numba cannot write there either
        return False
    dropped = False
    for f in [*folder.glob("*.nbi"), *folder.glob("*.nbc")]:
        try:
            f.unlink()
            dropped = True
        except OSError:  # another process took it first
            pass
    try:
        tmp = folder / f"{DIGEST_FILE}.{os.getpid()}"
        tmp.write_text(digest)
        tmp.replace(stamp)
    except OSError:  # a read-only cache: numba does not write to it either
        pass
    return dropped


def drop_stale_kernels(kernel) -> bool:
    """`drop_stale_cache` for the folder where numba caches ``kernel`` (a dispatcher of this
    package; every module here shares that folder) and the package's sources. Finds the
    folder through numba's cache object (a private API): if that fails, False."""
    try:
        cache_dir = kernel._cache._cache_path
    except Exception:  # another numba version, or no cache
        return False
    return drop_stale_cache(cache_dir, Path(__file__).parent.glob("*.py"))


#: Reductions may be reassociated (vectorised); the order is fixed by the compiled code.
RJIT = dict(JIT, fastmath={"reassoc"})

#: Both: loops that compute values and sum them in one pass.
SJIT = dict(JIT, fastmath={"contract", "reassoc"})
