"""Attribution: forward selection of effects by nested model comparison and held-out error.

For each round, every untried candidate is added to the current model and refitted (MAP, priors of
the baseline kept). Evidence of a candidate:

* ``delta_chi2``: drop of the MAP objective (data chi2 + prior chi2), ~ chi2(k) under the null,
  with k the gain in effective parameters (trace of the hat matrix);
* ``delta_bic`` = delta_chi2 - k ln(n_obs);
* ``p_value`` of the likelihood-ratio test, guarded for multiple comparisons by Holm over the
  candidates of the round;
* held-out RMS: K-fold over whole repetitions (every K-th repetition held out), before and after;
* ``survival``: the fraction of the effect's fitted signature that the current model cannot
  reproduce within its priors (penalised projection); small means absorbed.

A candidate is accepted when delta_bic > ``bic_min``, its Holm-adjusted p < ``alpha``, its
survival is at least ``min_survival`` (else it is reported as absorbed) and its held-out RMS
improves significantly (paired, z > ``cv_z``; not required of released priors, whose
evidence is the conflict between data and prior). Overlap between the signatures of two
candidates (after removing the current model) tells which ones the data cannot separate.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import stats

from .calibrate import Columns, Fit, fit_map, stack
from .problem import Problem

__all__ = ["Candidate", "Selection", "select_effects", "folds_of", "cv_rms"]


@dataclass
class Candidate:
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


@dataclass
class Selection:
    selected: list
    candidates: dict
    rounds: list = field(default_factory=list)
    overlaps: list = field(default_factory=list)


def folds_of(prob: Problem, k: int = 5) -> np.ndarray:
    """Fold index of each row: whole repetitions (rep rank modulo k); single-rep maps: z slabs."""
    reps = np.unique(prob.rep)
    if reps.size >= 2:
        rank = np.searchsorted(reps, prob.rep)
        return rank % min(k, reps.size)
    # one repetition: interleaved blocks of points along the scan order
    return prob.point % k


def cv_rms(prob: Problem, sigma, cols: Columns, folds) -> tuple[float, np.ndarray]:
    """Held-out RMS (display units) and the per-row held-out squared error (for paired tests)."""
    out = np.empty(prob.n)
    for f in np.unique(folds):
        test = folds == f
        fit = fit_map(prob.y, sigma, cols, mask=~test)
        r = fit.resid[test] * prob.to_display
        out[test] = (r**2).mean(1)
    return float(np.sqrt(out.mean())), out


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


def _overlap(prob, sigma, model: Columns, a: Columns, b: Columns) -> float:
    """Largest canonical correlation between two effect spaces after projecting out the model."""

    def resid_basis(c):
        w = (c.J / sigma[..., None]).reshape(-1, c.p)
        m = (model.J / sigma[..., None]).reshape(-1, model.p)
        q, _ = np.linalg.qr(m)
        w = w - q @ (q.T @ w)
        u, s, _ = np.linalg.svd(w, full_matrices=False)
        return u[:, s > 1e-8 * max(s[0], 1e-300)]

    ua, ub = resid_basis(a), resid_basis(b)
    if ua.shape[1] == 0 or ub.shape[1] == 0:
        return 0.0
    return float(np.linalg.svd(ua.T @ ub, compute_uv=False)[0])


def select_effects(
    prob: Problem,
    sigma_fn,
    blocks: dict,
    prior_release=(),
    bic_min: float = 10.0,
    alpha: float = 0.01,
    cv_z: float = 2.0,
    max_effects: int = 4,
    k_folds: int = 5,
    min_survival: float = 0.2,
    progress=None,
) -> Selection:
    """Forward selection (see module docstring).

    Parameters
    ----------
    prob : Problem
    sigma_fn : callable
        ``sigma_fn(resid, edf) -> sigma (n, 3)``: noise model re-estimated after each accepted
        effect (effects that live in the repetitions inflate the pure error until modelled).
    blocks : dict name -> Columns
    prior_release : set of str
        Names whose block re-uses baseline columns without priors.
    """
    model = stack(prob.baseline)
    fit0 = fit_map(prob.y, np.ones_like(prob.y), model)
    sigma = sigma_fn(fit0.resid, fit0.edf)
    current = fit_map(prob.y, sigma, model)
    folds = folds_of(prob, k_folds)
    log_n = np.log(current.n_obs)
    selected, cands, rounds = [], {}, []
    for rnd in range(max_effects):
        round_c = []
        for name, blk in blocks.items():
            if name in selected:
                continue
            trial = stack([model, blk])
            f = fit_map(prob.y, sigma, trial)
            d = current.objective - f.objective
            k = max(f.edf - current.edf, 1e-9)
            if name in prior_release:
                # freed priors: the null distribution of the prior-term drop has as many dof as
                # the released directions the data determine (their share of the baseline edf)
                idx = [model.names.index(nm) for nm in blk.names]
                s0 = model.prior_std[idx]
                k = float(np.sum(np.clip(1 - np.diag(current.cov)[idx] / s0**2, 0, 1)))
                k = max(k, 0.5)
            theta_e = f.theta[model.p :]
            surv = (
                _survival(prob, sigma, model, blk, theta_e)
                if name not in prior_release
                else float("nan")
            )
            c = Candidate(
                name=name,
                delta_chi2=float(d),
                k=float(k),
                delta_bic=float(d - k * log_n),
                p_value=float(stats.chi2.sf(max(d, 0.0), max(k, 0.5))),
                survival=surv,
                fit=f,
                cols=blk,
                round=rnd,
            )
            round_c.append(c)
            if progress:
                progress(1)
        if not round_c:
            break
        # Holm over this round's candidates
        order = sorted(round_c, key=lambda c: c.p_value)
        m = len(order)
        running = 0.0
        for i, c in enumerate(order):
            running = max(running, min(1.0, (m - i) * c.p_value))
            c.p_holm = running
        for c in round_c:
            prev = cands.get(c.name)
            if prev is None or rnd == 0:
                cands[c.name] = c
            else:
                c.status = prev.status
                cands[c.name] = c
        ok = [c for c in round_c if c.delta_bic > bic_min and c.p_holm < alpha]
        for c in ok:
            if c.name not in prior_release and c.survival < min_survival:
                c.status = "absorbed"
        ok = [c for c in ok if c.status != "absorbed"]
        ok.sort(key=lambda c: -c.delta_bic)
        accepted = None
        for c in ok[:2]:  # the best; the runner-up if the best fails the held-out test
            cvb, eb = cv_rms(prob, sigma, model, folds)
            cva, ea = cv_rms(prob, sigma, stack([model, c.cols]), folds)
            diff = eb - ea
            z = float(diff.mean() / (diff.std(ddof=1) / np.sqrt(diff.size) + 1e-300))
            c.cv_before, c.cv_after, c.cv_z = cvb, cva, z
            # a released prior changes the fit only where the data already decide, so its
            # held-out error cannot improve: its evidence is the prior-data conflict alone
            if z > cv_z or c.name in prior_release:
                accepted = c
                break
            c.status = "fails held-out test"
        rounds.append([(c.name, c.delta_bic) for c in sorted(round_c, key=lambda c: -c.delta_bic)])
        if accepted is None:
            break
        accepted.status = "found"
        selected.append(accepted.name)
        model = stack([model, accepted.cols])
        # re-estimate the noise with the effect in the model, then refit
        sigma = sigma_fn(accepted.fit.resid, accepted.fit.edf)
        current = fit_map(prob.y, sigma, model)
    sel = Selection(selected=selected, candidates=cands, rounds=rounds)
    sel.model = model
    sel.sigma = sigma
    sel.fit = current
    sel.folds = folds
    return sel


def overlaps(prob, sigma, model: Columns, blocks: dict, names) -> list:
    """Pairwise overlap (0..1) of candidate signatures beyond ``model``, largest first."""
    out = []
    names = list(names)
    for i, a in enumerate(names):
        for b in names[i + 1 :]:
            o = _overlap(prob, sigma, model, blocks[a], blocks[b])
            out.append((a, b, o))
    return sorted(out, key=lambda t: -t[2])
