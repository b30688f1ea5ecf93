"""The noise model of the observations: a floor per component plus the bench's vibration.

Every reading scatters by the instrument's own noise (the Hall probe's, the tracker's), which
does not depend on where the probe is, plus the bench's vibration and reading jitter seen through
the field gradient (``var_known``, from the bench model). The variance of an observation is

    sigma_ic**2 = a_c + b_c * var_known_ic

with the floor ``a_c`` and the scale ``b_c`` of the bench model's vibration both estimated from
the data, per component, and both >= 0. The floor holds where the gradient vanishes (beyond the
magnet ends), the scale lets the data say how much vibration the bench really has (the bench
file may describe another bench). Against a piecewise-linear reference (an FEM or measured map),
the variance of its interpolation error is added (:func:`reference_error_var`): the reference
is not exact between its nodes, and that error is no effect of the bench or the probe. That
variance is a bound stated from the map alone (the spread of neighbouring nodes' fits, the
map's curvature), often far above the error in one component; it is scaled per component by
the share of it the residuals' point means show (:func:`reference_share`), never above 1.

Where the data come from:

* repeated readings of the same point: the within-point sample variances (model independent,
  ``R - 1`` degrees of freedom per point), fitted by iteratively reweighted least squares with
  Var(s^2) = 2 sigma^4 / (R - 1);
* one reading per point: second differences of the residuals along straight scan lines of
  equally spaced points (r_{k-1} - 2 r_k + r_{k+1} has variance 6 a for white noise, and a
  smooth misfit cancels to second order), with gross outliers excluded;
* too few such triples: the residuals themselves (degrees of freedom n - edf), as a last
  resort, said so in ``source``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = [
    "NoiseModel",
    "estimate_noise",
    "line_triples",
    "reference_error_var",
    "reference_share",
    "vibration_covariance",
]

#: Second differences beyond this many model standard deviations are gross outliers (a bad
#: plane, a glitch), left out of the noise estimate; they are for `locate` to find.
_OUTLIER_Z = 5.0
_MIN_TRIPLES = 10


@dataclass
class NoiseModel:
    """Variance model sigma_ic^2 = floor_c + scale_c var_known_ic (units of ``y`` squared).

    Attributes
    ----------
    floor : ndarray, shape (3,)
        Instrument noise variance per component.
    scale : ndarray, shape (3,)
        Multiplier of the bench model's vibration variance per component (1: as the bench file
        says; 0: none seen).
    source : str
        What the estimate rests on (repeated readings, second differences, residuals).
    dof : float
        Degrees of freedom of the estimate (per component).
    ref_share : ndarray, shape (3,)
        Share of the reference's stated error variance carried per component, in [0, 1]
        (:func:`reference_share`); ones when the reference states none.
    """

    floor: np.ndarray
    scale: np.ndarray
    source: str
    dof: float
    ref_share: np.ndarray = field(default_factory=lambda: np.ones(3))

    def sigma(self, var_known, var_ref=None) -> np.ndarray:
        """Standard deviation of each observation, shape (n, 3); ``var_ref`` (n, 3): the
        reference map's own stated error variance, added at its share per component."""
        v = self.floor[None, :] + self.scale[None, :] * var_known
        return np.sqrt(v if var_ref is None else v + self.ref_share[None, :] * var_ref)


def _normalised(s2, v, w_dof, mult):
    """The arguments of :func:`_fit_floor_scale` made dimensionless: (sn, vn, k, S, use_b), or
    None when there is no scatter at all."""
    s2 = np.asarray(s2, dtype=float)
    v = np.asarray(v, dtype=float)
    k = np.asarray(w_dof, dtype=float)
    if s2.size == 0 or not float(np.mean(s2)) > 0.0:
        return None
    S = float(np.sum(k * s2) / np.sum(k)) / mult  # variance scale of the problem
    return s2 / (mult * S), v / S, k, S, bool(np.any(v > 0))


