"""Attribution: forward selection of effects by nested model comparison and held-out error.

For each round, every untried candidate is added to the current model and refitted (MAP, priors of
the baseline kept). A candidate has up to two parts:

* new columns (a new signature): ``delta_chi2`` = drop of the MAP objective, ~ chi2(k) under the
  null with k the gain in effective parameters (trace of the hat matrix); likelihood-ratio p;
* released priors of baseline parameters (``parameter_bias``, ``magnet_misalignment``, Hall
  gains): per parameter the prior-data conflict z = (theta_post - m) / sqrt(s^2 - C), exactly
  N(0, 1) under the null in a linear-Gaussian model (theta_post, C: posterior mean and variance,
  m, s: prior); Holm over the parameters the data determine (C < s^2 / 2); the parameters in
  conflict are released one by one while the data still determine each of them alone.

Evidence of a candidate: ``delta_bic`` = delta_chi2 - k ln(n_obs), delta_chi2 of an effect with
the shape of the reference's own error (volume averaging) less what an error of the stated size
could give (:func:`reference_explains`); its p-value (Bonferroni over its parts), guarded by
Holm over the candidates of the round; held-out RMS (K-fold over whole repetitions) before and
after; ``survival``: the fraction of the fitted new signature that the
current model cannot reproduce within its priors (small: absorbed).

A candidate is accepted when delta_bic > ``bic_min``, its Holm-adjusted p < ``alpha``, its
survival is at least ``min_survival`` (else: absorbed), its fitted parameters are physically
plausible (else: implausible fit, with the reason) and it predicts data it was not fitted to
(folds of whole repetitions in time order, :func:`folds_of`): for a new signature the held-out
chi2 (each reading weighted by its noise; the held-out RMS, which the noisiest readings rule, is
reported, not tested) drops, and the held-out residuals follow the change the fit on the other
folds predicts, significantly in the paired test over the rows (z > ``cv_z``,
:func:`_held_out_score`) or the chi2 gain replicated in every fold beyond its parameters'
estimation cost (:func:`_replicated_gain`), over
the folds whose training data determine the new signature (:func:`determined_folds`); for a
prior release, whose data already steer the calibration, the conflict is replicated in every
fold on its own (Stouffer z > ``cv_z``) and the held-out chi2 is no worse than the released
freedom's own estimation noise explains (:func:`_release_within_its_freedom`).
Last, its parameters estimated from either half of the map must agree
(:mod:`~cfm_fem.workflows.diagnose.stability`; else: unstable, with the reason).

An accepted effect whose model is approximate where it carries the signal
(:attr:`~cfm_fem.workflows.diagnose.calibrate.Columns.model_rows`: the soft ends) states its
misfit there as a model error added to the noise of those rows for the later rounds and the
final fit (:func:`approximation_error`): that misfit is the same on every repetition, so
without it a further effect whose columns share its structure would pass every test on it.
Further effects are tested where the accepted models describe the readings to their noise,
the rows with a stated error weighed 1e-6 (:func:`_testing_sigma`): the stated error is a
variance per plane, the misfit it stands for is structured within the plane.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import stats

from .calibrate import Columns, Fit, fit_map, released_in, stack
from .functions import (
    ALT_MIN_WEIGHT,
    family_weights,
    function_options,
    model_average,
    model_basis,
    other_functions,
    pair_members,
    screen_gram,
    screened_drop,
)
from .priors import bounds_for
from .problem import Problem
from .reference_rows import REF_GROUP
from .stability import unstable_in

__all__ = [
    "Candidate",
    "Selection",
    "select_effects",
    "folds_of",
    "cv_rms",
    "structural_absorption",
    "implausible_reason",
    "reference_explains",
    "stated_error_rows",
]


@dataclass
class Candidate:
    """Evidence for one effect in one round (see module docstring)."""

    name: str
    delta_chi2: float
    k: float
    delta_bic: float
    p_value: float
    survival: float
    fit: Fit | None = None
    cols: Columns | None = None
    p_holm: float = 1.0
    cv_before: float | None = None
    cv_after: float | None = None
    cv_z: float | None = None
    status: str = "not significant"
    round: int = 0
    trial: Columns | None = None
    param_names: list = field(default_factory=list)
    released: list = field(default_factory=list)
    conflict: list = field(default_factory=list)
    has_new: bool = True
    reason: str = ""
    family: str | None = None
    functions: list = field(default_factory=list)
    alternatives: list = field(default_factory=list)
    family_block: Columns | None = None
    averaged: dict | None = None


@dataclass
class Selection:
    selected: list
    candidates: dict
    rounds: list = field(default_factory=list)
    overlaps: list = field(default_factory=list)


def folds_of(prob: Problem, k: int = 5) -> np.ndarray:
    """Fold index of each row for the held-out test.

    With repetitions: whole repetitions in contiguous blocks of their time order (a model
    trained on the other blocks must predict a block it never saw, so a ramp cannot fit a step
    from its neighbours). One repetition: points, interleaved (point index modulo k).
    """
    reps = np.unique(prob.rep)
    if reps.size >= 2:
        if prob.t_h is not None:
            t0 = np.array([prob.t_h[prob.rep == r].min() for r in reps])
            reps = reps[np.argsort(t0, kind="stable")]
        kk = min(k, reps.size)
        block = np.arange(reps.size) * kk // reps.size
        out = np.empty(prob.n, dtype=np.int64)
        for r, b in zip(reps, block, strict=True):
            out[prob.rep == r] = b
        return out
    return prob.point % k


def cv_rms(prob: Problem, sigma, cols: Columns, folds, rows=None) -> tuple[float, np.ndarray]:
    """Held-out RMS (display units; over ``rows``, default all) and the per-row held-out chi2
    (sum over the components of the squared residual in units of its sigma), for paired tests:
    weighting by the noise keeps the quiet readings from being drowned by the noisy ones."""
    rms, w = _held_out(prob, sigma, cols, folds)
    return float(np.sqrt(rms[slice(None) if rows is None else rows].mean())), (w**2).sum(1)


def _held_out(prob: Problem, sigma, cols: Columns, folds) -> tuple[np.ndarray, np.ndarray]:
    """Each row's held-out mean squared residual (display units, shape (n,)) and its held-out
    residual in units of its sigma (shape (n, 3)), the model fitted to the other folds."""
    rms = np.empty(prob.n)
    w = np.empty((prob.n, 3))
    for f in np.unique(folds):
        test = folds == f
        fit = fit_map(prob.y, sigma, cols, mask=~test)
        r = fit.resid[test]
        rms[test] = ((r * prob.to_display) ** 2).mean(1)
        w[test] = r / sigma[test]
    return rms, w


def _held_out_score(w_before, w_after) -> float:
    """Paired z over the rows of the held-out score: does each held-out residual lie along the
    change the other folds predict?

    Per row u = sum_c w_b (w_b - w_a) (whitened held-out residuals before and after the
    candidate; w_b - w_a is the change its fit on the other folds predicts there). The held-out
    noise is independent of that prediction, so u has mean 0 without the effect and the
    effect's own chi2 per row with it; its rows' scatter is the noise times the prediction.
    The held-out chi2 gain per row, 2 u - (w_b - w_a)^2, scatters twice as much for the same
    mean: its paired z is half this one (3 against 6 for an effect of joint significance 6).
    """
    u = np.nansum(w_before * (w_before - w_after), axis=1)
    if u.size < 2:
        return -np.inf
    return float(u.mean() / (u.std(ddof=1) / np.sqrt(u.size) + 1e-300))


def determined_folds(prob, sigma, model: Columns, trial: Columns, folds,
                     min_survival: float = 0.05) -> np.ndarray:  # fmt: skip
    """Rows whose fold the other folds can predict with the candidate's new columns.

    A fold is left out of the held-out test when, on the rows trained without it, some new
    column of ``trial`` has less than ``min_survival`` of its whitened signature outside the
    span of the ``model`` columns (no priors; :func:`free_columns`): the training data cannot
    tell that parameter from the baseline, so its value, and the fold's prediction, is
    arbitrary. (A step from the second of three repetitions on is a constant over the last two:
    the fold of the first repetition cannot test it.)

    Returns
    -------
    ndarray of bool, shape (n,)
    """
    new = np.arange(model.p, trial.p)
    use = np.ones(prob.n, dtype=bool)
    if new.size == 0:
        return use
    model = free_columns(prob, model)
    for f in np.unique(folds):
        train = folds != f
        A = _whiten(model.J[train], sigma[train])
        W = _whiten(trial.J[train][..., new], sigma[train])
        ok = np.isfinite(A).all(1) & np.isfinite(W).all(1)
        A, W = A[ok], W[ok]
        sc = np.linalg.norm(A, axis=0)
        sc[sc == 0] = 1.0
        u, sv, _ = np.linalg.svd(A / sc, full_matrices=False)
        u = u[:, sv > 1e-8 * sv[0]] if sv.size else u[:, :0]
        norm = np.linalg.norm(W, axis=0)
        rest = np.linalg.norm(W - u @ (u.T @ W), axis=0)
        surv = np.where(norm > 0, rest / np.where(norm > 0, norm, 1.0), 0.0)
        if surv.min() < min_survival:
            use[folds == f] = False
    return use


def _release_within_its_freedom(diff, k: int, folds, cv_z: float) -> bool:
    """Whether releasing ``k`` priors leaves the held-out chi2 no worse than freedom alone would.

    ``diff``: per-row held-out chi2 before minus after. A released parameter that predicts
    nothing still costs held-out chi2: in K-fold cross-validation its estimation noise adds about
    chi2(k) K / (K - 1) (mean k K / (K - 1), std sqrt(2 k) K / (K - 1)). The rows' differences
    all follow those k estimates, so a paired test over rows would call that cost significant;
    the release is rejected only if the loss exceeds its mean by ``cv_z`` stds.
    """
    n_folds = np.unique(folds).size
    scale = n_folds / max(n_folds - 1, 1)
    allowed = scale * (k + cv_z * np.sqrt(2.0 * k))
    return bool(diff.sum() > -allowed)


def _replicated_gain(diff, folds, k: float, cv_z: float) -> float:
    """Held-out evidence of a new signature concentrated on few readings: its total held-out
    chi2 gain, replicated in every fold.

    The paired test over rows has little power when the signature lives on a few points (a
    planar Hall term where two field components are large together, near one end): the other
    rows' differences are noise that swamps the mean. Fitted on the other folds, a real effect
    lowers the held-out chi2 of every fold, and of all together by more than the cost the
    estimation noise of ``k`` parameters adds to it (mean c = k K / (K - 1), std
    s = sqrt(2 k) K / (K - 1), :func:`_release_within_its_freedom`); an outlier of one
    repetition helps its own fold only.

    Returns
    -------
    float
        (total gain - c) / s when every fold gains, else -inf.
    """
    labels = np.unique(folds)
    if labels.size < 2 or any(diff[folds == f].sum() <= 0 for f in labels):
        return -np.inf
    scale = labels.size / (labels.size - 1)
    k = max(float(k), 0.5)
    return float((diff.sum() - scale * k) / (scale * np.sqrt(2.0 * k)))


def _replicated_conflict(prob, sigma, trial, released, model, folds) -> float:
    """Held-out evidence of a prior-data conflict: Stouffer's z of the conflict of the released
    parameter estimated from each fold alone.

    Where the data outweigh the prior, releasing it changes the predictions little, so a
    held-out RMS cannot show the conflict; but a real conflict shows in every fold on its own,
    on the same side of the prior. The parameter is the released one in strongest conflict;
    each fold's z = (theta_f - m) / sqrt(var_f + s^2), signed by the conflict of all the data.
    """
    if not released:
        return -np.inf
    full = fit_map(prob.y, sigma, trial)
    best, sign = None, 1.0
    for nm in released:
        i = trial.names.index(nm)
        j = model.names.index(nm)
        zz = (full.theta[i] - model.prior_mean[j]) / model.prior_std[j]
        if best is None or abs(zz) > abs(best[1]):
            best, sign = (nm, zz), np.sign(zz) or 1.0
    i = trial.names.index(best[0])
    j = model.names.index(best[0])
    m, s = model.prior_mean[j], model.prior_std[j]
    zs = []
    for f in np.unique(folds):
        fit = fit_map(prob.y, sigma, trial, mask=folds == f)
        zs.append(sign * (fit.theta[i] - m) / np.sqrt(fit.cov[i, i] + s**2))
    return float(np.sum(zs) / np.sqrt(len(zs)))


def _survival(prob, sigma, model: Columns, eff: Columns, theta_e) -> float:
    """Fraction (0..1) of an effect's signature the model cannot absorb within its priors."""
    v = np.einsum("nkp,p->nk", eff.J, theta_e)
    if not np.any(v):
        return 0.0
    fit = fit_map(v, sigma, _zero_mean(model))
    tot = float(((v / sigma) ** 2).sum())
    return float(np.sqrt(min(1.0, fit.objective / tot))) if tot > 0 else 0.0


