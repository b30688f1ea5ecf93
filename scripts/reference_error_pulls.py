"""The stated error of a coarse reference map against its true error at the family's readings.

For the Hall nulls of the randomized family (:mod:`cfm_fem.simulation.family`) whose drawn
reference is a coarse FEM-like grid, the map is written as the family writes it, read by the
diagnosis's reference model (:func:`cfm_fem.workflows.diagnose.reference.reference_model`) at
the scan's distinct points, and compared with the exact field there
(:func:`cfm_fem.simulation.magnets.field`). Per component and point, the pull is the reading's
error over the stated standard deviation (:meth:`NodeExactHarmonic.error_var`). Only the values
that matter are judged: those whose stated std times the root of the readings sharing its cell
(the factor the diagnosis applies) exceeds ``--share`` of the noise of the point's mean.

The table gives, per stratum (cell kind: inner, or outermost along some axis; magnet order;
scan kind), the number of values, the pulls' std, their 99.9 % quantile of abs and largest abs,
and the ratio rms(stated) / rms(true)::

    nice -n 5 python scripts/reference_error_pulls.py --first-seed 46013 --seeds 200
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np


def case_values(seed: int, folder: Path, share: float):
    """Pulls of one family seed's coarse reference at its readings, or None (not coarse).

    Returns
    -------
    dict
        ``pull`` (k,), ``err`` (k,), ``std`` (k,) in T, and the strata of each value:
        ``edge`` (k,) bool (an outermost cell), ``magnet`` and ``scan`` (str).
    """
    from cfm_fem.simulation import family_hall as FH
    from cfm_fem.simulation import magnets, scans
    from cfm_fem.simulation.family import _reference, draw_config
    from cfm_fem.workflows.diagnose.reference import (
        axis_steps,
        node_spacing_mm,
        reference_model,
        shared_readings,
    )
    from cfm_fem.workflows.inputs import field_map

    cfg = draw_config(seed, "small", "null", "hall")
    if cfg.get("reference") != "coarse":
        return None
    pts = np.unique(np.round(scans.map_points(cfg["scan"]), 9), axis=0)
    fm = field_map(str(_reference(cfg, None, folder, f"family_{seed}")), None)
    model, kind, _ = reference_model(fm, "auto")
    if kind != "harmonic":
        return None
    err = model(pts) - magnets.field(cfg["magnet"], pts)
    std = np.sqrt(model.error_var(pts))
    ctx = FH.context(cfg)
    noise = float(np.median(FH.noise_std(cfg, ctx, FH.gradient(cfg, ctx))))
    reps = int(cfg["scan"]["n_reps"])
    cell = shared_readings(pts, np.full(len(pts), reps), fm.points)
    keep = (np.sqrt(cell / reps)[:, None] * std > share * noise / np.sqrt(reps)) & (std > 0)
    keep &= model.fit.field_at(pts)[1][:, None]
    lo, hi = fm.points.min(0), fm.points.max(0)
    steps = axis_steps(fm.points, node_spacing_mm(fm.points))
    outer = ((np.minimum(pts - lo, hi - pts) < steps * (1 - 1e-9)) & (hi > lo)).any(1)
    edge = np.broadcast_to(outer[:, None], std.shape)
    return {"pull": err[keep] / std[keep], "err": err[keep], "std": std[keep],
            "edge": edge[keep], "magnet": cfg["strata"]["magnet"],
            "scan": cfg["strata"]["scan"]}  # fmt: skip


def table(values) -> str:
    """The markdown table of the pulls per stratum."""
    groups = {}
    for v in values:
        every = np.ones(v["pull"].size, dtype=bool)
        strata = [("all", every), ("cells inner", ~v["edge"]), ("cells outermost", v["edge"]),
                  (f"magnet {v['magnet']}", every), (f"scan {v['scan']}", every)]  # fmt: skip
        for key, m in strata:
            g = groups.setdefault(key, [[], [], []])
            for i, name in enumerate(("pull", "err", "std")):
                g[i].append(v[name][m])
    lines = ["| stratum | values | pull std | 99.9 % of abs | largest abs | stated / true |",
             "|---|---|---|---|---|---|"]  # fmt: skip
    for key in sorted(groups):
        z, e, s = (np.concatenate(a) for a in groups[key])
        if z.size == 0:
            continue
        ratio = np.sqrt(np.mean(s**2) / np.mean(e**2)) if np.any(e) else np.inf
        lines.append(f"| {key} | {z.size} | {np.std(z):.2f} | "
                     f"{np.quantile(np.abs(z), 0.999):.2f} | {np.abs(z).max():.2f} | "
                     f"{ratio:.2f} |")  # fmt: skip
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--first-seed", type=int, required=True)
    ap.add_argument("--seeds", type=int, required=True, help="family seeds to draw from")
    ap.add_argument("--share", type=float, default=0.3,
                    help="judge values whose stated error in the noise exceeds this share "
                    "of the point mean's noise")  # fmt: skip
    a = ap.parse_args(argv)
    values = []
    with tempfile.TemporaryDirectory() as tmp:
        for seed in range(a.first_seed, a.first_seed + a.seeds):
            got = case_values(seed, Path(tmp), a.share)
            if got is not None:
                values.append(got)
    print(f"{len(values)} coarse maps among seeds {a.first_seed}-{a.first_seed + a.seeds - 1}")
    print(table(values))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
