"""Measure what `--hull-slivers remove` does on the bundled map's COMSOL layout.

The COMSOL layout carries the nodes of ``meshes/quadrupole.vtu`` without its cells, so it is
triangulated by Delaunay; the native mesh is the reference. Per node, U_f of |B| (units) at
U_p = 50 um, 2,000 trials, for the hull slivers removed (the default) and kept, with
``--outside exclude`` (the default) and ``extrapolate``; printed for the nodes of the native
mesh's surface cells (cells with a face on its border) and the others, with the ratio of the
GUM figure (cell-averaged gradient) to the native mesh's at the former.

    python scripts/hull_slivers.py
"""

import time
import warnings

import numpy as np

from cfm_fem.io import read_field
from cfm_fem.models.sweep import SweepConfig
from cfm_fem.workflows.sweep.in_memory import run_sweep


def main():
    warnings.simplefilter("ignore")
    native = read_field("meshes/quadrupole.vtu")
    comsol = read_field("meshes/quadrupole_comsol.txt")
    on = np.lexsort(np.round(native.points, 6).T)
    oc = np.lexsort(np.round(comsol.points, 6).T)
    assert np.allclose(native.points[on], comsol.points[oc], atol=1e-5), "not the same nodes"
    for outside in ("exclude", "extrapolate"):
        cfg = dict(up_um=[50.0], trials=2000, seed=0, outside=outside)
        ref = run_sweep(native, SweepConfig(**cfg))
        m = ref.mesh
        surface = np.zeros(native.n_nodes, bool)
        surface[np.unique(m.simplices[(m.neighbors < 0).any(axis=1)])] = True
        surface = surface[on]
        uf_ref = ref.uf_units()[on, 0]
        print(f"--outside {outside}: {surface.sum()} of {len(surface)} nodes in surface cells")
        for rule in ("remove", "keep"):
            t = time.perf_counter()
            res = run_sweep(comsol, SweepConfig(**cfg, hull_slivers=rule))
            d = np.abs(res.uf_units()[oc, 0] - uf_ref)
            gum = res.gum_u[oc, 0, 3] / ref.gum_u[on, 0, 3]
            print(
                f"  {rule:6s} ({time.perf_counter() - t:.1f} s, {len(res.mesh.hull_slivers)} "
                f"cells removed): in surface cells |U_f - native| median "
                f"{np.median(d[surface]):.2f}, p99 {np.percentile(d[surface], 99):.1f}, "
                f"max {d[surface].max():.1f} units; "
                f"others median {np.median(d[~surface]):.2f}, max {d[~surface].max():.1f}; GUM "
                f"figure in surface cells median {np.median(gum[surface]):.3g}x the native "
                f"mesh's, p99 {np.percentile(gum[surface], 99):.4g}x, max {gum[surface].max():.4g}x"
            )


if __name__ == "__main__":
    main()
