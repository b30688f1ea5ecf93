"""Outputs of ``cfm-fem coupled``, ``cfm-fem compare`` and ``cfm-fem fig4``: JSON and CSV.

The ``*_summary`` functions build the JSON documents (plain dicts), the ``*_csv`` functions the
per-point tables (text); `cfm_fem.io.run_files.write_run` puts everything of one run on disk,
each file atomically, only after everything was computed.
"""

from __future__ import annotations

import io

import numpy as np

from ..models.field_model import PAPER_TABLE_V, QUANTITIES
from ._finite import check_finite
from .kinematics_out import PAPER_TABLE_IV, bench_description
from .run_files import write_run

__all__ = [
    "coupled_summary",
    "coupled_points_csv",
    "tracker_summary",
    "tracker_points_csv",
    "hall_summary",
    "hall_points_csv",
    "write_run",
]

DEFINITIONS = {
    "E_f": "(B_meas - B_nom) / B_ref in units of 1e-4 B_ref, per point and component "
    "(measured minus nominal, the sign convention of E_p; the paper's eq. 14 writes nom - meas)",
    "pooling": "Table V / Table IV: systematic = RMS over points of the per-point mean; "
    "std = RMS over points of the per-point standard deviation; U = sqrt(systematic^2 + std^2)",
    "u95": "per point: max(|low|, |high|) of the 95 % probabilistically symmetric interval",
    "num_u": "numerical standard uncertainty of a pooled value: std over consecutive batches of "
    "trials / sqrt(batches)",
    "B_ref": "units are 1e-4 of B_ref, never of the local field: a component that passes through "
    "zero (B_x on the mid-plane of a quadrupole) would make eq. 14 of the paper infinite",
}


#: The comment every per-point CSV states: how a value that does not exist is written.
NO_FIGURE = "an empty cell: no figure (undefined, e.g. a z-score 0/0 of a component that is 0)"


def _csv(header, rows, comments=()) -> str:
    """CSV text; a NaN cell is written empty (`NO_FIGURE`, said in a comment line), an
    infinite one refused (`check_finite`)."""
    buf = io.StringIO()
    for c in comments:
        buf.write(f"# {c}\n")
    buf.write(f"# {NO_FIGURE}\n")
    buf.write(",".join(header) + "\n")
    for r in rows:
        buf.write(",".join(_cell(v, header[j]) for j, v in enumerate(r)) + "\n")
    return buf.getvalue()


def _cell(v, column: str) -> str:
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    v = float(v)
    if v != v:
        return ""
    check_finite("points.csv", column, v)
    return repr(v)


# --------------------------------------------------------------------------- coupled


def coupled_summary(res, bench, *, field_budget=None, bench_budget=None, extra=None) -> dict:
    """``summary.json`` of ``cfm-fem coupled``: Table V beside the paper, with every assumption."""
    pooled = res.pooled()
    ep_sys = 1e3 * np.sqrt(np.mean(res.ep_mean**2, axis=0))
    ep_u = 1e3 * np.sqrt(np.mean(res.ep_std**2, axis=0))
    doc = {
        "table_v": {
            "simulated": pooled["all"],
            "paper_simulated": PAPER_TABLE_V["simulation"],
            "paper_experimental": PAPER_TABLE_V["experiment"],
        },
        "pooled": pooled,
        "b_ref_T": res.field.b_ref_T,
        "b_ref_rule": res.field.b_ref_rule,
        "r_ref_mm": res.field.r_ref_mm,
        "field": res.field.describe(),
        "region": res.region,
        "points": int(len(res.points)),
        "trials": int(res.trials),
        "seed": int(res.seed),
        "align": res.align,
        "probe": res.probe.assumptions(),
        "positioning_at_points_um": {
            a: {
                "systematic_um": float(ep_sys[k]),
                "std_um": float(ep_u[k]),
                "U_p_um": float(np.hypot(ep_sys[k], ep_u[k])),
            }
            for k, a in enumerate("xyz")
        },
        "bench": bench_description(bench),
        "magnet_translation_mm": np.asarray(bench.magnet.translation_mm).tolist(),
        "magnet_rotation_rad": np.asarray(bench.magnet.rotation_rad).tolist(),
        "definitions": DEFINITIONS,
        "notes": list(res.notes),
        "seconds": res.seconds,
    }
    if field_budget is not None:
        doc["field_budget"] = field_budget
    if bench_budget is not None:
        doc["positioning_budget"] = bench_budget
    if extra:
        doc.update(extra)
    return doc


