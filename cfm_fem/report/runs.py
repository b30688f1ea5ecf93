"""The HTML report of each run type, from its result and its JSON summary.

Each ``*_report`` returns an `HtmlReport` (figures embedded; ``report.images`` holds the PNGs for
the side files). Numbers in the tables come from the summary document, so the report and
``summary.json`` / ``compare.json`` always agree.
"""

from __future__ import annotations

import numpy as np

from .html import HtmlReport
from .plots import (
    fig4_curve,
    fig4_plane,
    fig10_systematic,
    hist_figure,
    interval_figure,
    residual_figure,
)

__all__ = ["coupled_report", "tracker_report", "hall_report", "fig4_report"]


def _budget_table(rep: HtmlReport, budget: dict) -> None:
    rep.heading("Uncertainty budget of the positioning (kinematics.uncertainty_budget)", 3)
    rep.paragraph(budget["estimator"], "note")
    rows = []
    for r in sorted(budget["rows"], key=lambda r: -max(r["up_share"].values())):
        rows.append(
            [
                r["name"],
                r["pdf"],
                *(100 * r["up_share"][a] for a in "xyz"),
                *(100 * r["var_share"][a] for a in "xyz"),
            ]
        )
    rep.table(
        ["error", "PDF", "U_p^2 share X %", "Y %", "Z %", "u^2 share X %", "Y %", "Z %"],
        rows,
        table_id="budget",
        digits=2,
    )


def _reproduce(rep: HtmlReport, command_line: str | None, extra=()) -> None:
    rep.heading("Reproduce", 3)
    lines = [command_line or "(command line not recorded)", *extra]
    rep.code("\n".join(lines))


def _assumptions(rep: HtmlReport, bench_doc: dict, notes, more=()) -> None:
    rep.heading("Assumptions and notes", 3)
    rep.bullets([*more, *bench_doc.get("assumptions", []), *notes])


# --------------------------------------------------------------------------- coupled


