"""Time the README's command as a user runs it, against the same command of another checkout.

Runs ``python -m cfm_fem sweep meshes/quadrupole.vtu --up 0:50:10 --out DIR`` in a process of
its own, alternately in this checkout and in a reference checkout (``--reference``, e.g. a
``git worktree`` of an older commit: the command runs in its folder, which ``-m`` puts first on
the module path), ``--repeat`` times each, on this checkout's map, and
prints the wall and CPU time (user + system, of the process and its children) of every run,
the median of each side and the ratio of the reference's median wall time to this one's.
Alternating the two sides spreads the other jobs of a shared machine over both.

    python scripts/bench_command.py --reference /tmp/ref --repeat 5
    python scripts/bench_command.py --reference /tmp/ref --cold   # empty numba and fit caches

``--cold`` gives each run an empty numba cache and an empty fit cache (the first run after an
install). The numba cache of both sides is otherwise warmed by one run each before the timed
runs; the reference writes its kernels into a cache folder of its own.
"""

from __future__ import annotations

import argparse
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
COMMAND = ["sweep", str(ROOT / "meshes" / "quadrupole.vtu"), "--up", "0:50:10"]


def _run(checkout: Path, out: str, env_extra: dict) -> tuple[float, float]:
    """One run of the command with the package of ``checkout``; (wall s, CPU s)."""
    env = dict(os.environ, PYTHONPATH=str(checkout), **env_extra)
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t = time.perf_counter()
    subprocess.run(
        [sys.executable, "-m", "cfm_fem", *COMMAND, "--out", out], cwd=checkout, env=env,
        check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )  # fmt: skip
    wall = time.perf_counter() - t
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return wall, cpu


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reference", type=Path, required=True,
                    help="checkout of the reference commit (its package is used)")  # fmt: skip
    ap.add_argument("--repeat", type=int, default=3, help="timed runs of each side")
    ap.add_argument("--cold", action="store_true",
                    help="empty numba and fit caches at every run (a first run)")  # fmt: skip
    args = ap.parse_args(argv)
    sides = {"this checkout": ROOT, f"reference {args.reference}": args.reference.resolve()}
    with tempfile.TemporaryDirectory() as tmp:
        caches = {name: f"{tmp}/numba{i}" for i, name in enumerate(sides)}

        def env(name, k):
            if args.cold:
                return {"NUMBA_CACHE_DIR": f"{tmp}/cold{k}_{len(name)}",
                        "CFM_FEM_FIT_CACHE": f"{tmp}/fits{k}_{len(name)}"}  # fmt: skip
            return {"NUMBA_CACHE_DIR": caches[name]}

        print(f"load average before: {os.getloadavg()[0]:.2f}; {os.cpu_count()} CPUs")
        if not args.cold:
            for name, path in sides.items():  # compile each side's kernels into its cache
                _run(path, f"{tmp}/warm", env(name, 0))
        times = {name: [] for name in sides}
        for k in range(args.repeat):
            for name, path in sides.items():
                wall, cpu = _run(path, f"{tmp}/out{k}", env(name, k))
                times[name].append((wall, cpu))
                print(f"{name:40s} run {k + 1}: {wall:6.2f} s wall {cpu:6.2f} s CPU", flush=True)
        med = {}
        for name, runs in times.items():
            med[name] = statistics.median(w for w, _ in runs)
            cpu = statistics.median(c for _, c in runs)
            print(f"{name:40s} median {med[name]:6.2f} s wall {cpu:6.2f} s CPU")
        mine, ref = med.values()
        print(f"reference / this checkout, median wall time: {ref / mine:.2f}")
        print(f"load average after: {os.getloadavg()[0]:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
