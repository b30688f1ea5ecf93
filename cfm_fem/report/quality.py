"""Report of ``cfm-fem quality``: harmonics with their U95 against the tolerances, the magnetic
centre with its 95 % uncertainty ellipse, the budget by error group."""

from __future__ import annotations

import numpy as np

from ..models.quality.harmonics import N_HARMONICS
from .html import HtmlReport
from .plots import png_bytes, subplots

__all__ = ["quality_report", "harmonics_figure", "centre_figure", "budget_figure"]

#: chi-square quantile of 2 degrees of freedom at 95 %: the ellipse of a bivariate normal.
CHI2_2DOF_95 = 5.991464547107979


def harmonics_figure(summary: dict) -> bytes:
    """Bars of |b_n| and |a_n| (units) with U95 whiskers and the user's tolerances (log scale)."""
    integ = summary["integrated"]
    n = np.array(integ["n"])
    main = summary["main_order"]
    tol = {t["quantity"]: t["tolerance"] for t in (summary.get("tolerances") or [])}
    fig, axes = subplots(1, 2, figsize=(11, 3.8), sharey=True)
    for ax, key, letter in ((axes[0], "b_n_units", "b"), (axes[1], "a_n_units", "a")):
        v = np.array([np.nan if x is None else abs(x) for x in integ[key]])
        u = integ.get(f"U95_{key}")
        u = None if u is None else np.array([np.nan if x is None else x for x in u])
        keep = n != main if letter == "b" else np.ones(n.size, bool)
        ax.bar(n[keep], np.maximum(v[keep], 1e-6), color="C0", alpha=0.8, label=f"|{letter}_n|")
        if u is not None:
            ax.errorbar(n[keep], np.maximum(v[keep], 1e-6), yerr=[np.zeros(keep.sum()), u[keep]],
                        fmt="none", ecolor="k", capsize=3, label="+ U95")  # fmt: skip
            ax.plot(n[keep], u[keep], "r_", ms=12, mew=2, label="U95")
        tn = [k for k in n[keep] if f"{letter}{k}" in tol]
        if tn:
            ax.plot(tn, [tol[f"{letter}{k}"] for k in tn], "gv", ms=8, label="tolerance")
        ax.set_yscale("log")
        ax.set_xlabel("n")
        ax.set_xticks(n)
        ax.set_title(f"integrated {letter}_n at R_ref = {summary['r_ref_mm']:g} mm (units)")
        ax.legend(fontsize=7)
    axes[0].set_ylabel("units of 1e-4 of the main harmonic")
    return png_bytes(fig)


def centre_figure(summary: dict, deviations) -> bytes:
    """Monte Carlo centres (um, about the map's centre) with the 95 % covariance ellipse about
    their mean."""
    k = 2 * N_HARMONICS
    d = 1e3 * np.asarray(deviations)[:, k : k + 2]
    cov = np.cov(d.T)
    w, v = np.linalg.eigh(cov)
    t = np.linspace(0, 2 * np.pi, 200)
    ell = (v @ (np.sqrt(CHI2_2DOF_95 * np.maximum(w, 0))[:, None] * np.vstack([np.cos(t),
           np.sin(t)]))).T  # fmt: skip
    mean = d.mean(axis=0)
    ell = ell + mean
    fig, ax = subplots(figsize=(5, 5))
    ax.plot(d[:2000, 0], d[:2000, 1], ".", ms=2, alpha=0.4, color="C0", label="trials")
    ax.plot(ell[:, 0], ell[:, 1], "k-", lw=1.5, label="95 % ellipse about the mean")
    ax.plot([mean[0]], [mean[1]], "k+", ms=10, label="mean (systematic)")
    ax.plot([0.0], [0.0], "rx", ms=8, label="map's centre")
    c = summary["centre_mm"]
    ax.set_title(f"centre ({c[0] * 1e3:.3g}, {c[1] * 1e3:.3g}) um; deviations", fontsize=9)
    ax.set_xlabel("x deviation (um)")
    ax.set_ylabel("y deviation (um)")
    ax.set_aspect("equal", "datalim")
    ax.legend(fontsize=7)
    return png_bytes(fig)


def budget_figure(budget: dict) -> bytes:
    """U95 of centre x, y, roll and magnetic length per error group."""
    groups = budget["groups"]
    names = [g["name"] for g in groups]
    centre = [g["U95_centre_mm"] or (None, None) for g in groups]  # None: no centre
    panels = [("centre x (um)", [None if c[0] is None else 1e3 * c[0] for c in centre]),
              ("centre y (um)", [None if c[1] is None else 1e3 * c[1] for c in centre]),
              ("roll (mrad)", [g["U95_roll_mrad"] for g in groups]),
              ("magnetic length (mm)", [g["U95_magnetic_length_mm"] for g in groups])]  # fmt: skip
    fig, axes = subplots(1, 4, figsize=(13, 3.2), sharey=True)
    y = np.arange(len(names))
    for ax, (title, vals) in zip(axes, panels, strict=True):
        ax.barh(y, [np.nan if x is None else x for x in vals], color="C1")
        ax.set_title(f"U95 {title}", fontsize=9)
        ax.tick_params(labelsize=7)
    axes[0].set_yticks(y)
    axes[0].set_yticklabels(names)
    return png_bytes(fig)


