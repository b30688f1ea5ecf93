"""Time the README's sweep phase by phase, under the default and the linear field model.

Runs ``cfm-fem sweep meshes/quadrupole.vtu --up 0:50:10 --out DIR`` in this process (the
command line's own code), once with the default field model and once with
``--field-model linear``, ``--repeat`` times each, alternating, and prints per phase the wall
time and the CPU time of the process (all its threads), then the ratio of the linear run's wall
time to the default run's (both from the same process, the best of the repeats).

    python scripts/bench_readme.py                 # README command, both models, one pass
    python scripts/bench_readme.py --repeat 2      # best of two passes each
    python scripts/bench_readme.py --profile prof  # also a cProfile of the first default run
    python scripts/bench_readme.py --only default --busy 2   # and beside 2 busy processes

With ``--busy N`` each pass is followed by one more of each model while N competing processes
(`bench_setup.COMPETITORS`, each in a session of its own, like another user's program) keep
the cores busy; the best busy wall time of each model is printed with its ratio to the best
quiet one. ``--busy-session same`` starts them in this process's session instead: with
``kernel.sched_autogroup_enabled = 1`` Linux shares the CPU between sessions first, so the
two settings give different ratios (docs/performance.md).

Phases are timed by wrapping the functions the command calls (reading, set-up and harmonic
fit, the chunks of the Monte Carlo kernel, gradients and GUM figures, the maps' VTU files,
the report); "other" is the rest of the command (option checks, locks, summary, imports of
modules first used inside a phase are counted in that phase; a phase indented under another
is not added to the whole: the report's figures are drawn on a thread while the maps are
written, so CPU time there is the whole process's). The numba kernels are compiled by a small
warm-up sweep before the timed passes, unless ``--cold``.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
MESH = ROOT / "meshes" / "quadrupole.vtu"


class Phases:
    """Wall and CPU seconds per named phase, accumulated over calls."""

    def __init__(self):
        self.wall: dict[str, float] = {}
        self.cpu: dict[str, float] = {}

    def wrap(self, name, fn):
        def timed(*args, **kwargs):
            t, c = time.perf_counter(), time.process_time()
            try:
                return fn(*args, **kwargs)
            finally:
                self.wall[name] = self.wall.get(name, 0.0) + time.perf_counter() - t
                self.cpu[name] = self.cpu.get(name, 0.0) + time.process_time() - c

        return timed


#: (phase, module, attribute): the functions whose time makes each phase; a phase named
#: with a leading "  " lies inside the phase above it and is not added to the whole.
TIMED = (
    ("read the map", "cfm_fem.io", "read_field"),
    ("set-up: mesh, kernel arrays, fit", "cfm_fem.workflows.sweep.in_memory", "prepare_sweep"),
    ("  of which the harmonic fit", "cfm_fem.workflows.sweep.problem", "_harmonic_fit"),
    ("Monte Carlo kernels", "cfm_fem.workflows.sweep.problem", "SweepProblem.run_chunk"),
    ("gradients and GUM", "cfm_fem.workflows.sweep.in_memory", "sweep_gradients"),
    ("gradients and GUM", "cfm_fem.workflows.sweep.in_memory", "_gum_u"),
    ("outputs: maps, summary, index", "cfm_fem.io.sweep_out", "write_sweep"),
    ("  of which the summary statistics", "cfm_fem.io.sweep_out", "summarize"),
    (
        "  figures and HTML, on a thread beside the maps",
        "cfm_fem.report.sweep",
        "draw_sweep_report",
    ),
    ("report files, the chunk store", "cfm_fem.workflows.sweep.run", "_finish"),
)


def _patch(phases: Phases):
    """Wrap the timed functions; returns a callable that undoes it."""
    import importlib

    undo = []
    for name, module, attr in TIMED:
        try:
            mod = importlib.import_module(module)
        except ImportError:
            continue
        owner = mod
        parts = attr.split(".")
        for p in parts[:-1]:
            owner = getattr(owner, p)
        if not hasattr(owner, parts[-1]):
            continue
        original = getattr(owner, parts[-1])
        setattr(owner, parts[-1], phases.wrap(name, original))
        undo.append((owner, parts[-1], original))

    def restore():
        for owner, a, original in reversed(undo):
            setattr(owner, a, original)

    return restore


def _run(argv, profile=None):
    from cfm_fem.cli import main

    phases = Phases()
    restore = _patch(phases)
    t, c = time.perf_counter(), time.process_time()
    try:
        with (
            open(os.devnull, "w") as null,
            contextlib.redirect_stderr(null),
            contextlib.redirect_stdout(null),
        ):
            if profile:
                import cProfile

                prof = cProfile.Profile()
                rc = prof.runcall(main, argv)
                prof.dump_stats(profile)
            else:
                rc = main(argv)
    finally:
        restore()
    if rc != 0:
        raise SystemExit(f"cfm-fem {' '.join(argv)} exited with {rc}")
    return phases, time.perf_counter() - t, time.process_time() - c


def _beside_busy(n, competitor, run, own_session=True):
    """``run()`` while ``n`` competing processes (`bench_setup.COMPETITORS`) keep the cores
    busy, each in a session of its own (Linux shares the CPU between sessions first, when
    ``kernel.sched_autogroup_enabled`` is 1), or with ``own_session`` False in this one (the
    CPU then shared between threads: this command's threads against the competitors)."""
    from bench_setup import COMPETITORS

    procs = [
        subprocess.Popen(
            [sys.executable, "-c", COMPETITORS[competitor]], start_new_session=own_session
        )
        for _ in range(n)
    ]
    try:
        time.sleep(1.0)  # let the competitors reach their loops
        return run()
    finally:
        for proc in procs:
            proc.kill()
            proc.wait()


def _table(title, phases, wall, cpu):
    print(f"\n{title}")
    print(f"{'phase':40s} {'wall s':>8s} {'CPU s':>8s}")
    for name in dict.fromkeys(p[0] for p in TIMED):
        if name in phases.wall:
            print(f"{name:40s} {phases.wall[name]:8.2f} {phases.cpu[name]:8.2f}")
    ow = wall - sum(v for k, v in phases.wall.items() if not k.startswith(" "))
    oc = cpu - sum(v for k, v in phases.cpu.items() if not k.startswith(" "))
    print(f"{'other':40s} {ow:8.2f} {oc:8.2f}")
    print(f"{'whole command':40s} {wall:8.2f} {cpu:8.2f}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--field", default=str(MESH))
    ap.add_argument("--up", default="0:50:10")
    ap.add_argument("--extra", default="", help="more sweep options, e.g. '--trials 2000'")
    ap.add_argument("--only", choices=("default", "linear"), help="time one model only")
    ap.add_argument("--cold", action="store_true", help="no warm-up (compilation included)")
    ap.add_argument("--profile", help="write a cProfile of the first default run here")
    ap.add_argument("--busy", type=int, default=0,
                    help="also run each pass beside this many busy processes")  # fmt: skip
    ap.add_argument("--competitor", default="python", choices=("python", "blas"),
                    help="what the busy processes run (bench_setup.py)")  # fmt: skip
    ap.add_argument("--busy-session", default="own", choices=("own", "same"),
                    help="busy processes each in a session of its own (another user's "
                         "programs), or in this one")  # fmt: skip
    args = ap.parse_args(argv)
    print(f"load average before: {os.getloadavg()[0]:.2f}; {os.cpu_count()} CPUs")
    with tempfile.TemporaryDirectory() as tmp:
        if not args.cold:
            _run(["sweep", args.field, "--up", "0,20", "--trials", "64", "--out", f"{tmp}/w"])
            _run(["sweep", args.field, "--up", "0,20", "--trials", "64", "--out", f"{tmp}/w",
                  "--field-model", "linear"])  # fmt: skip
            from cfm_fem.workflows.sweep.compile_ahead import compile_now

            compile_now()  # the adaptive estimator's kernel, which --trials does not run
        models = ("default", "linear") if args.only is None else (args.only,)
        best = {}
        busy = {}
        for r in range(args.repeat):
            for model in models:
                argv = ["sweep", args.field, "--up", args.up, "--out", f"{tmp}/{model}"]
                argv += args.extra.split()
                if model == "linear":
                    argv += ["--field-model", "linear"]
                prof = args.profile if (args.profile and model == "default" and r == 0) else None
                phases, wall, cpu = _run(argv, prof)
                _table(f"{model} model, pass {r + 1}: cfm-fem {' '.join(argv)}", phases, wall, cpu)
                if model not in best or wall < best[model][0]:
                    best[model] = (wall, cpu)
                print(f"load average: {os.getloadavg()[0]:.2f}")
                if args.busy:
                    phases, wall, cpu = _beside_busy(args.busy, args.competitor,
                                                     lambda argv=argv: _run(argv),
                                                     args.busy_session == "own")  # fmt: skip
                    _table(f"{model} model, pass {r + 1}, beside {args.busy} busy "
                           f"'{args.competitor}' process(es), {args.busy_session} session",
                           phases, wall, cpu)  # fmt: skip
                    if model not in busy or wall < busy[model][0]:
                        busy[model] = (wall, cpu)
        print()
        for model, (wall, cpu) in best.items():
            print(f"best {model}: {wall:.2f} s wall, {cpu:.2f} s CPU")
            if model in busy:
                bw, bc = busy[model]
                print(f"best {model} beside {args.busy} busy process(es): {bw:.2f} s wall, "
                      f"{bc:.2f} s CPU; busy wall / quiet wall: {bw / wall:.2f}")  # fmt: skip
        if len(best) == 2:
            print(f"linear wall / default wall: {best['linear'][0] / best['default'][0]:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