def _nll(la, b, sn, vn, k):
    """Negative log-likelihood of one component (:func:`_fit_floor_scale`) at floor exp(la),
    scale b, with the scale's prior; value and gradient in (la, b)."""
    a = np.exp(la)
    m = np.maximum(a + b * vn, 1e-12)
    with np.errstate(over="ignore"):  # a floor the search tries far out: sn / m^2 -> 0, its limit
        g = 0.5 * k * (1.0 / m - sn / m**2)
    f = float(np.sum(0.5 * k * (sn / m + np.log(m))) + 0.5 * (b - 1.0) ** 2)
    return f, float(g.sum()) * a, float((g * vn).sum()) + b - 1.0


def _fit_floor_scale(s2, v, w_dof, mult=1.0):
    """Maximum-likelihood fit of E[s2] = mult * (a + b v), a, b >= 0; s2, v, w_dof shape (k,).

    Each ``s2`` is a sample variance with ``w_dof`` degrees of freedom: s2 ~ m chi2_k / k with
    m = mult (a + b v), so the negative log-likelihood is sum k/2 (s2 / m + log m). Unlike a
    least-squares fit of s2 (whose weights follow the largest variances), the likelihood lets
    the points where the bench's vibration is small decide the floor: a floor cannot collapse
    below the scatter of the readings where the field gradient vanishes.

    The scale b has a weak prior N(1, 1) (the bench file's vibration as stated): it decides
    only when the data cannot tell the floor from the vibration (v nearly the same at every
    point), and then splits the variance as the bench file says.
    """
    from scipy.optimize import minimize

    got = _normalised(s2, v, w_dof, mult)
    if got is None:  # no scatter at all: nothing to fit
        return 0.0, 0.0
    sn, vn, k, S, use_b = got
    if not use_b:  # the floor alone: its estimate in closed form
        return S, 0.0
    tiny = 1e-12

    def nll(x):
        a, b = x
        m = np.maximum(a + b * vn, tiny)
        r = 0.5 * k * (sn / m + np.log(m))
        with np.errstate(over="ignore"):  # as in `_nll`
            g = 0.5 * k * (1.0 / m - sn / m**2)
        return float(r.sum() + 0.5 * (b - 1.0) ** 2), np.array([g.sum(), (g * vn).sum() + b - 1.0])

    low = vn <= np.quantile(vn, 0.25)
    a0 = max(float(np.sum(k[low] * sn[low]) / np.sum(k[low])), 1e-6)
    res = minimize(nll, [a0, 1.0], jac=True, method="L-BFGS-B",
                   bounds=[(tiny, None), (0.0, None)])  # fmt: skip
    a, b = res.x
    return float(a) * S, float(b)


#: Spread of the three Hall elements' noise floors about their common value (one standard
#: deviation of ln floor): a factor 3 between elements of one probe and its readout.
FLOOR_SPREAD = float(np.log(3.0))