def coupled_report(res, summary: dict, command_line: str | None = None) -> HtmlReport:
    """Report of ``cfm-fem coupled``: Table V beside the paper, budget, histograms."""
    rep = HtmlReport("Coupled magnetic measurement model (paper eq. 12-14, Table V)")
    tv = summary["table_v"]
    s, ps, pe = tv["simulated"], tv["paper_simulated"], tv["paper_experimental"]
    rep.paragraph(
        f"Field: {summary['field']}. B_ref = {summary['b_ref_T']:.6g} T ({summary['b_ref_rule']}); "
        f"units = 1e-4 B_ref. Region: {summary['region']} ({summary['points']} points). "
        f"{summary['trials']} trials, seed {summary['seed']}, alignment '{summary['align']}'."
    )
    rep.heading("Table V (simulated E_f, units)")
    rep.table(
        ["", "systematic", "std", "U_f", "num. u (systematic / std / U_f)"],
        [
            [
                "this run (pooled Bx, By)" if len(res.field.components) == 2 else "this run (all)",
                s["systematic_units"],
                s["std_units"],
                s["U_f_units"],
                f"{s['systematic_num_u']:.2g} / {s['std_num_u']:.2g} / {s['U_f_num_u']:.2g}",
            ],
            ["paper, simulated", ps["systematic_units"], ps["std_units"], ps["U_f_units"], "-"],
            ["paper, experimental", pe["systematic_units"], pe["std_units"], pe["U_f_units"], "-"],
        ],
        table_id="table_v",
    )
    rows = [
        [
            q,
            d["systematic_units"],
            d["std_units"],
            d["U_f_units"],
            d["u95_p50_units"],
            d["u95_p95_units"],
            d["u95_max_units"],
        ]
        for q, d in summary["pooled"].items()
    ]
    rep.table(
        ["quantity", "systematic", "std", "U_f", "U95 p50", "U95 p95", "U95 max"],
        rows,
        table_id="pooled",
    )
    fb = summary.get("field_budget")
    if fb:
        rep.heading("Field budget", 3)
        rep.table(
            ["contribution", "systematic", "std", "U_f"],
            [
                [
                    "positioning only (probe exact)",
                    fb["positioning_only"]["systematic_units"],
                    fb["positioning_only"]["std_units"],
                    fb["positioning_only"]["U_f_units"],
                ],
                [
                    "probe only (bench exact)",
                    fb["probe_only"]["systematic_units"],
                    fb["probe_only"]["std_units"],
                    fb["probe_only"]["U_f_units"],
                ],
                ["both (this run)", s["systematic_units"], s["std_units"], s["U_f_units"]],
            ],
            table_id="field_budget",
        )
        rep.paragraph(f"{fb['definition']}; {fb['trials']} trials each.", "note")
    pp = summary["positioning_at_points_um"]
    rep.heading("Positioning error at the scan points (bench frame, um)", 3)
    rep.table(
        ["axis", "systematic", "std", "U_p"],
        [[a.upper(), pp[a]["systematic_um"], pp[a]["std_um"], pp[a]["U_p_um"]] for a in "xyz"],
        table_id="positioning",
    )
    if summary.get("positioning_budget"):
        _budget_table(rep, summary["positioning_budget"])
    i = res.probe_point
    panels = []
    for k, a in enumerate("xyz"):
        x = 1e3 * res.samples_ep[:, k]
        lo, hi = np.quantile(x, [0.025, 0.975])
        panels.append((x, lo, hi, f"E_p,{a}", "um"))
    for c in res.field.components:
        x = res.samples_ef[:, c]
        panels.append((x, res.low[i, c], res.high[i, c], f"E_f {res_q(c)}", "units"))
    rep.figure(
        "hist_point.png",
        hist_figure(
            panels, f"E_p and E_f at point {np.round(res.points[i], 3).tolist()} mm (largest |B|)"
        ),
        "Histograms of the positioning error E_p (bench frame) and of the field error E_f at the "
        "point of largest |B|, with the mean (solid) and the 95 % interval (dashed).",
    )
    panels = []
    for c in res.field.components:
        x = res.hist_ef[:, c]
        lo, hi = np.quantile(x, [0.025, 0.975])
        panels.append((x, lo, hi, f"E_f {res_q(c)}, all points", "units"))
    rep.figure(
        "hist_pooled.png",
        hist_figure(panels, "E_f pooled over the scan points"),
        f"E_f of the first {res.hist_ef.shape[0] // max(len(res.points), 1)} trials of every "
        "point, pooled; dashed: 2.5 % and 97.5 % quantiles of the pooled sample.",
    )
    _assumptions(rep, summary["bench"], summary["notes"], summary["probe"])
    rep.heading("Definitions", 3)
    rep.bullets(f"{k}: {v}" for k, v in summary["definitions"].items())
    _reproduce(rep, (summary.get("provenance") or {}).get("command_line"))
    return rep


def res_q(c: int) -> str:
    return ("Bx", "By", "Bz", "|B|")[c]


# --------------------------------------------------------------------------- tracker


