"""Where the GUM-S1 section 8 flag of |B| falls on a sweep map, band by band along z.

    python scripts/gum_flag_zones.py results/uf_up20um.vtu

For the nodes that kept every trial (`complete`), per |z| band: the fraction flagged
(`absB_gum_disagree`) and the median over the nodes of the largest deviation of a node's cell
gradients of B (3 x 3, Frobenius norm) from their volume-weighted mean, the gradient the GUM
column uses. The flag follows that deviation: the Monte Carlo samples the piecewise-linear
interpolant of B, whose cells around a node have different gradients. Needs a map written on
tetrahedra (native cells).
"""

from __future__ import annotations

import argparse

import numpy as np
import pyvista as pv

BANDS = [(0, 30), (30, 38), (38, 45), (45, 60), (60, 80), (80, np.inf)]


def cell_gradient_deviation(points, tets, f):
    """Per node: max over its cells of |grad_cell f - mean| / |mean| (mean volume-weighted).

    points (n, 3) mm, tets (m, 4), f (n, 3) T: cell gradients (m, 9) T/mm, Frobenius norms.
    """
    edges = points[tets[:, 1:]] - points[tets[:, :1]]  # (m, 3, 3)
    vol = np.abs(np.linalg.det(edges)) / 6
    grad = np.linalg.solve(edges, f[tets[:, 1:]] - f[tets[:, :1]]).reshape(len(tets), 9)
    n = len(points)
    acc = np.zeros((n, 9))
    wsum = np.zeros(n)
    for k in range(4):
        np.add.at(acc, tets[:, k], grad * vol[:, None])
        np.add.at(wsum, tets[:, k], vol)
    mean = acc / wsum[:, None]
    dev = np.zeros(n)
    for k in range(4):
        g = mean[tets[:, k]]
        np.maximum.at(dev, tets[:, k], np.linalg.norm(grad - g, axis=1) / np.linalg.norm(g, axis=1))
    return dev


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("vtu", help="a map written by cfm-fem sweep (uf_up<U_p>um.vtu)")
    a = ap.parse_args()
    m = pv.read(a.vtu)
    tets = m.cells_dict.get(pv.CellType.TETRA)
    if tets is None:
        raise SystemExit(f"{a.vtu}: no tetrahedra; this script needs a map on native cells")
    d = {k: np.asarray(v) for k, v in m.point_data.items()}
    points = np.asarray(m.points, dtype=np.float64)
    dev = cell_gradient_deviation(points, tets, d["B_nominal_T"].astype(np.float64))
    done = d["complete"] == 1
    flag = d["absB_gum_disagree"] == 1
    z = np.abs(points[:, 2])
    print(f"{a.vtu}: {done.sum()} of {len(done)} nodes kept every trial")
    print("  |z| band [mm]    nodes   flagged   median cell-gradient deviation")
    for lo, hi in BANDS:
        sel = done & (z >= lo) & (z < hi)
        print(
            f"  {lo:>4g} - {hi:<6g} {sel.sum():8d} {flag[sel].mean():8.1%}   "
            f"{np.median(dev[sel]):8.1%}"
        )
    print(
        f"  all              {done.sum():8d} {flag[done].mean():8.1%}   {np.median(dev[done]):8.1%}"
        f"   (flagged nodes {np.median(dev[done & flag]):.1%}, "
        f"others {np.median(dev[done & ~flag]):.1%})"
    )


if __name__ == "__main__":
    main()
