"""Least-squares fit of local harmonic field models (`cfm_fem.models.harmonic`), one node at a time.

A node's model is B(x) = sum_j coef[j] F_j(u), u = (x - x_node) / scale, with F_j the harmonic
basis fields (`cfm_fem.models.harmonic_basis`, ordered by degree), fitted to the three field
components at the node's k nearest nodes. The normal matrix of degree L is the leading block of
that of the highest degree, and so is its Cholesky factor: one factorisation gives the fit of
every degree, and one triangular solve of the design rows gives every degree's hat matrix
(leave-one-node-out residuals). Columns are scaled to unit norm before the factorisation, so
its pivots measure how well each basis field is determined by the neighbourhood.
"""

from __future__ import annotations

import numba as nb
import numpy as np

from .harmonic import sparse_basis
from .options import JIT, RJIT

#: A Cholesky pivot of the column-scaled normal matrix (unit diagonal) below this means the
#: neighbourhood cannot tell the basis field from the lower ones: that degree and higher are
#: not fitted.
FIT_PIVOT_MIN = 1e-10

#: A degree needs at least this many equations (3 per neighbour) per unknown.
FIT_EQ_PER_UNKNOWN = 2.0

#: Leave-one-node-out needs I - H_node invertible; below this determinant the node decides
#: its own fit alone and the degree is not eligible.
FIT_LEVERAGE_DET_MIN = 1e-12

#: Degree of the Laplace check: the harmonic fit against an unconstrained polynomial fit.
FIT_CHECK_DEGREE = 2

#: Columns of the ``checks`` output of `harmonic_fit_block`.
CHECK_SPREAD, CHECK_LEVEL, CHECK_HARMONIC, CHECK_FREE = 0, 1, 2, 3

#: Weight of a neighbour at scaled distance |u| <= 1: (1 - FIT_TAPER |u|^2)^4, from 1 at the
#: node to 1e-4 at the k-th neighbour. A local model serves points near its node: tapered
#: weights let the far neighbours steady the fit without bending it near the node.
FIT_TAPER = 0.9

#: Flag bits of `harmonic_fit_block`.
FIT_CAPPED_EQUATIONS = 1  # the highest degree was lowered for want of equations
FIT_CAPPED_PIVOT = 2  # the highest degree was lowered by a small pivot
FIT_FAILED = 4  # no degree >= the lowest asked for could be fitted: coefficients are 0


@nb.njit(inline="always", **JIT)
def _n_basis(degree):
    return (degree + 1) * (degree + 3)


@nb.njit(**RJIT)
def _cholesky(a, n):
    """Lower Cholesky factor, in place, of the symmetric matrix in the lower triangle of
    ``a[:n, :n]``, column by column up to the first pivot <= `FIT_PIVOT_MIN`.

    Returns the number of columns factorised: the leading block of that size is the factor
    of the matrix's leading block. Its dot products are summed in the order the compiled
    (vectorised) loop fixes.
    """
    for j in range(n):
        for col in range(j + 1):
            s = a[j, col]
            for q in range(col):
                s -= a[j, q] * a[col, q]
            if col < j:
                a[j, col] = s / a[col, col]
            elif s > FIT_PIVOT_MIN:
                a[j, j] = np.sqrt(s)
            else:
                return j
    return n


