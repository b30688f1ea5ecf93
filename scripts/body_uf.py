"""U_f of a sweep map in the magnet body against all nodes with a full figure.

    python scripts/body_uf.py results/uf_up20um.vtu            # body: |z| < 30 mm
    python scripts/body_uf.py results/uf_up20um.vtu --body 20

Prints the median U_f (units) over the complete nodes (``complete`` = 1) in the body and over
all of them (the p50 that ``cfm-fem sweep`` prints), with the linear figure
1.96 U_p |grad |B|| / B_ref at the body's median gradient.
"""

from __future__ import annotations

import argparse

import numpy as np
import pyvista as pv


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("vtu")
    ap.add_argument("--body", type=float, default=30.0, help="half-length of the body, mm")
    args = ap.parse_args(argv)
    grid = pv.read(args.vtu)
    up = float(np.asarray(grid.field_data["U_p_um"])[0])
    b_ref = float(np.asarray(grid.field_data["B_ref_T"])[0])
    ok = np.asarray(grid.point_data["complete"]) == 1
    uf = np.asarray(grid.point_data["U_f_units"], dtype=np.float64)
    body = ok & (np.abs(grid.points[:, 2]) < args.body)
    B = np.asarray(grid.point_data["B_nominal_T"])
    g = np.asarray(grid.point_data["grad_B_T_per_mm"]).reshape(-1, 3, 3)
    absb = np.linalg.norm(B, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        grad_abs = np.linalg.norm(np.einsum("nc,ncj->nj", B, g) / absb[:, None], axis=1)
    linear = 1.96 * up * 1e-3 * np.nanmedian(grad_abs[body]) / b_ref * 1e4
    print(f"U_p = {up:g} um, B_ref = {b_ref:.4g} T")
    print(f"body (|z| < {args.body:g} mm): {body.sum()} nodes, median U_f {np.median(uf[body]):.1f}"
          f" units; 1.96 U_p |grad |B|| / B_ref = {linear:.1f} units")  # fmt: skip
    print(f"all complete nodes: {ok.sum()}, median U_f {np.median(uf[ok]):.1f} units")


if __name__ == "__main__":
    main()