def _zero_mean(c: Columns) -> Columns:
    return Columns(c.J, c.names, c.units, np.zeros(c.p), c.prior_std, c.group)


def _whiten(J, sigma):
    return (J / sigma[..., None]).reshape(-1, J.shape[-1])


def free_columns(prob, model: Columns) -> Columns:
    """The columns of ``model`` whose parameters take whatever value the data ask.

    All but the smooth term of the reference's error (baseline group :data:`.REF_GROUP`): its
    priors are the stated error, so it reproduces an effect's signature only up to that size,
    which the fits, with their priors, weigh. The tests that ask what the baseline could
    reproduce with no priors (:func:`structural_absorption`, :func:`determined_folds`) leave
    it out: a probe tilt's B_z-shaped column is not absorbed by a term whose prior allows
    nanotesla."""
    fixed = {n for b in prob.baseline if b.group == REF_GROUP for n in b.names}
    keep = [k for k, n in enumerate(model.names) if n not in fixed]
    return model if len(keep) == model.p else model.subset(keep)


def structural_absorption(prob, sigma, base: Columns, blk: Columns, min_survival: float = 0.05):
    """Which new parameters of an effect the baseline absorbs, whatever the data say.

    A parameter is absorbed when less than ``min_survival`` of its (whitened) signature lies
    outside the span of the baseline columns (no priors: any value of the baseline parameters
    reproduces it; :func:`free_columns`), or when it has no signature at all (below 1e-3 of the
    noise of the whole data set even at the edge of its plausible range). Scale-free in the
    noise (an effect that inflates the noise estimate does not hide itself); depends on the
    design (positions, field, time, directions), never on the measured values.

    Returns
    -------
    list of dict
        Per invisible parameter: ``name``, ``survival`` (0..1), ``max_z`` (at the plausible
        bound), ``absorbed_by`` (the baseline parameters that reproduce it best).
    """
    if blk.p == 0:
        return []
    base = free_columns(prob, base)
    A = _whiten(base.J, sigma)
    sc = np.linalg.norm(A, axis=0)
    sc[sc == 0] = 1.0
    u, s, vt = np.linalg.svd(A / sc, full_matrices=False)
    good = s > 1e-8 * s[0]
    u, s, vt = u[:, good], s[good], vt[good]
    W = _whiten(blk.J, sigma)
    bnd = blk.bounds if blk.bounds is not None else np.tile([-np.inf, np.inf], (blk.p, 1))
    out = []
    for j in range(blk.p):
        w = W[:, j]
        nw = float(np.linalg.norm(w))
        proj = u.T @ w
        rest = float(np.sqrt(max(nw**2 - proj @ proj, 0.0)))
        surv = rest / nw if nw > 0 else 0.0
        big = float(np.max(np.abs(bnd[j])))
        max_z = nw * big if np.isfinite(big) else np.inf
        if surv < min_survival or max_z < 1e-3:
            coef = (vt.T @ (proj / s)) / sc  # baseline parameters reproducing the column
            contrib = np.abs(coef) * np.linalg.norm(A, axis=0)
            top = [base.names[k] for k in np.argsort(-contrib)[:3] if contrib[k] > 0.1 * nw]
            out.append(
                {
                    "name": blk.names[j],
                    "survival": round(surv, 4),
                    "max_z": round(max_z, 3),
                    "absorbed_by": top,
                }
            )
    return out


