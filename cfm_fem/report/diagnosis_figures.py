"""Readable report of a diagnosis: Markdown text and matplotlib figures (no file I/O here)."""

from __future__ import annotations

import numpy as np

__all__ = ["markdown", "figures"]


def _f(v, nd=3):
    return "n/a" if v is None else f"{v:.{nd}g}"


def markdown(summary: dict, source: str = "") -> str:
    """The report as Markdown (the figures are referenced by file name)."""
    s = summary
    fit = s["fit"]
    u = fit["unit"]
    lines = [
        f"# cfm-fem diagnose: {s['kind']} recording",
        "",
        f"Source: `{source}`" if source else "",
        "",
        f"**Mismatch: {'yes' if s['mismatch'] else 'no'}.** "
        + (
            "Effects found: " + ", ".join(e["name"] for e in s["effects"]) + "."
            if s["effects"]
            else "No catalogued effect is supported by the evidence."
        ),
        "",
        "## Fit before and after",
        "",
        "| | before | after |",
        "|---|---|---|",
        f"| residual RMS [{u}] | {_f(fit['rms_before'])} | {_f(fit['rms_after'])} |",
        f"| chi2/dof | {_f(fit['chi2_dof_before'])} | {_f(fit['chi2_dof_after'])} |",
        f"| held-out RMS [{u}] | {_f(fit['cv_rms_before'])} | {_f(fit['cv_rms_after'])} |",
        "",
        f"Noise std per component (pure error of the repetitions): "
        f"{', '.join(_f(v) for v in fit['noise_std'])} {u}; {fit['n_points']} points x "
        f"{fit['n_reps']} repetitions.",
        "",
        "![fit](fit.png)",
        "",
        "## Effects found (strongest first)",
        "",
    ]
    if not s["effects"]:
        lines.append("None.")
    for e in s["effects"]:
        lines.append(
            f"### {e['name']}: {e['description']}\n\ndelta BIC {e['delta_bic']}, "
            f"k_eff {e['k_eff']}, Holm p {_f(e['p_holm'])}, signature surviving the baseline "
            f"{_f(e['survival'])}, held-out RMS {_f(e['cv_rms_before'])} -> "
            f"{_f(e['cv_rms_after'])} {u}; evidence: {e.get('evidence', 'new signature')}\n"
        )
        lines.append("| parameter | value | std | unit |\n|---|---|---|---|")
        for k, v in e["params"].items():
            sd = e["param_std"].get(k)
            sd = f"{sd:.2g}" if sd is not None else f"at its {e['at_bound'][k]} bound"
            lines.append(f"| {k} | {v:.4g} | {sd} | {e['units'][k]} |")
        if e["not_determined"]:
            lines.append(f"\nNot determined by these data: {', '.join(e['not_determined'])}.")
        lines.append("")
    imp = s.get("implausible", [])
    if imp:
        lines += ["## Implausible fits (not claimed)", ""]
        lines += [f"- {c['name']} (delta BIC {c['delta_bic']}): {c['reason']}" for c in imp]
        lines.append("")
    lines += [
        "## All candidates",
        "",
        "| effect | status | delta BIC | k_eff | Holm p | survival | absorbed parameters |",
        "|---|---|---|---|---|---|---|",
    ]
    for c in s["candidates"]:
        lines.append(
            f"| {c['name']} | {c['status']} | {c['delta_bic']} | {c['k_eff']} | "
            f"{_f(c['p_holm'])} | {_f(c['survival'])} | "
            f"{', '.join(c.get('absorbed_params', [])) or '-'} |"
        )
    for name, why in s["untestable"].items():
        lines.append(f"| {name} | not testable: {why} | | | | |")
    lines += ["", "## Where the residuals are significant (baseline, BH-controlled)", ""]
    if not s["located"]:
        lines.append("Nowhere.")
    for loc in s["located"]:
        lines.append(
            f"- component {loc['component']}: {loc['where']}; {loc['n_points']} points, "
            f"max |z| {loc['max_abs_z']}"
        )
    lines += ["", "![residuals](residuals.png)", "", "## Calibration of the baseline", ""]
    cal = s["calibration"]
    lines.append(
        f"Condition number {_f(cal['condition_number'])}; rank {cal['rank']} of "
        f"{cal['n_params']} parameters; {cal['n_not_identifiable']} combinations not "
        "identifiable (held at their priors):"
    )
    for comb in cal["not_identifiable"]:
        lines.append("- " + " + ".join(f"{v:+.2f} {k}" for k, v in comb.items()))
    if cal["correlated_pairs"]:
        lines.append("\nStrongly correlated estimates:")
        for p in cal["correlated_pairs"]:
            lines.append(f"- {p['a']} / {p['b']}: {p['correlation']}")
    worst = sorted(cal["parameters"], key=lambda p: -abs(p["z_vs_prior"]))[:5]
    lines.append("\nParameters furthest from their priors:\n")
    lines.append(
        "| parameter | value | std | prior mean | prior std | z |\n|---|---|---|---|---|---|"
    )
    for p in worst:
        lines.append(
            f"| {p['name']} [{p['unit']}] | {p['value']:.4g} | {p['std']:.2g} | "
            f"{p['prior_mean']:.3g} | {_f(p['prior_std'])} | {p['z_vs_prior']:.2f} |"
        )
    lines += ["", "## Advice", ""] + [f"- {a}" for a in s["advice"]] + ["", "## Notes", ""]
    lines += [f"- {n}" for n in s["notes"]]
    lines.append(f"- thresholds: {s['thresholds']}")
    return "\n".join(lines) + "\n"


