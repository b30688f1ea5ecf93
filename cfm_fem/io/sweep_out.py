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
    data = {
        "B_nominal_T": res.fieldmap.B,
        "absB_nominal_T": absb,
        "grad_B_T_per_mm": res.gradient.reshape(len(absb), 9),
        "U_f_units": units(U95[:, 3]),
        "outside_fraction": res.n_outside[:, k] / res.config.trials,
        "walk_failed_fraction": res.n_walk_failed[:, k] / res.config.trials,
        "complete": res.complete()[:, k].astype(np.uint8),
        "linear_in_up": res.linear_in_up.astype(np.uint8),
    }
    for c, name in enumerate(COMPONENTS):
        data[f"{name}_systematic_T"] = st[:, c, 0]
        data[f"{name}_systematic_units"] = units(st[:, c, 0])
        data[f"{name}_u_T"] = st[:, c, 1]
        data[f"{name}_u_units"] = units(st[:, c, 1])
        data[f"{name}_sym95_low_units"] = units(st[:, c, 2])
        data[f"{name}_sym95_high_units"] = units(st[:, c, 3])
        data[f"{name}_short95_low_units"] = units(st[:, c, 4])
        data[f"{name}_short95_high_units"] = units(st[:, c, 5])
        data[f"{name}_U95_T"] = U95[:, c]
        data[f"{name}_U95_units"] = units(U95[:, c])
        data[f"{name}_Uk2_units"] = units(2.0 * st[:, c, 1])
        data[f"{name}_gum_U95_units"] = units(1.959963984540054 * res.gum_u[:, k, c])
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
            "interpolation": res.mesh.description,
            "source": res.fieldmap.source,
        }
        write_vtu(path, res.fieldmap.points, res.mesh.simplices, _point_data(res, k), fields)
        entries.append((up, path))
    write_pvd(out / "sweep.pvd", entries)
    write_json(out / "summary.json", summary)
    return summary