def implausible_reason(names, est, sd, bounds, why, unit, k: float = 3.0) -> str:
    """Reason why fitted parameters are physically implausible ('' when they are not).

    A parameter is implausible when its whole interval est +- k sd lies outside its bounds.
    """
    bad = []
    for i, nm in enumerate(names):
        lo, hi = bounds[i]
        if est[i] - k * sd[i] > hi or est[i] + k * sd[i] < lo:
            bad.append(
                f"{nm} = {est[i]:.4g} +- {sd[i]:.2g} {unit[i]} outside [{lo:g}, {hi:g}]"
                + (f" ({why[i]})" if why[i] else "")
            )
    return "; ".join(bad)


def _conflict(model: Columns, current: Fit, names, alpha):
    """Per-parameter prior-data conflict (module docstring) with Holm over determined ones."""
    out = []
    for nm in names:
        i = model.names.index(nm)
        s2 = model.prior_std[i] ** 2
        if not np.isfinite(s2):
            continue  # already released
        C = float(current.cov[i, i])
        det = 0.5 * s2 > C  # the data tell more than the prior
        z = (current.theta[i] - model.prior_mean[i]) / np.sqrt(max(s2 - C, 1e-300))
        out.append(
            {
                "name": nm,
                "z": float(z) if det else None,
                "p": float(2 * stats.norm.sf(abs(z))) if det else 1.0,
                "determined": bool(det),
            }
        )
    det = [c for c in out if c["determined"]]
    m = len(det)
    running = 0.0
    for r, c in enumerate(sorted(det, key=lambda c: c["p"])):
        running = max(running, min(1.0, (m - r) * c["p"]))
        c["p_holm"] = running
    for c in out:
        c.setdefault("p_holm", 1.0)
    return out


