"""The soft magnet ends a 2-D reference lacks (``fringe_field_3d``): the 3-D field of a body
multipole whose amplitude varies along z, the Enge/Fermi profile that locates the ends, the
per-plane profile values measured near them, and the baseline seen through that field.

A field whose 2-D potential V varies along z as g(z) is the gradient of
sum_k (-1)^k g^(2k)(z) U_k, U_0 = V and lap_perp U_k = U_(k-1) (:func:`potential_layers`).
See :mod:`cfm_fem.workflows.diagnose.effects` for how the effect enters the catalogue.
"""

from __future__ import annotations

import math

import numpy as np

from .priors import effect_columns
from .problem import UM, URAD

__all__ = [
    "fringe_profile",
    "fringe_derivatives",
    "potential_layers",
    "fringe_field_3d",
    "PLANE_LAYERS",
    "PLANE_REACH",
    "PLANE_ORDERS",
]


def fringe_profile(z, z_entry, z_exit, lam):
    """Soft-edge (Enge/Fermi) profile of a magnet and its z-derivative (1/mm).

    g = f((z - z_entry) / lam) f((z_exit - z) / lam), f(u) = 1 / (1 + exp(-u)): the fraction of
    the body field at z; z_entry, z_exit are where one end alone halves the field (effective
    edges, mm), lam the fringe length (mm; 10-90 % over 4.4 lam).
    """
    fi = 0.5 * (1.0 + np.tanh(0.5 * (z - z_entry) / lam))
    fo = 0.5 * (1.0 + np.tanh(0.5 * (z_exit - z) / lam))
    g = fi * fo
    return g, g * ((1.0 - fi) - (1.0 - fo)) / lam


def _scalar_potential(field_fn, pts, n: int = 8):
    """V, W and grad W of the transverse field at ``pts`` (line integrals from (0, 0, z)).

    (B_x, B_y) = grad V, V = 0 on the axis: exact for a curl-free 2-D field. W solves
    lap_perp W = V (W = r^2 / 4 int_0^1 V(t p) dt: a harmonic V_n of degree n gives
    r^2 V_n / (4 (n + 1))), the next order of the 3-D potential g V - g'' W of a field whose
    amplitude g(z) varies along z.

    Returns
    -------
    V : ndarray, shape (m,), T mm
    W3 : ndarray, shape (m, 3)
        W (T mm^3) and dW/dx, dW/dy (T mm^2).
    """
    t, w = np.polynomial.legendre.leggauss(n)
    t, w = 0.5 * (t + 1.0), 0.5 * w
    V = np.zeros(len(pts))
    avg = np.zeros(len(pts))  # int_0^1 V(t p) dt = int_0^1 (1 - s) p . B(s p) ds
    moment = np.zeros((len(pts), 2))  # int_0^1 s B(s p) ds, the gradient of avg
    for tk, wk in zip(t, w, strict=True):
        q = pts.copy()
        q[:, :2] *= tk
        b = field_fn(q)
        pb = pts[:, 0] * b[:, 0] + pts[:, 1] * b[:, 1]
        V += wk * pb
        avg += wk * (1.0 - tk) * pb
        moment += wk * tk * b[:, :2]
    r2 = pts[:, 0] ** 2 + pts[:, 1] ** 2
    W3 = np.empty((len(pts), 3))
    W3[:, 0] = 0.25 * r2 * avg
    W3[:, 1:] = 0.5 * pts[:, :2] * avg[:, None] + 0.25 * r2[:, None] * moment
    return V, W3


#: Potential layers of the per-plane soft-end model: the 3-D potential to order (r / lam)^8.
PLANE_LAYERS = 4


def potential_layers(field_fn, pts, layers: int = PLANE_LAYERS, n: int = 8):
    """Layers U_k (k = 1 .. ``layers``) of the 3-D potential of a field whose amplitude varies
    along z, and their transverse gradients, at ``pts`` (line integrals from (0, 0, z)).

    The potential sum_k (-1)^k g^(2k)(z) U_k with U_0 = V (grad V = B_perp of the 2-D field)
    and lap_perp U_k = U_(k-1) is harmonic for any profile g. For a harmonic V_n of degree n,
    U_k = r^(2k) V_n n! / (4^k k! (n + k)!); for any V,
    U_k = r^(2k) / (4^k k! (k - 1)!) I_k with I_k = int_0^1 (1 - u)^k / k p . B(u p) du and
    grad I_k = int_0^1 (1 - u)^(k - 1) u B(u p) du (B curl-free).

    Returns
    -------
    ndarray, shape (layers, m, 3)
        U_k (T mm^(2k+1)) and dU_k/dx, dU_k/dy (T mm^(2k)).
    """
    t, w = np.polynomial.legendre.leggauss(n)
    t, w = 0.5 * (t + 1.0), 0.5 * w
    m = len(pts)
    ints = np.zeros((layers, m))
    grads = np.zeros((layers, m, 2))
    for tk, wk in zip(t, w, strict=True):
        q = pts.copy()
        q[:, :2] *= tk
        b = field_fn(q)
        pb = pts[:, 0] * b[:, 0] + pts[:, 1] * b[:, 1]
        for k in range(1, layers + 1):
            ints[k - 1] += wk * (1.0 - tk) ** k / k * pb
            grads[k - 1] += wk * (1.0 - tk) ** (k - 1) * tk * b[:, :2]
    r2 = pts[:, 0] ** 2 + pts[:, 1] ** 2
    out = np.empty((layers, m, 3))
    for k in range(1, layers + 1):
        c = 1.0 / (4.0**k * math.factorial(k) * math.factorial(k - 1))
        out[k - 1, :, 0] = c * r2**k * ints[k - 1]
        out[k - 1, :, 1:] = c * (
            2 * k * (r2 ** (k - 1))[:, None] * pts[:, :2] * ints[k - 1][:, None]
            + (r2**k)[:, None] * grads[k - 1]
        )
    return out


