"""The diagnosis workflow: calibrate, locate, attribute, model, advise.

``diagnose(problem)`` returns a :class:`Diagnosis` whose ``summary`` is the ``diagnosis.json``
document (``mismatch``, ``located``, ``effects`` sorted by evidence, strongest first, ``fit``,
``advice``); the arrays (residuals before/after, standardised residuals) feed the report and the
``.vtu`` maps.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from threadpoolctl import threadpool_limits

from . import effects as fx
from .calibrate import correlated_pairs, fit_map, identifiability, stack
from .locate import locate
from .problem import Problem, noise_sigma
from .select import cv_rms, overlaps, select_effects, structural_absorption

__all__ = ["Diagnosis", "diagnose", "DEFAULTS"]

#: Decision thresholds (documented in the outputs).
DEFAULTS = {"bic_min": 10.0, "alpha": 0.01, "cv_z": 2.0, "fdr_q": 0.01, "overlap_max": 0.9}


@dataclass
class Diagnosis:
    summary: dict
    arrays: dict = field(default_factory=dict)
    seconds: float = 0.0


def _rms(prob, resid):
    return float(np.sqrt(np.mean((resid * prob.to_display) ** 2)))


def _chi2_dof(resid, sigma, edf):
    r = resid / sigma
    return float((r**2).sum() / max(r.size - edf, 1))


def diagnose(prob: Problem, progress=None, **opts) -> Diagnosis:
    """Run the whole diagnosis on a problem.

    Parameters
    ----------
    prob : Problem
    progress : callable, optional
        Called with an increment after each candidate fit.
    **opts
        Overrides of ``DEFAULTS``.

    Notes
    -----
    The fits are many small dense solves: BLAS runs them on one thread. A threaded BLAS gains
    nothing at these sizes and, when other work loads the machine, its threads spin against it
    (a tracker diagnosis took 45 s instead of 10 s next to a matrix product in another process).
    """
    with threadpool_limits(limits=1, user_api="blas"):
        return _diagnose(prob, progress, **opts)


def _diagnose(prob: Problem, progress=None, **opts) -> Diagnosis:
    t0 = time.perf_counter()
    o = {**DEFAULTS, **opts}
    base = stack(prob.baseline)

    def sigma_fn(resid, edf, var_known=None):
        return noise_sigma(prob, resid, edf, var_known)[0]

    # 1. calibrate what the model already contains
    fit0 = fit_map(prob.y, np.ones_like(prob.y), base)
    sigma0 = sigma_fn(fit0.resid, fit0.edf)
    fit_b = fit_map(prob.y, sigma0, base)
    ident = identifiability(sigma0, base)
    corr = correlated_pairs(fit_b, base.names)
    # prior consistency of the calibrated parameters (z of posterior vs prior)
    has = np.isfinite(base.prior_std)
    zprior = np.where(has, (fit_b.theta - base.prior_mean) / np.where(has, base.prior_std, 1), 0)
    calib = {
        "parameters": [
            {
                "name": n,
                "unit": u,
                "value": float(v),
                "std": float(s),
                "prior_mean": float(m),
                "prior_std": float(ps) if np.isfinite(ps) else None,
                "z_vs_prior": float(z),
            }
            for n, u, v, s, m, ps, z in zip(
                base.names,
                base.units,
                fit_b.theta,
                fit_b.std,
                base.prior_mean,
                base.prior_std,
                zprior,
                strict=True,
            )
        ],
        **ident,
        "correlated_pairs": corr,
    }
    # 2. locate (against the calibrated baseline)
    loc0 = locate(prob, fit_b.resid, sigma0, q=o["fdr_q"], edf=fit_b.edf)
    # 3. attribute
    blocks, untestable = fx.build(prob)
    absorption = {
        name: structural_absorption(prob, sigma0, base, blk) for name, blk in blocks.items()
    }
    absorbed = [
        name
        for name, blk in blocks.items()
        if blk.p and not blk.release and len(absorption[name]) == blk.p
    ]
    # invisible parameters are not fitted: their value would be set by the baseline's priors,
    # not by the data (and would dilute the evidence of the visible ones)
    for name, blk in list(blocks.items()):
        gone = {a["name"] for a in absorption[name]}
        if gone and name not in absorbed:
            blocks[name] = blk.subset([k for k, n in enumerate(blk.names) if n not in gone])
    sel = select_effects(
        prob,
        sigma_fn,
        blocks,
        bic_min=o["bic_min"],
        alpha=o["alpha"],
        cv_z=o["cv_z"],
        absorbed=absorbed,
        progress=progress,
    )
    # 4. model: final fit with the selected effects
    model = sel.model
    sigma1 = sel.sigma
    fit1 = fit_map(prob.y, sigma1, model)
    loc1 = locate(prob, fit1.resid, sigma1, q=o["fdr_q"], edf=fit1.edf)
    cv_b, _ = cv_rms(prob, sigma0, base, sel.folds)
    cv_a, _ = cv_rms(prob, sigma1, model, sel.folds) if sel.selected else (cv_b, None)
    eff_out = []
    for c in sel.accepted:
        idx = [model.names.index(n) for n in c.param_names]
        th, sd = fit1.theta[idx], fit1.std[idx]
        keep = sd < 0.5 * fx.WIDE  # parameters the data determine
        units = [model.units[i] for i in idx]
        base_prior = dict(
            zip(base.names, zip(base.prior_mean, base.prior_std, strict=True), strict=True)
        )
        phys = None
        if c.has_new and c.cols.physical is not None:
            nb = c.cols.p
            ib = [model.names.index(n) for n in c.param_names[-nb:]]
            phys = c.cols.physical(c.param_names[-nb:], fit1.theta[ib], fit1.cov[np.ix_(ib, ib)])
        det = [i for i, k in zip(idx, keep, strict=True) if k]
        sd_det = np.sqrt(np.clip(np.diag(fit1.cov)[det], 1e-300, None))
        corr = fit1.cov[np.ix_(det, det)] / np.outer(sd_det, sd_det)
        eff_out.append(
            {
                "name": c.name,
                "params": {
                    n: float(v) for n, v, k in zip(c.param_names, th, keep, strict=True) if k
                },
                "param_std": {
                    n: float(s) for n, s, k in zip(c.param_names, sd, keep, strict=True) if k
                },
                "units": {n: u for n, u, k in zip(c.param_names, units, keep, strict=True) if k},
                "not_determined": [n for n, k in zip(c.param_names, keep, strict=True) if not k],
                # posterior correlations of the determined parameters (order of ``params``)
                "param_corr": [[float(v) for v in row] for row in corr],
                "evidence": (
                    "prior-data conflict" + (" and new signature" if c.has_new else "")
                    if c.released
                    else "new signature"
                ),
                "released_priors": {
                    n: {"mean": float(base_prior[n][0]), "std": float(base_prior[n][1])}
                    for n in c.released
                },
                "conflict_z": {
                    d["name"]: round(d["z"], 2) for d in c.conflict if d["name"] in c.released
                },
                "delta_bic": round(c.delta_bic, 2),
                "delta_chi2": round(c.delta_chi2, 2),
                "k_eff": round(c.k, 2),
                "p_holm": c.p_holm,
                "survival": None if not np.isfinite(c.survival) else round(c.survival, 3),
                "cv_rms_before": c.cv_before,
                "cv_rms_after": c.cv_after,
                "cv_z": c.cv_z,
                "description": fx.DESCRIPTION[c.name],
            }
        )
        if phys:  # a linearised non-linear effect: report its physical parameters
            e = eff_out[-1]
            e["linear_params"] = {"params": e["params"], "param_std": e["param_std"]}
            e["params"] = {n: v[0] for n, v in phys.items()}
            e["param_std"] = {n: v[1] for n, v in phys.items()}
            e["units"] = {n: v[2] for n, v in phys.items()}
            e["param_corr"] = None
    # candidates table
    cand_out = []
    for name, c in sorted(sel.candidates.items(), key=lambda kv: -kv[1].delta_bic):
        status = c.status
        if status == "not significant" and name in absorbed:
            status = "absorbed"
        cand_out.append(
            {
                "name": name,
                "status": status,
                "reason": c.reason,
                "round": c.round,
                "delta_bic": round(c.delta_bic, 2),
                "delta_chi2": round(c.delta_chi2, 2),
                "k_eff": round(c.k, 2),
                "p_holm": c.p_holm,
                "survival": None if not np.isfinite(c.survival) else round(c.survival, 3),
                "released": c.released,
                "absorbed_params": [a["name"] for a in absorption.get(name, [])],
            }
        )
    implausible = [
        {"name": c["name"], "reason": c["reason"], "delta_bic": c["delta_bic"]}
        for c in cand_out
        if c["status"] == "implausible fit"
    ]
    # 5. advise
    advice = []
    ov = []
    cand_names = list(blocks)
    strong = [nm for nm, b in (sel.rounds[0] if sel.rounds else []) if b > o["bic_min"]]
    if strong:
        ov = overlaps(prob, sigma0, base, sel.candidates, strong[:6])
        for a, b, val in ov:
            if val > o["overlap_max"] and (a in sel.selected or b in sel.selected):
                other = b if a in sel.selected else a
                chosen = a if a in sel.selected else b
                advice.append(
                    f"'{chosen}' and '{other}' have nearly the same signature in these data "
                    f"(overlap {val:.2f}): the choice rests on the smaller model. To separate "
                    f"them: {fx.ADVICE[other]}; {fx.ADVICE[chosen]}."
                )
    for c in implausible:
        advice.append(
            f"'{c['name']}' would fit (delta BIC {c['delta_bic']}) but only with physically "
            f"implausible parameters, so it is not claimed: {c['reason']}."
        )
    for name in absorbed:
        by = sorted({b for a in absorption[name] for b in a["absorbed_by"]})
        advice.append(
            f"'{name}' is absorbed: in these data its signature is reproduced by the baseline "
            f"parameters ({', '.join(by[:4]) or 'none: no signature'}), so it cannot be revealed "
            f"whatever its size. To reveal it: {fx.ADVICE[name]}."
        )
    released = {n for c in sel.accepted for n in c.released}
    for name, lst in absorption.items():
        lst = [a for a in lst if a["absorbed_by"]]  # parameters without any signature: silent
        if name in absorbed or not lst:
            continue
        by = sorted({b for a in lst for b in a["absorbed_by"]})
        hit = released.intersection(by)
        txt = (
            f"parameters {', '.join(a['name'] for a in lst)} of '{name}' are absorbed by the "
            f"baseline ({', '.join(by[:4])}): these data cannot reveal them"
        )
        if hit:
            txt += f"; the prior conflict found in {', '.join(sorted(hit))} may equally be {name}"
        advice.append(f"{txt}. To reveal them: {fx.ADVICE[name]}.")
    for name, why in untestable.items():
        advice.append(f"{name} cannot be tested: {why}. To test it: {fx.ADVICE[name]}.")
    # an implausible fit is still a difference between recording and model (e.g. a 50 % gain
    # absorbed by the calibration at a huge prior cost): a mismatch, not an effect
    mismatch = bool(sel.selected) or bool(loc0["located"]) or bool(implausible)
    residual_left = bool(loc1["located"])
    if residual_left and sel.selected:
        advice.append(
            "significant residuals remain after the selected effects (see 'located' after): "
            "an effect outside the catalogue, or one the data cannot separate"
        )
    elif mismatch and not sel.selected:
        advice.append(
            "the recordings differ from the calibrated model but no catalogued effect explains "
            "it with enough evidence; nothing is claimed. Check the located regions and "
            + "; ".join(fx.ADVICE[n] for n in cand_names[:2])
        )
    if ident["n_not_identifiable"]:
        advice.append(
            f"{ident['n_not_identifiable']} combinations of the bench parameters are not "
            "identifiable from these data (held at their priors): see calibration."
            "not_identifiable"
        )
    fit_doc = {
        "unit": prob.unit,
        "rms_before": _rms(prob, fit_b.resid),
        "rms_after": _rms(prob, fit1.resid),
        "chi2_dof_before": _chi2_dof(fit_b.resid, sigma1, fit_b.edf),
        "chi2_dof_after": _chi2_dof(fit1.resid, sigma1, fit1.edf),
        "cv_rms_before": cv_b,
        "cv_rms_after": cv_a,
        "noise_std": [
            float(v)
            for v in np.sqrt(noise_sigma(prob, fit1.resid, fit1.edf, model.var_known)[1])
            * prob.to_display
        ],
        "n_obs": int(prob.n * 3),
        "n_points": prob.n_points,
        "n_reps": prob.n_reps,
        "edf_before": fit_b.edf,
        "edf_after": fit1.edf,
        "lack_of_fit_before": loc0["lack_of_fit"],
        "lack_of_fit_after": loc1["lack_of_fit"],
    }
    summary = {
        "mismatch": mismatch,
        "located": loc0["located"][:20],
        "effects": eff_out,
        "fit": fit_doc,
        "advice": advice,
        "located_after": loc1["located"][:20],
        "candidates": cand_out,
        "implausible": implausible,
        "untestable": untestable,
        "overlaps": [{"a": a, "b": b, "overlap": round(v, 3)} for a, b, v in ov],
        "calibration": calib,
        "thresholds": o,
        "kind": prob.kind,
        "notes": prob.notes,
    }
    arrays = {
        "pos": prob.pos,
        "point": prob.point,
        "resid_before": fit_b.resid * prob.to_display,
        "resid_after": fit1.resid * prob.to_display,
        "z_before": loc0["z_row"],
        "z_after": loc1["z_row"],
        "zp_before": loc0["z_point"],
        "zp_after": loc1["z_point"],
        "sig_before": loc0["significant_point"],
        "point_pos": loc0["point_pos"],
        "rep": prob.rep,
        "t_h": prob.t_h,
    }
    dt = time.perf_counter() - t0
    summary["seconds"] = round(dt, 2)
    return Diagnosis(summary=summary, arrays=arrays, seconds=dt)
