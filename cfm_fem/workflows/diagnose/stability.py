"""Stability of a verdict between neighbouring parts of the same map.

An effect of the bench or the probe acts over the whole scanned volume with the same
parameters, so its estimates from either half of the map must agree. A candidate that fits a
structured residual the catalogue does not contain (the reference's own interpolation error, a
local defect, a transient confined to part of the scan) picks up different parts of it in
different halves, and its halves disagree.

The test is a heterogeneity chi2 (Cochran's Q of the two halves' estimates with their
covariances, in its likelihood-ratio form): along each transverse axis (x and y, split at the
median plane: rows at or below it on one side, above it on the other), the effect's parameters
(its new columns and the baseline parameters whose priors it releases) are given a second copy
acting on one half only, and the whole map is fitted again with the rest of the model shared.
The drop of the objective is ~ chi2(r) when the effect is the same in both halves, r being the
rank the copy adds (a half that cannot see a parameter adds nothing to test). The candidate is
unstable when a split's drop has p below ``ALPHA`` / (number of splits) (Bonferroni,
family-wise ``ALPHA``) and the drop is at least ``MATERIAL`` of the effect's own drop on the
whole map (a strong effect fitted by an approximate model differs between halves by a small
share of itself; a structure confined to one half, by about the whole). Where the model leaves
a lack of fit (chi2/dof > 1 with the effect), the noise is scaled up by its square root first,
so that unmodelled structure does not count as disagreement.

Neither half needs to show the effect on its own: at the selection's threshold a real effect
is significant in a half only about as often as not, and its halves' estimates still agree. An
effect present in one half only (a step, a drift, a transient) gives the halves estimates
apart by the effect itself, and is rejected.
"""

from __future__ import annotations

import numpy as np
from scipy import stats

from .calibrate import Columns, fit_map, stack

__all__ = ["ALPHA", "heterogeneity", "heterogeneity_p", "split_halves", "unstable_in"]

#: Family-wise level of the heterogeneity tests of a candidate (Bonferroni over the splits):
#: a real effect is called unstable in one map of a thousand.
ALPHA = 0.001
#: Share of the effect's own chi2 (its drop on the whole map) a disagreement must reach: below
#: it, the halves differ by the model's approximation of a strong effect, not by a structure
#: confined to part of the map (which disagrees by about the effect itself).
MATERIAL = 0.1


def split_halves(pos) -> list:
    """The two-part splits of the map along x and y at the median plane.

    Parameters
    ----------
    pos : ndarray, shape (n, 3), mm

    Returns
    -------
    list of (str, ndarray of bool (n,), ndarray of bool (n,), float)
        Axis label, rows at or below the median plane, rows above it, the median plane (mm).
        Axes with fewer than three distinct positions are not split.
    """
    out = []
    for a in (0, 1):
        v = np.round(pos[:, a], 6)
        vals = np.unique(v)
        if vals.size < 3:
            continue
        mid = float(vals[(vals.size - 1) // 2])
        out.append(("xy"[a], v <= mid, v > mid, mid))
    return out


def _effect_columns(model: Columns, trial: Columns) -> list:
    """Indices in ``trial`` of the effect's parameters: its new columns and the baseline
    parameters whose priors it releases."""
    released = [
        i
        for i in range(model.p)
        if np.isfinite(model.prior_std[i]) and not np.isfinite(trial.prior_std[i])
    ]
    return released + list(range(model.p, trial.p))


def _copy_on(trial: Columns, idx, rows) -> Columns:
    """Vague copies of the columns ``idx`` of ``trial`` acting on ``rows`` only."""
    return Columns(
        trial.J[..., idx] * rows[:, None, None],
        [f"{trial.names[i]} (part)" for i in idx],
        [trial.units[i] for i in idx],
        np.zeros(len(idx)),
        np.full(len(idx), np.inf),
        "heterogeneity",
    )


def heterogeneity(y, sigma, model: Columns, trial: Columns, rows) -> dict:
    """Heterogeneity chi2 of the effect's parameters, and of the rest of the model's, between
    ``rows`` and the other rows.

    Parameters
    ----------
    y, sigma : ndarray, shape (n, 3)
        Residuals and their standard deviations.
    model, trial : Columns
        The current model, and the model with the candidate effect.
    rows : ndarray of bool, shape (n,)
        One part of the map; the other is its complement.

    Returns
    -------
    dict
        ``q``, ``dof``: the drop of the MAP objective when the effect's parameters take other
        values on ``rows``, and its degrees of freedom (rank added; 0: nothing to test);
        ``q_rest``, ``dof_rest``: the further drop when every other parameter of the model
        does too.
    """
    idx = _effect_columns(model, trial)
    rest = [i for i in range(trial.p) if i not in idx]
    f0 = fit_map(y, sigma, trial)
    if not idx:
        return {"q": 0.0, "dof": 0, "q_rest": 0.0, "dof_rest": 0}
    own = stack([trial, _copy_on(trial, idx, rows)])
    f1 = fit_map(y, sigma, own)
    f2 = fit_map(y, sigma, stack([own, _copy_on(trial, rest, rows)])) if rest else f1
    return {
        "q": max(f0.objective - f1.objective, 0.0),
        "dof": int(f1.rank - f0.rank),
        "q_rest": max(f1.objective - f2.objective, 0.0),
        "dof_rest": int(f2.rank - f1.rank),
    }


def heterogeneity_p(h: dict) -> float:
    """p-value of the effect's heterogeneity ``h`` (:func:`heterogeneity`).

    The larger of the chi2 test against the stated noise and the F test against the
    heterogeneity of the rest of the model (structure the model leaves out that differs between
    the parts moves every parameter, not only the effect's).
    """
    if h["dof"] == 0:
        return 1.0
    p = float(stats.chi2.sf(h["q"], h["dof"]))
    if h["dof_rest"] > 0 and h["q_rest"] > 0:
        f = (h["q"] / h["dof"]) / (h["q_rest"] / h["dof_rest"])
        p = max(p, float(stats.f.sf(f, h["dof"], h["dof_rest"])))
    return p


def unstable_in(prob, sigma, model: Columns, trial: Columns) -> str:
    """'' when the halves of the map agree on the effect (``trial`` = ``model`` with it), else
    the reason.

    Parameters
    ----------
    prob : Problem
    sigma : ndarray, shape (n, 3)
    model, trial : Columns
        The current model, and the model with the candidate effect.
    """
    full = fit_map(prob.y, sigma, trial)
    scale = np.sqrt(max(1.0, full.chi2_data / max(full.n_obs - full.edf, 1.0)))
    s = sigma * scale
    splits = split_halves(prob.pos)
    own = fit_map(prob.y, s, model).objective - fit_map(prob.y, s, trial).objective
    for label, _, high, mid in splits:
        h = heterogeneity(prob.y, s, model, trial, high)
        p = heterogeneity_p(h)
        if p < ALPHA / len(splits) and h["q"] > MATERIAL * own:
            return (
                f"its parameters differ between the parts {label} <= {mid:g} mm and "
                f"{label} > {mid:g} mm of the map (heterogeneity chi2 = {h['q']:.1f} on "
                f"{h['dof']} dof, p = {p:.2g}): the fit follows a local structure, not an "
                "effect over the whole map"
            )
    return ""