def tracker_report(comp, summary: dict, command_line: str | None = None) -> HtmlReport:
    """Report of ``cfm-fem compare --tracker``: Table IV, Fig. 10, Fig. 12, residuals, ISO."""
    rep = HtmlReport("Laser tracker recording against the kinematic model (Table IV, Fig. 12)")
    rep.paragraph(
        f"Recording {summary['recording']}: {summary['points']} points, {summary['readings']} "
        f"readings ({summary['repetitions']['min']}-{summary['repetitions']['max']} per point). "
        f"Simulation: {summary['trials']} trials, seed {summary['seed']}, same commanded positions."
    )
    t = summary["table_iv"]
    pap = summary["paper_table_iv"]
    rows = []
    for a in "xyz":
        e, s = t["experiment"][a], t["simulation"][a]
        rows.append(
            [
                a.upper(),
                e["systematic_um"],
                e["std_um"],
                e["U_p_um"],
                s["systematic_um"],
                s["std_um"],
                s["U_p_um"],
                pap["experiment"][a]["systematic_um"],
                pap["experiment"][a]["std_um"],
                pap["simulation"][a]["systematic_um"],
                pap["simulation"][a]["std_um"],
            ]
        )
    rep.heading("Table IV (um)")
    rep.table(
        [
            "axis",
            "exp. systematic",
            "exp. std",
            "exp. U_p",
            "sim. systematic",
            "sim. std",
            "sim. U_p",
            "paper exp. sys",
            "paper exp. std",
            "paper sim. sys",
            "paper sim. std",
        ],
        rows,
        table_id="table_iv",
    )
    rep.figure(
        "fig12.png",
        interval_figure(
            comp.fig12,
            "E_p [um]",
            "Fig. 12 analogue: systematic -+ 2u per axis",
            labels=("MC", "LT"),
        ),
        "Systematic error (RMS over points) with -+ 2 pooled std for the simulation (MC) and the "
        "recording (LT), per axis.",
    )
    rep.table(
        ["axis", "sim low", "sim high", "exp low", "exp high", "overlap"],
        [
            [
                r["name"].upper(),
                r["sim"]["low"],
                r["sim"]["high"],
                r["exp"]["low"],
                r["exp"]["high"],
                r["overlap"],
            ]
            for r in summary["fig12"]
        ],
        table_id="fig12",
    )
    pp = summary["per_point"]
    rep.heading("Per point: measured against simulated", 3)
    rep.table(
        ["axis", "z RMS", "|z| > 2 fraction", "mean inside sim. 95 %", "readings inside sim. 95 %"],
        [
            [
                a.upper(),
                pp["z_rms"][a],
                pp["fraction_abs_z_above_2"][a],
                pp["mean_inside_sim_95"][a],
                pp["readings_inside_sim_95"][a],
            ]
            for a in "xyz"
        ],
        table_id="per_point",
    )
    rep.paragraph(pp["definition"], "note")
    rep.figure(
        "residuals.png",
        residual_figure(comp.z, ["x", "y", "z"], "standardised residuals of the per-point means"),
        "Histogram of z per axis against N(0, 1) (dashed).",
    )
    rep.figure(
        "fig10.png",
        fig10_systematic(comp.cmd, 1e3 * comp.exp_mean[:, :3], "Fig. 10 analogue (recording)"),
        "Measured systematic positioning error per point over the commanded volume.",
    )
    if summary["iso230_2"]:
        rep.heading("ISO 230-2 bidirectional single-axis runs (um)", 3)
        rows = []
        for r in summary["iso230_2"]:
            v = r["axis_values_um"]
            fixed = ", ".join(f"{k}={x:g}" for k, x in r["fixed_mm"].items())
            rows.append(
                [
                    f"{r['axis'].upper()} ({fixed} mm)",
                    r["targets"],
                    r["runs_up"],
                    v["A"],
                    v["E"],
                    v["M"],
                    v["R"],
                    v["B"],
                    v["B_mean"],
                ]
            )
        rep.table(
            ["line", "targets", "runs/dir", "A", "E", "M", "R", "B", "B mean"],
            rows,
            table_id="iso230",
        )
    if summary.get("positioning_budget"):
        _budget_table(rep, summary["positioning_budget"])
    _assumptions(rep, summary["bench"], summary["notes"])
    _reproduce(rep, command_line)
    return rep


# --------------------------------------------------------------------------- Hall map


