"""Stability of a verdict between neighbouring parts of the same map.

An effect of the bench or the probe acts over the whole scanned volume, so it must show in
either half of the map. A candidate that fits a structured residual the catalogue does not
contain (the reference's own interpolation error, a local defect) tends to pick up different
parts of it in different halves. Each candidate that passed the other tests is therefore
refitted on the two halves of the map along each transverse axis (x and y, split at the median
plane, which both halves keep): in every half, adding the effect must still improve the fit
significantly. Where the model leaves a lack of fit (chi2/dof > 1 with the effect), the noise is
scaled up by its square root first, so that unmodelled structure does not count as evidence.

A half is tested only where it can show the effect: the whole map's fit, taken as noiseless
data on the half's rows, gives the drop the effect should make there (the noncentrality of the
half's test). An effect whose signature the baseline reproduces on a half (a quadratic error
function along the split axis looks linear on half its stroke) has little to show there, and
failing a test that had little power is no sign of a local structure; a half whose test would
find the effect less likely than not (power below `MIN_POWER`) is left out.
"""

from __future__ import annotations

import numpy as np
from scipy import stats

from .calibrate import fit_map

__all__ = ["neighbouring_halves", "unstable_in"]

#: Level of the per-half test (each half must show the effect at this level).
ALPHA_HALF = 0.01
#: Power below which a half's test is not made (the effect as fitted on the whole map).
MIN_POWER = 0.5


def neighbouring_halves(pos) -> list:
    """(label, row mask) of the halves along x and y, split at the median plane (kept by both).

    Axes with fewer than three distinct positions are not split.
    """
    out = []
    for a in (0, 1):
        vals = np.unique(np.round(pos[:, a], 6))
        if vals.size < 3:
            continue
        mid = vals[(vals.size - 1) // 2]
        v = np.round(pos[:, a], 6)
        out.append((f"{'xy'[a]} <= {mid:g} mm", v <= mid))
        out.append((f"{'xy'[a]} >= {mid:g} mm", v >= mid))
    return out


def unstable_in(prob, sigma, model, trial, k: float) -> str:
    """'' when the effect (``trial`` = ``model`` with it) shows in every half, else the reason.

    Parameters
    ----------
    prob : Problem
    sigma : ndarray, shape (n, 3)
    model, trial : Columns
        The current model, and the model with the candidate effect.
    k : float
        Effective number of parameters the effect adds (degrees of freedom of the test).
    """
    full = fit_map(prob.y, sigma, trial)
    scale = np.sqrt(max(1.0, full.chi2_data / max(full.n_obs - full.edf, 1.0)))
    s = sigma * scale
    dof = max(k, 0.5)
    critical = float(stats.chi2.isf(ALPHA_HALF, dof))
    expected = prob.y - full.resid  # the whole map's fit, noiseless
    for label, rows in neighbouring_halves(prob.pos):
        lam = (fit_map(expected, s, model, mask=rows).objective
               - fit_map(expected, s, trial, mask=rows).objective)  # fmt: skip
        if float(stats.ncx2.sf(critical, dof, max(lam, 1e-12))) < MIN_POWER:
            continue
        f1 = fit_map(prob.y, s, trial, mask=rows)
        f0 = fit_map(prob.y, s, model, mask=rows)
        d = f0.objective - f1.objective
        p = float(stats.chi2.sf(max(d, 0.0), dof))
        if p > ALPHA_HALF:
            return (
                f"not significant in the neighbouring part {label} of the map (p = {p:.2g}): "
                "the fit follows a local structure, not an effect over the whole map"
            )
    return ""