def _pooled_floors(data, spread: float = FLOOR_SPREAD):
    """Floors and scales of the three components, each floor held by a prior towards the
    others: ln a_c ~ N(mu, spread^2), mu free; the joint maximum a posteriori.

    A component whose readings nearly all scatter by the bench's vibration (a transverse
    component across a multipole's body) hardly determines its floor: fitted alone it can
    collapse to zero, and its few quiet readings then weigh as if exact. The elements of one
    probe share its readout, so the components that do determine their floor tell what the
    others' is; a floor the data determine well stays where its data put it.

    Parameters
    ----------
    data : list of 3 tuples (s2, v, w_dof, mult)
        Each component's arguments of :func:`_fit_floor_scale`.

    Returns
    -------
    floor, scale : ndarray, shape (3,)
    """
    from scipy.optimize import minimize

    alone = [_fit_floor_scale(*d) for d in data]
    comps = [(i, _normalised(*d)) for i, d in enumerate(data)]
    comps = [(i, g) for i, g in comps if g is not None]
    if len(comps) < 2:
        return np.array([f[0] for f in alone]), np.array([f[1] for f in alone])
    n = len(comps)
    lS = np.array([np.log(g[3]) for _, g in comps])

    def objective(x):  # x: ln(a_c / S_c), b_c per component, then mu (ln a, absolute)
        la, b, mu = x[:n], x[n : 2 * n], x[-1]
        f, grad = 0.0, np.zeros_like(x)
        for j, (_, (sn, vn, k, _, _)) in enumerate(comps):
            fj, ga, gb = _nll(la[j], b[j], sn, vn, k)
            dz = (la[j] + lS[j] - mu) / spread
            f += fj + 0.5 * dz**2
            grad[j] = ga + dz / spread
            grad[n + j] = gb
            grad[-1] -= dz / spread
        return f, grad

    a_alone = np.array([max(alone[i][0], 1e-12 * g[3]) for i, g in comps])
    la0 = np.log(a_alone) - lS
    mu0 = float(np.median(np.log(a_alone)))  # a collapsed floor aside
    x0 = np.concatenate([la0, [alone[i][1] for i, _ in comps], [mu0]])
    bounds = ([(np.log(1e-12), None)] * n
              + [(0.0, None if g[4] else 0.0) for _, g in comps] + [(None, None)])  # fmt: skip
    res = minimize(objective, x0, jac=True, method="L-BFGS-B", bounds=bounds)
    floor = np.array([f[0] for f in alone])
    scale = np.array([f[1] for f in alone])
    for j, (i, g) in enumerate(comps):
        floor[i] = float(np.exp(res.x[j])) * g[3]
        scale[i] = float(res.x[n + j])
    return floor, scale


def line_triples(pos, tol: float = 1e-3):
    """Triples of points (k-1, k, k+1) consecutive and equally spaced on straight axis lines.

    Parameters
    ----------
    pos : ndarray, shape (m, 3), mm
        Distinct points.
    tol : float
        Relative tolerance of equal spacing.

    Returns
    -------
    ndarray, shape (t, 3), int
        Indices into ``pos``, middle point in column 1.
    """
    out = []
    key = np.round(pos, 6)
    for a in range(3):
        others = [b for b in range(3) if b != a]
        _, line = np.unique(key[:, others], axis=0, return_inverse=True)
        line = line.reshape(-1)
        order = np.lexsort((pos[:, a], line))
        ln, x = line[order], pos[order, a]
        same = (ln[:-2] == ln[1:-1]) & (ln[1:-1] == ln[2:])
        h1, h2 = x[1:-1] - x[:-2], x[2:] - x[1:-1]
        ok = same & (h1 > 0) & (np.abs(h2 - h1) <= tol * h1)
        k = np.flatnonzero(ok)
        if k.size:
            out.append(np.column_stack([order[k], order[k + 1], order[k + 2]]))
    return np.concatenate(out) if out else np.zeros((0, 3), dtype=np.int64)


def _fit_components(data, pooled: bool):
    """Floors and scales of the three components (``data``: :func:`_pooled_floors`), pooled
    or each on its own."""
    if pooled:
        return _pooled_floors(data)
    fits = [_fit_floor_scale(*d) for d in data]
    return np.array([f[0] for f in fits]), np.array([f[1] for f in fits])


def _from_repeats(point, resid, vk, n_points, pooled=False):
    cnt = np.bincount(point, minlength=n_points).astype(float)
    rep_ok = cnt >= 2
    data = []
    for c in range(3):
        mean = np.bincount(point, resid[:, c], n_points) / np.maximum(cnt, 1)
        dev2 = np.bincount(point, (resid[:, c] - mean[point]) ** 2, n_points)
        v = np.bincount(point, vk[:, c], n_points) / np.maximum(cnt, 1)
        s2 = dev2[rep_ok] / (cnt[rep_ok] - 1)
        data.append((s2, v[rep_ok], cnt[rep_ok] - 1, 1.0))
    floor, scale = _fit_components(data, pooled)
    return floor, scale, float(np.sum(cnt[rep_ok] - 1))