def hall_report(comp, summary: dict, command_line: str | None = None) -> HtmlReport:
    """Report of ``cfm-fem compare --hall-map``: Table V both sides, Fig. 13, histograms."""
    rep = HtmlReport(
        "Hall map against the reference field and the coupled model (Table V, Fig. 13)"
    )
    rep.paragraph(
        f"Recording {summary['recording']}: {summary['points']} points, {summary['readings']} "
        f"readings. Reference: {summary['reference']}. B_ref = {summary['b_ref_T']:.6g} T "
        f"({summary['b_ref_rule']}). Simulation: {summary['trials']} trials, seed "
        f"{summary['seed']}, alignment '{summary['align']}'."
    )
    t = summary["table_v"]
    pap = summary["paper_table_v"]
    rows = []
    for q in t["experiment"]:
        e, s = t["experiment"][q], t["simulation"][q]
        rows.append(
            [
                q,
                e["systematic_units"],
                e["std_units"],
                e["U_f_units"],
                s["systematic_units"],
                s["std_units"],
                s["U_f_units"],
            ]
        )
    pe, ps = pap["experiment"], pap["simulation"]
    rows.append(
        [
            "paper",
            pe["systematic_units"],
            pe["std_units"],
            pe["U_f_units"],
            ps["systematic_units"],
            ps["std_units"],
            ps["U_f_units"],
        ]
    )
    rep.heading("Table V (units)")
    rep.table(
        [
            "quantity",
            "exp. systematic",
            "exp. std",
            "exp. U_f",
            "sim. systematic",
            "sim. std",
            "sim. U_f",
        ],
        rows,
        table_id="table_v",
    )
    rep.figure(
        "fig13.png",
        interval_figure(comp.fig13, "E_f [units]", "Fig. 13 analogue: systematic -+ 2u"),
        "Systematic E_f (RMS over points) with -+ 2 pooled std, simulation (MC) and experiment.",
    )
    rep.table(
        ["quantity", "sim low", "sim high", "exp low", "exp high", "overlap"],
        [
            [
                r["name"],
                r["sim"]["low"],
                r["sim"]["high"],
                r["exp"]["low"],
                r["exp"]["high"],
                r["overlap"],
            ]
            for r in summary["fig13"]
        ],
        table_id="fig13",
    )
    comps = comp.sim.field.components
    labels = [res_q(c) for c in comps]
    rep.figure(
        "residuals.png",
        residual_figure(comp.z[:, list(comps)], labels, "standardised residuals per point"),
        "(exp mean - sim mean) / sim std per point, against N(0, 1) (dashed).",
    )
    sim = comp.sim
    panels = []
    for c in comps:
        x = sim.hist_ef[:, c]
        lo, hi = np.quantile(x, [0.025, 0.975])
        panels.append((x, lo, hi, f"simulated E_f {res_q(c)}", "units"))
    rep.figure(
        "hist_sim.png",
        hist_figure(panels, "simulated E_f pooled over the map's points"),
        "Simulated E_f, first trials of every point pooled; dashed: 2.5 % and 97.5 % quantiles.",
    )
    fb = summary.get("field_budget")
    if fb:
        rep.heading("Field budget", 3)
        rep.table(
            ["contribution", "systematic", "std", "U_f"],
            [
                [name, fb[key]["systematic_units"], fb[key]["std_units"], fb[key]["U_f_units"]]
                for name, key in (
                    ("positioning only", "positioning_only"),
                    ("probe only", "probe_only"),
                )
            ],
            table_id="field_budget",
        )
    _assumptions(rep, summary["bench"], summary["notes"], summary["probe"])
    _reproduce(rep, command_line)
    return rep


# --------------------------------------------------------------------------- Fig. 4


def fig4_report(summary: dict, plane_points, plane_uf, command_line: str | None = None):
    """Report of ``cfm-fem fig4``: U_f against U_p beside the paper, with the scaling law."""
    rep = HtmlReport("Fig. 4 analogue: field uncertainty U_f against positioning uncertainty U_p")
    rep.paragraph(
        f"Map {summary['source']} ({summary['nodes']} nodes); B_ref = {summary['b_ref_T']:.6g} T "
        f"({summary['b_ref_rule']}); {summary['trials']} trials per node, seed {summary['seed']}; "
        f"U_f of one node known to +-{100 * summary['uf_relative_mc_std']:.1f} % (1 sigma)."
    )
    t = summary["table"]
    rep.heading("U_f (95 %, units) over the nodes of the magnet body")
    rep.table(
        ["U_p [um]", "p50", "p95", "max", "1.96 U_p G_med / B_ref", "paper"],
        [[r["up_um"], r["p50"], r["p95"], r["max"], r["analytic"], r["paper"]] for r in t],
        table_id="fig4",
    )
    rep.paragraph(summary["explanation"])
    rep.figure(
        "fig4_curve.png",
        fig4_curve(
            [r["up_um"] for r in t],
            {"p50": [r["p50"] for r in t], "p95": [r["p95"] for r in t]},
            paper={float(k): v for k, v in summary["paper"].items()},
            analytic=[r["analytic"] for r in t],
        ),
        "U_f (95 %) over the magnet-body nodes against U_p, with the linear law and the paper's "
        "two values (for its own magnet).",
    )
    rep.figure(
        "fig4_plane.png",
        fig4_plane(
            plane_points,
            plane_uf,
            [r["up_um"] for r in t],
            "U_f on the longitudinal plane |y| < 0.5 mm",
        ),
        "Paper Fig. 4 view: U_f per node on the x-z plane through the axis, one panel per U_p.",
    )
    rep.heading("Notes", 3)
    rep.bullets(summary["notes"])
    _reproduce(rep, command_line)
    return rep
