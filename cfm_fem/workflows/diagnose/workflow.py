"""The diagnosis workflow: calibrate, locate, attribute, model, advise.

``diagnose(problem)`` returns a :class:`Diagnosis` whose ``summary`` is the ``diagnosis.json``
document (``mismatch``, ``located``, ``effects`` sorted by evidence, strongest first, ``fit``,
``advice``); the arrays (residuals before/after, standardised residuals) feed the report and the
``.vtu`` maps.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from types import SimpleNamespace

import numpy as np
from threadpoolctl import threadpool_limits

from . import effects as fx
from .advice import advise
from .calibrate import correlated_pairs, fit_map, identifiability, stack
from .conflicts import prior_conflicts
from .elements import elements_note, holds_offsets
from .locate import isolated_planes, locate
from .noise import estimate_noise, vibration_covariance
from .priors import WIDE, bounds_for
from .problem import Problem, located_sigma, model_sigma, noise_sigma, subset_rows
from .register import (
    applies,
    refit_step,
    register,
    registration_note,
    relinearise_elements,
    share_reference_error,
)
from .select import cv_rms, select_effects, stated_error_rows, structural_absorption

__all__ = ["Diagnosis", "diagnose", "DEFAULTS"]

#: Decision thresholds (documented in the outputs). ``null_alpha``: the family-wise rate at
#: which a clean recording is said to differ from the model by a test other than an effect's
#: claim; its three families (residuals located, planes called bad, calibrated parameters in
#: conflict with their priors) share it equally (Bonferroni), whatever the number of readings,
#: planes or parameters tested. ``fdr_q`` then names the locations (Benjamini-Hochberg).
DEFAULTS = {
    "bic_min": 10.0,
    "alpha": 0.01,
    "cv_z": 2.0,
    "fdr_q": 0.01,
    "overlap_max": 0.9,
    "null_alpha": 0.005,
}


def _family_alpha(o: dict) -> float:
    """The family-wise level of each of the three non-claim alarm families (``DEFAULTS``)."""
    return o["null_alpha"] / 3.0


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
    nothing at these sizes and, when other work loads the machine, its threads spin against it.
    """
    with threadpool_limits(limits=1, user_api="blas"):
        return _diagnose(prob, progress, **opts)


def _registration_prior_doc(prob: Problem) -> dict | None:
    """The registration prior the calibration used (1 sigma per axis, um and urad) and the
    source of each (an argument, the bench file's key, or the default)."""
    prior = prob.ctx.registration_prior
    if prior is None:
        return None
    doc = {
        "translation_um": round(prior["translation_mm"] * 1e3, 9),
        "rotation_urad": round(prior["rotation_rad"] * 1e6, 9),
        "translation_source": prior["translation_source"],
        "rotation_source": prior["rotation_source"],
    }
    if "bench file" in (doc["translation_source"], doc["rotation_source"]):
        doc["bench_file"] = prior["bench_file"]
    return doc


def _calibrate(prob: Problem) -> SimpleNamespace:
    """Fit the baseline (what the model already contains) and describe the calibration."""
    base = stack(prob.baseline)
    sigma0 = model_sigma(prob, base)
    fit_b = fit_map(prob.y, sigma0, base)
    ident = identifiability(sigma0, base)
    has = np.isfinite(base.prior_std)
    zprior = np.where(has, (fit_b.theta - base.prior_mean) / np.where(has, base.prior_std, 1), 0)
    rows = zip(
        base.names,
        base.units,
        fit_b.theta,
        fit_b.std,
        base.prior_mean,
        base.prior_std,
        zprior,
        strict=True,
    )
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
            for n, u, v, s, m, ps, z in rows
        ],
        **ident,
        "correlated_pairs": correlated_pairs(fit_b, base.names),
        "registration_prior": _registration_prior_doc(prob),
    }
    return SimpleNamespace(base=base, sigma0=sigma0, fit_b=fit_b, ident=ident, calib=calib)