@nb.njit(**JIT)
def harmonic_fit_block(centers, scale, nbr, points, B, gmat, exps, lmin, lmax):
    """Fit the harmonic field model of each node of a block to its neighbours' field values.

    Per node: the weighted design of the highest degree (weights `FIT_TAPER`), scaled
    columns, one Cholesky factorisation; the degree is the one of lowest weighted
    leave-one-node-out residual (PRESS) among ``lmin`` .. the highest the neighbourhood
    supports (`FIT_EQ_PER_UNKNOWN`, `FIT_PIVOT_MIN`).

    Parameters
    ----------
    centers : ndarray, shape (n, 3), mm
        The nodes whose models are fitted.
    scale : ndarray, shape (n,), mm
        Length scale of each node: u = (x - centers[g]) / scale[g]; > 0.
    nbr : ndarray, shape (n, k), int64
        Indices into ``points`` of each node's neighbours (the node itself included), in an
        order that does not depend on the map's row order.
    points : ndarray, shape (N, 3), mm
    B : ndarray, shape (N, 3), T
    gmat : ndarray, shape (3, M, NB)
        `field_basis` of degree ``lmax``.
    exps : ndarray, shape (M, 3), int64
        `monomial_exponents` of degree ``lmax``.
    lmin, lmax : int
        Degrees allowed, 0 <= lmin <= lmax <= 5.

    Returns
    -------
    coef : ndarray, shape (n, NB), T
        Coefficients of the basis fields; zero past the node's degree.
    degree : ndarray, shape (n,), int64
    resid : ndarray, shape (n,), T
        RMS residual of the fit over the neighbours' 3 k components, weighted by the fit's
        weights (normalised to sum 1).
    flag : ndarray, shape (n,), int64
        Bits `FIT_CAPPED_EQUATIONS`, `FIT_CAPPED_PIVOT`, `FIT_FAILED`.
    checks : ndarray, shape (n, 4), T
        RMS over the same components of: B minus its mean over the neighbourhood
        (`CHECK_SPREAD`); B (`CHECK_LEVEL`); the residual of the harmonic fit of degree
        `FIT_CHECK_DEGREE` (`CHECK_HARMONIC`) and of the unconstrained polynomial fit of that
        degree, each component apart (`CHECK_FREE`), both weighted as ``resid``; NaN where a
        fit is not determined.
    """
    n, k = nbr.shape
    nbf = _n_basis(lmax)
    rows = 3 * k
    basis = sparse_basis(gmat)
    # np.empty only, filled here: numba compiles np.zeros and np.full (and np.empty for
    # each dtype argument they pass it) apart, about 0.1 s of CPU time each
    coef = np.empty((n, nbf))
    degree = np.empty(n, dtype=np.int64)
    resid = np.empty(n)
    flag = np.empty(n, dtype=np.int64)
    checks = np.empty((n, 4))
    for g in range(n):
        for j in range(nbf):
            coef[g, j] = 0.0
        degree[g] = lmin
        resid[g] = np.nan
        flag[g] = 0
        for j in range(4):
            checks[g, j] = np.nan
    n_free = (FIT_CHECK_DEGREE + 1) * (FIT_CHECK_DEGREE + 2) * (FIT_CHECK_DEGREE + 3) // 6
    free_at = np.empty((n_free, k))  # weighted monomials of the unconstrained fit
    free_work = np.empty((n_free, n_free + 2))
    arow = np.empty((rows, nbf))  # weighted design: (neighbour, component) x basis field
    at = np.empty((nbf, rows))  # the same, transposed, columns scaled
    zt = np.empty((nbf, rows))  # L^-1 at: leverages of every degree
    b = np.empty(rows)  # weighted field values
    braw = np.empty(rows)
    colnorm = np.empty(nbf)
    chol = np.empty((nbf, nbf))
    y = np.empty(nbf)
    cs = np.empty(nbf)
    best = np.empty(nbf)
    e = np.empty(rows)
    hat = np.empty((k, 6))  # running leverage blocks of each neighbour: xx yy zz xy xz yz

    # highest degree the equations support
    lcap = lmax
    while lcap >= 0 and rows < FIT_EQ_PER_UNKNOWN * _n_basis(lcap):
        lcap -= 1

    for g in range(n):
        sumw = _node_rows(g, centers, scale, nbr, points, B, exps, basis, arow, b, braw, free_at)
        norm_w = np.sqrt(3.0 * sumw)  # weighted RMS = residual norm / norm_w
        checks[g, CHECK_SPREAD], checks[g, CHECK_LEVEL] = _spread_level(braw, k)
        checks[g, CHECK_FREE] = _free_fit_rms(free_at, b, free_work) / norm_w
        n_ok = _factor(arow, at, colnorm, cs, chol)
        lhi = lcap
        while lhi >= 0 and _n_basis(lhi) > n_ok:
            lhi -= 1
        if lcap < lmax:
            flag[g] |= FIT_CAPPED_EQUATIONS
        if lhi < lcap:
            flag[g] |= FIT_CAPPED_PIVOT
        if lhi < lmin:
            flag[g] |= FIT_FAILED
            continue
        _forward(at, b, chol, _n_basis(lhi), y, zt)
        hat[:, :] = 0.0
        best_press = np.inf
        best_rss = np.nan
        j0 = np.int64(0)  # not a literal: one compiled `_add_leverages`
        for lev in range(min(lmin, FIT_CHECK_DEGREE), lhi + 1):
            nb_l = _n_basis(lev)
            _add_leverages(zt, j0, nb_l, hat)
            j0 = nb_l
            rss = _fit_degree(y, chol, nb_l, at, b, cs, e)
            if lev == FIT_CHECK_DEGREE:
                checks[g, CHECK_HARMONIC] = np.sqrt(rss) / norm_w
            if lev < lmin:
                continue
            press = _press(e, hat)
            if press < best_press or lev == lmin:
                best_press = press
                best_rss = rss
                degree[g] = lev
                for j in range(nb_l):
                    best[j] = cs[j]
        for j in range(_n_basis(degree[g])):
            coef[g, j] = best[j] / colnorm[j]
        resid[g] = np.sqrt(best_rss) / norm_w
    return coef, degree, resid, flag, checks


@nb.njit(**JIT)
def _node_rows(g, centers, scale, nbr, points, B, exps, basis, arow, b, braw, free_at):
    """Weighted design rows and field values of node g's neighbourhood, in place: ``arow``
    (3 k, NB), ``b`` and ``braw`` (3 k,) weighted and not, ``free_at`` (P, k) the weighted
    monomials of the unconstrained fit. Returns the sum of the weights."""
    start, mono_of, val = basis
    k = nbr.shape[1]
    n_mono = exps.shape[0]
    nbf = arow.shape[1]
    mono = np.empty(n_mono)
    pw = np.empty((3, 6))
    inv = 1.0 / scale[g]
    sumw = 0.0
    for i in range(k):
        p = nbr[g, i]
        u2 = 0.0
        for a in range(3):
            pw[a, 0] = 1.0
            ua = (points[p, a] - centers[g, a]) * inv
            u2 += ua * ua
            for q in range(1, 6):
                pw[a, q] = pw[a, q - 1] * ua
        t = 1.0 - FIT_TAPER * u2
        sw = t * t  # square root of the weight
        sumw += sw * sw
        for a in range(3):
            braw[3 * i + a] = B[p, a]
            b[3 * i + a] = sw * B[p, a]
        for m in range(n_mono):
            mono[m] = sw * pw[0, exps[m, 0]] * pw[1, exps[m, 1]] * pw[2, exps[m, 2]]
        for m in range(free_at.shape[0]):
            free_at[m, i] = mono[m]
        for c in range(3):
            for j in range(nbf):
                s = 0.0
                for q in range(start[c, j], start[c, j + 1]):
                    s += val[q] * mono[mono_of[q]]
                arow[3 * i + c, j] = s
    return sumw


@nb.njit(**JIT)
def _spread_level(braw, k):
    """RMS over the 3 k components ``braw`` of B minus its mean over the k nodes, and of B."""
    mean = np.empty(3)
    for a in range(3):
        mean[a] = 0.0
    for i in range(k):
        for a in range(3):
            mean[a] += braw[3 * i + a]
    ss = 0.0
    s2 = 0.0
    for i in range(k):
        for a in range(3):
            d = braw[3 * i + a] - mean[a] / k
            ss += d * d
            s2 += braw[3 * i + a] * braw[3 * i + a]
    return np.sqrt(ss / (3 * k)), np.sqrt(s2 / (3 * k))


@nb.njit(**JIT)
def _factor(arow, at, colnorm, cs, chol):
    """Scale the columns of ``arow`` to unit norm (norms to ``colnorm``, ``at`` its
    transpose), form the normal matrix (`_gram`) and factorise it in ``chol``. Returns the
    number of columns factorised (`_cholesky`)."""
    rows, nbf = arow.shape
    for j in range(nbf):
        colnorm[j] = 0.0
    for r in range(rows):
        for j in range(nbf):
            colnorm[j] += arow[r, j] * arow[r, j]
    for j in range(nbf):
        colnorm[j] = np.sqrt(colnorm[j])
        cs[j] = 1.0 / colnorm[j] if colnorm[j] > 0.0 else 0.0
    for r in range(rows):
        for j in range(nbf):
            arow[r, j] *= cs[j]
            at[j, r] = arow[r, j]
    _gram(at, chol)
    return _cholesky(chol, nbf)


@nb.njit(**RJIT)
def _gram(at, chol):
    """Lower triangle of at @ at.T into ``chol`` (upper left zero): dot products of the
    contiguous rows of ``at``, four columns of a row at a time (each row read once per four),
    summed in the order the compiled (vectorised) loop fixes."""
    nbf, rows = at.shape
    for j in range(nbf):
        col = 0
        while col + 3 <= j:
            s0 = s1 = s2 = s3 = 0.0
            for r in range(rows):
                a = at[j, r]
                s0 += a * at[col, r]
                s1 += a * at[col + 1, r]
                s2 += a * at[col + 2, r]
                s3 += a * at[col + 3, r]
            chol[j, col] = s0
            chol[j, col + 1] = s1
            chol[j, col + 2] = s2
            chol[j, col + 3] = s3
            col += 4
        while col <= j:
            s0 = 0.0
            for r in range(rows):
                s0 += at[j, r] * at[col, r]
            chol[j, col] = s0
            col += 1
        for col in range(j + 1, nbf):
            chol[j, col] = 0.0


@nb.njit(**RJIT)
def _forward(at, b, chol, nhi, y, zt):
    """y = L^-1 A^T b and Z = L^-1 A^T over the first ``nhi`` fields (each row of Z from
    the rows above it, four at a time, into a row of work space)."""
    rows = at.shape[1]
    for j in range(nhi):
        s = 0.0
        for r in range(rows):
            s += at[j, r] * b[r]
        for q in range(j):
            s -= chol[j, q] * y[q]
        y[j] = s / chol[j, j]
    t = np.empty(rows)
    for j in range(nhi):
        for r in range(rows):
            t[r] = at[j, r]
        q = 0
        while q + 3 < j:
            f0, f1, f2, f3 = chol[j, q], chol[j, q + 1], chol[j, q + 2], chol[j, q + 3]
            z0, z1, z2, z3 = zt[q], zt[q + 1], zt[q + 2], zt[q + 3]
            for r in range(rows):
                t[r] -= (f0 * z0[r] + f1 * z1[r]) + (f2 * z2[r] + f3 * z3[r])
            q += 4
        while q < j:
            f = chol[j, q]
            z0 = zt[q]
            for r in range(rows):
                t[r] -= f * z0[r]
            q += 1
        f = 1.0 / chol[j, j]
        for r in range(rows):
            zt[j, r] = t[r] * f


@nb.njit(**JIT)
def _add_leverages(zt, j0, j1, hat):
    """Add fields j0 .. j1 - 1 to the 3 x 3 hat-matrix blocks of the neighbours."""
    for i in range(hat.shape[0]):
        r0 = 3 * i
        for j in range(j0, j1):
            zx, zy, zz = zt[j, r0], zt[j, r0 + 1], zt[j, r0 + 2]
            hat[i, 0] += zx * zx
            hat[i, 1] += zy * zy
            hat[i, 2] += zz * zz
            hat[i, 3] += zx * zy
            hat[i, 4] += zx * zz
            hat[i, 5] += zy * zz


@nb.njit(**JIT)
def _fit_degree(y, chol, nb_l, at, b, cs, e):
    """Coefficients of the first ``nb_l`` scaled fields (L^T cs = y, leading block), the
    residuals ``e`` = A cs - b; returns their sum of squares."""
    rows = at.shape[1]
    for j in range(nb_l - 1, -1, -1):
        s = y[j]
        for q in range(j + 1, nb_l):
            s -= chol[q, j] * cs[q]
        cs[j] = s / chol[j, j]
    for r in range(rows):
        e[r] = -b[r]
    for j in range(nb_l):
        f = cs[j]
        for r in range(rows):
            e[r] += f * at[j, r]
    rss = 0.0
    for r in range(rows):
        rss += e[r] * e[r]
    return rss


@nb.njit(**JIT)
def _press(e, hat):
    """Sum of squares of the leave-one-node-out residuals (I - H_i)^-1 e_i; inf if a block
    I - H_i is near singular (`FIT_LEVERAGE_DET_MIN`)."""
    press = 0.0
    for i in range(hat.shape[0]):
        r0 = 3 * i
        ex, ey, ez = e[r0], e[r0 + 1], e[r0 + 2]
        # by the adjugate of the symmetric 3 x 3 block
        a00, a11, a22 = 1.0 - hat[i, 0], 1.0 - hat[i, 1], 1.0 - hat[i, 2]
        a01, a02, a12 = -hat[i, 3], -hat[i, 4], -hat[i, 5]
        c00 = a11 * a22 - a12 * a12
        c01 = a02 * a12 - a01 * a22
        c02 = a01 * a12 - a02 * a11
        c11 = a00 * a22 - a02 * a02
        c12 = a01 * a02 - a00 * a12
        c22 = a00 * a11 - a01 * a01
        det = a00 * c00 + a01 * c01 + a02 * c02
        if det < FIT_LEVERAGE_DET_MIN:
            return np.inf
        qx = (c00 * ex + c01 * ey + c02 * ez) / det
        qy = (c01 * ex + c11 * ey + c12 * ez) / det
        qz = (c02 * ex + c12 * ey + c22 * ez) / det
        press += qx * qx + qy * qy + qz * qz
    return press


@nb.njit(**JIT)
def _free_fit_rms(ft, b, work):
    """Residual norm of the least-squares polynomial fit of each field component apart.

    ``ft`` (P, k): the P monomials at the k neighbours; ``b`` (3 k,): their field values;
    ``work``: (P, P + 2) scratch. Normal equations with scaled columns; NaN if a pivot
    is below `FIT_PIVOT_MIN`.
    """
    npar, k = ft.shape
    norm = np.empty(npar)
    for j in range(npar):
        s = 0.0
        for i in range(k):
            s += ft[j, i] * ft[j, i]
        norm[j] = np.sqrt(s) if s > 0.0 else 1.0
    for j in range(npar):  # scaled Gram matrix in work[:, :npar], then its Cholesky factor
        for col in range(j + 1):
            s = 0.0
            for i in range(k):
                s += ft[j, i] * ft[col, i]
            work[j, col] = s / (norm[j] * norm[col])
    if _cholesky(work, npar) < npar:
        return np.nan
    rss = 0.0
    for c in range(3):
        for j in range(npar):  # forward: w = L^-1 (scaled A^T b_c)
            s = 0.0
            for i in range(k):
                s += ft[j, i] * b[3 * i + c]
            s /= norm[j]
            for q in range(j):
                s -= work[j, q] * work[q, npar]
            work[j, npar] = s / work[j, j]
        for j in range(npar - 1, -1, -1):  # back: L^T x = w
            s = work[j, npar]
            for q in range(j + 1, npar):
                s -= work[q, j] * work[q, npar + 1]
            work[j, npar + 1] = s / work[j, j]
        for i in range(k):
            s = -b[3 * i + c]
            for j in range(npar):
                s += work[j, npar + 1] / norm[j] * ft[j, i]
            rss += s * s
    return np.sqrt(rss)


@nb.njit(**JIT)
def canonical_neighbours(points, centres, cand):
    """Candidates of each centre sorted by (squared distance, x, y, z): an order that does
    not depend on the map's row order (the twin: `cfm_fem.models.harmonic._canonical`).

    Parameters
    ----------
    points : ndarray, shape (N, 3), mm
    centres : ndarray, shape (m, 3), mm
    cand : ndarray, shape (m, c), int64
        Indices into ``points``: each centre's candidate neighbours.

    Returns
    -------
    nbr : ndarray, shape (m, c), int64
        ``cand`` of each row in that order.
    d2 : ndarray, shape (m, c), mm^2
        Their squared distances, (dx^2 + dy^2) + dz^2 as numpy sums them.
    """
    m, c = cand.shape
    nbr = np.empty((m, c), dtype=np.int64)
    d2 = np.empty((m, c))
    for i in range(m):
        for j in range(c):
            g = cand[i, j]
            dx = points[g, 0] - centres[i, 0]
            dy = points[g, 1] - centres[i, 1]
            dz = points[g, 2] - centres[i, 2]
            d = dx * dx + dy * dy + dz * dz
            # insertion: shift the larger keys up (c is some 50: no faster sort needed)
            t = j
            while t > 0 and _after(points, nbr[i, t - 1], d2[i, t - 1], g, d):
                nbr[i, t] = nbr[i, t - 1]
                d2[i, t] = d2[i, t - 1]
                t -= 1
            nbr[i, t] = g
            d2[i, t] = d
    return nbr, d2


@nb.njit(inline="always", **JIT)
def _after(points, a, da, b, db):
    """Whether node ``a`` (squared distance ``da``) sorts after node ``b`` (``db``)."""
    if da != db:
        return da > db
    for k in range(3):
        if points[a, k] != points[b, k]:
            return points[a, k] > points[b, k]
    return False