def _from_lines(point, pos_pt, resid, vk, n_points, pooled=False):
    tri = line_triples(pos_pt)
    if len(tri) < _MIN_TRIPLES:
        return None
    cnt = np.bincount(point, minlength=n_points).astype(float)
    data = []
    for c in range(3):
        r = np.bincount(point, resid[:, c], n_points) / np.maximum(cnt, 1)
        v = np.bincount(point, vk[:, c], n_points) / np.maximum(cnt, 1)
        e2 = (r[tri[:, 0]] - 2 * r[tri[:, 1]] + r[tri[:, 2]]) ** 2
        # per-triple weights of the floor and of the vibration (point means of one reading each)
        vv = (v[tri[:, 0]] + 4 * v[tri[:, 1]] + v[tri[:, 2]]) / 6.0
        keep = np.ones(e2.size, dtype=bool)
        for _ in range(3):  # exclude gross outliers against the current model
            a, b = _fit_floor_scale(e2[keep], vv[keep], np.ones(keep.sum()), 6.0)
            model = 6.0 * (a + b * vv)
            new = e2 <= _OUTLIER_Z**2 * np.maximum(model, 1e-300)
            if np.array_equal(new, keep):
                break
            keep = new
        data.append((e2[keep], vv[keep], np.ones(keep.sum()), 6.0))
    floor, scale = _fit_components(data, pooled)
    return floor, scale, float(len(tri))


def estimate_noise(prob, resid, edf: float = 0.0, var_known=None) -> NoiseModel:
    """Fit the noise model to the residuals of a problem (module docstring).

    Parameters
    ----------
    prob : Problem
    resid : ndarray, shape (n, 3)
        Residuals of the current model (y units).
    edf : float
        Effective number of fitted parameters (used only by the last-resort estimate).
    var_known : ndarray, shape (n, 3), optional
        Bench-model vibration variance in place of ``prob.var_known``.

    Returns
    -------
    NoiseModel
    """
    vk = prob.var_known if var_known is None else var_known
    m = prob.n_points
    pooled = getattr(prob, "kind", None) == "hall"  # the elements of one probe (_pooled_floors)
    if prob.n_reps >= 2:
        floor, scale, dof = _from_repeats(prob.point, resid, vk, m, pooled)
        source = "repeated readings of the same points (within-point scatter)"
    else:
        cnt = np.bincount(prob.point, minlength=m).astype(float)
        pos_pt = np.zeros((m, 3))
        np.add.at(pos_pt, prob.point, prob.pos)
        pos_pt /= np.maximum(cnt, 1)[:, None]
        got = _from_lines(prob.point, pos_pt, resid, vk, m, pooled)
        if got is not None:
            floor, scale, dof = got
            source = "one reading per point: second differences of the residuals along scan lines"
        else:
            dof = max(prob.n - edf / 3.0, 1.0)
            data = [(resid[:, c] ** 2, vk[:, c], np.ones(prob.n), 1.0) for c in range(3)]
            floor, scale = _fit_components(data, pooled)
            floor, scale = floor * prob.n / dof, scale * prob.n / dof
            source = "one reading per point, no scan lines: the residuals themselves (n - edf)"
    tiny = 1e-12 * max(float(np.mean(prob.y**2)), 1e-300)
    floor = np.maximum(floor, tiny)
    share = np.ones(3)
    if getattr(prob, "var_ref", None) is not None:
        own = floor[None, :] + scale[None, :] * vk
        share = reference_share(prob.point, resid, own, prob.var_ref, prob.ref_cell, edf)
    return NoiseModel(floor=floor, scale=scale, source=source, dof=dof, ref_share=share)


