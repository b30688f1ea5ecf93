"""Render a U_f map off-screen with pyvista (the README picture).

    python scripts/render_uf_map.py results/uf_up20um.vtu docs/uf_map_20um.png

Shows U_f (units) on the longitudinal x-z plane through the axis (where a quadrupole's gradient is
strongest, like the paper's Fig. 4) and on a transverse slice in the magnet body.
"""

from __future__ import annotations

import argparse

import numpy as np
import pyvista as pv


def main():
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("vtu")
    ap.add_argument("png")
    ap.add_argument("--array", default="U_f_units")
    a = ap.parse_args()
    pv.OFF_SCREEN = True
    grid = pv.read(a.vtu)
    up = float(np.asarray(grid.field_data["U_p_um"])[0])
    b_ref = float(np.asarray(grid.field_data["B_ref_T"])[0])
    grid = grid.threshold(0.5, scalars="complete")  # nodes whose every trial stayed in the map
    c = grid.center
    longitudinal = grid.slice(normal="y", origin=c)
    transverse = grid.slice(normal="z", origin=c)
    clim = [0.0, float(np.nanmax(grid[a.array]))]
    # the bar's title goes in its own text: a horizontal bar draws title and labels on one line
    bar = dict(title="", n_labels=5, fmt="%.0f", position_x=0.42, position_y=0.06, width=0.5,
               height=0.1)  # fmt: skip
    p = pv.Plotter(off_screen=True, shape=(1, 2), window_size=(1600, 560), border=False)
    p.subplot(0, 0)
    p.add_mesh(longitudinal, scalars=a.array, cmap="viridis", clim=clim, scalar_bar_args=bar,
               nan_opacity=0.0)  # fmt: skip
    p.add_text(f"U_p = {up:g} um: x-z plane through the axis (z horizontal)", font_size=10)
    p.add_text(f"U_f (95 %), units of 1e-4 x {b_ref:.3g} T", position=(20, 40), font_size=9)
    p.view_zx()
    p.camera.zoom(1.3)
    p.subplot(0, 1)
    p.add_mesh(transverse, scalars=a.array, cmap="viridis", clim=clim, show_scalar_bar=False,
               nan_opacity=0.0)  # fmt: skip
    p.add_text("x-y slice at the magnet centre", font_size=10)
    p.view_xy()
    p.screenshot(a.png)
    print(f"wrote {a.png}")


if __name__ == "__main__":
    main()