def _candidates(prob: Problem, cal) -> tuple[dict, dict, dict, list]:
    """Candidate blocks, the untestable effects, and what the baseline absorbs of each."""
    blocks, untestable = fx.build(prob)
    absorption = {
        name: structural_absorption(prob, cal.sigma0, cal.base, blk) for name, blk in blocks.items()
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
    return blocks, untestable, absorption, absorbed


def _determined(effect: str, names, std) -> np.ndarray:
    """True where the data determine a parameter: its standard uncertainty is below a quarter of
    its plausible range (or, without a range, far below the catalogue's vague prior)."""
    bounds, _ = bounds_for(effect, names)
    width = bounds[:, 1] - bounds[:, 0]
    limit = np.where(np.isfinite(width), 0.25 * width, 0.5 * WIDE)
    return np.asarray(std) < limit


def _lack_of_fit(cols, fit1, sigma) -> float:
    """Reduced chi2 of the final fit in the rows an approximate effect model carries
    (:attr:`Columns.model_rows`), at least 1; 1 without such rows."""
    rows = cols.model_rows
    if rows is None or len(rows) != len(fit1.resid) or not rows.any():
        return 1.0
    r = fit1.resid[rows] / sigma[rows]
    return max(1.0, float(np.mean(r[np.isfinite(r)] ** 2)))


def _per_gain(cands, model, fit1, names) -> tuple[np.ndarray, np.ndarray]:
    """Value (p,) and covariance (p, p) of the parameters ``names``, those of an effect on the
    field an element senses (:attr:`Columns.element`) divided by (1 + that element's gain):
    the reading is the sensed field, the effect's change included, times (1 + gain), so the
    columns fit the parameter times (1 + gain). Uncertainty propagated (gains included)."""
    idx = [model.names.index(n) for n in names]
    element = {}
    for c in cands:
        if c.cols.element is not None:
            element.update(zip(c.cols.names, c.cols.element, strict=True))
    gains = [f"gain_{a}" for a in "xyz"]
    ext = list(idx) + [model.names.index(g) for g in gains if g in model.names]
    theta = fit1.theta[idx].copy()
    T = np.eye(len(idx), len(ext))  # Jacobian of the reported values by the fitted ones
    for r, n in enumerate(names):
        if n not in element or gains[element[n]] not in model.names:
            continue
        k = ext.index(model.names.index(gains[element[n]]))
        f = 1.0 + 1e-2 * fit1.theta[ext[k]]  # gains in %
        theta[r] = fit1.theta[idx[r]] / f
        T[r, r] = 1.0 / f
        T[r, k] = -1e-2 * fit1.theta[idx[r]] / f**2
    return theta, T @ fit1.cov[np.ix_(ext, ext)] @ T.T


def _effect_entry(cands, model, fit1, base, sigma, noise=None) -> dict:
    """The ``effects[]`` entry of one effect (one or several of its functions accepted);
    ``noise``: ``sigma`` without the stated errors of approximate models (the lack of fit of
    such a model is reported against it)."""
    c0 = cands[0]
    names = [n for c in cands for n in c.param_names]
    idx = [model.names.index(n) for n in names]
    th, cov = _per_gain(cands, model, fit1, names)
    sd = np.sqrt(np.clip(np.diag(cov), 0, None))
    keep = _determined(c0.name, names, sd)
    units = [model.units[i] for i in idx]
    base_prior = dict(
        zip(base.names, zip(base.prior_mean, base.prior_std, strict=True), strict=True)
    )
    det = [k for k, ok in enumerate(keep) if ok]
    sd_det = np.sqrt(np.clip(np.diag(cov)[det], 1e-300, None))
    corr = cov[np.ix_(det, det)] / np.outer(sd_det, sd_det)
    released = [n for c in cands for n in c.released]
    info = {}
    for c in cands:
        info.update({n: v for n, v in (c.cols.info or {}).items() if n in c.param_names})
    e = {
        "name": c0.name,
        "params": {n: float(v) for n, v, k in zip(names, th, keep, strict=True) if k},
        "param_std": {n: float(s) for n, s, k in zip(names, sd, keep, strict=True) if k},
        "units": {n: u for n, u, k in zip(names, units, keep, strict=True) if k},
        "not_determined": [n for n, k in zip(names, keep, strict=True) if not k],
        # posterior correlations of the determined parameters (order of ``params``)
        "param_corr": [[float(v) for v in row] for row in corr],
        "evidence": (
            "prior-data conflict" + (" and new signature" if any(c.has_new for c in cands) else "")
            if released
            else "new signature"
        ),
        "released_priors": {
            n: {"mean": float(base_prior[n][0]), "std": float(base_prior[n][1])} for n in released
        },
        "conflict_z": {
            d["name"]: round(d["z"], 2) for c in cands for d in c.conflict if d["name"] in released
        },
        "delta_bic": round(sum(c.delta_bic for c in cands), 2),
        "delta_chi2": round(sum(c.delta_chi2 for c in cands), 2),
        "k_eff": round(sum(c.k for c in cands), 2),
        "p_holm": max(c.p_holm for c in cands),
        "survival": None if not np.isfinite(c0.survival) else round(c0.survival, 3),
        "cv_rms_before": c0.cv_before,
        "cv_rms_after": cands[-1].cv_after,
        "cv_z": min((c.cv_z for c in cands if c.cv_z is not None), default=None),
        "description": fx.DESCRIPTION[c0.name],
    }
    fams = [f for c in cands for f in c.functions]
    if fams:
        e["functions"] = fams
    if info:
        e["where"] = {n: v for n, v in info.items() if n in e["params"]}
    phys = None
    if c0.has_new and c0.cols.physical is not None:
        # every function of the effect found, in whichever round
        own = [n for c in cands if c.has_new for n in c.cols.names]
        ib = [model.names.index(n) for n in own]
        lof = _lack_of_fit(c0.cols, fit1, sigma)
        cov = fit1.cov[np.ix_(ib, ib)] * lof
        phys = c0.cols.physical(own, fit1.theta[ib], cov)
        if c0.cols.model_rows is not None:
            e["lack_of_fit"] = {
                "reduced_chi2": round(_lack_of_fit(c0.cols, fit1, _or(noise, sigma)), 2),
                "note": "the parameters listed in model_dependent are those of an assumed shape "
                "fitted to these data, not of the data alone; reduced_chi2 is the fit's against "
                "the noise where the model carries the signal: that misfit is stated as a model "
                "error added to the noise there (every std of the fit includes it, and a further "
                "effect must exceed it), and every std of the effect is scaled by sqrt(reduced "
                "chi2) of what is left",
            }
    if phys:  # a linearised non-linear or constrained effect: report its physical parameters
        e["linear_params"] = {"params": e["params"], "param_std": e["param_std"]}
        pn = list(phys)
        # a parameter on a bound of its range: (value, None, unit, "lower" | "upper")
        bound = {n: phys[n][3] for n in pn if len(phys[n]) > 3 and phys[n][3]}
        sd = [0.0 if n in bound else phys[n][1] for n in pn]
        ok = _determined(c0.name, pn, sd)
        e["params"] = {n: phys[n][0] for n, k in zip(pn, ok, strict=True) if k}
        e["param_std"] = {
            n: phys[n][1] for n, k in zip(pn, ok, strict=True) if k and n not in bound
        }
        e["units"] = {n: phys[n][2] for n, k in zip(pn, ok, strict=True) if k}
        e["not_determined"] = [n for n, k in zip(pn, ok, strict=True) if not k]
        if bound:  # reported as the bound it is, with no std
            e["at_bound"] = bound
        e["param_corr"] = None
        if "lack_of_fit" in e:
            shaped = c0.cols.model_dependent
            e["model_dependent"] = [n for n in e["params"] if shaped is None or n in shaped]
    _averaged(e, cands)
    _lower_order(e, cands)
    _unseen_elements(e, cands)
    return e


def _or(a, b):
    """``a`` unless it is None, else ``b``."""
    return b if a is None else a


def _lower_order(e: dict, cands) -> None:
    """Lower-order terms of a function reported without its higher-order term
    (:attr:`Columns.lower_order`) listed as model-dependent in the entry ``e``."""
    alone = []
    for c in cands:
        pairs = c.cols.lower_order or {}
        alone += [
            n
            for n in c.param_names
            if n in pairs and pairs[n] not in c.param_names and n in e["params"]
        ]
    _mark_model_dependent(
        e,
        alone,
        "a linear term fitted without its quadratic term is the slope of the straight line the "
        "selection chose through the error over the scanned part of the stroke; a curved error "
        "has another linear coefficient",
    )


def _unseen_elements(e: dict, cands) -> None:
    """Hall elements' offsets from their centroid along a direction listed as model-dependent
    in the entry ``e`` (``sensor_offset``) where one element is fitted along it and another's
    displacement along it is one the data cannot see (its column absorbed by the calibrated
    model: a quadrupole's x element along x, where dB_x/dx vanishes and dB_y/dx moves the y
    element's reading as the magnet's offset does). The fitted element is displaced from the
    others taken together; the data fix its offset from the elements they see only, so the
    offsets from the centroid hold only if the unseen element sits with the others."""
    if e.get("name") != "sensor_offset":
        return
    fitted = {n for c in cands if c.has_new for n in c.cols.names}
    seen = fitted | {n for c in cands if c.family_block is not None for n in c.family_block.names}
    unseen = []
    for j in "xyz":
        along = [f"e_{i}_{j}" for i in "xyz"]
        if sum(n in fitted for n in along) == 1 and not all(n in seen for n in along):
            unseen += [f"d_{i}_{j}" for i in "xyz" if f"d_{i}_{j}" in e["params"]]
    _mark_model_dependent(
        e,
        unseen,
        "an element fitted alone along a direction along which another element's displacement "
        "is unseen (absorbed by the calibrated model) is displaced from the others taken "
        "together: its offsets from the centroid along it hold only if the unseen element sits "
        "with the others",
    )


def _mark_model_dependent(e: dict, names, note: str) -> None:
    """Add ``names`` to the entry's ``model_dependent`` list, with ``note`` as its note unless
    it has one."""
    if names:
        e["model_dependent"] = sorted(set(e.get("model_dependent", [])) | set(names))
        e.setdefault("model_dependent_note", note)


def _averaged(e: dict, cands) -> None:
    """Parameters of functions the data cannot tell apart, averaged over them
    (:func:`~cfm_fem.workflows.diagnose.functions.model_average`), into the entry ``e``: the
    mixture's mean, and its std with the chosen function's own variance beyond its plain fit
    (the vibration's correlation) added; ``alternatives`` lists the functions and weights."""
    alts = []
    for c in cands:
        if not c.averaged:
            continue
        for nm, (m, s, s_own) in c.averaged["params"].items():
            extra = 0.0
            if nm in e["param_std"] and s_own:
                extra = max(e["param_std"][nm] ** 2 - s_own**2, 0.0)
            e["params"][nm] = float(m)
            e["param_std"][nm] = float(np.sqrt(s**2 + extra))
            e["units"].setdefault(nm, c.averaged["units"][nm])
        alts += [
            {"function": lb, "params": names, "weight": round(w, 3)}
            for lb, w, names in c.averaged["alternatives"]
        ]
    if alts:
        e["alternatives"] = alts
        e["param_corr"] = None  # the mixture has no single correlation matrix


def _effects_out(prob, sel, fit1, base) -> list:
    """One entry per effect, the functions of one effect merged, strongest first; their std
    with the vibration correlated across the components of a reading
    (:func:`~cfm_fem.workflows.diagnose.noise.vibration_covariance`)."""
    noise = None
    if sel.accepted:
        model = sel.model
        vk = prob.var_known if model.var_known is None else model.var_known
        noise = estimate_noise(prob, fit1.resid, fit1.edf, vk)
        fit1 = replace(fit1, cov=vibration_covariance(prob, model, fit1, sel.sigma, noise))
    groups: dict = {}
    for c in sel.accepted:
        groups.setdefault(c.name, []).append(c)
    out = []
    for cs in groups.values():
        nuis = cs[0].cols.nuisance if cs[0].has_new else None
        noise_only = getattr(sel, "noise_sigma", None)
        if nuis is None:
            out.append(_effect_entry(cs, sel.model, fit1, base, sel.sigma, noise_only))
            continue
        # the effect's estimates marginalised over its nuisance parameters (Columns.nuisance)
        model = stack([sel.model, nuis])
        fit = fit_map(prob.y, sel.sigma, model)
        fit = replace(fit, cov=vibration_covariance(prob, model, fit, sel.sigma, noise))
        out.append(_effect_entry(cs, model, fit, base, sel.sigma, noise_only))
    return sorted(out, key=lambda e: -e["delta_bic"])


def _candidate_table(sel, absorbed, absorption) -> list:
    out = []
    for name, c in sorted(sel.candidates.items(), key=lambda kv: -kv[1].delta_bic):
        status = c.status
        if status == "not significant" and name in absorbed:
            status = "absorbed"
        out.append(
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
                **({"function": c.family} if c.family else {}),
            }
        )
    return out