#: One-sided level of the upper bound taken as a reference error's share
#: (:func:`reference_share`): chi^2_1 at 90 % two-sided, 95 % one-sided.
_SHARE_CHI2 = 2.705543454095404


def reference_share(point, resid, own_var, var_ref, ref_cell, edf: float = 0.0) -> np.ndarray:
    """Share of a reference's stated error variance that the residuals show, per component.

    A reference map states its error between nodes from the map alone (the spread of the
    nearest nodes' harmonic fits, the curvature of a linear reading): a bound, the same in
    every component where the map is coarse, while a multipole's error there may lie mostly
    in one component (a sextupole's B_z varies as the product of x, y and the end's slope;
    its transverse components as r^2). Stated in full, it drowns a component's signal under
    an error that component does not carry. The error is one value per point, the same in
    every repetition: the point means of the residuals scatter by the readings' own noise
    over their count plus f times the point's stated variance, f in [0, 1] per component.
    With r_i the mean residual of point i (scaled by m / (m - edf) for the parameters the
    model fitted, in variance), the likelihood of r_i ~ N(0, N_i + f V_i) is maximised over
    f, and its one-sided 95 % upper bound is returned (the share is never set below what the
    data allow: a clean map's claims stay as conservative as the data permit).

    Parameters
    ----------
    point : ndarray, shape (n,), int
        Distinct point of each row.
    resid : ndarray, shape (n, 3)
        Residuals of the current model.
    own_var : ndarray, shape (n, 3)
        The readings' own noise variance (floor and vibration).
    var_ref : ndarray, shape (n, 3)
        The reference's stated error variance per row, as the rows carry it (times ``ref_cell``).
    ref_cell : ndarray, shape (n,), or None
        Factor by which a row's ``var_ref`` exceeds its point's own error variance (the
        readings that share the error: :func:`~cfm_fem.workflows.diagnose.reference_rows.shared_by`,
        :func:`~cfm_fem.workflows.diagnose.reference.shared_readings`); None: 1.
    edf : float
        Parameters the model fitted.

    Returns
    -------
    ndarray, shape (3,)
        The share per component, in [0, 1].
    """
    from scipy.optimize import minimize_scalar

    point = np.asarray(point)
    m = int(point.max()) + 1
    cnt = np.bincount(point, minlength=m).astype(float)
    has = cnt > 0
    cell = np.ones(len(point)) if ref_cell is None else np.asarray(ref_cell, dtype=float)
    inflate = m / max(m - float(edf), 1.0)
    share = np.ones(3)
    for c in range(3):
        ok = np.isfinite(resid[:, c]) & np.isfinite(own_var[:, c]) & np.isfinite(var_ref[:, c])
        n_ok = np.bincount(point, ok, m)
        use = has & (n_ok == cnt)
        if use.sum() < 10:
            continue
        r = np.bincount(point, np.where(ok, resid[:, c], 0.0), m)[use] / cnt[use]
        own = np.bincount(point, np.where(ok, own_var[:, c], 0.0), m)[use] / cnt[use] ** 2
        ref = np.bincount(point, np.where(ok, var_ref[:, c] / cell, 0.0), m)[use] / cnt[use]
        r2 = inflate * r**2
        if not np.any(ref > 0):
            continue
        scale = float(np.median(own[own > 0])) if np.any(own > 0) else float(np.mean(r2))
        if not scale > 0:
            continue
        r2, own, ref = r2 / scale, own / scale, ref / scale

        def nll(f, r2=r2, own=own, ref=ref):
            v = np.maximum(own + f * ref, 1e-300)
            return float(np.sum(r2 / v + np.log(v)))

        best = minimize_scalar(nll, bounds=(0.0, 1.0), method="bounded")
        f_hat = 0.0 if nll(0.0) <= best.fun else float(best.x)
        lo = nll(f_hat)
        if nll(1.0) - lo <= _SHARE_CHI2:
            continue  # the full stated error is within the bound
        a, b = f_hat, 1.0  # bisect for nll(f) - lo = chi2 (-2 log L rises monotonically)
        for _ in range(40):
            mid = 0.5 * (a + b)
            a, b = (mid, b) if nll(mid) - lo < _SHARE_CHI2 else (a, mid)
        share[c] = b
    return share