def figures(summary: dict, arrays: dict) -> dict:
    """Matplotlib figures: ``fit`` (before/after bars and residual histograms) and
    ``residuals`` (standardised point means against the three coordinates)."""
    from .plots import subplots

    fit = summary["fit"]
    u = fit["unit"]
    f1, ax = subplots(1, 2, figsize=(10, 3.8))
    labels = ["RMS", "held-out RMS"]
    before = [fit["rms_before"], fit["cv_rms_before"]]
    after = [fit["rms_after"], fit["cv_rms_after"]]
    x = np.arange(2)
    ax[0].bar(x - 0.2, before, 0.4, label="baseline")
    ax[0].bar(x + 0.2, after, 0.4, label="with effects")
    ax[0].set_xticks(x, labels)
    ax[0].set_ylabel(u)
    ax[0].set_title(
        f"RMS of the residuals; chi2/dof {fit['chi2_dof_before']:.3g} -> "
        f"{fit['chi2_dof_after']:.3g}",
        fontsize=10,
    )
    ax[0].set_ylim(0, 1.35 * max(max(before), max(after), 1e-300))  # room for the legend
    ax[0].legend(loc="upper right", ncol=2)
    rb, ra = arrays["resid_before"].ravel(), arrays["resid_after"].ravel()
    lim = np.quantile(np.abs(rb), 0.999)
    bins = np.linspace(-lim, lim, 80)
    ax[1].hist(rb, bins, histtype="step", lw=2.5, alpha=0.6, label="baseline")
    ax[1].hist(ra, bins, histtype="step", lw=1.2, ls="--", label="with effects")
    ax[1].set_xlabel(f"residual [{u}]")
    ax[1].set_ylabel("count")
    ax[1].set_title("residuals of every reading", fontsize=10)
    ax[1].legend()
    f1.tight_layout()
    f2, ax = subplots(3, 3, figsize=(11, 8), sharey="row")
    zp, pp = arrays["zp_before"], arrays["point_pos"]
    za = arrays["zp_after"]
    for c in range(3):
        for a in range(3):
            ax[c, a].plot(pp[:, a], zp[:, c], "o", ms=5, mfc="none", label="baseline")
            ax[c, a].plot(pp[:, a], za[:, c], ".", ms=4, label="with effects")
            ax[c, a].axhline(0, color="k", lw=0.5)
            if c == 2:
                ax[c, a].set_xlabel(f"{'xyz'[a]} [mm]")
        ax[c, 0].set_ylabel(f"mean residual {'xyz'[c]} / its std")
    ax[0, 0].legend(fontsize=8)
    f2.suptitle("standardised mean residual per point against the point's position", fontsize=11)
    f2.tight_layout()
    return {"fit": f1, "residuals": f2}
