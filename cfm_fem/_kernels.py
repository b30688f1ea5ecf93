"""All numba code of cfm_fem: raw kernels with no I/O and no checks.

Callers validate inputs. Every kernel has a plain-numpy twin (in the module that calls it or in the
tests) that the tests compare it with. Numba options are set once, here.
"""

from __future__ import annotations

import numba as nb
import numpy as np

#: One place for numba options. ``cache`` keeps compile time out of repeated runs.
JIT = dict(nopython=True, nogil=True, cache=True, fastmath=False, error_model="numpy")
PJIT = dict(JIT, parallel=True)
