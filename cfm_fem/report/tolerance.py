"""The HTML report of ``cfm-fem tolerance``: which geometric tolerances set U_p, how far each
may go for the target, and the plan that meets it."""

from __future__ import annotations

import numpy as np

from .html import HtmlReport
from .plots import share_bars
from .runs import _assumptions, _reproduce

__all__ = ["tolerance_report"]

AXES = "xyz"


def _factor_text(f) -> str:
    if f is None:
        return "cannot alone"
    if isinstance(f, str) or not np.isfinite(f):
        return "free"
    return f"{f:.3g}"


def tolerance_report(d: dict, meaning: str, command_line: str | None = None) -> HtmlReport:
    """Report of ``cfm-fem tolerance``.

    Parameters
    ----------
    d : dict
        The ``tolerance.json`` document (`cfm_fem.models.kinematics.budget.design_tolerances`
        with ``bench`` and, after ``--check``, ``plan_check_mc``).
    meaning : str
        What ``up_share`` means (`UP_SHARE_MEANING`).
    command_line : str, optional
    """
    rep = HtmlReport("Tolerances of the bench for a target U_p")
    if not d["feasible"]:
        verdict = "the target cannot be met: it lies below the vibration and delay floor"
    elif d["plan"]:
        verdict = "the plan below meets the target"
    else:
        verdict = "the current tolerances meet the target"
    rep.paragraph(
        f"Bench {d['bench']['name']}: {verdict}. A factor > 1 says how far a tolerance may be "
        "loosened on its own, < 1 how far it must be tightened."
    )
    rep.heading("U_p per axis (um, 95 %)")
    rows = [
        ["target", *d["target_um"]],
        ["now (linearised)", *d["current_um"]],
        ["floor: vibration and delay", *d["noise_floor_um"]],
        [f"all tolerances x {_factor_text(d['common_factor'])}", *d["up_at_common_um"]],
    ]
    if d["plan"]:
        rows.append(["after the plan", *d["up_after_plan_um"]])
    check = d.get("plan_check_mc")
    if check:
        rows.append([f"plan, Monte Carlo ({check['trials']} trials)",
                     *(check[a]["U_p_um"] for a in AXES)])  # fmt: skip
    rep.table(["", "X", "Y", "Z"], rows, table_id="up")
    if d["plan"]:
        rep.heading("Plan (largest contributors first)", 3)
        rep.table(["error", "factor"], [[s["name"], s["factor"]] for s in d["plan"]],
                  table_id="plan")  # fmt: skip
    ranked = sorted(d["rows"], key=lambda r: -max(r["up_share"].values()))
    rep.heading("Each error's share of U_p^2 and the factor that meets the target alone", 3)
    rep.table(
        ["error", "tolerance now", "share X %", "Y %", "Z %", "factor", "U_p X", "Y", "Z"],
        [
            [r["name"], r["pdf"], *(100 * r["up_share"][a] for a in AXES),
             _factor_text(r["factor"]), *(r.get("up_at_factor_um") or [None] * 3)]
            for r in ranked
        ],
        table_id="errors",
        digits=3,
    )  # fmt: skip
    rep.paragraph(f"{meaning}.", "note")
    top = ranked[:10]
    rep.figure(
        "up_share.png",
        share_bars(
            [r["name"] for r in top],
            np.array([[100 * r["up_share"][a] for a in AXES] for r in top]),
            "Share of U_p^2 per error, ten largest (%)",
        ),  # fmt: skip
        "Each error's share of U_p^2 per axis (negative: its mean error opposes the total "
        "systematic error).",
    )
    _assumptions(rep, d["bench"], [f"method: {d['method']}"])
    _reproduce(rep, command_line)
    return rep
