"""The HTML report of ``cfm-fem diagnose``, from its ``diagnosis.json`` document.

Sections: verdict, fit before and after, effects found with their parameters, implausible fits,
every candidate, where the residuals are significant, the calibration of the baseline, advice,
notes and provenance. Keys beyond the 4.3 contract are read with defaults, so a summary that
lacks one still gives a report.
"""

from __future__ import annotations

import json

from .html import HtmlReport

__all__ = ["diagnosis_report"]


def _fit(rep: HtmlReport, s: dict) -> None:
    fit = s["fit"]
    u = fit.get("unit", "")
    rep.heading("Fit before and after")
    rep.table(
        ["", "before", "after"],
        [
            [f"residual RMS [{u}]", fit["rms_before"], fit["rms_after"]],
            ["chi2/dof", fit["chi2_dof_before"], fit["chi2_dof_after"]],
            [f"held-out RMS [{u}]", fit.get("cv_rms_before"), fit.get("cv_rms_after")],
        ],
        table_id="fit",
    )
    if "noise_std" in fit:
        rep.paragraph(
            "Noise std per component (pure error of the repetitions): "
            + ", ".join(f"{v:.3g}" for v in fit["noise_std"])
            + f" {u}; {fit.get('n_points', '?')} points x {fit.get('n_reps', '?')} repetitions.",
            "note",
        )


def _effects(rep: HtmlReport, s: dict) -> None:
    rep.heading("Effects found (strongest first)")
    if not s["effects"]:
        rep.paragraph("None: no catalogued effect is supported by the evidence.")
    for e in s["effects"]:
        rep.heading(f"{e['name']}: {e.get('description', '')}".rstrip(": "), 3)
        rep.paragraph(
            f"delta BIC {e['delta_bic']}; held-out RMS {e['cv_rms_before']:.3g} -> "
            f"{e['cv_rms_after']:.3g}; evidence: {e.get('evidence', 'new signature')}",
            "note",
        )
        units = e.get("units", {})
        rep.table(
            ["parameter", "value", "std", "unit"],
            [[k, v, e["param_std"].get(k), units.get(k, "")] for k, v in e["params"].items()],
            digits=4,
        )
        if e.get("not_determined"):
            rep.paragraph("Not determined by these data: " + ", ".join(e["not_determined"]))
    if s.get("implausible"):
        rep.heading("Implausible fits (not claimed)", 3)
        rep.bullets(
            f"{c['name']} (delta BIC {c.get('delta_bic')}): {c['reason']}" for c in s["implausible"]
        )


def _candidates(rep: HtmlReport, s: dict) -> None:
    if not s.get("candidates") and not s.get("untestable"):
        return
    rep.heading("All candidates", 3)
    rows = [
        [
            c["name"],
            c.get("status"),
            c.get("delta_bic"),
            c.get("k_eff"),
            c.get("p_holm"),
            c.get("survival"),
            ", ".join(c.get("absorbed_params", [])) or "-",
        ]
        for c in s.get("candidates", [])
    ]
    rows += [[n, f"not testable: {why}", None, None, None, None, "-"]
             for n, why in s.get("untestable", {}).items()]  # fmt: skip
    rep.table(
        ["effect", "status", "delta BIC", "k_eff", "Holm p", "survival", "absorbed parameters"],
        rows,
        table_id="candidates",
    )


def _calibration(rep: HtmlReport, cal: dict) -> None:
    rep.heading("Calibration of the baseline", 3)
    rep.paragraph(
        f"Condition number {cal.get('condition_number', float('nan')):.3g}; rank "
        f"{cal.get('rank')} of {cal.get('n_params')} parameters; "
        f"{cal.get('n_not_identifiable', 0)} combinations not identifiable (held at their priors)."
    )
    combos = cal.get("not_identifiable", [])
    if combos:
        rep.bullets(" + ".join(f"{v:+.2f} {k}" for k, v in c.items()) for c in combos)
    pairs = cal.get("correlated_pairs", [])
    if pairs:
        rep.paragraph("Strongly correlated estimates:")
        rep.bullets(f"{p['a']} / {p['b']}: {p['correlation']}" for p in pairs)
    worst = sorted(cal.get("parameters", []), key=lambda p: -abs(p["z_vs_prior"]))[:5]
    if worst:
        rep.table(
            ["parameter", "value", "std", "prior mean", "prior std", "z"],
            [
                [
                    f"{p['name']} [{p['unit']}]",
                    p["value"],
                    p["std"],
                    p["prior_mean"],
                    p["prior_std"],
                    p["z_vs_prior"],
                ]
                for p in worst
            ],  # fmt: skip
            table_id="calibration",
            digits=4,
        )


def diagnosis_report(summary: dict, images: dict, source: str = "") -> HtmlReport:
    """Report of ``cfm-fem diagnose``.

    Parameters
    ----------
    summary : dict
        The ``diagnosis.json`` document.
    images : dict of str -> bytes
        PNG figures by file name (``fit.png``, ``residuals.png``); embedded in that order.
    source : str
        The recording's path.

    Returns
    -------
    HtmlReport
    """
    s = summary
    rep = HtmlReport(f"Diagnosis of a {s.get('kind', '')} recording (cfm-fem diagnose)")
    found = ", ".join(e["name"] for e in s["effects"]) or "none"
    rep.paragraph(
        (f"Recording {source}. " if source else "")
        + f"Mismatch: {'yes' if s['mismatch'] else 'no'}. Effects found: {found}."
    )
    _fit(rep, s)
    if "fit.png" in images:
        rep.figure("fit.png", images["fit.png"], "Residual RMS and held-out RMS before and "
                   "after the effects; residual histograms.")  # fmt: skip
    _effects(rep, s)
    _candidates(rep, s)
    rep.heading("Where the residuals are significant (baseline, BH-controlled)", 3)
    rep.bullets(
        [f"component {loc['component']}: {loc['where']}; {loc['n_points']} points, max |z| "
         f"{loc['max_abs_z']}" for loc in s["located"]] or ["Nowhere."]
    )  # fmt: skip
    if "residuals.png" in images:
        caption = "Standardised residuals of the point means against each coordinate."
        rep.figure("residuals.png", images["residuals.png"], caption)
    for name, png in images.items():
        if name not in ("fit.png", "residuals.png"):
            rep.figure(name, png, name.removesuffix(".png").replace("_", " "))
    if s.get("calibration"):
        _calibration(rep, s["calibration"])
    rep.heading("Advice", 3)
    rep.bullets(s["advice"] or ["None."])
    rep.heading("Notes", 3)
    notes = list(s.get("notes", []))
    if "thresholds" in s:
        notes.append(f"thresholds: {s['thresholds']}")
    rep.bullets(notes or ["None."])
    prov = s.get("provenance") or {}
    rep.heading("Provenance", 3)
    rep.code(json.dumps(prov, indent=1, sort_keys=True, default=str))
    rep.heading("Reproduce", 3)
    rep.code(prov.get("command_line") or "(command line not recorded)")
    return rep