def coupled_points_csv(res) -> str:
    """Per-point statistics of a coupled run (units; positions in mm)."""
    header = ["x_mm", "y_mm", "z_mm", "q_x_mm", "q_y_mm", "q_z_mm", "Bx_T", "By_T", "Bz_T"]
    for q in QUANTITIES:
        header += [f"{q}_{s}_units" for s in ("mean", "std", "low", "high", "u95")]
    header.append("n_valid")
    u95 = res.u95
    rows = []
    for i in range(len(res.points)):
        r = [*res.points[i], *res.q_cmd[i], *res.B_nom[i]]
        for c in range(4):
            r += [res.mean[i, c], res.std[i, c], res.low[i, c], res.high[i, c], u95[i, c]]
        r.append(int(res.n_valid[i]))
        rows.append(r)
    comments = [
        f"cfm-fem coupled: {res.field.describe()}; trials={res.trials}; seed={res.seed}; "
        f"align={res.align}",
        f"B_ref = {res.field.b_ref_T!r} T ({res.field.b_ref_rule}); units = 1e-4 B_ref",
        "positions: magnet frame (x, y, z) and commanded axis positions (q); E_f = meas - nom",
    ]
    return _csv(header, rows, comments)


# --------------------------------------------------------------------------- tracker


def tracker_summary(comp, bench, *, budget=None, extra=None) -> dict:
    """``compare.json`` of ``cfm-fem compare --tracker``: Table IV both sides, Fig. 12, ISO."""
    keep = ("systematic_um", "std_um", "U_p_um")
    table = {
        side: {a: {k: d[a][k] for k in keep} for a in ("x", "y", "z", "norm")}
        for side, d in (("experiment", comp.pooled_exp), ("simulation", comp.pooled_sim))
    }
    doc = {
        "kind": "tracker",
        "recording": comp.source,
        "points": int(len(comp.ids)),
        "readings": int(comp.count.sum()),
        "repetitions": {"min": int(comp.count.min()), "max": int(comp.count.max())},
        "table_iv": table,
        "paper_table_iv": PAPER_TABLE_IV,
        "pooled_experiment": comp.pooled_exp,
        "pooled_simulation": comp.pooled_sim,
        "fig12": comp.fig12,
        "per_point": {
            "z_rms": {
                a: float(np.sqrt(np.nanmean(comp.z[:, k] ** 2))) for k, a in enumerate("xyz")
            },
            "fraction_abs_z_above_2": {
                a: float(np.nanmean(np.abs(comp.z[:, k]) > 2)) for k, a in enumerate("xyz")
            },
            "mean_inside_sim_95": {a: float(comp.inside[:, k].mean()) for k, a in enumerate("xyz")},
            "readings_inside_sim_95": {
                a: float(comp.readings_inside[k]) for k, a in enumerate("xyz")
            },
            "definition": "z = (exp mean - sim mean) / sqrt(sim std^2 + u_tracker^2) per point "
            "and axis. A real bench is one draw of the simulated population, so the z of "
            "different points are correlated: a common shift says where this bench sits in the "
            "error PDFs; a spread or a trend of z over the volume says the model misses a "
            "position or time dependence",
        },
        "iso230_2": comp.iso,
        "tracker_u_um": comp.tracker_u_um,
        "trials": int(comp.sim.trials),
        "seed": int(comp.sim.seed),
        "bench": bench_description(bench),
        "notes": list(comp.notes) + list(comp.sim.notes),
    }
    if budget is not None:
        doc["positioning_budget"] = budget
    if extra:
        doc.update(extra)
    return doc