def _layer_hessians(field_fn, pts, h: float = 1e-3):
    """Transverse Hessians of the potential layers of :func:`potential_layers` at ``pts``:
    ndarray, shape (layers, m, 2, 2), T mm^(2k-1); central differences of their gradients
    over +-``h`` mm (the layers are polynomials of low degree in x, y)."""
    out = None
    for j in range(2):
        e = np.zeros(3)
        e[j] = h
        diff = (
            potential_layers(field_fn, pts + e)[..., 1:]
            - potential_layers(field_fn, pts - e)[..., 1:]
        )
        if out is None:
            out = np.empty(diff.shape[:2] + (2, 2))
        out[:, :, :, j] = diff / (2.0 * h)
    return 0.5 * (out + np.swapaxes(out, -1, -2))


class _Projector:
    """Fast MAP objective of ``y - D`` against the baseline (D the same on every repetition of a
    position): ||b||^2 - ||U' b||^2 of the whitened, prior-augmented system, summed per
    position so that one evaluation costs O(positions x parameters)."""

    def __init__(self, prob, sigma, base, uinv, m):
        w = 1.0 / sigma
        A = (base.J * w[..., None]).reshape(-1, base.p)
        P = np.where(np.isfinite(base.prior_std), 1.0 / base.prior_std, 0.0)
        hp = P > 0
        sc = np.sqrt((A**2).sum(0) + P**2)
        sc[sc == 0] = 1.0
        Aa = np.vstack([A, np.diag(P)[hp]]) / sc
        u, sv, _ = np.linalg.svd(Aa, full_matrices=False)
        u = u[:, sv > 1e-10 * sv[0]]
        nd = A.shape[0]
        b0 = np.concatenate([(prob.y * w).reshape(-1), (base.prior_mean * P)[hp]])
        self.bb = float(b0 @ b0)
        self.c0 = u.T @ b0
        ud = u[:nd].reshape(prob.n, 3, -1) * w[..., None]
        self.M = np.zeros((m, 3, u.shape[1]))
        np.add.at(self.M, uinv, ud)
        self.s1 = np.zeros((m, 3))
        np.add.at(self.s1, uinv, prob.y * w**2)
        self.s2 = np.zeros((m, 3))
        np.add.at(self.s2, uinv, w**2)

    def __call__(self, D):
        c = self.c0 - np.einsum("mcr,mc->r", self.M, D)
        return self.bb - 2 * np.sum(self.s1 * D) + np.sum(self.s2 * D * D) - float(c @ c)


def _fringe_derivatives(z, z_entry, z_exit, lam):
    """g of :func:`fringe_profile` and its first three z-derivatives (1/mm^k)."""

    def logistic(u, sign):
        f = 0.5 * (1.0 + np.tanh(0.5 * u))
        d1 = f * (1.0 - f)  # derivatives in u, times (sign / lam)^k for z
        d2 = d1 * (1.0 - 2.0 * f)
        d3 = d1 * (1.0 - 6.0 * f + 6.0 * f * f)
        return f, sign * d1 / lam, d2 / lam**2, sign * d3 / lam**3

    a0, a1, a2, a3 = logistic((z - z_entry) / lam, 1.0)
    b0, b1, b2, b3 = logistic((z_exit - z) / lam, -1.0)
    g = a0 * b0
    g1 = a1 * b0 + a0 * b1
    g2 = a2 * b0 + 2.0 * a1 * b1 + a0 * b2
    g3 = a3 * b0 + 3.0 * a2 * b1 + 3.0 * a1 * b2 + a0 * b3
    return g, g1, g2, g3