def _release_set(prob, sigma, model, conflict, alpha):
    """Parameters in conflict released one by one (strongest first) while the data still
    determine each released parameter on its own (posterior variance below half its prior)."""
    S = []
    for c in sorted(conflict, key=lambda c: c["p"]):
        if c["p_holm"] >= alpha:
            break
        trial = released_in(model, S + [c["name"]])
        f = fit_map(prob.y, sigma, trial)
        idx = [model.names.index(n) for n in S + [c["name"]]]
        ok = f.rank == trial.p and all(f.cov[i, i] < 0.5 * model.prior_std[i] ** 2 for i in idx)
        if ok:
            S.append(c["name"])
    return S


def _evaluate(prob, sigma, model, current, blk, name, *, alpha, bic_min, log_n):
    """Evidence of one candidate effect (both parts, module docstring)."""
    parts = {}
    if blk.p:
        trial = stack([model, blk])
        f = fit_map(prob.y, sigma, trial)
        # less what the reference's own error could give (blocks of its shape only)
        d = current.objective - f.objective - reference_explains(prob, sigma, trial, f, blk)
        k = max(f.edf - current.edf, 1e-9)
        mult = max(float(blk.multiplicity), 1.0)
        parts["new"] = {
            "d": d,
            "k": k,
            "p": min(1.0, mult * float(stats.chi2.sf(max(d, 0.0), max(k, 0.5)))),
            "pen": 2.0 * np.log(mult),  # the choice among mult alternatives (BIC prior)
            "fit": f,
            "surv": _survival(prob, sigma, model, blk, f.theta[model.p :]),
        }
    conflict = []
    if blk.release:
        conflict = _conflict(model, current, blk.release, alpha)
        det = [c for c in conflict if c["determined"]]
        if det:
            S = _release_set(prob, sigma, model, det, alpha)
            best = min(det, key=lambda c: c["p"])
            shown = S or [best["name"]]
            f = fit_map(prob.y, sigma, released_in(model, shown))
            d = current.objective - f.objective
            parts["release"] = {
                "d": d,
                "k": float(len(shown)),
                "p": min(c["p_holm"] for c in det),
                "S": S,
                "shown": shown,
            }
    if not parts:
        return None
    n_parts = len(parts)

    def bic(pt):
        return pt["d"] - pt["k"] * log_n - pt.get("pen", 0.0)

    def passes(pt):
        return bic(pt) > bic_min and n_parts * pt["p"] < alpha

    use = [nm for nm, pt in parts.items() if passes(pt)]
    if not use:  # report the stronger part
        use = [max(parts, key=lambda nm: bic(parts[nm]))]
    rel = parts["release"]["shown"] if "release" in use else []
    trial = released_in(model, rel)
    if "new" in use:
        trial = stack([trial, blk])
    f = fit_map(prob.y, sigma, trial)
    d = current.objective - f.objective
    if "new" in use:
        d -= reference_explains(prob, sigma, trial, f, blk)
    k = sum(parts[nm]["k"] for nm in use)
    pen = sum(parts[nm].get("pen", 0.0) for nm in use)
    p = min(1.0, n_parts * min(parts[nm]["p"] for nm in use))
    return Candidate(
        name=name,
        delta_chi2=float(d),
        k=float(k),
        delta_bic=float(d - k * log_n - pen),
        p_value=float(p),
        survival=parts["new"]["surv"] if "new" in use else float("nan"),
        fit=f,
        cols=blk,
        trial=trial,
        param_names=list(rel) + (list(blk.names) if "new" in use else []),
        released=list(rel),
        conflict=conflict,
        has_new="new" in use,
    )