def tracker_points_csv(comp) -> str:
    """Per point: commanded position, measured and simulated mean/std, z, in um."""
    header = ["point_id", "reps", "q_x_mm", "q_y_mm", "q_z_mm"]
    for a in "xyz":
        header += [
            f"exp_mean_{a}_um",
            f"exp_std_{a}_um",
            f"sim_mean_{a}_um",
            f"sim_std_{a}_um",
            f"sim_low_{a}_um",
            f"sim_high_{a}_um",
            f"z_{a}",
        ]
    rows = []
    for i in range(len(comp.ids)):
        r = [int(comp.ids[i]), int(comp.count[i]), *comp.cmd[i]]
        for k in range(3):
            r += [
                1e3 * comp.exp_mean[i, k],
                1e3 * comp.exp_std[i, k],
                1e3 * comp.sim.mean[i, k],
                1e3 * comp.sim.std[i, k],
                1e3 * comp.sim.low[i, k],
                1e3 * comp.sim.high[i, k],
                comp.z[i, k],
            ]
        rows.append(r)
    return _csv(header, rows, [f"cfm-fem compare --tracker {comp.source}; bench frame"])


# --------------------------------------------------------------------------- Hall map


def hall_summary(comp, bench, *, field_budget=None, extra=None) -> dict:
    """``compare.json`` of ``cfm-fem compare --hall-map``: Table V both sides and Fig. 13."""
    keep = ("systematic_units", "std_units", "U_f_units")
    table = {
        side: {q: {k: d[q][k] for k in keep} for q in d}
        for side, d in (("experiment", comp.pooled_exp), ("simulation", comp.pooled_sim))
    }
    sim = comp.sim
    doc = {
        "kind": "hall",
        "recording": comp.source,
        "points": int(len(comp.ids)),
        "readings": int(comp.count.sum()),
        "repetitions": {"min": int(comp.count.min()), "max": int(comp.count.max())},
        "table_v": table,
        "paper_table_v": PAPER_TABLE_V,
        "pooled_experiment": comp.pooled_exp,
        "pooled_simulation": comp.pooled_sim,
        "fig13": comp.fig13,
        "per_point": {
            "z_rms": {
                q: float(np.sqrt(np.nanmean(comp.z[:, c] ** 2)))
                for c, q in enumerate(QUANTITIES)
                if c in sim.field.components
            },
            "definition": "z = (exp mean - sim mean) / sim std per point and component",
        },
        "b_ref_T": comp.b_ref_T,
        "b_ref_rule": sim.field.b_ref_rule,
        "r_ref_mm": sim.field.r_ref_mm,
        "reference": sim.field.describe(),
        "trials": int(sim.trials),
        "seed": int(sim.seed),
        "align": sim.align,
        "probe": sim.probe.assumptions(),
        "bench": bench_description(bench),
        "definitions": DEFINITIONS,
        "notes": list(comp.notes) + list(sim.notes),
    }
    if field_budget is not None:
        doc["field_budget"] = field_budget
    if extra:
        doc.update(extra)
    return doc


def hall_points_csv(comp) -> str:
    """Per point: position (magnet frame), reference field, measured and simulated E_f, units."""
    header = ["point_id", "reps", "x_mm", "y_mm", "z_mm", "Bx_ref_T", "By_ref_T", "Bz_ref_T"]
    for q in QUANTITIES:
        header += [f"exp_mean_{q}", f"exp_std_{q}", f"sim_mean_{q}", f"sim_std_{q}", f"z_{q}"]
    rows = []
    for i in range(len(comp.ids)):
        r = [int(comp.ids[i]), int(comp.count[i]), *comp.points[i], *comp.B_reference[i]]
        for c in range(4):
            r += [
                comp.exp_mean[i, c],
                comp.exp_std[i, c],
                comp.sim.mean[i, c],
                comp.sim.std[i, c],
                comp.z[i, c],
            ]
        rows.append(r)
    return _csv(
        header,
        rows,
        [
            f"cfm-fem compare --hall-map {comp.source}; E_f in units of 1e-4 B_ref = "
            f"{comp.b_ref_T!r} T"
        ],
    )
