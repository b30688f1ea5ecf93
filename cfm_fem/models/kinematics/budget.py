"""Uncertainty budget of the bench and design in reverse (linearised model, exact sensitivities).

Also the GUM check of the Monte Carlo result (`gum_check`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..bench import ERROR_DESCRIPTIONS, ERROR_NAMES, Bench
from ..mc import gum_validation, numerical_tolerance
from .chain import sensitivities
from .geometry import kernel_geometry
from .monte_carlo import KinematicsResult

NOISE_NAME = "vibration+delay"


#: The two shares of the budget (`uncertainty_budget`), for its ``estimator`` text and the tables
#: that print them (``cfm-fem kinematics``, ``cfm-fem tolerance``).
VAR_SHARE_MEANING = (
    "var_share = the error's share of the variance u^2 (random part only; the first-order Sobol "
    "index of the linear model, in [0, 1])"
)


UP_SHARE_MEANING = (
    "up_share = the error's share of U_p^2 = sys^2 + u^2: (its variance + the mean over points of "
    "its mean error times the total mean error) / U_p^2, i.e. (1/2) d ln U_p^2 / d ln s_k for its "
    "tolerance scaled by s_k; the shares of an axis sum to 1 (100 %), and an error's is negative "
    "where its mean error opposes the total systematic error (tightening it slightly, alone, "
    "raises U_p)"
)


@dataclass(frozen=True)
class LinearModel:
    """First-order model of the pooled Table IV quantities in the 21 error amplitudes.

    With sensitivities c_ika = dE_a(point i)/dX_k at X = 0 (exact model, central differences),
    amplitude means mu_k and standard deviations sigma_k, and the axis-noise variance v_ia:

        mean_ia(s) = sum_k s_k c_ika mu_k                   (s_k scales error k)
        var_ia(s)  = sum_k s_k**2 c_ika**2 sigma_k**2 + v_ia
        U_p,a(s)**2 = mean_i [mean_ia(s)**2 + var_ia(s)]    (= sys_a**2 + u_a**2 of Table IV)

    Attributes
    ----------
    b : ndarray, shape (n, 3, 21), mm
        c_ika mu_k, the systematic contribution of each error.
    v : ndarray, shape (n, 3, 21), mm**2
        (c_ika sigma_k)**2, the variance contribution.
    noise_var : ndarray, shape (n, 3), mm**2
    """

    b: np.ndarray
    v: np.ndarray
    noise_var: np.ndarray

    def pooled(self, scale=None):
        """(systematic, std, U_p) per axis, each shape (3,), mm, for scale factors (21,)."""
        s = np.ones(self.b.shape[-1]) if scale is None else np.asarray(scale, dtype=np.float64)
        mean = (self.b * s).sum(-1)
        var = (self.v * s**2).sum(-1) + self.noise_var
        sys2 = np.mean(mean**2, axis=0)
        u2 = np.mean(var, axis=0)
        return np.sqrt(sys2), np.sqrt(u2), np.sqrt(sys2 + u2)

    def up2_coefficients(self, k: int):
        """U_p,a**2 = A s**2 + B s + C when only error k is scaled by s; arrays of shape (3,)."""
        bk = self.b[..., k]
        rest = self.b.sum(-1) - bk
        a = np.mean(bk**2 + self.v[..., k], axis=0)
        b = 2.0 * np.mean(bk * rest, axis=0)
        c = np.mean(rest**2 + self.v.sum(-1) - self.v[..., k] + self.noise_var, axis=0)
        return a, b, c

    def shares(self):
        """Budget per axis, shape (3, 22) each (21 errors + noise).

        Returns
        -------
        var_share : shares of the variance u**2 = mean_i var_ia: mean_i v_ika / u_a**2, in [0, 1]
            (linearised GUM; equal to first-order Sobol indices here since the inputs are
            independent and the model is linear to 1e-5). The systematic part is not in them.
        up_share : shares of U_p**2 = sys**2 + u**2: (mean_i b_ika m_ia + mean_i v_ika) /
            U_p,a**2, m_ia = sum_k b_ika the total mean error at point i; equal to
            (1/2) d ln U_p**2 / d ln s_k (elasticity: how much of U_p**2 goes with error k when
            its tolerance is scaled). They sum to 1; one is negative where error k's mean error
            opposes the total one (b_ika m_ia < 0 outweighs its variance), and is not a variance
            share.
        """
        mean = self.b.sum(-1)  # (n, 3)
        var_k = np.mean(self.v, axis=0)  # (3, 21)
        var_n = np.mean(self.noise_var, axis=0)  # (3,)
        u2 = var_k.sum(-1) + var_n
        sys_k = np.mean(self.b * mean[..., None], axis=0)  # (3, 21)
        up2 = np.mean(mean**2, axis=0) + u2
        # an axis with u = 0 (a bench with no error at all) has no shares to split: 0/0 is
        # reported as 0 (`uncertainty_budget` says so in a note) instead of NaN, which JSON refuses
        var_share = _share(np.concatenate([var_k, var_n[:, None]], axis=1), u2)
        up_share = _share(np.concatenate([sys_k + var_k, var_n[:, None]], axis=1), up2)
        return var_share, up_share


def _share(parts, total):
    """``parts / total[:, None]``, 0 where ``total`` is 0."""
    out = np.zeros_like(parts)
    np.divide(parts, total[:, None], out=out, where=total[:, None] > 0)
    return out


def linear_model(bench: Bench, q_cmd=None) -> LinearModel:
    """Sensitivities of the exact HTM model at zero error, for the budget and the design."""
    q = bench.grid_points() if q_cmd is None else np.atleast_2d(q_cmd)
    c = sensitivities(bench, q, at=np.zeros(len(ERROR_NAMES)))  # (n, 3, 21)
    mu, sd = bench.error_means(), bench.error_stds()
    g = kernel_geometry(bench)
    # noise enters through D_a ~ unit vectors: variance of the axis noise itself
    if g.tau_code >= 0:
        tau = bench.delay.tau_pdf
        nv = g.sig**2 + g.speed**2 * (tau.std**2 + tau.mean**2)
    else:
        nv = g.sig**2
    return LinearModel(b=c * mu, v=(c * sd) ** 2, noise_var=np.broadcast_to(nv, (q.shape[0], 3)))


def uncertainty_budget(bench: Bench, q_cmd=None) -> dict:
    """Share of each of the 21 errors (and of the noise) in u**2 and U_p**2 per axis.

    Estimator: the linearised model of :class:`LinearModel` with exact sensitivities (central
    differences of the HTM chain). ``var_share``, the share of the variance u**2, is the
    first-order (here also total) Sobol index for this near-linear model with independent
    inputs, in [0, 1]. ``up_share``, the share of U_p**2 = sys**2 + u**2, also counts the
    error's mean error times the total mean error: an elasticity, which sums to 1 over the rows
    and is negative for an error whose mean opposes the total systematic error
    (`LinearModel.shares`).

    Returns
    -------
    dict
        ``rows``: one dict per error (name, description, pdf, mean, std, per-axis shares);
        ``predicted``: linearised pooled systematic/std/U_p per axis in um.
    """
    lm = linear_model(bench, q_cmd)
    var_share, up_share = lm.shares()
    sys, u, up = lm.pooled()
    rows = []
    for k, spec in enumerate(bench.errors):
        unit_scale = 1e6 if spec.is_angle else 1e3  # rad -> urad, mm -> um
        rows.append(
            {
                "name": spec.name,
                "description": ERROR_DESCRIPTIONS[spec.name],
                "pdf": spec.pdf.scaled(unit_scale).describe(spec.unit if spec.unit else ""),
                "mean": spec.pdf.mean * unit_scale,
                "std": spec.pdf.std * unit_scale,
                "unit": "urad" if spec.is_angle else "um",
                "var_share": {a: float(var_share[j, k]) for j, a in enumerate("xyz")},
                "up_share": {a: float(up_share[j, k]) for j, a in enumerate("xyz")},
            }
        )
    rows.append(
        {
            "name": NOISE_NAME,
            "description": "vibration and reading delay (per point and trial)",
            "pdf": "normal per axis",
            "mean": 0.0,
            "std": float(np.mean(np.sqrt(lm.noise_var[0])) * 1e3),
            "unit": "um",
            "var_share": {a: float(var_share[j, -1]) for j, a in enumerate("xyz")},
            "up_share": {a: float(up_share[j, -1]) for j, a in enumerate("xyz")},
        }
    )
    notes = []
    for j, a in enumerate("xyz"):
        if not up[j] > 0:
            notes.append(f"U_p = 0 on axis {a}: no error contributes; its shares are written as 0")
        elif not u[j] > 0:
            notes.append(f"u = 0 on axis {a}: no random error; its var_share is written as 0")
    return {
        "estimator": (
            "linearised model with exact sensitivities (central differences of the HTM chain at "
            f"zero error); {VAR_SHARE_MEANING}; {UP_SHARE_MEANING}"
        ),
        "notes": notes,
        "rows": rows,
        "predicted": {
            a: {"systematic_um": 1e3 * sys[j], "std_um": 1e3 * u[j], "U_p_um": 1e3 * up[j]}
            for j, a in enumerate("xyz")
        },
    }


def design_tolerances(bench: Bench, target_up_mm, q_cmd=None) -> dict:
    """Design in reverse: how far each tolerance may be loosened (or must be tightened).

    Scaling a tolerance by s scales that error's PDF about zero (mean and width). For each error
    alone, the largest s that keeps U_p,a <= target_a on every axis follows from the quadratic
    U_p,a**2(s) = A s**2 + B s + C. A common factor for all 21 errors is given too.

    Parameters
    ----------
    bench : Bench
    target_up_mm : array_like, shape (3,), mm
        Target U_p per axis (x, y, z); ``inf`` leaves an axis free.

    Returns
    -------
    dict
        ``current``: U_p per axis (um); ``rows`` sorted by the largest absolute ``up_share`` first
        (share of U_p**2, `LinearModel.shares`: may be negative), each with
        ``factor`` (largest admissible s; > 1 loosen, < 1 tighten, None if no s works alone,
        inf if the error does not matter), ``up_at_factor_um``; ``common_factor`` and
        ``up_at_common_um``; ``noise_floor_um`` (U_p with all 21 errors at zero).
    """
    target = np.broadcast_to(np.asarray(target_up_mm, dtype=np.float64), (3,))
    lm = linear_model(bench, q_cmd)
    _, _, up_now = lm.pooled()
    _, up_share = lm.shares()
    t2 = target**2
    nerr = len(bench.errors)
    rows = []
    for k, spec in enumerate(bench.errors):
        s_max = _factor_alone(lm, k, np.ones(nerr), t2)
        up_at = None
        if s_max is not None and np.isfinite(s_max):
            s = np.ones(nerr)
            s[k] = s_max
            up_at = (1e3 * lm.pooled(s)[2]).tolist()
        rows.append(
            {
                "name": spec.name,
                "description": ERROR_DESCRIPTIONS[spec.name],
                "pdf": spec.pdf.scaled(1e6 if spec.is_angle else 1e3).describe(spec.unit),
                "up_share": {a: float(up_share[j, k]) for j, a in enumerate("xyz")},
                "factor": s_max,
                "up_at_factor_um": up_at,
            }
        )
    order = sorted(range(nerr), key=lambda k: -max(abs(up_share[:, k])))
    rows = [rows[k] for k in order]
    # common factor f for all errors: U_p^2 = f^2 (sys^2 + u_err^2) + noise (b scales with f)
    mean = lm.b.sum(-1)
    err2 = np.mean(mean**2, axis=0) + np.mean(lm.v.sum(-1), axis=0)
    noise = np.mean(lm.noise_var, axis=0)
    with np.errstate(divide="ignore", invalid="ignore"):
        f_axes = np.sqrt(np.maximum(t2 - noise, 0.0) / err2)
    f_axes = np.where(t2 <= noise, 0.0, f_axes)
    common = float(np.min(f_axes))
    # common = inf when no error matters (a bench without errors): any factor leaves U_p as is
    up_common = (1e3 * lm.pooled(np.full(nerr, common if np.isfinite(common) else 1.0))[2]).tolist()
    # greedy plan: tighten the largest contributors to a violated axis, one at a time
    s = np.ones(nerr)
    plan = []
    for _ in range(3 * nerr):
        up = lm.pooled(s)[2]
        bad = np.nonzero(up > target * (1 + 1e-12))[0]
        if len(bad) == 0:
            break
        a = bad[np.argmax(up[bad] / target[bad])]
        _, shares_now = LinearModel(lm.b * s, lm.v * s**2, lm.noise_var).shares()
        cand = [
            k for k in np.argsort(-shares_now[a, :nerr]) if s[k] > 0.05 and shares_now[a, k] > 0
        ]
        if not cand:
            break
        k = int(cand[0])
        f = _factor_alone(lm, k, s, t2, axes=[a])
        new = max(0.5 * s[k], f * s[k] if f is not None and f < 1 else 0.5 * s[k])
        s[k] = new
        plan.append({"name": bench.errors[k].name, "factor": float(new)})
    merged = {}
    for step in plan:
        merged[step["name"]] = step["factor"]
    return {
        "target_um": (1e3 * target).tolist(),
        "current_um": (1e3 * up_now).tolist(),
        "noise_floor_um": (1e3 * np.sqrt(noise)).tolist(),
        "rows": rows,
        "common_factor": common,
        "up_at_common_um": up_common,
        "plan": [{"name": n, "factor": f} for n, f in merged.items()],
        "up_after_plan_um": (1e3 * lm.pooled(s)[2]).tolist(),
        "feasible": bool(np.all(t2 > noise)),
        "method": (
            "linearised Table IV pooling, U_p^2 = mean over points of (mean error^2 + variance); "
            "scaling a tolerance by s scales that error's PDF about zero; 'factor' is the largest "
            "s for that error alone that keeps every axis it influences within target"
        ),
    }


def _factor_alone(lm, k, s0, t2, axes=None):
    """Largest multiplier of s0[k] meeting the targets on the axes error k influences."""
    base = LinearModel(lm.b * s0, lm.v * s0**2, lm.noise_var)
    a, b, c = base.up2_coefficients(k)
    infl = a > 1e-9 * (a + np.abs(b) + c)
    if axes is not None:
        infl = infl & np.isin(np.arange(3), axes)
    if not np.any(infl):
        return np.inf
    return _largest_admissible(a[infl], b[infl], c[infl], t2[infl])


def _largest_admissible(a, b, c, t2):
    """Largest s >= 0 with a s^2 + b s + c <= t2 on every axis; inf if unbounded, None if none."""
    lo, hi = 0.0, np.inf
    for ai, bi, ci, ti in zip(a, b, c, t2, strict=True):
        if not np.isfinite(ti):
            continue
        cc = ci - ti
        if ai <= 1e-30 * max(abs(bi), abs(cc), 1e-300):  # error k has no effect on this axis
            if abs(bi) < 1e-300:
                if cc > 0:
                    return None
                continue
            root = -cc / bi
            if bi > 0:
                hi = min(hi, root)
            else:
                lo = max(lo, root)
            continue
        disc = bi * bi - 4 * ai * cc
        if disc < 0:
            return None
        r1 = (-bi - np.sqrt(disc)) / (2 * ai)
        r2 = (-bi + np.sqrt(disc)) / (2 * ai)
        lo, hi = max(lo, r1), min(hi, r2)
    if hi < max(lo, 0.0):
        return None
    return float(hi)


def gum_check(bench: Bench, result: KinematicsResult, ndig: int = 2) -> dict:
    """JCGM 101 section 8 per point and axis: linearised GUM interval vs the Monte Carlo one.

    GUM: y = linearised mean, u = linearised std, interval y -+ 1.96 u (normal output);
    delta = numerical tolerance of the Monte Carlo u for ``ndig`` significant digits.

    Returns
    -------
    dict of axis -> {"valid_fraction", "max_d_um", "median_delta_um"}
    """
    lm = linear_model(bench, result.q_cmd)
    y = lm.b.sum(-1)
    u = np.sqrt(lm.v.sum(-1) + lm.noise_var)
    k = 1.959963984540054
    out = {}
    for j, a in enumerate("xyz"):
        delta = numerical_tolerance(result.std[:, j], ndig)
        d_low, d_high, ok = gum_validation(
            y[:, j], k * u[:, j], result.low[:, j], result.high[:, j], delta
        )
        out[a] = {
            "valid_fraction": float(np.mean(ok)),
            "max_d_um": 1e3 * float(np.max(np.maximum(d_low, d_high))),
            "median_delta_um": 1e3 * float(np.median(delta)),
        }
    return out