def reference_explains(prob, sigma, trial: Columns, fit: Fit, blk: Columns) -> float:
    """Part of a new block's drop of the objective that the reference's own error could give.

    A block that carries ``ref_error = (std (m, 3), key (n,))`` (the stated standard deviation
    of the reference's error at each distinct point, and each row's point) has the shape of
    that error (``sensor_volume_averaging``: a reference read between its nodes errs by a
    curvature term, one sign across a plane where the field curves). The error is one value
    per point, shared by its readings, and may be coherent across the map: its effect on the
    block's estimate is bounded by b_k = sum_p sum_c |A_kpc| std_pc, with A the estimate's
    influence of each point's error (``fit.cov`` J' W summed over the point's readings): the
    largest shift an error within its stated size, of any sign pattern, can make. The
    evidence left is that of the estimate moved towards zero by b per parameter,
    theta_a = sign(theta) max(|theta| - b, 0); the part returned is
    theta' C^-1 theta - theta_a' C^-1 theta_a (C: the block's posterior covariance), >= 0.

    Parameters
    ----------
    prob : Problem
    sigma : ndarray, shape (n, 3)
    trial : Columns
        The model the block was fitted in, the block's columns last.
    fit : Fit
        That fit.
    blk : Columns

    Returns
    -------
    float
        0 for a block without ``ref_error``.
    """
    ref = getattr(blk, "ref_error", None)
    if ref is None or not blk.p:
        return 0.0
    std, key = ref
    idx = np.arange(trial.p - blk.p, trial.p)
    theta, C = fit.theta[idx], fit.cov[np.ix_(idx, idx)]
    w = np.where(np.isfinite(prob.y), 1.0 / sigma**2, 0.0)
    infl = np.einsum("kq,ncq->knc", fit.cov[idx], np.nan_to_num(trial.J) * w[..., None])
    m = len(std)
    per_point = np.stack([np.stack([np.bincount(key, weights=infl[k, :, c], minlength=m)
                                    for c in range(3)], axis=-1)
                          for k in range(blk.p)])  # fmt: skip
    bound = np.einsum("kmc,mc->k", np.abs(per_point), std)
    left = np.sign(theta) * np.maximum(np.abs(theta) - bound, 0.0)
    try:
        Ci = np.linalg.pinv(C)
    except np.linalg.LinAlgError:
        return 0.0
    return float(max(theta @ Ci @ theta - left @ Ci @ left, 0.0))


def _evaluate_block(prob, sigma, model, current, blk, name, *, alpha, bic_min, log_n,
                    min_survival=0.0):  # fmt: skip
    """Evidence of a candidate; an effect made of several error functions (``families``) is
    the best of its functions, alone or in pairs (:func:`function_options`), corrected for the
    choice among them: Bonferroni within each of the two stages (singles, pairs) and over the
    two, and in the BIC 2 ln of that factor.
    The options are ranked by the drop of the objective each gives (one projection each, less
    k ln n), and the best is evaluated in full. Where the pair's better function passes
    ``bic_min`` alone, the pair is taken only where its score passes that function's by more
    than ``bic_min`` (the evidence a function must carry on its own); where neither function
    does, the pair is the effect's only evidence and is weighed whole. A pair whose fitted
    signature the current model reproduces (survival below ``min_survival``: its second
    function is the baseline's) gives way to that function. A function whose fit is
    implausible gives way to the best plausible one among the next :data:`IMPLAUSIBLE_TRIES`
    by score."""
    if not blk.families:
        return _evaluate(prob, sigma, model, current, blk, name, alpha=alpha, bic_min=bic_min,
                         log_n=log_n)  # fmt: skip
    options = function_options(blk.families, blk.pairs)
    stages = {st: sum(1 for o in options if o[2] == st) for st in (1, 2)}
    per_stage = 2.0 if stages[2] else 1.0
    if current.q_data is None:
        current.q_data = model_basis(sigma, model)
    M, g = screen_gram(sigma, model, current, blk.J)
    score = np.array([
        screened_drop(M, g, idx) - len(idx) * log_n - 2.0 * np.log(stages[st])
        for _, idx, st in options
    ])  # fmt: skip

    def evaluated(i):
        labels, idx, st = options[i]
        sub = blk.subset(idx)
        sub.families = None
        sub.multiplicity = blk.multiplicity * per_stage * stages[st]
        c = _evaluate(prob, sigma, model, current, sub, name, alpha=alpha, bic_min=bic_min,
                      log_n=log_n)  # fmt: skip
        if c is None:
            return None
        c.family = "+".join(labels)
        c.functions = list(labels)
        w = family_weights(score)
        # other functions, not the chosen one's own order (its linear term with or without the
        # quadratic, an offset drift with or without the scale drift): the BIC chose that order
        c.alternatives = [
            ("+".join(lb), ix, float(w[j]))
            for j in np.argsort(-w, kind="stable")
            for lb, ix, _ in [options[j]]
            if w[j] >= ALT_MIN_WEIGHT and (ix == idx or not set(ix) & set(idx))
        ]  # fmt: skip
        c.family_block = blk
        return c

    best = int(np.argmax(score))
    # a pair's better function alone (a single function is its own)
    member = best
    if options[best][2] == 2:
        member = max(pair_members(options, best), key=score.__getitem__)
    # where the better function carries the effect on its own, the second must carry evidence
    # of its own too; where neither does, the pair is the effect's only evidence
    if score[member] > bic_min and score[best] - score[member] <= bic_min:
        best = member
    c = evaluated(best)
    if best != member and c is not None and c.has_new and c.survival < min_survival:
        c = evaluated(member)  # the pair's part the baseline does not reproduce
    if c is None or not c.has_new or not _plausibility(c, model.p):
        return c
    # a function outside the effect's plausible range is no evidence of the effect: the next
    # ones by score stand in for it (the choice among all of them is accounted for already)
    for i in np.argsort(-score, kind="stable")[1 : 1 + IMPLAUSIBLE_TRIES]:
        if i in (best, member):
            continue
        alt = evaluated(int(i))
        if alt is not None and alt.has_new and not _plausibility(alt, model.p):
            return alt
    return c