def fringe_derivatives(z, z_entry, z_exit, lam, order: int):
    """g of :func:`fringe_profile` and its z-derivatives up to ``order``: ndarray, shape
    (order + 1, len(z)), row m in 1/mm^m. The m-th derivative of the logistic f is a
    polynomial in f (P_(m+1) = P_m' f (1 - f)); the product rule joins the two ends."""
    polys = [np.polynomial.Polynomial([0.0, 1.0])]
    step = np.polynomial.Polynomial([0.0, 1.0, -1.0])  # f (1 - f)
    for _ in range(order):
        polys.append(polys[-1].deriv() * step)
    fi = 0.5 * (1.0 + np.tanh(0.5 * (z - z_entry) / lam))
    fo = 0.5 * (1.0 + np.tanh(0.5 * (z_exit - z) / lam))
    di = np.array([polys[m](fi) / lam**m for m in range(order + 1)])
    do = np.array([polys[m](fo) * (-1.0 / lam) ** m for m in range(order + 1)])
    out = np.zeros((order + 1, len(z)))
    for m in range(order + 1):
        for j in range(m + 1):
            out[m] += math.comb(m, j) * di[j] * do[m - j]
    return out


#: Registration columns of :func:`~cfm_fem.workflows.diagnose.problem.hall_problem` that move
#: the probe relative to the magnet (translation axis) or rotate it (rotation axis).
#: ``magnet_dz`` moves both ends together, exactly as a common shift of the edges: it is left
#: as it is (no signature in a 2-D reference), so the edges come out in the map frame (they
#: carry the magnet's z offset).
_REG_T = {"magnet_dx": 0, "magnet_dy": 1}
_REG_R = {"magnet_rot_x": 0, "magnet_rot_y": 1, "magnet_roll": 2}
_GAIN = {"gain_x": 0, "gain_y": 1, "gain_z": 2}


def _baseline_3d(prob, base):
    """``J3(a, th)``: the baseline columns seen through the 3-D field of the fringe model.

    The field with soft ends is F_i = g_a B_i (i = x, y) and F_z = g_a' V, g_a = 1 + a (g - 1)
    (a = 1: the field vanishes outside the magnet); its gradient is curl-free and symmetric,
    dF_i/dx_j = g_a G_ij, dF_i/dz = dF_z/dx_i = g_a' B_i, dF_z/dz = g_a'' V. A baseline parameter
    that moves the probe relative to the magnet by d (bench errors, magnet offsets and
    rotations) changes the reading by (dF/dx) d: through the steep fringe gradient a z
    displacement shows, which the 2-D reference cannot show; a rotation also turns F, a gain
    scales it. Other baseline columns scale with the body field (g_a). The bench's vibration
    is seen through the same gradient (known variance of the observations).

    Returns
    -------
    callable
        ``(a, th) -> (J3 (n, 3, base.p), var_known (n, 3))``.
    """
    ctx = prob.ctx
    uinv = ctx.uinv
    B0, G, V = ctx.B0, ctx.G, ctx.V[uinv]
    if ctx.U is None:
        ctx.U = potential_layers(ctx.field_fn, ctx.upts)
    if ctx.HU is None:
        ctx.HU = _layer_hessians(ctx.field_fn, ctx.upts)
    U, HU = ctx.U[:, uinv], ctx.HU[:, uinv]
    z, p = prob.pos[:, 2], prob.pos
    disp = ctx.bench_disp
    bench = ctx.bench

    def j3(a, th, prof=None):
        """J3 and var_known with the Fermi profile (a, th), or with ``prof`` (rows g, g', ...
        per row, at least 2 layers + 3 of them) in its place."""
        if prof is None:
            d = a * fringe_derivatives(z, *th, 2 * len(U) + 2)
            d[0] += 1.0 - a
        else:
            d = prof
        ge = d[0]
        F = B0 * ge[:, None]
        F[:, 2] += d[1] * V
        G3 = G * ge[:, None, None]
        G3[:, :, 2] += d[1][:, None] * B0
        G3[:, 2, :2] += d[1][:, None] * B0[:, :2]
        G3[:, 2, 2] += d[2] * V
        for k in range(1, len(U) + 1):  # the layers of the 3-D potential, sign (-1)^k
            u, s = U[k - 1], (-1.0) ** k
            F[:, :2] += s * d[2 * k][:, None] * u[:, 1:]
            F[:, 2] += s * d[2 * k + 1] * u[:, 0]
            G3[:, :2, :2] += s * d[2 * k][:, None, None] * HU[k - 1]
            dz = s * d[2 * k + 1][:, None] * u[:, 1:]
            G3[:, :2, 2] += dz
            G3[:, 2, :2] += dz
            G3[:, 2, 2] += s * d[2 * k + 2] * u[:, 0]
        J = base.J * ge[:, None, None]
        k = 0
        for b in prob.baseline:
            if b.group == "bench" and disp is not None:
                J[..., k : k + b.p] = np.einsum("nij,njp->nip", G3, disp)
            else:
                for j, nm in enumerate(b.names):
                    col = None
                    if nm in _REG_T:
                        col = -G3[:, :, _REG_T[nm]] * UM
                    elif nm in _REG_R:
                        e = np.zeros(3)
                        e[_REG_R[nm]] = URAD
                        col = np.cross(e, F) - np.einsum("nij,nj->ni", G3, np.cross(e, p))
                    elif nm in _GAIN:
                        col = np.zeros_like(F)
                        col[:, _GAIN[nm]] = F[:, _GAIN[nm]] * 1e-2
                    elif nm == "magnet_dz":
                        col = b.J[..., j]
                    if col is not None:
                        J[..., k + j] = col
            k += b.p
        vk = prob.var_known
        if bench is not None and disp is not None:
            lever = np.einsum("nij,jk->nik", G3, bench.bench_to_magnet_rotation())
            vk = np.einsum("nik,k->ni", lever**2, bench.noise_std_mm() ** 2)
        return J, vk

    return j3