def _rows(summary):
    u = summary.get("uncertainty") or {}
    nt = (u.get("numerical_tolerance") or {}).get("U95_spread") or {}
    c, uc = summary["centre_mm"], summary.get("U95_centre_mm") or [None, None]
    sc = nt.get("centre_mm") or [None, None]
    um = lambda x: None if x is None else 1e3 * x  # noqa: E731
    return [
        ["centre x (um)", um(c[0]), um(uc[0]), um(sc[0])],
        ["centre y (um)", um(c[1]), um(uc[1]), um(sc[1])],
        ["roll (mrad)", summary["roll_mrad"], summary.get("U95_roll_mrad"), nt.get("roll_mrad")],
        ["magnetic length (mm)", summary["magnetic_length_mm"],
         summary.get("U95_magnetic_length_mm"), nt.get("magnetic_length_mm")],
        ["integrated main harmonic (T mm)", summary["main_integral_Tmm"],
         summary.get("U95_main_integral_Tmm"), nt.get("main_integral_Tmm")],
    ]  # fmt: skip


def quality_report(run, summary: dict, command_line: str | None = None) -> HtmlReport:
    """The HTML report of a `cfm_fem.workflows.quality.QualityRun` and its ``quality.json``."""
    r = HtmlReport("Field quality and its uncertainty")
    if command_line:
        r.code(command_line)
    r.paragraph(f"Map: {summary['field']['source']} ({summary['field']['nodes']} nodes); "
                f"{summary['sampling']['description']}; model between nodes: "
                f"{summary['field']['model']}.")  # fmt: skip
    u = summary.get("uncertainty")
    if u:
        r.paragraph(f"Uncertainty: mode {u['mode']}, {u['trials']} trials, seed {u['seed']}; "
                    f"{u['sources']}.")  # fmt: skip
    r.heading("Centre, roll, magnetic length")
    r.table(["quantity", "map", "U95", "U95 numerical tolerance"], _rows(summary))
    r.heading("Integrated harmonics")
    integ = summary["integrated"]
    rows = []
    for k in range(N_HARMONICS):
        ub = integ["U95_b_n_units"][k] if integ["U95_b_n_units"] else None
        ua = integ["U95_a_n_units"][k] if integ["U95_a_n_units"] else None
        rows.append([k + 1, integ["B_n_Tmm"][k], integ["A_n_Tmm"][k], integ["b_n_units"][k], ub,
                     integ["a_n_units"][k], ua])  # fmt: skip
    r.table(["n", "B_n (T mm)", "A_n (T mm)", "b_n (units)", "U95 b_n", "a_n (units)",
             "U95 a_n"], rows, table_id="harmonics")  # fmt: skip
    r.figure("harmonics.png", harmonics_figure(summary),
             "Integrated |b_n|, |a_n| (bars) with U95 (red, and whiskers above the bars) and "
             "the tolerances given (green); the main harmonic is left out.")  # fmt: skip
    if summary.get("tolerances"):
        r.heading("Tolerances")
        r.table(["quantity", "tolerance", "unit", "U95", "U95 / tolerance", "determined"],
                [[t["quantity"], t["tolerance"], t["unit"], t["U95"], t["ratio"],
                  t["determined"]] for t in summary["tolerances"]])  # fmt: skip
        r.paragraph("determined: the bench gives the quantity with U95 within its tolerance.",
                    "note")  # fmt: skip
    has_centre = None not in (summary["centre_mm"] or [None])  # a dipole has none
    if run.mc is not None and has_centre:
        r.heading("Magnetic centre")
        r.figure("centre.png", centre_figure(summary, run.mc.deviations),
                 "Centre of each Monte Carlo trial minus the map's, their mean (the bench's "
                 "systematic error) and the 95 % ellipse of their covariance about it "
                 "(chi-square, 2 degrees of freedom).")  # fmt: skip
    b = (u or {}).get("budget")
    if b:
        r.heading("Budget by error group")
        r.figure("budget.png", budget_figure(b), b["definition"])
        d = b["dominant"]
        r.table(["quantity", "dominant group"],
                [[k, d.get(k)] for k in ("centre_x", "centre_y", "roll", "length",
                                         "main_integral", "b1", "a1", "a2", "b3")])  # fmt: skip
    r.heading("Definitions and notes")
    r.bullets([f"{k}: {v}" for k, v in summary["definitions"].items()])
    if summary["notes"]:
        r.bullets(summary["notes"])
    return r
