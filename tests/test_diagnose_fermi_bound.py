"""The Fermi summary of soft ends: a length on a bound of its range is reported as a bound."""

from __future__ import annotations

import numpy as np

from cfm_fem.workflows.diagnose.fringe import (
    LAMBDA_MIN_FRACTION,
    _fermi_summary,
    fringe_derivatives,
)


def _profile(z, zi, zo, lam, noise, seed):
    """Observations (z, order, index), values and covariance of g, g', g'' at planes z."""
    d = fringe_derivatives(z, zi, zo, lam, 2)
    obs, vals, var = [], [], []
    rng = np.random.default_rng(seed)
    for j, zj in enumerate(z):
        for m in range(3):
            obs.append((float(zj), m, len(vals)))
            vals.append(d[m, j] + noise * rng.standard_normal())
            var.append(noise**2)
    return obs, np.array(vals), np.diag(var)


def test_a_resolved_end_is_an_estimate_with_a_std():
    z = np.linspace(-40.0, 40.0, 17)
    obs, vals, cov = _profile(z, -100.0, 10.0, 6.0, 1e-4, seed=1)
    out = _fermi_summary(obs, vals, cov, (-100.0, 8.0, 5.0))
    value, std, unit = out["lambda"]
    assert abs(value - 6.0) < 5 * std and std > 0 and unit == "mm"
    assert abs(out["z_exit"][0] - 10.0) < 5 * out["z_exit"][1]


def test_an_end_sharper_than_the_planes_sits_on_the_lower_bound_without_a_std():
    z = np.linspace(-40.0, 40.0, 17)  # planes 5 mm apart, an end 0.05 mm long between two
    obs, vals, cov = _profile(z, -100.0, 12.5, 0.05, 1e-4, seed=2)
    out = _fermi_summary(obs, vals, cov, (-100.0, 12.0, 5.0))
    value, std, unit, bound = out["lambda"]
    assert bound == "lower" and std is None
    assert np.isclose(value, LAMBDA_MIN_FRACTION * np.ptp(z))
    for name in ("z_entry", "z_exit"):
        if name in out:
            assert out[name][1] is not None and np.isfinite(out[name][1])
