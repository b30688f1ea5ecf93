"""CPU time numba spends compiling the README sweep's kernels, per function, on an empty cache.

    python scripts/bench_compile.py            # harmonic_cv_sweep (the adaptive sweep's kernel)
    python scripts/bench_compile.py fit        # harmonic_fit_block (the harmonic fit's kernel)
    python scripts/bench_compile.py both --top 40

Each run compiles into a fresh temporary numba cache (set before numba is imported), the way
the first run after an install does: ``cv`` calls the adaptive kernel on a one-node model as
`cfm_fem.workflows.sweep.compile_ahead` does in a child process, ``fit`` fits a small map.
It prints the process's CPU time for the whole compilation, then per compiled function (numba's
own helpers included) the CPU time spent in it alone (``self``, its callees' compilation taken
out) and with its callees (``with callees``), and how many versions (type signatures) of it were
compiled: a function compiled twice is one to look at.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


class CompileTimes:
    """CPU seconds per compiled function, from numba's ``numba:compile`` events (the methods
    of a ``numba.core.event.Listener``)."""

    def __init__(self):
        self.stack: list[list[float]] = []
        self.self_s: dict[str, float] = defaultdict(float)
        self.total_s: dict[str, float] = defaultdict(float)
        self.versions: dict[str, int] = defaultdict(int)

    def on_start(self, event) -> None:
        self.stack.append([time.process_time(), 0.0])

    def on_end(self, event) -> None:
        t0, callees = self.stack.pop()
        spent = time.process_time() - t0
        func = event.data["dispatcher"].py_func
        name = f"{func.__module__.rsplit('.', 1)[-1]}.{func.__qualname__}"
        self.self_s[name] += spent - callees
        self.total_s[name] += spent
        self.versions[name] += 1
        if self.stack:
            self.stack[-1][1] += spent


def main() -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("what", nargs="?", default="cv", choices=("cv", "fit", "both"))
    ap.add_argument("--top", type=int, default=25, help="functions to list (most CPU first)")
    a = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="cfm_fem_numba_") as cache:
        os.environ["NUMBA_CACHE_DIR"] = cache  # before numba is imported
        sys.path.insert(0, str(ROOT))
        import numpy as np
        from numba.core import event

        listener = type("Listener", (CompileTimes, event.Listener), {})()
        event.register("numba:compile", listener)
        times = listener
        c0 = time.process_time()
        if a.what in ("cv", "both"):
            from cfm_fem.workflows.sweep.compile_ahead import compile_now

            compile_now()
        if a.what in ("fit", "both"):
            from cfm_fem.models.harmonic import fit_harmonic

            warm = np.random.default_rng(0).uniform(-1.0, 1.0, (80, 3))
            fit_harmonic(warm, warm, k=40)
        cpu = time.process_time() - c0
    print(f"compiling {a.what}: {cpu:.1f} s CPU in all (imports included), "
          f"{len(times.versions)} functions")  # fmt: skip
    print(f"{'self s':>7} {'with callees s':>15} {'versions':>9}  function")
    for name in sorted(times.self_s, key=lambda n: -times.self_s[n])[: a.top]:
        print(f"{times.self_s[name]:7.2f} {times.total_s[name]:15.2f} "
              f"{times.versions[name]:9d}  {name}")  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