#: Further functions of an effect tried, best score first, when its best is implausible.
IMPLAUSIBLE_TRIES = 3


def _plausibility(c: Candidate, model_p: int) -> str:
    blk = c.cols
    names, est, sd, bnd, why, unit = [], [], [], [], [], []
    th, st = c.fit.theta, c.fit.std
    if c.released:
        rb = dict(zip(blk.release, blk.release_bounds, strict=True))
        for nm in c.released:
            i = c.trial.names.index(nm)
            names.append(nm)
            est.append(th[i])
            sd.append(st[i])
            bnd.append(rb[nm])
            unit.append(c.trial.units[i])
    if c.has_new:
        for j, nm in enumerate(blk.names):
            i = c.trial.p - blk.p + j
            names.append(nm)
            est.append(th[i])
            sd.append(st[i])
            bnd.append(blk.bounds[j])
            unit.append(blk.units[j])

    why = bounds_for(c.name, names)[1]
    if c.has_new and blk.bounds_why is not None:
        own = [w or why[len(why) - blk.p + j] for j, w in enumerate(blk.bounds_why)]
        why = why[: len(why) - blk.p] + own
    return implausible_reason(names, np.array(est), np.array(sd), np.array(bnd), why, unit)


def _holm(round_c) -> None:
    """Holm-adjusted p-values (``p_holm``) over one round's candidates."""
    order = sorted(round_c, key=lambda c: c.p_value)
    m = len(order)
    running = 0.0
    for i, c in enumerate(order):
        running = max(running, min(1.0, (m - i) * c.p_value))
        c.p_holm = running


def _predicts_held_out(prob, sigma, model, c: Candidate, folds, cv_z: float) -> bool:
    """The held-out test of a candidate (module docstring); sets its ``cv_before``,
    ``cv_after`` and ``cv_z``."""
    use = determined_folds(prob, sigma, model, c.trial, folds)
    rms_b, wb = _held_out(prob, sigma, model, folds)
    rms_a, wa = _held_out(prob, sigma, c.trial, folds)
    cvb, cva = float(np.sqrt(rms_b[use].mean())), float(np.sqrt(rms_a[use].mean()))
    diff = ((wb**2).sum(1) - (wa**2).sum(1))[use]
    z = _held_out_score(wb[use], wa[use])
    better = diff.sum() > 0  # the held-out chi2: the RMS is ruled by the noisiest readings
    if c.has_new and better and not z > cv_z:
        z = max(z, _replicated_gain(diff, folds[use], c.k, cv_z))
    if not c.has_new:  # a prior conflict: replicated in every fold on its own, and the
        # held-out error no worse than the released freedom explains (where the data outweigh
        # the prior, the predictions barely change)
        better = _release_within_its_freedom(diff, len(c.released), folds, cv_z)
        z = _replicated_conflict(prob, sigma, c.trial, c.released, model, folds)
    c.cv_before, c.cv_after, c.cv_z = cvb, cva, z
    return bool(z > cv_z and better)


