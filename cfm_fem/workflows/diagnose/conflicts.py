"""Prior-data conflicts of the calibrated parameters that no accepted effect released.

Every baseline parameter with a prior (bench errors of Table II, magnet registration from the
survey, Hall gains from the probe's calibration) is checked in the final model: the conflict
z = (theta_post - m) / sqrt(s^2 - C) is N(0, 1) under the prior in a linear-Gaussian model
(theta_post, C: posterior mean and variance; m, s: prior). Holm's procedure runs over the
parameters the data inform (C < 0.9 s^2). A significant conflict is reported with the effect
whose prior release would model it: the recording disagrees with the stated PDF.
"""

from __future__ import annotations

import numpy as np
from scipy import stats

__all__ = ["prior_conflicts", "ROUTE"]

#: Which effect releases the prior of a baseline block.
ROUTE = {
    "bench": "parameter_bias",
    "registration": "magnet_misalignment",
    "probe": "hall_offset_gain",
}


def _group_of(base_blocks, name):
    for b in base_blocks:
        if name in b.names:
            return b.group
    return None


def prior_conflicts(model, fit, base, released, alpha: float, blocks=(), kind="hall") -> list:
    """Significant prior-data conflicts of baseline parameters (module docstring).

    Parameters
    ----------
    model : Columns
        The final model (baseline and accepted effects).
    fit : Fit
        Its MAP fit.
    base : Columns
        The stacked baseline (its names say which parameters are calibrated).
    released : set of str
        Parameters whose priors an accepted effect released (not tested again).
    alpha : float
        Family-wise level (Holm).
    blocks : list of Columns
        The baseline blocks, to name the route of each parameter.
    kind : {'tracker', 'hall'}
        A tracker's registration (tracker to bench) has no effect that models it.

    Returns
    -------
    list of dict
        ``name``, ``value``, ``std``, ``prior_mean``, ``prior_std``, ``z``, ``p_holm``,
        ``effect`` (the prior release that would model it, or None), strongest first.
    """
    rows = []
    for nm in base.names:
        if nm in released or nm not in model.names:
            continue
        i = model.names.index(nm)
        s = model.prior_std[i]
        if not (np.isfinite(s) and s > 0):
            continue
        C = float(fit.cov[i, i])
        if 0.9 * s**2 <= C:
            continue  # the data say little about it on its own
        z = (fit.theta[i] - model.prior_mean[i]) / np.sqrt(s**2 - C)
        rows.append((nm, i, float(z), float(2 * stats.norm.sf(abs(z)))))
    rows.sort(key=lambda r: r[3])
    m = len(rows)
    out, running = [], 0.0
    for k, (nm, i, z, p) in enumerate(rows):
        running = max(running, min(1.0, (m - k) * p))
        if running >= alpha:
            break
        group = _group_of(blocks, nm) if blocks else None
        out.append(
            {
                "name": nm,
                "unit": model.units[i],
                "value": float(fit.theta[i]),
                "std": float(np.sqrt(max(fit.cov[i, i], 0.0))),
                "prior_mean": float(model.prior_mean[i]),
                "prior_std": float(model.prior_std[i]),
                "z": round(z, 2),
                "p_holm": running,
                "effect": None
                if kind == "tracker" and group == "registration"
                else ROUTE.get(group),
            }
        )
    return out
