"""The HTML report of ``cfm-fem kinematics``: Table IV beside the paper, the systematic error
over the volume (Fig. 10), the uncertainty budget, assumptions and provenance."""

from __future__ import annotations

import json

from .html import HtmlReport
from .plots import fig10_systematic
from .runs import _assumptions, _budget_table, _reproduce

__all__ = ["kinematics_report"]


def kinematics_report(res, summary: dict) -> HtmlReport:
    """Report of ``cfm-fem kinematics``.

    Parameters
    ----------
    res : cfm_fem.models.kinematics.monte_carlo.KinematicsResult
    summary : dict
        Its ``summary.json`` document (`cfm_fem.io.kinematics_out.kinematics_summary`).
    """
    s = summary
    rep = HtmlReport("Probe positioning error of the bench (paper Table IV)")
    rep.paragraph(
        f"Bench {s['bench']['name']}: {s['points']} scan points, {s['trials']} trials, seed "
        f"{s['seed']}; 95 % intervals: {s['interval_method']}."
    )
    paper = s["paper_table_iv"]
    rows = []
    for a in ("x", "y", "z", "norm"):
        d = s["axes"][a] if a in s["axes"] else s["norm"]
        sim = paper["simulation"].get(a, {})
        exp = paper["experiment"].get(a, {})
        rows.append(
            [
                a.upper() if a != "norm" else "|E_p|",
                d["systematic_um"],
                d["std_um"],
                d["U_p_um"],
                d["U_p_max_um"],
                sim.get("systematic_um"),
                sim.get("std_um"),
                exp.get("systematic_um"),
                exp.get("std_um"),
            ]
        )
    rep.heading("Table IV (um)")
    rep.table(
        ["axis", "systematic", "std", "U_p", "U_p max (point)", "paper sim. sys",
         "paper sim. std", "paper exp. sys", "paper exp. std"],
        rows,
        table_id="table_iv",
    )  # fmt: skip
    rep.paragraph(s["pooling"], "note")
    rep.figure(
        "fig10.png",
        fig10_systematic(res.q_cmd, 1e3 * res.mean[:, :3], "Fig. 10 analogue (simulation)"),
        "Systematic positioning error per scan point over the commanded volume.",
    )
    if s.get("budget"):
        _budget_table(rep, s["budget"])
    gum = s.get("gum_validation")
    if gum:
        rep.heading("GUM against Monte Carlo (JCGM 101 section 8, per point)", 3)
        keys = list(next(iter(gum.values())))
        rep.table(["axis", *keys], [[a, *(gum[a].get(k) for k in keys)] for a in gum],
                  table_id="gum")  # fmt: skip
    _assumptions(rep, s["bench"], s["notes"])
    rep.heading("Provenance", 3)
    rep.code(json.dumps(s.get("provenance") or {}, indent=1, sort_keys=True))
    _reproduce(rep, (s.get("provenance") or {}).get("command_line"))
    return rep
