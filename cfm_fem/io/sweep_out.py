"""Write a sweep: one ``.vtu`` per U_p value, ``sweep.pvd`` (U_p as ParaView's time) and
``summary.json``."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..sweep import COMPONENTS, SweepResult, summarize
from ._atomic import write_json
from .vtk import write_pvd, write_vtu

__all__ = ["write_sweep", "vtu_name"]


def vtu_name(up_um: float) -> str:
    """File name of the map for one U_p value, e.g. ``uf_up20um.vtu``."""
    return f"uf_up{up_um:g}um.vtu"


def _point_data(res: SweepResult, k: int) -> dict:
    """Per-node arrays for U_p index ``k``; names say the quantity and the unit."""
    st = res.stats[:, k]  # (n, 4, 6)
    units = res.to_units
    U95 = res.expanded_95()[:, k]
    _, _, disagree = res.gum_check()
    absb = np.sqrt((res.fieldmap.B**2).sum(axis=1))
    f32 = np.float32  # Monte Carlo noise is ~1e-2 relative: float32 loses nothing, halves the files
    data = {
        "B_nominal_T": res.fieldmap.B,
        "absB_nominal_T": absb,
        "grad_B_T_per_mm": res.gradient.reshape(len(absb), 9),
        "U_f_units": units(U95[:, 3]).astype(f32),
        "outside_fraction": (res.n_outside[:, k] / res.config.trials).astype(f32),
        "walk_failed_fraction": (res.n_walk_failed[:, k] / res.config.trials).astype(f32),
        "complete": res.complete()[:, k].astype(np.uint8),
        "linear_in_up": res.linear_in_up.astype(np.uint8),
    }
    for c, name in enumerate(COMPONENTS):
        per = {
            "systematic_units": units(st[:, c, 0]),
            "u_units": units(st[:, c, 1]),
            "sym95_low_units": units(st[:, c, 2]),
            "sym95_high_units": units(st[:, c, 3]),
            "short95_low_units": units(st[:, c, 4]),
            "short95_high_units": units(st[:, c, 5]),
            "U95_units": units(U95[:, c]),
            "Uk2_units": units(2.0 * st[:, c, 1]),
            "Uk2_T": 2.0 * st[:, c, 1],
            "gum_U95_units": units(1.959963984540054 * res.gum_u[:, k, c]),
        }
        for key, values in per.items():
            data[f"{name}_{key}"] = values.astype(f32)
        data[f"{name}_gum_disagree"] = disagree[:, k, c].astype(np.uint8)
    return data


def write_sweep(out_dir, res: SweepResult, provenance: dict | None = None) -> dict:
    """Write every output of a sweep into ``out_dir``; return the summary that was written.

    The maps are written first, then ``sweep.pvd``, then ``summary.json``: each file atomically,
    so an interrupted run never leaves a partial file and a present summary means a complete run.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    summary = summarize(res)
    summary["provenance"] = provenance or {}
    entries = []
    for k, up in enumerate(res.config.up_um):
        path = out / vtu_name(up)
        fields = {
            "U_p_um": up,
            "B_ref_T": res.b_ref_T,
            "trials": res.config.trials,
            "seed": res.config.seed,
        }  # numbers only: meshio rejects VTK string arrays; the text is in summary.json
        write_vtu(path, res.fieldmap.points, res.mesh.simplices, _point_data(res, k), fields)
        entries.append((up, path))
    write_pvd(out / "sweep.pvd", entries)
    write_json(out / "summary.json", summary)
    return summary