def _search_edges(obj, delta, zmin, zmax):
    """Edges and fringe length of the soft ends that best explain the residual: a grid search
    of each end alone (the other far away), then Nelder-Mead on both together.

    ``obj(D)``: the MAP objective of the residual less D against the calibrated baseline;
    ``delta(th)``: D of the soft-end model with edges and length ``th`` (mm).
    """
    from scipy.optimize import minimize

    zc, span = 0.5 * (zmin + zmax), zmax - zmin
    lams = np.geomspace(1.0, span / 4.0, 12)
    far = 30.0  # edge this many fringe lengths outside the map: no signature
    best = []
    for side in (1.0, -1.0):  # exit end, then entry end, the other one far away
        top = (np.inf, None)
        for lam in lams:
            for u in np.linspace(0.0, 1.0, 41):
                ze = zc + side * (u * (0.5 * span + 10 * lam))
                th = (
                    (zmin - far * lams[-1], ze, lam)
                    if side > 0
                    else (ze, zmax + far * lams[-1], lam)
                )
                v = obj(delta(th))
                top = min(top, (v, th), key=lambda t: t[0])
        best.append(top[1])
    th0 = (best[1][0], best[0][1], np.sqrt(best[0][2] * best[1][2]))

    def f(x):
        return obj(delta((x[0], x[1], np.exp(x[2]))))

    res = minimize(
        f,
        [th0[0], th0[1], np.log(th0[2])],
        method="Nelder-Mead",
        options={"xatol": 1e-3, "fatol": 1e-3, "maxiter": 600},
    )
    return res.x[0], res.x[1], float(np.exp(res.x[2]))


#: Planes within this many fringe lengths of an end the data cover get their own profile.
PLANE_REACH = 16.0

#: Fewest distinct points of a plane that gets its own profile.
PLANE_MIN_POINTS = 6

#: Orders of the profile reported per plane: g, g' and g''.
PLANE_ORDERS = ("g", "g'", "g''")


def _plane_columns(B0u, Vu, U, idx, layers):
    """Columns (len(idx), 3, 2 layers) of one plane's profile values g^(m), m = 0 .. 2 layers - 1:
    the change of the reading per unit of each, from the potential sum_k (-1)^k g^(2k) U_k."""
    cols = np.zeros((len(idx), 3, 2 * layers))
    cols[:, :, 0] = B0u[idx]
    cols[:, 2, 1] = Vu[idx]
    for k in range(1, layers):
        sign = (-1.0) ** k
        cols[:, :2, 2 * k] = sign * U[k - 1, idx, 1:]
        cols[:, 2, 2 * k + 1] = sign * U[k - 1, idx, 0]
    return cols


def _plane_layers(cols, cond_max: float = 1e6) -> int:
    """Largest number of layers whose columns the plane's points separate (condition number of
    the unit-normalised columns at most ``cond_max``); 0 if not even the first."""
    best = 0
    for layers in range(1, cols.shape[-1] // 2 + 1):
        a = cols[..., : 2 * layers].reshape(-1, 2 * layers)
        nrm = np.linalg.norm(a, axis=0)
        if not np.all(nrm > 0):
            break
        sv = np.linalg.svd(a / nrm, compute_uv=False)
        if not sv[-1] * cond_max > sv[0]:
            break
        best = layers
    return best


def _truncation_bias(fitted, omitted, z, th, a):
    """What leaving out the higher layers does to a plane's fitted values: the least-squares
    projection of the omitted columns, at the Fermi profile's derivatives, on the fitted ones.

    Parameters
    ----------
    fitted : ndarray, shape (m, 3, p)
        The plane's fitted columns (its layers first).
    omitted : ndarray, shape (m, 3, q)
        The columns of the layers it cannot separate (orders p .. p + q - 1 of the profile).
    z : float, mm
    th : sequence
        Fermi (z_entry, z_exit, lambda), mm.
    a : float
        Fermi amplitude.

    Returns
    -------
    ndarray, shape (p,)
        Bias of each fitted value (its units).
    """
    p, q = fitted.shape[-1], omitted.shape[-1]
    derivs = a * fringe_derivatives(np.array([z]), *th, p + q)[:, 0]
    layers_2 = p - (p % 2)  # the profile orders among the fitted columns
    left = omitted.reshape(-1, q) @ derivs[layers_2 : layers_2 + q]
    return np.linalg.lstsq(fitted.reshape(-1, p), left, rcond=None)[0]


#: Shortest fringe length of the Fermi summary, as a fraction of the z span of the planes that
#: define it: a shorter end is a step between two planes, whose length the planes cannot set.
LAMBDA_MIN_FRACTION = 0.01


def _fermi_summary(obs, values, cov, th0):
    """The Fermi profile's edges and length fitted to per-plane profile values.

    Least squares of :func:`fringe_derivatives` to the values weighted by their std (their
    correlations left out: with a shape that does not fit, a fit whitened by them leans on
    differences between orders of one plane). A real end is not a Fermi shape: the std
    combines the fit's own, scaled by the square root of its reduced chi2 where above 1, with
    the spread of the fit over the planes that define it (jackknife, leaving out one plane at a
    time), which is what the shape's parameters change by when the shape is sampled elsewhere.

    Parameters
    ----------
    obs : list of (z mm, order m, index)
        Profile value g^(m) at plane z, ``values[index]``.
    values, cov : ndarray, shapes (p,), (p, p)
    th0 : sequence of 3 floats
        Start (z_entry, z_exit, lambda), mm.

    Returns
    -------
    dict or None
        {"z_entry", "z_exit", "lambda": (value, std, "mm")}; None with fewer than three planes.
        A length on a bound of its range (`LAMBDA_MIN_FRACTION` of the planes' z span, the
        span) is (value, None, "mm", "lower" | "upper"): a bound, not an estimate; the edges
        are then fitted with it held there (left out if that fit is singular).
    """
    from scipy.optimize import least_squares

    if len({o[0] for o in obs}) < 3:
        return None
    z = np.array([o[0] for o in obs])
    order = np.array([o[1] for o in obs])
    idx = np.array([o[2] for o in obs])
    y = values[idx]
    c = cov[np.ix_(idx, idx)]

    w = 1.0 / np.sqrt(np.maximum(np.diag(c), 1e-300))
    span = float(np.ptp(z))
    lo = np.array([-np.inf, -np.inf, LAMBDA_MIN_FRACTION * span])
    hi = np.array([np.inf, np.inf, span])
    start = np.clip(np.asarray(th0, dtype=float), lo + 1e-9 * span, hi - 1e-9 * span)

    def fit(keep):
        def resid(th):
            d = fringe_derivatives(z[keep], th[0], th[1], th[2], 2)
            return w[keep] * (d[order[keep], np.arange(keep.sum())] - y[keep])

        r = least_squares(resid, start, x_scale=[1.0, 1.0, 0.1], bounds=(lo, hi))
        return r.x, r.jac, float(r.fun @ r.fun), r.active_mask

    every = np.ones(len(z), dtype=bool)
    th, jac, chi2, active = fit(every)
    names = ("z_entry", "z_exit", "lambda")
    if active[2]:  # the length sits on a bound: the data set no value, nor a std, for it
        bound = "lower" if active[2] < 0 else "upper"
        return {"lambda": (float(th[2]), None, "mm", bound)} | _edges_with_lambda_held(
            fit, th, jac, chi2, z
        )
    dof = max(len(z) - 3, 1)
    try:
        var = np.diag(np.linalg.inv(jac.T @ jac)) * max(1.0, chi2 / dof)
    except np.linalg.LinAlgError:
        return None
    planes = np.unique(z)
    jk = np.array([fit(z != zp)[0] for zp in planes])
    n = len(planes)
    var = var + (n - 1) / n * ((jk - jk.mean(0)) ** 2).sum(0)
    sd = np.sqrt(var)
    return {name: (float(th[k]), float(sd[k]), "mm") for k, name in enumerate(names)}


def _edges_with_lambda_held(fit, th, jac, chi2, z) -> dict:
    """The edges' std with the length held at its bound (the fit's own, scaled by its reduced
    chi2 where above 1, plus the jackknife spread over the planes)."""
    dof = max(len(z) - 2, 1)
    try:
        var = np.diag(np.linalg.inv(jac[:, :2].T @ jac[:, :2])) * max(1.0, chi2 / dof)
    except np.linalg.LinAlgError:
        return {}
    planes = np.unique(z)
    jk = np.array([fit(z != zp)[0][:2] for zp in planes])
    n = len(planes)
    sd = np.sqrt(var + (n - 1) / n * ((jk - jk.mean(0)) ** 2).sum(0))
    return {n: (float(th[k]), float(sd[k]), "mm") for k, n in enumerate(("z_entry", "z_exit"))}


def _near_ends(zs, th, inside) -> np.ndarray:
    """Which planes ``zs`` (mm) lie within `PLANE_REACH` Fermi lengths of an end the data cover
    (``th``: entry, exit, length; ``inside``: whether each end is covered)."""
    zi, zo, lam = th
    near = np.zeros(len(zs), dtype=bool)
    for edge, ok in zip((zi, zo), inside, strict=True):
        if ok:
            near |= np.abs(zs - edge) <= PLANE_REACH * lam
    return near


def _plane_block(prob, blk, th, a, inside, shape):
    """The soft ends measured plane by plane: near each end the data cover, every z plane of
    at least `PLANE_MIN_POINTS` points gets its own profile values g - 1, g', g'', ... (the
    generalised gradients of the body multipole relative to the 2-D reference), so the fit
    does not rest on the Fermi shape there; the Fermi profile of ``blk`` (its amplitude
    column) carries the other planes. None if no plane near an end has points that separate
    the layers.

    ``a``: the Fermi profile's amplitude (its planes beyond, until the block is fitted).
    ``shape``: the Fermi edges and length with their std ({name: (value, std, unit)}), reported
    as model-dependent, as are the values of a plane whose points separate fewer than
    `PLANE_LAYERS` layers; their std includes what the layers left out do to them
    (`_truncation_bias`).
    """
    ctx = prob.ctx
    upts, uinv = ctx.upts, ctx.uinv
    if ctx.U is None:
        ctx.U = potential_layers(ctx.field_fn, upts)
    U, Vu = ctx.U, ctx.V
    B0u = ctx.field_fn(upts)
    zs, plane = np.unique(np.round(upts[:, 2], 6), return_inverse=True)
    plane = plane.reshape(-1)
    near = _near_ends(zs, th, inside)
    Jp, names, units, freed, short = [], [], [], np.zeros(len(zs), dtype=bool), []
    slots = []  # (rows of the plane, first column, layers)
    trunc = {}  # truncation bias of the values of planes that separate too few layers
    for j in np.flatnonzero(near):
        idx = np.flatnonzero(plane == j)
        if len(idx) < PLANE_MIN_POINTS:  # scattered z: no plane to fit on its own
            continue
        cols = _plane_columns(B0u, Vu, U, idx, PLANE_LAYERS)
        layers = _plane_layers(cols)
        if layers == 0:
            continue
        freed[j] = True
        slots.append((plane[uinv] == j, len(names), layers))
        # and B_z = g' times the constant of V at the plane: V is known up to a constant, its
        # value on the magnet's axis where the axis is off the map's (-G c_x c_y / 2 for an
        # offset c of a quadrupole: the second-order term of the offset through the ends)
        full = np.zeros((len(upts), 3, 2 * layers + 1))
        full[idx, :, : 2 * layers] = cols[..., : 2 * layers]
        full[idx, 2, 2 * layers] = 1.0
        Jp.append(full)
        if layers < PLANE_LAYERS:  # the higher layers are assumed negligible: a truncation
            short += [f"{o}@{zs[j]:g}" for o in PLANE_ORDERS]
            bias = _truncation_bias(full[idx], cols[..., 2 * layers :], zs[j], th, a)
            trunc.update({f"g{m}@{zs[j]:g}": float(abs(bias[m])) for m in range(2 * layers)})
        for m in range(2 * layers):
            names.append(f"g{m}@{zs[j]:g}")
            units.append("1" if m == 0 else "1/mm" if m == 1 else f"1/mm{m}")
        names.append(f"bz_axis@{zs[j]:g}")
        units.append("T")
    if not freed.any():
        return None

    in_planes = freed[plane[uinv]]
    amp = blk.J[..., :1] * ~in_planes[:, None, None]  # the Fermi profile beyond those planes
    first = [amp] if np.any(amp) else []
    J = np.concatenate(first + [c[uinv] for c in Jp], axis=-1)
    lead = ["amplitude"] if first else []
    out = effect_columns(J, lead + names, ["1"] * len(lead) + units, "fringe_field_3d")
    out.bounds_why = [""] * out.p
    out.replaces, out.var_known = blk.replaces, blk.var_known
    out.model_rows = in_planes
    out.model_dependent = tuple(shape) + tuple(short)
    label = dict(enumerate(PLANE_ORDERS))

    def physical(nm, theta, cov):
        """Per plane g, g', g'' (g = 1 + the fitted g - 1) and the Fermi edges and length fitted
        to the model-independent ones (`_fermi_summary`; to every plane's where fewer than
        three planes are model-independent; ``shape``, the Fermi fit to the readings, where
        fewer than three planes have values). The amplitude of the Fermi tail beyond the
        planes is a nuisance of the fit, not reported."""
        nm = list(nm)
        ones = [k for k, n in enumerate(nm) if n.startswith("g0@")]
        res = dict(shape)
        obs, every = [], []  # (z, order, index) of the model-independent profile values; all
        for k, (name, unit) in enumerate(zip(nm, units_of(nm), strict=True)):
            m, _, z = name.partition("@")
            if not z or not m.startswith("g") or int(m[1:]) not in label:
                continue
            value = float(theta[k]) + (1.0 if m == "g0" else 0.0)
            phys = f"{label[int(m[1:])]}@{z}"
            sd = float(np.sqrt(max(cov[k, k], 0.0) + trunc.get(name, 0.0) ** 2))
            res[phys] = (value, sd, unit)
            every.append((float(z), int(m[1:]), k))
            if phys not in short:
                obs.append(every[-1])
        values = theta + np.isin(np.arange(len(nm)), ones)
        cov_t = cov + np.diag([trunc.get(n, 0.0) ** 2 for n in nm])
        fermi = _fermi_summary(obs, values, cov_t, th) or _fermi_summary(every, values, cov_t, th)
        for name in shape:
            if fermi is not None and name in fermi:
                res[name] = fermi[name]
        return res

    def units_of(nm):
        where = dict(zip(out.names, out.units, strict=True))
        return [where.get(n, "") for n in nm]

    n_lead = len(lead)
    fermi_rows = fringe_derivatives(prob.pos[:, 2], *th, 2 * PLANE_LAYERS + 2)

    def profile(theta):
        """Per row g, g', ... (2 `PLANE_LAYERS` + 3 rows): the fitted values of the planes that
        separate every layer; the Fermi profile elsewhere, with the amplitude fitted to the
        Fermi tail beyond the planes there, within its plausible range [0, 2] (far from the
        ends that tail is g - 1 ~ 0 and its amplitude is not determined: a value of thousands
        would scale the baseline's columns wherever the Fermi shape departs from 1), and with
        the amplitude ``a`` of the whole profile in the planes that keep it (truncated)."""
        amp = float(np.clip(theta[0], 0.0, 2.0)) if n_lead else a
        prof = amp * fermi_rows
        prof[0] += 1.0 - amp
        for rows, first, layers in slots:
            if layers < PLANE_LAYERS:  # a truncated plane keeps the Fermi profile
                prof[:, rows] = a * fermi_rows[:, rows]
                prof[0, rows] += 1.0 - a
                continue
            for m in range(2 * layers):
                prof[m, rows] = theta[n_lead + first + m] + (1.0 if m == 0 else 0.0)
        return prof

    out.physical = physical
    out.profile = profile
    return out


def _edges_of(zi, zo, lam):
    """``physical(names, theta, cov)`` of the soft-end block linearised at the edges ``zi``,
    ``zo`` and length ``lam`` (mm): the amplitude, and each edge and the length moved by its
    fitted increment over the amplitude, with the std of that ratio (delta method)."""
    centre = {"dz_entry": ("z_entry", zi), "dz_exit": ("z_exit", zo), "dlambda": ("lambda", lam)}

    def physical(nm, theta, cov):
        nm = list(nm)
        if "amplitude" not in nm:
            return None
        ia = nm.index("amplitude")
        a = theta[ia]
        out = {"amplitude": (float(a), float(np.sqrt(max(cov[ia, ia], 0.0))), "1")}
        for k, n in enumerate(nm):
            if n not in centre:
                continue
            grad = np.zeros(len(nm))
            grad[k] = 1.0 / a
            grad[ia] = -theta[k] / a**2
            name, c0 = centre[n]
            sd = float(np.sqrt(max(grad @ cov @ grad, 0.0)))
            out[name] = (float(c0 + theta[k] / a), sd, "mm")
        return out

    return physical


def fringe_field_3d(prob):
    from .calibrate import fit_map, stack
    from .problem import noise_sigma

    ctx = prob.ctx
    upts, uinv = ctx.upts, ctx.uinv
    z = upts[:, 2]
    if np.ptp(z) <= 0:
        return "a single z plane: no z-dependence to see"
    G = ctx.G
    dz = np.abs(G[:, :, 2]).max()
    if dz > 1e-3 * max(np.abs(G[:, :, :2]).max(), 1e-300):
        return (
            "the reference field varies along z (a 3-D map): the magnet ends are part of it, "
            "and the effect describes ends missing from a 2-D reference"
        )
    if ctx.V is None or ctx.W3 is None:
        ctx.V, ctx.W3 = _scalar_potential(ctx.field_fn, upts)
    B0u = ctx.field_fn(upts)
    Vu, W3u = ctx.V, ctx.W3

    def delta(th):
        """Change of the reading from the 2-D reference to the field with soft ends (a = 1):
        the gradient of the potential g V - g'' W (grad V = B_perp, lap_perp W = V)."""
        g, dg, d2g, d3g = _fringe_derivatives(z, *th)
        D = (g - 1.0)[:, None] * B0u
        D[:, :2] -= d2g[:, None] * W3u[:, 1:]
        D[:, 2] += dg * Vu - d3g * W3u[:, 0]
        return D

    base = stack(prob.baseline)
    j3 = _baseline_3d(prob, base)
    resid0 = fit_map(prob.y, np.ones_like(prob.y), base).resid  # for the pure error
    sigma = noise_sigma(prob, resid0)[0]
    obj = _Projector(prob, sigma, base, uinv, len(upts))
    zmin, zmax = z.min(), z.max()
    span = zmax - zmin
    zi, zo, lam = _search_edges(obj, delta, zmin, zmax)
    # an end is estimated only inside the z range the data cover: beyond it the data see a
    # tail, and an edge placed there would be an extrapolation, not a finding
    inside = [zmin < zi < zmax, zmin < zo < zmax]
    if not any(inside):  # no end in or near the map: test for a soft end just outside it
        lam = span / 20.0
        zi, zo = zmin - 3 * lam, zmax + 3 * lam
    th = np.array([zi, zo, lam])
    free = [k for k in range(3) if (inside + [True])[k]] if any(inside) else []
    names = ["amplitude"] + [["dz_entry", "dz_exit", "dlambda"][k] for k in free]
    units = ["1"] + ["mm"] * len(free)

    def block(a, th, theta_b):
        """Columns of a X(th) + J3(a, th) theta_b linearised at (a, th, theta_b): amplitude
        (X: the change for a = 1) and edge increments a dth (derivatives of the whole model
        per unit amplitude; J3 is affine in a, its th-dependent part is a J3(1, th)), with J3
        in place of the baseline columns."""
        J3, vk = j3(a, th)

        def per_a(t):
            m = delta(t)[uinv]
            if theta_b is not None:
                m = m + np.einsum("nkp,p->nk", j3(1.0, t)[0], theta_b)
            return m

        cols = [delta(th)[uinv]]
        for k in free:
            e = np.zeros(3)
            e[k] = 1e-3 * th[2]
            cols.append((per_a(th + e) - per_a(th - e)) / (2 * e[k]))
        blk = effect_columns(np.stack(cols, -1), names, units, "fringe_field_3d")
        blk.bounds_why = [""] * len(names)
        for j, k in enumerate(free):
            if k < 2:  # the edge (th + increment / a, a ~ 1) must stay in the data's z range
                blk.bounds[1 + j] = (zmin - th[k], zmax - th[k])
                blk.bounds_why[1 + j] = (
                    f"the magnet end would lie outside the z range the data cover "
                    f"[{zmin:g}, {zmax:g}] mm"
                )
        blk.replaces = {nm: J3[..., i] for i, nm in enumerate(base.names)}
        blk.var_known = vk
        return blk

    # Gauss-Newton on the joint model (baseline with its priors + ends), from a = 1
    a, theta_b = 1.0, None
    blk = block(a, th, theta_b)
    for _ in range(12):
        sigma = noise_sigma(prob, resid0, var_known=blk.var_known)[0]
        f = fit_map(prob.y, sigma, stack([base, blk]))
        a_new, step = f.theta[base.p], f.theta[base.p + 1 :]
        sd = f.std[base.p :]
        theta_b = f.theta[: base.p]
        moved = bool(free) and 0.2 < a_new < 5.0
        if moved:
            new = th.copy()
            new[free] += step / a_new
            moved = new[2] > 0
            if moved:
                th = new
        done = abs(a_new - a) < 1e-3 * sd[0] and (
            not moved or np.all(np.abs(step / a_new) < 1e-3 * sd[1:])
        )
        a = float(np.clip(a_new, 0.0, 2.0))  # the plausible range of the amplitude
        blk = block(a, th, theta_b)
        if done or (free and not moved):
            break
    zi, zo, lam = th
    physical = _edges_of(zi, zo, lam)
    blk.physical = physical
    # where the soft-end model carries the signal: a real end is not exactly this profile
    g = fringe_profile(prob.pos[:, 2], zi, zo, lam)[0]
    blk.model_rows = (g > 1e-3) & (g < 1.0 - 1e-3)
    if not free:
        return blk
    # the Fermi shape's edges and length, their std scaled by its lack of fit at the ends
    sigma = noise_sigma(prob, resid0, var_known=blk.var_known)[0]
    f = fit_map(prob.y, sigma, stack([base, blk]))
    r = f.resid[blk.model_rows] / sigma[blk.model_rows]
    lof = max(1.0, float(np.mean(r[np.isfinite(r)] ** 2))) if r.size else 1.0
    ib = slice(base.p, None)
    shape = physical(blk.names, f.theta[ib], f.cov[ib, ib] * lof)
    shape = {k: v for k, v in shape.items() if k != "amplitude"}
    planes = _plane_block(prob, blk, th, a, inside, shape)
    if planes is None:
        return blk
    # the baseline through the measured profile: the Fermi tails are off by factors at the
    # outer planes, where a transverse offset of the magnet is a dipole term g G dx
    for _ in range(2):
        sigma = noise_sigma(prob, resid0, var_known=planes.var_known)[0]
        f = fit_map(prob.y, sigma, stack([base, planes]))
        J3, planes.var_known = j3(a, th, planes.profile(f.theta[base.p :]))
        planes.replaces = {nm: J3[..., i] for i, nm in enumerate(base.names)}
    return planes