def _noise_doc(prob, noise) -> dict:
    d = prob.to_display
    ref = share = None
    if prob.var_ref is not None:
        ref = float(np.sqrt((prob.var_ref * noise.ref_share).mean()) * d)
        share = [float(v) for v in noise.ref_share]
    return {
        "reference_error_rms": ref,
        "reference_error_share": share,
        "source": noise.source,
        "floor_std": [float(v) for v in np.sqrt(noise.floor) * d],
        "vibration_scale": [float(v) for v in noise.scale],
        "dof": noise.dof,
        "model": "sigma^2 = floor_std^2 + vibration_scale * (bench vibration through the "
        "gradient)^2, per component, both estimated from the data",
    }


def _fit_doc(prob, cal, sel, fit1, cv_b, cv_a, loc0, loc1) -> dict:
    model = sel.model
    vk = prob.var_known if model.var_known is None else model.var_known
    noise = estimate_noise(prob, fit1.resid, fit1.edf, vk)
    return {
        "unit": prob.unit,
        "rms_before": _rms(prob, cal.fit_b.resid),
        "rms_after": _rms(prob, fit1.resid),
        "chi2_dof_before": _chi2_dof(cal.fit_b.resid, sel.sigma, cal.fit_b.edf),
        "chi2_dof_after": _chi2_dof(fit1.resid, sel.sigma, fit1.edf),
        "cv_rms_before": cv_b,
        "cv_rms_after": cv_a,
        "noise_std": [
            float(v) for v in np.median(noise.sigma(vk, prob.var_ref), axis=0) * prob.to_display
        ],
        "noise_model": _noise_doc(prob, noise),
        "n_obs": int(prob.n * 3),
        "n_points": prob.n_points,
        "n_reps": prob.n_reps,
        "edf_before": cal.fit_b.edf,
        "edf_after": fit1.edf,
        "lack_of_fit_before": loc0["lack_of_fit"],
        "lack_of_fit_after": loc1["lack_of_fit"],
    }


def _arrays(prob, cal, fit1, loc0, loc1) -> dict:
    return {
        "pos": prob.pos,
        "point": prob.point,
        "resid_before": cal.fit_b.resid * prob.to_display,
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


def _attribute(prob: Problem, o: dict, progress=None, max_refits: int = 2) -> SimpleNamespace:
    """Steps 1-4 with the magnet's registration non-linear (a Hall map): the problem is
    linearised at the registration and the bench errors the baseline fits, and again at those
    the selected model fits (a released ``magnet_misalignment`` moves the pose; an effect the
    baseline lacks moves both) until they stay put; with no effect selected, only where the
    baseline's objective falls (:func:`~cfm_fem.workflows.diagnose.register.refit_step`). Hall
    elements found displaced (``sensor_offset``) are read where the selected model puts them
    (:func:`~cfm_fem.workflows.diagnose.register.relinearise_elements`) when the field is not
    linear over their offsets; should the offsets not be found again there (the offsets'
    signature taken by the baseline at the elements' points), the problem and attribution
    where it was found are kept, and the offsets Gauss-Newton moved the elements to are
    returned as ``unheld``: the offsets that linearisation fits are not the readings' (they
    are then reported as not determined, :func:`_offsets_not_held`)."""
    prob = register(share_reference_error(prob))
    kept = None  # the problem and attribution before the elements were relinearised
    unheld = None
    refits = relinearised = 0
    while True:
        a = _attribute_at(prob, o, progress)
        if kept is not None and not holds_offsets(prob, a.sel.model):
            unheld = prob.ctx.elements_at
            (prob, a), kept = kept, None
            relinearised = max_refits  # the linearisation does not hold the effect
        moved = _at_elements(prob, a) if relinearised < max_refits else prob
        if moved is not prob:
            kept = (prob, a)
            prob = moved
            relinearised += 1
            continue
        if refits == max_refits or not applies(prob) or _ends_on_2d(prob, a.sel):
            break
        refits += 1
        stepped = refit_step(prob, a.sel.model, a.fit1, a.sel.sigma, _replaced(a),
                             checked=not a.sel.selected)  # fmt: skip
        if stepped is None or stepped is prob:
            break
        prob = stepped
    a.unheld = unheld
    return a


def _at_elements(prob: Problem, a) -> Problem:
    """``prob`` linearised at the Hall elements' offsets the selected model fits, where the
    field is not linear over them; else ``prob`` itself."""
    if "sensor_offset" not in a.sel.selected and prob.ctx.elements_at is None:
        return prob
    return relinearise_elements(prob, a.sel.model, a.fit1, a.sel.sigma, _replaced(a))


def _replaced(a) -> set:
    """Names of the baseline columns an accepted effect of the attribution ``a`` replaced."""
    return {n for c in a.sel.accepted if c.has_new and c.cols.replaces for n in c.cols.replaces}


def _offsets_not_held(effects: list, unheld) -> str | None:
    """The Hall elements' offsets reported as not determined when the linearisation at the
    offsets the model fits does not hold the effect (``unheld``: those offsets, (3, 3) um;
    None: it does, or was not needed), with the note saying why.

    The offsets of the entry are those of the elements read at the probe's point, where the
    field's change over them is not their gradient times them: Gauss-Newton moves them
    elsewhere, and there the attribution does not fit them again (their signature at the
    elements' points is the baseline's, or another direction's). Neither linearisation
    states them with an uncertainty that holds: the effect stays found, its offsets are not
    determined."""
    entry = next((e for e in effects if e["name"] == "sensor_offset"), None)
    if unheld is None or entry is None:
        return None
    fitted = ", ".join(f"{n} {v:.4g}" for n, v in entry["params"].items())
    moved = ", ".join(
        f"d_{e}_{c} {unheld[i][j]:.4g}"
        for i, e in enumerate("xyz")
        for j, c in enumerate("xyz")
        if unheld[i][j]
    )
    entry["not_determined"] = list(entry["params"]) + list(entry["not_determined"])
    entry["params"], entry["param_std"], entry["units"] = {}, {}, {}
    entry["param_corr"] = None
    entry.pop("linear_params", None)  # the linear fit's std does not hold either
    return (
        f"sensor_offset: the Hall elements' offsets fitted with the elements read at the probe's "
        f"point ({fitted or 'none determined'}; um) are not the readings' offsets: read where "
        f"the fit puts them, Gauss-Newton moves them ({moved}; um), where the attribution does "
        "not fit them again; the offsets are reported as not determined"
    )


def _ends_on_2d(prob: Problem, sel) -> bool:
    """Whether the selected model holds the soft ends against 2-D harmonics read at the pose.

    The ends scale the body field at the nominal placement (every effect's columns against a
    2-D reference stay those of the nominal placement); a pose moved by a model holding them
    would read the body exactly at that pose while the ends still scale the nominal field,
    leaving the pose's second-order terms (a sextupole's g d^2, hundreds of uT for d ~ 100 um)
    wherever the ends remove the field: the pose stays where the baseline put it."""
    keywords = getattr(prob.ctx.rebuild, "keywords", {})
    return bool(keywords.get("planar")) and "fringe_field_3d" in sel.selected


def _attribute_at(prob: Problem, o: dict, progress=None) -> SimpleNamespace:
    """Calibrate, locate, select the effects and fit them together (steps 1-4)."""

    def sigma_fn(resid, edf, var_known=None):
        return noise_sigma(prob, resid, edf, var_known)[0]

    cal = _calibrate(prob)
    fw = _family_alpha(o)
    sigma_loc = located_sigma(prob, cal.sigma0, cal.fit_b.resid, cal.fit_b.edf)
    loc0 = locate(prob, cal.fit_b.resid, sigma_loc, q=o["fdr_q"], edf=cal.fit_b.edf, alpha=fw)
    blocks, untestable, absorption, absorbed = _candidates(prob, cal)
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
    fit1 = fit_map(prob.y, sel.sigma, sel.model)
    sigma_loc = located_sigma(prob, sel.sigma, fit1.resid, fit1.edf, sel.model.var_known)
    loc1 = locate(prob, fit1.resid, sigma_loc, q=o["fdr_q"], edf=fit1.edf, alpha=fw)
    return SimpleNamespace(
        prob=prob,
        cal=cal,
        loc0=loc0,
        blocks=blocks,
        untestable=untestable,
        absorption=absorption,
        absorbed=absorbed,
        sel=sel,
        fit1=fit1,
        loc1=loc1,
    )


def _outlier_entries(isolated) -> list:
    return [
        {
            "component": d["component"],
            "where": f"isolated plane {d['axis']} = {d['position_mm']:.6g} mm (outlier: left out "
            "of the attribution)",
            "n_points": int(d["rows"].sum()),
            "max_abs_z": abs(d["z_mean"]),
            "mean_z": d["z_mean"],
        }
        for d in isolated
    ]


def _lone_plane(prob, plane, rows, out) -> bool:
    """Whether ``plane`` (an `isolated_planes` entry, ``rows`` its rows) may be left out beyond
    a fifth of the rows: the first left out, on an axis of four planes or more (a quarter of
    the rows each, or less), holding no more rows than its axis' planes on average (a typical
    plane, not one that holds most of a sparse map)."""
    axis = "xyz".index(plane["axis"])
    n_planes = np.unique(np.round(prob.pos[:, axis], 6)).size
    return not out.any() and n_planes >= 4 and rows.sum() <= 1.05 * prob.n / n_planes


def _without_bad_planes(prob, full, o, progress, max_planes: int = 3):
    """Leave out planes that depart from their neighbours after the effects (bad readings, not
    physics), strongest first, one at a time with the attribution done again, while one is
    found and they stay under a fifth of the rows (or it is a lone plane, `_lone_plane`).
    A plane whose every reading carries an accepted approximate model's stated error is not
    one: that model's misfit there is structured, and the plane's departure may be it."""
    a, isolated = full, []
    idx = np.arange(prob.n)
    out = np.zeros(prob.n, dtype=bool)
    for _ in range(max_planes):
        iso = isolated_planes(a.prob, a.loc1["z_row"], q=o["fdr_q"], alpha=_family_alpha(o))
        stated = stated_error_rows(a.sel)
        if stated is not None:  # a misfit stated as an approximate model's error is no bad plane
            iso = [d for d in iso if not stated[d["rows"]].all()]
        if not iso:
            break
        top = dict(iso[0])
        rows = np.zeros(prob.n, dtype=bool)
        rows[idx[top["rows"]]] = True
        if (out | rows).sum() > 0.2 * prob.n and not _lone_plane(prob, top, rows, out):
            break
        out |= rows
        top["rows"] = rows
        isolated.append(top)
        idx = np.flatnonzero(~out)
        a = _attribute(subset_rows(prob, ~out), o, progress)
    return a, isolated


def _diagnose(prob: Problem, progress=None, **opts) -> Diagnosis:
    t0 = time.perf_counter()
    o = {**DEFAULTS, **opts}
    full = _attribute(prob, o, progress)
    a, isolated = _without_bad_planes(full.prob, full, o, progress)
    sel, cal, fit1, loc1 = a.sel, a.cal, a.fit1, a.loc1
    p = a.prob
    cv_b, _ = cv_rms(p, cal.sigma0, cal.base, sel.folds)
    cv_a, _ = cv_rms(p, sel.sigma, sel.model, sel.folds) if sel.selected else (cv_b, None)
    eff_out = _effects_out(p, sel, fit1, cal.base)
    unheld_note = _offsets_not_held(eff_out, getattr(a, "unheld", None))
    cand_out = _candidate_table(sel, a.absorbed, a.absorption)
    implausible = [
        {"name": c["name"], "reason": c["reason"], "delta_bic": c["delta_bic"]}
        for c in cand_out
        if c["status"] == "implausible fit"
    ]
    released = {n for c in sel.accepted for n in c.released}
    # the baseline priors an accepted effect's free nuisance makes untestable (Columns.nuisance)
    released |= {n for c in sel.accepted if c.has_new and c.cols.nuisance is not None
                 for n in c.cols.nuisance.release}  # fmt: skip
    conflicts = prior_conflicts(
        sel.model, fit1, cal.base, released, _family_alpha(o), p.baseline, p.kind
    )
    advice, ov = advise(
        p, o, cal, sel, a.blocks, absorption=a.absorption, absorbed=a.absorbed,
        implausible=implausible, untestable=a.untestable, conflicts=conflicts, loc1=loc1,
    )  # fmt: skip
    outliers = _outlier_entries(isolated)
    if outliers:
        advice.insert(
            0,
            f"{len(outliers)} plane(s) depart from their neighbours beyond the noise (see "
            "'located'): bad readings, not a field or bench effect; they are left out of the "
            "attribution. Check those acquisitions (settling at the start of a line, a glitch)",
        )
    located = sorted(full.loc0["located"] + outliers, key=lambda d: -d["max_abs_z"])
    # an implausible fit or a prior conflict is still a difference between recording and model
    mismatch = bool(sel.selected or located or implausible or conflicts)
    summary = {
        "mismatch": mismatch,
        "located": located[:20],
        "effects": eff_out,
        "fit": _fit_doc(p, cal, sel, fit1, cv_b, cv_a, a.loc0, loc1),
        "advice": advice,
        "located_after": loc1["located"][:20],
        "candidates": cand_out,
        "implausible": implausible,
        "prior_conflicts": conflicts,
        "outliers": [{k: v for k, v in d.items() if k != "rows"} for d in isolated],
        "untestable": a.untestable,
        "overlaps": [{"a": x, "b": y, "overlap": round(v, 3)} for x, y, v in ov],
        "calibration": cal.calib,
        "thresholds": o,
        "kind": prob.kind,
        "notes": p.notes + [n for n in [registration_note(p), elements_note(p), unheld_note] if n],
    }
    dt = time.perf_counter() - t0
    summary["seconds"] = round(dt, 2)
    return Diagnosis(summary=summary, arrays=_arrays(p, cal, fit1, a.loc0, loc1), seconds=dt)