def vibration_covariance(prob, model, fit, sigma, noise: NoiseModel) -> np.ndarray:
    """Covariance of the parameters of ``fit`` with the vibration correlated across the
    components of a reading.

    The fit weighs each component of a reading on its own (``sigma``), but the bench's
    vibration moves the probe as a whole: one displacement d of the probe changes every
    component, dB = L d (``L`` = ``prob.ctx.lever``, T/mm per bench-frame displacement), so
    the components of one reading covary by sqrt(scale_a scale_b) (L diag(v) L^T)_ab, ``v``
    the bench's vibration variance per axis and ``scale`` the noise model's. With S the
    readings' covariance (its diagonal sigma^2), C the fit's posterior covariance and P the
    prior precisions, the estimate's covariance is C (J^T W S W J + P) C, W = diag(sigma^-2)
    (C itself when S is diagonal).

    Parameters
    ----------
    prob : Problem
        A Hall map with ``ctx.lever`` (n, 3, 3) and ``ctx.axis_var`` (3,), mm^2.
    model : Columns
    fit : Fit
        ``fit_map(prob.y, sigma, model)``.
    sigma : ndarray, shape (n, 3)
    noise : NoiseModel
        The noise model behind ``sigma`` (its vibration scale).

    Returns
    -------
    ndarray, shape (p, p)
        ``fit.cov`` where the problem has no lever or the model brings its own vibration
        variance (:attr:`Columns.var_known`).
    """
    lever = prob.ctx.lever
    if lever is None or model.var_known is not None:
        return fit.cov
    root = np.sqrt(np.clip(noise.scale, 0.0, None))
    Lv = lever * root[None, :, None]
    S = np.einsum("nik,k,njk->nij", Lv, prob.ctx.axis_var, Lv)
    idx = np.arange(3)
    S[:, idx, idx] = sigma**2
    w = np.where(np.isfinite(sigma), 1.0 / sigma**2, 0.0)
    K = model.J * w[..., None]
    S = np.where(np.isfinite(S), S, 0.0)
    M = np.einsum("nip,niq->pq", np.einsum("nij,nip->njp", S, K), K)
    P = np.where(np.isfinite(model.prior_std) & (model.prior_std > 0), model.prior_std, np.inf)
    return fit.cov @ (M + np.diag(1.0 / P**2)) @ fit.cov


def reference_error_var(field_fn, pts, h: float) -> np.ndarray:
    """Variance of the linear interpolation error of a reference map at points, T^2.

    Along a direction with node spacing ``h`` and curvature c, linear interpolation errs by
    c t (h - t) / 2 at a distance t from a node: rms c h^2 / sqrt(120) over a cell, the points
    falling anywhere between nodes. The curvature per component and direction is the second
    difference of ``field_fn`` at step ``h``; the three directions add in variance.

    Parameters
    ----------
    field_fn : callable
        ``field_fn(points (k, 3) mm) -> B (k, 3) T``; NaN outside the map.
    pts : ndarray, shape (m, 3), mm
    h : float, mm
        Typical node spacing of the map.

    Returns
    -------
    ndarray, shape (m, 3)
    """
    b0 = field_fn(pts)
    var = np.zeros_like(b0)
    for j in range(3):
        e = np.zeros(3)
        e[j] = h
        d2 = field_fn(pts + e) - 2 * b0 + field_fn(pts - e)
        d2 = np.where(np.isfinite(d2), d2, 0.0)  # a border node: no estimate along j
        var += d2**2 / 120.0  # (c h^2)^2 / 120 with c h^2 = d2
    return var