def select_effects(
    prob: Problem,
    sigma_fn,
    blocks: dict,
    *,
    prior_release=(),
    bic_min: float = 10.0,
    alpha: float = 0.01,
    cv_z: float = 2.0,
    max_effects: int = 4,
    k_folds: int = 5,
    min_survival: float = 0.05,
    absorbed=(),
    progress=None,
) -> Selection:
    """Forward selection (see module docstring).

    Parameters
    ----------
    prob : Problem
    sigma_fn : callable
        ``sigma_fn(resid, edf, var_known=None) -> sigma (n, 3)``: noise model re-estimated
        after each accepted effect (effects that live in the repetitions inflate the pure error
        until modelled; ``var_known``: the model's, when an effect changes it).
    blocks : dict name -> Columns
    prior_release : iterable of str
        Unused (kept for compatibility): a block says itself what it releases.
    absorbed : iterable of str
        Effects the baseline absorbs structurally (:func:`structural_absorption`): evaluated
        and reported, never accepted.
    """
    model = stack(prob.baseline)
    fit0 = fit_map(prob.y, np.ones_like(prob.y), model)
    sigma = sigma_fn(fit0.resid, fit0.edf)
    if prob.var_ref is not None:  # the reference's share from a weighted fit (model_sigma)
        fit0 = fit_map(prob.y, sigma, model)
        sigma = sigma_fn(fit0.resid, fit0.edf)
    noise = sigma
    current = fit_map(prob.y, sigma, model)
    sigma_test, current_test = sigma, current  # what further effects are tested against
    folds = folds_of(prob, k_folds)
    log_n = np.log(current.n_obs)
    selected, cands, rounds, accepted_c = [], {}, [], []
    model_error = []  # (rows, variance (rows, 3)) of the accepted approximate models
    absorbed = set(absorbed)
    blocks = dict(blocks)
    done = set()
    for rnd in range(max_effects):
        round_c = []
        for name, blk in blocks.items():
            if name in done:
                continue
            c = _evaluate_block(prob, sigma_test, model, current_test, blk, name, alpha=alpha,
                                bic_min=bic_min, log_n=log_n,
                                min_survival=min_survival)  # fmt: skip
            if progress:
                progress(1)
            if c is None:
                continue
            c.round = rnd
            round_c.append(c)
        if not round_c:
            break
        _holm(round_c)
        for c in round_c:
            cands[c.name] = c
        ok = [c for c in round_c if c.delta_bic > bic_min and c.p_holm < alpha]
        for c in ok:
            if c.name in absorbed or (c.has_new and c.survival < min_survival):
                c.status = "absorbed"
        ok = [c for c in ok if c.status != "absorbed"]
        ok.sort(key=lambda c: -c.delta_bic)
        accepted = None
        n_cv = 0
        for c in ok:
            why = _plausibility(c, model.p)
            if why:
                c.status = "implausible fit"
                c.reason = why
                continue
            if n_cv == 2:  # the best two plausible ones get the held-out test
                break
            n_cv += 1
            if not _predicts_held_out(prob, sigma_test, model, c, folds, cv_z):
                c.status = "fails held-out test"
                continue
            why = unstable_in(prob, sigma_test, model, c.trial)
            if why:
                c.status = "unstable"
                c.reason = why
                continue
            accepted = c
            break
        rounds.append([(c.name, c.delta_bic) for c in sorted(round_c, key=lambda c: -c.delta_bic)])
        if accepted is None:
            break
        accepted.status = "found"
        selected.append(accepted.name)
        accepted_c.append(accepted)
        model = _untestable_released(accepted)
        rest = other_functions(sigma, model, accepted, blocks[accepted.name])
        if rest is None:
            done.add(accepted.name)
        else:
            blocks[accepted.name] = rest
        # re-estimate the noise with the effect in the model, then refit
        noise, sigma = _noise_with(prob, sigma_fn, accepted, model, model_error)
        current = fit_map(prob.y, sigma, model)
        sigma_test = _testing_sigma(sigma, model_error)
        current_test = current if sigma_test is sigma else fit_map(prob.y, sigma_test, model)
    for c in accepted_c:  # the final status of the found ones (later rounds overwrite cands)
        cands[c.name] = c
        c.averaged = model_average(prob, sigma, model, c, log_n)
    sel = Selection(selected=selected, candidates=cands, rounds=rounds)
    sel.model = model
    sel.sigma = sigma
    sel.noise_sigma = noise  # without the stated errors of approximate models
    sel.model_error = model_error
    sel.fit = current
    sel.folds = folds
    sel.accepted = accepted_c
    return sel


def _untestable_released(accepted: Candidate) -> Columns:
    """The model with an accepted effect, the baseline priors its free nuisance makes
    untestable released (:attr:`Columns.nuisance`: the elements' common shift moves the
    readings as the magnet's offset does), so that no later round tests them."""
    nuis = accepted.cols.nuisance if accepted.has_new else None
    if nuis is None or not nuis.release:
        return accepted.trial
    return released_in(accepted.trial, [n for n in nuis.release if n in accepted.trial.names])


#: Family-wise level at which a z plane's misfit under an accepted approximate model is taken
#: as that model's error there (:func:`approximation_error`).
PLANE_MISFIT_ALPHA = 0.01


def approximation_error(prob: Problem, sigma, model: Columns, rows) -> tuple:
    """The error of an accepted approximate model, stated as a variance per reading and
    component where the model misfits.

    Such a model (the soft ends: an Enge/Fermi profile per end, plane values truncated to the
    layers a plane's points separate, on a 2-D reference) need not describe a real magnet's
    3-D field to the noise: its misfit is the same on every repetition, so the held-out tests
    of a further effect whose columns share its structure along z and in r (the probe's tilt
    mixes B_z into B_x and B_y, volume averaging is the Laplacian term, the elements' offsets
    and the magnet's pose read the gradient, a planar Hall term the product of two
    components) would pass on it. Where the model carries the signal (``rows``: the soft ends'
    profile) the error is s_c^2 = mean(r^2 - sigma^2) over those rows of component c. A
    magnet whose field varies along z beyond the profile's transition (a short coil magnet's
    ends decay over several bore radii, slower than a Fermi tail) leaves misfit in planes
    the profile calls body: each z plane whose chi^2 per component exceeds its readings' count
    at the family-wise level :data:`PLANE_MISFIT_ALPHA` (the planes and components tested)
    gets its own s_c^2 = mean(r^2 - sigma^2) there; so does every other plane outside the
    rows when those planes' chi^2, pooled, exceeds their count at that level (a body whose 3-D
    field departs from the 2-D reference by a fraction of the noise in each plane). The larger
    of the two is added to the noise, so that a further claim must exceed it; a plane within
    the noise keeps 0.

    Parameters
    ----------
    prob : Problem
    sigma : ndarray, shape (n, 3)
        Noise of the readings (units of ``prob.y``).
    model : Columns
        The model holding the approximate effect.
    rows : ndarray of bool, shape (n,)

    Returns
    -------
    tuple
        ``(rows, variance)``: the rows with a stated error (n,) bool and its variance there
        (rows, 3), units of ``y`` squared.
    """
    fit = fit_map(prob.y, sigma, model)
    r2 = fit.resid**2 - sigma**2
    ok = np.isfinite(r2)
    r2 = np.where(ok, r2, 0.0)
    var = np.zeros_like(r2)
    n_c = np.maximum(ok[rows].sum(0), 1)
    var[rows] = np.maximum(r2[rows].sum(0) / n_c, 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):  # rows left out: sigma inf
        chi = np.where(ok, fit.resid**2 / sigma**2, 0.0)
    _, plane = np.unique(np.round(prob.pos[:, 2], 3), return_inverse=True)
    n_planes = int(plane.max()) + 1
    for c in range(3):
        count = np.bincount(plane, ok[:, c], n_planes)
        t = np.bincount(plane, chi[:, c], n_planes)
        p = stats.chi2.sf(t, np.maximum(count, 1))
        off = (p < PLANE_MISFIT_ALPHA / (3 * n_planes)) & (count > 0)
        # a misfit spread thinly over many planes: the planes left, pooled, in one test
        rest = ~off & (count > 0) & (np.bincount(plane, rows, n_planes) == 0)
        if rest.any() and stats.chi2.sf(t[rest].sum(), count[rest].sum()) < PLANE_MISFIT_ALPHA / 3:
            off |= rest
        excess = np.maximum(np.bincount(plane, r2[:, c], n_planes) / np.maximum(count, 1), 0.0)
        var[:, c] = np.maximum(var[:, c], np.where(off, excess, 0.0)[plane])
    has = np.any(var > 0, axis=1) | np.asarray(rows, dtype=bool)
    return has, var[has]


