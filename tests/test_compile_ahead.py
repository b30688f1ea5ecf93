"""The first run's compilation of the adaptive sweep's kernel in child processes."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

#: Compiles `compile_estimates`'s work into an empty cache, then the whole kernel in a fresh
#: process; prints the functions numba compiled (not loaded from the cache) in the second.
_SCRIPT = """
import sys
from numba.core import event
from cfm_fem.workflows.sweep import compile_ahead

if sys.argv[1] == "estimates":
    compile_ahead.compile_estimates()
else:
    names = []

    class Names(event.Listener):
        def on_start(self, ev):
            pass

        def on_end(self, ev):
            names.append(ev.data["dispatcher"].py_func.__name__)

    event.register("numba:compile", Names())
    compile_ahead.compile_now()
    print(" ".join(names))
"""


@pytest.mark.slow
def test_estimates_compiled_ahead_are_loaded_by_the_kernel(tmp_path):
    """`compile_estimates` compiles `_node_estimates` for the very argument types
    `harmonic_cv_sweep` passes it: the kernel's compilation then loads it from the cache
    (a type that differs, e.g. a readonly or non-contiguous array, would compile it again)."""
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path)}
    for what in ("estimates", "kernel"):
        out = subprocess.run(
            [sys.executable, "-c", _SCRIPT, what], env=env, capture_output=True, text=True,
            check=True, timeout=600,
        )  # fmt: skip
    compiled = out.stdout.split()
    assert "harmonic_cv_sweep" in compiled  # the kernel itself was compiled here
    assert "_add_trials" in compiled
    assert "_node_estimates" not in compiled and "cv_stats" not in compiled


def test_report_modules_are_imported_once_the_first_chunk_is_done():
    """The sweep's progress, wrapped, passes every count on and starts importing the report's
    modules (matplotlib) at its first call, in a fresh process; without a report it is the
    caller's own callable."""
    script = """
import sys, threading
from types import SimpleNamespace
from cfm_fem.workflows.sweep.run import _preloading_report

seen = []
job = SimpleNamespace(report=False, progress=seen.append)
assert _preloading_report(job) == seen.append
job.report = True
progress = _preloading_report(job)
assert "matplotlib" not in sys.modules
progress(5)
progress(7)
for t in threading.enumerate():
    if t.name == "cfm_fem report import":
        t.join()
assert seen == [5, 7], seen
assert "cfm_fem.report.sweep" in sys.modules and "matplotlib" in sys.modules
job.progress = None
_preloading_report(job)(3)  # no callable of the caller's: only the import
print("ok")
"""
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True)
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr
