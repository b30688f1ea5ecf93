"""Time every set-up phase of a sweep of a scattered map, quiet and on a busy machine.

A sweep spends its set-up (everything before the Monte Carlo kernel) reading the map,
triangulating it, removing hull slivers, tabulating the cells and preparing the kernels'
search arrays. Each phase is timed with the machine as it is ("quiet") and while competing
processes keep every core busy ("busy"), ``--repeat`` times each, alternating, and the shortest
wall time of each phase is kept; the table gives both, their ratio, and the CPU time of the
process in each (threads that spin instead of working show as CPU time that grows when busy).

    python scripts/bench_setup.py                          # bundled map as COMSOL text
    python scripts/bench_setup.py --field my_export.txt    # any scattered map
    python scripts/bench_setup.py --competitor blas        # competitors run numpy matmuls

Competitors (``--busy N`` processes, default one per core, each in a session of its own):
``python`` runs a pure Python loop, ``blas`` multiplies 400 x 400 matrices with numpy's default
BLAS threads. The numba
kernels are compiled by a warm-up pass before the timed passes.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
import warnings

import numpy as np

from cfm_fem import _kernels
from cfm_fem.io import read_field
from cfm_fem.models.mesh import (
    _delaunay,
    barycentric_transforms,
    build_mesh,
    exact_search,
    face_neighbors,
    hull_sliver_cells,
)
from cfm_fem.workflows.sweep.problem import edge_fit_gradients, node_gradients

COMPETITORS = {
    "python": "while True: pass",
    "blas": "import numpy as np\na = np.random.rand(400, 400)\nwhile True: a @ a",
}


def phases(path):
    """Run the set-up phases of a sweep of ``path`` once; return [(name, wall s, CPU s)]."""
    out = []

    def timed(name, fn, *args):
        t, c = time.perf_counter(), time.process_time()
        value = fn(*args)
        out.append((name, time.perf_counter() - t, time.process_time() - c))
        return value

    fm = timed("read the map", read_field, path)
    coords = fm.points
    span = float(np.ptp(coords, axis=0).max())
    simplices, _, moved, _, _ = timed("Delaunay", _delaunay, coords, path, span)
    timed("hull slivers", hull_sliver_cells, moved, simplices, coords)
    timed("barycentric transforms", barycentric_transforms, coords, simplices)
    timed("face neighbours", face_neighbors, simplices)
    mesh = timed("build_mesh (all of the above)", build_mesh, fm, "auto", "remove")
    eps = 1e-7 * float(np.ptp(mesh.coords, axis=0).max())
    timed(
        "octant start cells",
        _kernels.octant_cells,
        mesh.coords,
        mesh.node_cell,
        mesh.transform,
        mesh.neighbors,
        eps,
    )
    timed("exact search arrays", exact_search, mesh)
    timed("edge-fit gradients", edge_fit_gradients, mesh, fm.B)
    timed("node gradients", node_gradients, mesh, fm.B)
    return out


def _busy_pass(args):
    """`phases` while ``args.busy`` competing processes run."""
    # each in a session of its own, as the programs of other users are: Linux shares the CPU
    # between sessions first (autogroup), so competitors in this session would split its share
    procs = [
        subprocess.Popen(
            [sys.executable, "-c", COMPETITORS[args.competitor]], start_new_session=True
        )  # fmt: skip
        for _ in range(args.busy)
    ]
    try:
        time.sleep(1.0)  # let the competitors reach their loops
        return phases(args.field)
    finally:
        for proc in procs:
            proc.kill()
            proc.wait()


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--field", default="meshes/quadrupole_comsol.txt")
    p.add_argument("--busy", type=int, default=os.cpu_count() or 2)
    p.add_argument("--competitor", choices=sorted(COMPETITORS), default="python")
    p.add_argument("--repeat", type=int, default=1, help="quiet and busy passes, alternating")
    args = p.parse_args(argv)
    warnings.simplefilter("ignore")
    print(f"{args.field}: warm-up pass (compiles the kernels)", flush=True)
    phases(args.field)
    quiet, busy = [], []
    for _ in range(args.repeat):
        quiet.append(phases(args.field))
        busy.append(_busy_pass(args))
    print(f"{args.busy} busy '{args.competitor}' process(es) on {os.cpu_count()} core(s), "
          f"best of {args.repeat}; CPU: time of this process, all its threads")  # fmt: skip
    print(f"{'phase':32s} {'quiet s':>8s} {'busy s':>8s} {'ratio':>6s} {'CPU quiet':>10s} "
          f"{'CPU busy':>9s}")  # fmt: skip
    worst = 0.0
    for k, (name, _, _) in enumerate(quiet[0]):
        tq, cq = min((run[k][1], run[k][2]) for run in quiet)
        tb, cb = min((run[k][1], run[k][2]) for run in busy)
        ratio = tb / tq if tq > 0 else float("nan")
        worst = max(worst, ratio) if tq >= 0.05 else worst
        print(f"{name:32s} {tq:8.2f} {tb:8.2f} {ratio:6.1f} {cq:10.2f} {cb:9.2f}")
    print(f"worst ratio of the phases of 0.05 s or more: {worst:.1f}")


if __name__ == "__main__":
    main()