def _noise_with(prob, sigma_fn, accepted: Candidate, model: Columns, model_error) -> tuple:
    """The noise (n, 3) re-estimated with an accepted effect in ``model``, and that noise with
    the stated error of every accepted approximate model (``model_error``, extended by
    ``accepted``'s when its model is approximate, :func:`approximation_error`) added at its
    rows: ``(noise, sigma)``."""
    noise = sigma_fn(accepted.fit.resid, accepted.fit.edf, model.var_known)
    if accepted.has_new and accepted.cols.model_rows is not None:
        model_error.append(approximation_error(prob, noise, model, accepted.cols.model_rows))
    return noise, _with_model_error(noise, model_error)


def _with_model_error(sigma, model_error) -> np.ndarray:
    """``sigma`` (n, 3) with the stated errors of accepted approximate models added in
    quadrature at their rows (:func:`approximation_error`)."""
    if not model_error:
        return sigma
    var = sigma**2
    for rows, v in model_error:
        var[rows] += v
    return np.sqrt(var)


#: Factor on the noise of the rows where an accepted approximate model states an error, in
#: the tests of further effects (:func:`_testing_sigma`): their weight there is 1e-6.
UNTESTED_ROWS_FACTOR = 1e3


def _testing_sigma(sigma, model_error) -> np.ndarray:
    """The noise (n, 3) against which further effects are tested once approximate models are
    accepted: ``sigma`` where no accepted model states an error, and
    :data:`UNTESTED_ROWS_FACTOR` times it at the rows where one does.

    Such a model's misfit is stated as a variance per plane and component
    (:func:`approximation_error`), while the misfit itself is structured within the plane
    (a coil's end departs from a Fermi profile as r^n, differently in each component): an
    effect whose columns share that structure (a Hall offset, element offsets, a tilt) would
    take a share of the misfit at every repetition and pass every test on it. A further
    effect must therefore show itself where the accepted models describe the readings to
    their noise; where their error covers every plane, no further effect is claimed. The
    rows keep a finite weight so that the parameters they alone determine stay determined.
    """
    if not model_error:
        return sigma
    out = sigma.copy()
    for rows, _ in model_error:
        out[rows] *= UNTESTED_ROWS_FACTOR
    return out


def stated_error_rows(sel: Selection) -> np.ndarray | None:
    """Rows (n,) bool where an accepted approximate model of ``sel`` states an error, or None."""
    if not getattr(sel, "model_error", None):
        return None
    rows = np.zeros(len(sel.sigma), dtype=bool)
    for r, _ in sel.model_error:
        rows |= r
    return rows


def _signature(model: Columns, cand: Candidate):
    """Columns of a candidate's signature and the indices of the model columns it uses; an
    effect tested function by function signs with all its functions (``family_block``), not
    the one its evidence chose."""
    idx = [model.names.index(n) for n in cand.released]
    J = [model.J[..., idx]] if idx else []
    cols = cand.cols if cand.family_block is None else cand.family_block
    if cand.has_new and cols.p:
        J.append(cols.J)
    if not J:
        return None, idx
    return np.concatenate(J, axis=-1), idx


def _overlap(sigma, model: Columns, a: Candidate, b: Candidate) -> float:
    """Largest canonical correlation between two effect signatures beyond the rest of the model
    (released columns of either effect are not part of the rest)."""
    Ja, ia = _signature(model, a)
    Jb, ib = _signature(model, b)
    if Ja is None or Jb is None:
        return 0.0
    rest = np.setdiff1d(np.arange(model.p), ia + ib)
    m = _whiten(model.J[..., rest], sigma)
    q, _ = np.linalg.qr(m)

    def basis(J):
        w = _whiten(J, sigma)
        w = w - q @ (q.T @ w)
        u, s, _ = np.linalg.svd(w, full_matrices=False)
        return u[:, s > 1e-8 * max(s[0], 1e-300)] if s.size else u[:, :0]

    ua, ub = basis(Ja), basis(Jb)
    if ua.shape[1] == 0 or ub.shape[1] == 0:
        return 0.0
    return float(np.linalg.svd(ua.T @ ub, compute_uv=False)[0])


def overlaps(prob, sigma, model: Columns, cands: dict, names) -> list:
    """Pairwise overlap (0..1) of candidate signatures beyond ``model``, largest first."""
    out = []
    names = list(names)
    for i, a in enumerate(names):
        for b in names[i + 1 :]:
            o = _overlap(sigma, model, cands[a], cands[b])
            out.append((a, b, o))
    return sorted(out, key=lambda t: -t[2])
