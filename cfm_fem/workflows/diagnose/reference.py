"""A reference field map read between its nodes, with an estimate of its own error there.

A diagnosis compares readings with a reference map at the readings' points, which rarely are the
map's nodes. Read linearly between nodes, a coarse map errs by the field's curvature times the
cell size squared, one sign across a whole plane: an error far above a Hall probe's noise that a
fit then takes for a probe or magnet effect. :class:`NodeExactHarmonic` reads the map as the
per-node harmonic fits of :func:`cfm_fem.models.harmonic.fit_harmonic` (a Maxwell-consistent
polynomial around each node, fitted to its nearest nodes), corrected so that it reproduces the
map exactly at every node: the harmonic fits' own residuals at the nodes are interpolated
linearly and added. Where a node's fit fails Laplace's curl test (currents or iron in its
neighbourhood) or a point lies beyond every usable fit's reach, :class:`CurvatureCorrected`
serves: the linear interpolant corrected by the field's second and third derivatives from
differences of the node values, with no field equation assumed. A fit that passes the curl
test but follows its neighbours less closely than the misfit bound of
:data:`cfm_fem.models.harmonic.FALLBACK_RULE` still serves here (``misfit_rel=inf``): such a
field (a coil's conductors near the map) is read worse by the curvature-corrected
interpolant, whose differences span whole cells. On the coarse map of a coil dipole (11 mm
bore radius, nodes 1.47 mm apart across and 2.76 mm along the bore; 2,062 of its 6,561
nodes past the misfit bound, none failing the curl test), within 0.3 mm of one scan point
the curvature-corrected reading erred by 360-840 uT in B_y and the nearest misfitting
node's fit by at most 42 uT, and the diagnosis took the jump between the two readings for a
bad reading.

The model's error between nodes is estimated from the model itself, locally
(:meth:`error_var`): at a point, the fits of its :data:`SPREAD_NODES` nearest usable nodes (the
corners of the cell around it, on both sides along every axis, however unequal the steps) all
describe the field there; their largest departure from the nearest node's fit, per
component, is the size of the truncation error of the local polynomials across that cell. It
vanishes at a node (the model is exact there) and grows as the squared distance to the nearest
node over the median distance to the cell's nodes, to its full size at the cell's centre. In
the map's outermost layer of cells every node's fit is one-sided and the fits err alike (a
reading there erred by up to twelve times the corners' spread on the family's magnets), so
the fits of the :data:`SPREAD_WIDE` nearest nodes (the next layer inward too) are compared.
Where
no fit holds, :class:`CurvatureCorrected` serves; its error is estimated from the map's fourth
differences (:meth:`CurvatureCorrected.error_var`), and no smaller than its departure from the
nearest usable node's fit (two readings of one field: their difference bounds the worse one's
error), scaled the same way. The fits can also agree with one another and all miss the map (a
coil's end); :meth:`NodeExactHarmonic.error_bound` adds the node-exact correction's size, a
bound per point for naming points and planes that depart from the reference.
"""

from __future__ import annotations

import numpy as np

from ...errors import CfmInputError
from ...io.fit_cache import cached_fit
from ...models.harmonic import neighbourhoods
from ...models.harmonic_basis import MAX_DEGREE, field_basis, monomial_exponents

__all__ = [
    "NodeExactHarmonic",
    "CurvatureCorrected",
    "node_spacing_mm",
    "shared_readings",
    "smooth_error_basis",
    "SMOOTH_DEGREE",
    "SPREAD_NODES",
]

#: Nearest usable nodes whose fits are compared at a point to estimate the model's error (the
#: eight corners of a grid's cell).
SPREAD_NODES = 8
#: Nearest usable nodes compared at a point in the map's outermost layer of cells: the cell's
#: corners and the next layer inward (every fit near a border is one-sided and they err alike,
#: so the corners' fits alone understate their common error there).
SPREAD_WIDE = 18


def node_spacing_mm(points) -> float:
    """Typical node spacing of a map (median distance to the nearest other node), mm."""
    from scipy.spatial import cKDTree

    d, _ = cKDTree(points).query(points, k=2)
    d = d[:, 1]
    return float(np.median(d[d > 0])) if np.any(d > 0) else 0.0


def shared_readings(points, counts, nodes) -> np.ndarray:
    """Readings that share the reference's error with each point: those in its cell (m,).

    A reference's error between its nodes is one smooth function across a cell: every reading
    of a point (its repetitions) carries the same error, and so, nearly, does every reading of
    the points in the same cell. A fit that takes those errors as independent averages them
    down by their number; weighting each reading's share of the error by that number leaves a
    cell's readings, together, the weight of one draw of the error.

    Parameters
    ----------
    points : ndarray, shape (m, 3), mm
        Distinct points read.
    counts : ndarray, shape (m,)
        Readings of each point.
    nodes : ndarray, shape (k, 3), mm
        The reference's nodes: its cells are the boxes between consecutive node coordinates
        along each axis (:func:`axis_steps` apart, from the nodes' lowest corner).

    Returns
    -------
    ndarray, shape (m,)
        Readings in each point's cell (its own included), >= its own count.
    """
    p = np.asarray(points, dtype=float).reshape(-1, 3)
    nodes = np.asarray(nodes, dtype=float).reshape(-1, 3)
    steps = axis_steps(nodes, node_spacing_mm(nodes))
    steps = np.where(steps > 0, steps, 1.0)
    cell = np.floor((p - nodes.min(0)) / steps + 1e-9).astype(np.int64)
    _, inv = np.unique(cell, axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    return np.bincount(inv, weights=np.asarray(counts, dtype=float))[inv]


#: Total degree of the polynomials across the scanned volume that carry the smooth part of a
#: reference's error (:func:`smooth_error_basis`).
SMOOTH_DEGREE = 2


def smooth_error_basis(points, std, degree: int = SMOOTH_DEGREE):
    """The smooth part of a reference's error across the scan, as columns with unit priors.

    A reference read between its nodes errs by the field's higher derivatives times a function
    of the position in the cell: the derivatives change over the magnet's own scale, so the
    error keeps its sign over many cells, along a whole scan line (a quadrupole's B_z error
    odd in z over its body, a curvature of one sign along a line). Independent per cell, it
    would average down over the scan, and an effect of the same smooth shape (a volume
    average, a planar Hall term, a tilt) would be claimed from it. Here the error at a point is
    ``std(p) sum_j a_j P_j(u)``, with P_j the products of Legendre polynomials of the points'
    coordinates scaled to [-1, 1] over the scan, of total degree <= ``degree``, per component,
    and a_j ~ N(0, s^2) with s^2 the reciprocal of the mean of sum_j P_j^2 over the points:
    the term's variance std^2 s^2 sum_j P_j^2, averaged over the points, is the stated one
    (exactly where the stated error is the same everywhere).

    Parameters
    ----------
    points : ndarray, shape (m, 3), mm
        Distinct points read.
    std : ndarray, shape (m, 3), field units
        Stated standard deviation of the reference's error at each point, per component.
    degree : int

    Returns
    -------
    J : ndarray, shape (m, 3, 3 k), field units per unit coefficient
        Columns: the k polynomials for B_x, then for B_y, then for B_z; a component whose
        stated error is zero everywhere keeps zero columns.
    names : list of str, length 3 k
        ``ref_<component>_<i><j><l>`` (the degrees along x, y, z).
    prior_std : ndarray, shape (3 k,)
    """
    from numpy.polynomial import legendre

    p = np.asarray(points, dtype=float).reshape(-1, 3)
    std = np.asarray(std, dtype=float).reshape(-1, 3)
    lo, hi = p.min(0), p.max(0)
    half = 0.5 * (hi - lo)
    u = np.divide(p - 0.5 * (hi + lo), half, out=np.zeros_like(p), where=half > 0)
    spans = half > 0
    exps = [(i, j, k) for i in range(degree + 1) for j in range(degree + 1 - i)
            for k in range(degree + 1 - i - j)
            if (i == 0 or spans[0]) and (j == 0 or spans[1]) and (k == 0 or spans[2])]  # fmt: skip
    leg = [[legendre.legval(u[:, a], np.eye(degree + 1)[d]) for d in range(degree + 1)]
           for a in range(3)]  # fmt: skip
    basis = np.stack([leg[0][i] * leg[1][j] * leg[2][k] for i, j, k in exps], axis=1)
    s = 1.0 / np.sqrt(np.mean(np.sum(basis**2, axis=1)))
    k = basis.shape[1]
    J = np.zeros((len(p), 3, 3 * k))
    for c in range(3):
        J[:, c, c * k : (c + 1) * k] = std[:, c, None] * basis
    names = [f"ref_{'xyz'[c]}_{i}{j}{l}" for c in range(3) for i, j, l in exps]
    return J, names, np.full(3 * k, s)


class NodeExactHarmonic:
    """A map's field between its nodes: harmonic fits per node, exact at the nodes.

    Parameters
    ----------
    fm : FieldMap
        A 3-D map (its nodes not in one plane, at least
        :data:`cfm_fem.models.harmonic.MIN_NODES` of them).
    linear : LinearInterpolator
        The map's linear interpolant: the fallback, and the correction's interpolant.

    Raises
    ------
    CfmInputError
        The map is planar or too small for the harmonic model (the caller falls back to the
        linear interpolant).

    Attributes
    ----------
    fit : HarmonicFit
    spacing_mm : float
        Typical node spacing.
    n_fallback : int
        Nodes whose harmonic fit fails Laplace's test.
    """

    def __init__(self, fm, linear):
        from dataclasses import replace

        from scipy.spatial import cKDTree

        self.fit, _ = cached_fit(
            fm.points, fm.B, source=fm.source, metric="grid", misfit_rel=np.inf
        )
        self.linear = linear
        self.spacing_mm = node_spacing_mm(fm.points)
        self.n_fallback = int((~self.fit.use).sum())
        h, ok = self.fit.field_at(fm.points)
        resid = np.where(ok[:, None], fm.B - h, 0.0)
        self._resid = type(linear)(replace(fm, B=resid))
        self._gmat = field_basis(MAX_DEGREE)
        self._exps = monomial_exponents(MAX_DEGREE)
        self._fm, self._curved, self._border = fm, None, None
        self._node_tree = cKDTree(fm.points)

    @property
    def curved(self) -> CurvatureCorrected:
        """The map read by :class:`CurvatureCorrected` where no fit holds (built when first
        needed)."""
        if self._curved is None:
            self._curved = CurvatureCorrected(self._fm, self.linear)
        return self._curved

    def field_at(self, points) -> tuple[np.ndarray, np.ndarray]:
        """B (m, 3) T at ``points`` (m, 3) mm and ``inside`` (m,) bool (the map's cells hold
        the point). Outside the cells (a finite difference or a moved magnet at the map's
        border) the nearest usable node's fit serves, uncorrected, so the field has no hole
        there; NaN only on a map with no usable fit."""
        p = np.asarray(points, dtype=float).reshape(-1, 3)
        b_lin, inside = self.linear.field_at(p)
        h, ok = self.fit.field_at(p)
        corr, _ = self._resid.field_at(p)
        out = b_lin.copy()
        if (~ok).any():
            out[~ok] = self.curved(p[~ok])
        out[ok] = h[ok] + np.where(np.isfinite(corr[ok]), corr[ok], 0.0)
        far = ~np.isfinite(out).all(1)
        idx, used, tree = self.fit._used
        if far.any() and idx.size:  # beyond the cells and every reach: the nearest fit's
            near, _ = neighbourhoods(tree, used, p[far] * self.fit.metric, 1)
            out[far] = self._eval_node(idx[near[:, 0]], p[far])
        return out, inside

    def __call__(self, points) -> np.ndarray:
        return self.field_at(points)[0]

    def _eval_node(self, g, p) -> np.ndarray:
        """Field of node ``g``'s own fit (g (m,) node indices) at points ``p`` (m, 3)."""
        from ... import _kernels

        fit = self.fit
        u = (p - fit.centers[g]) / fit.scale[g, None]
        cexp = np.einsum("cmj,nj->ncm", self._gmat, fit.coef[g])
        val = np.empty((len(p), 3))
        _kernels.poly_points(cexp, np.arange(len(p), dtype=np.int64), self._exps,
                             np.ascontiguousarray(u), val)  # fmt: skip
        return val

    def error_var(self, points) -> np.ndarray:
        """Variance (m, 3) T^2 of the model's own error at ``points`` (m, 3) mm (module
        docstring): per component, the largest squared departure of the fits of the
        :data:`SPREAD_NODES` (in the map's outermost cells :data:`SPREAD_WIDE`) nearest
        usable nodes from the nearest one's, times
        (d_1 / d_med)^2 up to 1, d_1 the distance to the nearest of those nodes and d_med the
        median distance to them. Where no fit holds, :meth:`CurvatureCorrected.error_var`, or
        the squared largest departure of the curvature-corrected reading from the nearest
        usable node's fit, times the same factor over the map's nodes, if larger."""
        p = np.asarray(points, dtype=float).reshape(-1, 3)
        idx, used, tree = self.fit._used
        var = np.zeros((len(p), 3))
        _, ok = self.fit.field_at(p)
        k = min(SPREAD_NODES, idx.size)
        kw = min(SPREAD_WIDE, idx.size)
        if k >= 2 and ok.any():
            q = p[ok]
            qm = q * self.fit.metric
            near, _ = neighbourhoods(tree, used, qm, kw)
            b1 = self._eval_node(idx[near[:, 0]], q)
            dev = np.zeros((len(q), 3))
            edge = self._in_border_cell(q)
            for j in range(1, kw):
                dj = np.abs(self._eval_node(idx[near[:, j]], q) - b1)
                dev = np.maximum(dev, dj if j < k else np.where(edge[:, None], dj, 0.0))
            near = near[:, :k]
            dist = np.linalg.norm(used[near] - qm[:, None, :], axis=2)
            med = np.median(dist, axis=1)
            frac = np.divide(dist[:, 0], med, out=np.zeros(len(q)), where=med > 0)
            var[ok] = (dev * np.clip(frac, 0.0, 1.0)[:, None]) ** 2
        if (~ok).any() and idx.size:
            q = p[~ok]
            near, _ = neighbourhoods(tree, used, q * self.fit.metric, 1)
            cross = np.abs(self._eval_node(idx[near[:, 0]], q) - self.curved(q)).max(1)
            d_node, _ = self._node_tree.query(q, k=min(SPREAD_NODES, len(self._fm.points)))
            d_node = d_node.reshape(len(q), -1)
            med = np.median(d_node, axis=1)
            frac = np.clip(np.divide(d_node[:, 0], med, out=np.zeros(len(q)), where=med > 0), 0, 1)
            var[~ok] = np.maximum(self.curved.error_var(q), ((cross * frac) ** 2)[:, None])
        elif (~ok).any():
            var[~ok] = self.curved.error_var(p[~ok])
        return var

    def error_bound(self, points) -> np.ndarray:
        """A bound (m, 3) T^2 on the model's error at ``points`` (m, 3) mm, per point, for
        naming a point or plane that departs from it: :meth:`error_var` plus the square of the
        node-exact correction's largest component there times d_1 / d_med up to 1.

        The fits of neighbouring nodes can agree with one another and all miss the map (a
        coil's end: on a coarse map of a coil quadrupole, a reading just past the end erred by
        270 uT in B_z where their spread stated 11 uT); the correction, their misfit to the
        nodes around the point interpolated, measures that. One potential misfits in every
        component, so its largest component bounds each; an interpolated misfit that varies
        from node to node errs between the nodes by about its own size, hence the linear
        growth from zero at a node. The bound is not the error's variance: it lies above it
        in most components (the noise carries :meth:`error_var` at the share the readings
        show)."""
        p = np.asarray(points, dtype=float).reshape(-1, 3)
        var = self.error_var(p)
        idx, used, tree = self.fit._used
        _, ok = self.fit.field_at(p)
        k = min(SPREAD_NODES, idx.size)
        if k >= 2 and ok.any():
            qm = p[ok] * self.fit.metric
            near, _ = neighbourhoods(tree, used, qm, k)
            dist = np.linalg.norm(used[near] - qm[:, None, :], axis=2)
            med = np.median(dist, axis=1)
            frac = np.clip(np.divide(dist[:, 0], med, out=np.zeros(len(qm)), where=med > 0), 0, 1)
            miss = np.abs(np.nan_to_num(self._resid.field_at(p[ok])[0])).max(1)
            var[ok] += (miss**2 * frac)[:, None]
        return var

    def _in_border_cell(self, points) -> np.ndarray:
        """Whether each point (m, 3) mm lies in the map's outermost layer of cells (within a
        node step of its bounding box along some axis), where every node's fit is one-sided."""
        if self._border is None:
            nodes = self._fm.points
            self._border = (nodes.min(0), nodes.max(0), axis_steps(nodes, self.spacing_mm))
        lo, hi, steps = self._border
        span = hi - lo > 0
        near = np.minimum(points - lo, hi - points) < steps * (1.0 - 1e-9)
        return (near & span).any(1)

    def linear_fn(self, points) -> np.ndarray:
        """The linear interpolant's field (NaN outside)."""
        return self.linear.field_at(points)[0]


#: Pairs (j, k) of the second moments and second derivatives, in storage order.
PAIRS = ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))
#: Triples (j, k, l) of the third moments and third derivatives, in storage order.
TRIPLES = ((0, 0, 0), (1, 1, 1), (2, 2, 2), (0, 0, 1), (0, 0, 2), (1, 1, 0), (1, 1, 2),
           (2, 2, 0), (2, 2, 1), (0, 1, 2))  # fmt: skip
#: How many ordered triples each of :data:`TRIPLES` stands for.
TRIPLE_COUNT = np.array([1, 1, 1, 3, 3, 3, 3, 3, 3, 6], dtype=float)


def axis_steps(points, spacing_mm: float) -> np.ndarray:
    """Node spacing along each axis (3,), mm: the median step between a map's distinct
    coordinates on that axis where the map is a grid; ``spacing_mm`` along an axis whose
    distinct coordinates are closer than half of it (scattered nodes) or single."""
    out = np.full(3, float(spacing_mm))
    for j in range(3):
        u = np.unique(np.round(points[:, j], 3))
        if len(u) > 1:
            step = float(np.median(np.diff(u)))
            if step >= 0.5 * spacing_mm:
                out[j] = step
    return out


class _NodeValues:
    """Other values at a map's nodes, read by the map's linear interpolant (same cells)."""

    def __init__(self, linear, values):
        import copy
        from types import SimpleNamespace

        self._lin = copy.copy(linear)
        self._lin.fieldmap = SimpleNamespace(B=np.ascontiguousarray(values, dtype=float))

    def __call__(self, points) -> np.ndarray:
        return self._lin.field_at(points)[0]


#: Weights of the sixth difference (a smooth field's is h^6 d^6B/dx^6: small).
_D6 = (1, -6, 15, -20, 15, -6, 1)
#: Variance of a sixth difference of independent node errors, in units of their variance.
D6_NOISE_GAIN = float(sum(w * w for w in _D6))
#: Median of chi-square with one degree of freedom: a median of squares over it estimates
#: their variance.
CHI2_1_MEDIAN = 0.4549364231195724
#: Nodes over which the median of the sixth differences is taken (the local noise level).
NOISE_NODES = 27
#: Difference stencils (offsets, weights) of the derivatives of order 1-4 along an axis:
#: central first, then shifted into the map for a node near its border (the derivatives of
#: order 1 and 2 exact for a cubic either way).
_STENCILS = {
    1: (((-1, 1), (-0.5, 0.5)), ((0, 1, 2), (-1.5, 2.0, -0.5)),
        ((-2, -1, 0), (0.5, -2.0, 1.5))),
    2: (((-1, 0, 1), (1, -2, 1)), ((0, 1, 2, 3), (2, -5, 4, -1)),
        ((-3, -2, -1, 0), (-1, 4, -5, 2))),
    3: (((-2, -1, 1, 2), (-0.5, 1, -1, 0.5)), ((0, 1, 2, 3), (-1, 3, -3, 1)),
        ((-3, -2, -1, 0), (-1, 3, -3, 1))),
    4: (((-2, -1, 0, 1, 2), (1, -4, 6, -4, 1)), ((0, 1, 2, 3, 4), (1, -4, 6, -4, 1)),
        ((-4, -3, -2, -1, 0), (1, -4, 6, -4, 1))),
}  # fmt: skip


def _axis_derivative(f, order: int, h: float) -> np.ndarray:
    """Derivative of the given order from values ``f[offset]`` at nodes + offset h e_j: the
    first stencil of :data:`_STENCILS` whose values all exist; NaN where none does."""
    val = None
    for offs, wts in _STENCILS[order]:
        if not all(o in f for o in offs):
            continue
        d = sum(w * f[o] for o, w in zip(offs, wts, strict=True)) / h**order
        val = d if val is None else np.where(np.isfinite(val), val, d)
    return val


def _node_derivatives(lin, nodes, steps):
    """Second, third and fourth derivatives of a map's field at its nodes, by differences of
    its node values (steps ``steps`` (3,) mm along the axes).

    Returns
    -------
    d2 : ndarray, shape (n, c, 6), units of the values / mm^2
        d^2 B_i / dx_j dx_k for the pairs of :data:`PAIRS`.
    d3 : ndarray, shape (n, c, 10), / mm^3
        d^3 B_i / dx_j dx_k dx_l for the triples of :data:`TRIPLES`: along an axis from the
        values, mixed ones as the first derivative of the second ones.
    d4 : ndarray, shape (n, c, 3), / mm^4
        d^4 B_i / dx_j^4.
    noise : ndarray, shape (n, c), units of the values squared
        Variance of the node values' own errors: the largest over the axes of the median
        squared central sixth difference over the :data:`NOISE_NODES` nearest nodes that
        have one, over what independent errors of unit variance give
        (:data:`D6_NOISE_GAIN` times :data:`CHI2_1_MEDIAN`); 0 where no axis has seven
        nodes. A smooth field's sixth differences add little; a median leaves a single
        departing node out (the fit locates it).

    Central differences, else the ones shifted into the map (a node near its border); where
    neither fits, 0 (NaN for d4). Mixed second derivatives: the central cross difference,
    else first derivatives along one axis, then the other (three-point stencils, shifted in
    near the border: exact for a cubic field).
    """
    from scipy.spatial import cKDTree

    n = len(nodes)
    f0 = lin(nodes)
    c = f0.shape[1]
    d2, d3, d4 = np.zeros((n, c, 6)), np.zeros((n, c, 10)), np.zeros((n, c, 3))
    noise = np.zeros((n, c))
    for j in range(3):
        e = np.zeros(3)
        e[j] = steps[j]
        f = {s: (f0 if s == 0 else lin(nodes + s * e)) for s in range(-6, 7)}
        d2[:, :, j] = _axis_derivative(f, 2, steps[j])
        d3[:, :, j] = _axis_derivative(f, 3, steps[j])
        d4[:, :, j] = _axis_derivative(f, 4, steps[j])
        d6 = sum(w * f[o] for o, w in zip(range(-3, 4), _D6, strict=True))
        has = np.flatnonzero(np.isfinite(d6).all(1))
        if has.size:  # the map's own noise: a robust local level
            _, near = cKDTree(nodes[has]).query(nodes, k=min(NOISE_NODES, has.size))
            med = np.median(d6[has[near.reshape(n, -1)]] ** 2, axis=1)
            noise = np.fmax(noise, med / (D6_NOISE_GAIN * CHI2_1_MEDIAN))
    d2[:, :, :3] = np.where(np.isfinite(d2[:, :, :3]), d2[:, :, :3], 0.0)
    d3[:, :, :3] = np.where(np.isfinite(d3[:, :, :3]), d3[:, :, :3], 0.0)
    for q, (j, k) in enumerate(PAIRS[3:], start=3):
        ej, ek = np.zeros(3), np.zeros(3)
        ej[j], ek[k] = steps[j], steps[k]
        m = (lin(nodes + ej + ek) - lin(nodes + ej - ek) - lin(nodes - ej + ek)
             + lin(nodes - ej - ek)) / (4 * steps[j] * steps[k])  # fmt: skip
        bad = np.flatnonzero(~np.isfinite(m).all(1))
        if bad.size:  # near the border: first derivatives along j, then along k, shifted in
            g = {}
            for b in range(-2, 3):
                f = {a: lin(nodes[bad] + a * ej + b * ek) for a in range(-2, 3)}
                g[b] = _axis_derivative(f, 1, steps[j])
            m[bad] = _axis_derivative(g, 1, steps[k])
        d2[:, :, q] = np.where(np.isfinite(m), m, 0.0)
    return d2, d3, d4, noise


class CurvatureCorrected:
    """A map's field between its nodes: the linear interpolant corrected by the field's
    curvature, exact at the nodes.

    Read linearly, a point p with interpolation weights w_i on the nodes x_i of its cell gets
    sum_i w_i B(x_i) = B(p) + H : M2 / 2 + T : M3 / 6 + ..., with M2, M3 the second and third
    moments sum_i w_i (x_i - p)^(x2, x3) of its cell (zero at a node; h^2/4 and 0 midway
    between two nodes h apart along an axis) and H, T the field's second and third
    derivatives. The model subtracts those terms: M2 and M3 are read by the same interpolant
    from the coordinates' powers at the nodes, H and T by differences of the map's node
    values, interpolated linearly from its nodes. On a regular grid, midway between nodes
    along an axis, this is the four-point cubic reading (-B(-1) + 9 B(0) + 9 B(1) - B(2)) / 16.
    No field equation is assumed: it serves maps whose harmonic fits fail (a measured map
    with noise, one with currents or iron).

    Its own error (:meth:`error_var`) is the next term along each axis, from the map's fourth
    differences: e_j = (M2_jj / h_j^2) d4_j h_j^4 / 8 (3/128 d4 h^4 midway, the cubic
    reading's error there, exceeded by a third); where a fourth difference cannot be formed (a
    map fewer than five nodes long) the correction's own size H_jj M2_jj / 2 serves (the
    linear reading's error). The fourth-order terms of mixed axes, left out of the model,
    are taken as large as the geometric means of those along the axes: the error is
    (sum_j sqrt(e_j))^2. A measured map's node values carry their own errors (noise, a plane
    of a scan placed off its recorded position), which every reading inherits, at a node as
    between nodes: their variance, estimated near each node from the map's sixth differences
    (:func:`_node_derivatives`), is added.

    Parameters
    ----------
    fm : FieldMap
    linear : LinearInterpolator
        The map's linear interpolant (its cells are the model's).

    Attributes
    ----------
    steps : ndarray, shape (3,), mm
        Node spacing along each axis.
    """

    def __init__(self, fm, linear):
        self.linear = linear
        self.spacing_mm = node_spacing_mm(fm.points)
        self.steps = axis_steps(fm.points, self.spacing_mm)
        self._c = fm.points.mean(0)
        x = fm.points - self._c
        n = len(x)
        d2, d3, d4, noise = _node_derivatives(self.linear_fn, fm.points, self.steps)
        # mixed third derivatives: first differences of the second ones
        hess = _NodeValues(linear, d2.reshape(n, -1))
        for q, (j, k, l) in enumerate(TRIPLES[3:], start=3):
            pair = PAIRS.index((j, k)) if j != k else j
            e = np.zeros(3)
            e[l] = self.steps[l]
            f = {s: hess(fm.points + s * e).reshape(n, 3, 6)[:, :, pair] for s in (-2, -1, 1, 2)}
            f[0] = d2[:, :, pair]
            t = _axis_derivative(f, 1, self.steps[l])
            d3[:, :, q] = np.where(np.isfinite(t), t, 0.0)
        self._mom = _NodeValues(linear, _powers(x))
        self._deriv = _NodeValues(
            linear, np.concatenate([d.reshape(n, -1) for d in (d2, d3, d4, noise)], axis=1)
        )

    def _terms(self, p):
        """Linear reading (m, 3), second (m, 6) and third (m, 10) moments of the cells, and
        the derivatives d2 (m, 3, 6), d3 (m, 3, 10), d4 (m, 3, 3) and the map's noise variance
        (m, 3) at points ``p`` (m, 3) mm."""
        m = len(p)
        b_lin = self.linear_fn(p)
        mom = self._mom(p)  # L[x_j x_k], L[x_j x_k x_l]
        q = p - self._c
        pw = _powers(q)
        m2 = mom[:, :6] - pw[:, :6]
        m3 = np.empty((m, 10))
        for t, (j, k, l) in enumerate(TRIPLES):
            pair = [PAIRS.index(tuple(sorted(ab))) for ab in ((k, l), (j, l), (j, k))]
            m3[:, t] = (mom[:, 6 + t] - q[:, j] * mom[:, pair[0]] - q[:, k] * mom[:, pair[1]]
                        - q[:, l] * mom[:, pair[2]] + 2.0 * pw[:, 6 + t])  # fmt: skip
        der = self._deriv(p)
        d2 = der[:, :18].reshape(m, 3, 6)
        d3 = der[:, 18:48].reshape(m, 3, 10)
        d4 = der[:, 48:57].reshape(m, 3, 3)
        return b_lin, m2, m3, d2, d3, d4, np.maximum(der[:, 57:60], 0.0)

    def field_at(self, points) -> tuple[np.ndarray, np.ndarray]:
        """B (m, 3) T at ``points`` (m, 3) mm and ``inside`` (m,) bool; NaN outside the
        map's cells (never extrapolated)."""
        p = np.asarray(points, dtype=float).reshape(-1, 3)
        b_lin, m2, m3, d2, d3, _, _ = self._terms(p)
        w2 = m2 * np.array([1.0, 1.0, 1.0, 2.0, 2.0, 2.0])  # off-diagonal pairs twice
        corr = 0.5 * np.einsum("niq,nq->ni", d2, w2)
        corr += np.einsum("nit,nt->ni", d3, m3 * TRIPLE_COUNT) / 6.0
        return b_lin - corr, np.isfinite(b_lin).all(1)

    def __call__(self, points) -> np.ndarray:
        return self.field_at(points)[0]

    def error_var(self, points) -> np.ndarray:
        """Variance (m, 3) T^2 of the model's own error at ``points`` (m, 3) mm (class
        docstring); zero at a node."""
        p = np.asarray(points, dtype=float).reshape(-1, 3)
        _, m2, _, d2, _, d4, noise = self._terms(p)
        diag = m2[:, None, :3]  # (m, 1, 3): M2_jj
        h2 = self.steps**2
        err = np.where(np.isfinite(d4), diag / h2 * np.abs(d4) * h2**2 / 8.0,
                       0.5 * np.abs(d2[:, :, :3]) * diag)  # fmt: skip
        err = np.where(np.isfinite(err), err, 0.0)
        return np.sqrt(np.abs(err)).sum(-1) ** 4 + noise

    def linear_fn(self, points) -> np.ndarray:
        """The linear interpolant's field (NaN outside)."""
        return self.linear.field_at(points)[0]


def _powers(x) -> np.ndarray:
    """Second and third powers of coordinates (m, 3): (m, 16), pairs of :data:`PAIRS` then
    triples of :data:`TRIPLES`."""
    return np.stack([x[:, a] * x[:, b] for a, b in PAIRS]
                    + [x[:, a] * x[:, b] * x[:, c] for a, b, c in TRIPLES], axis=1)  # fmt: skip


def reference_model(fm, field_model: str):
    """The field function of a reference map for the diagnosis, and how it is read.

    Parameters
    ----------
    fm : FieldMap
    field_model : {'auto', 'harmonic', 'linear'}
        auto: :class:`NodeExactHarmonic` on a 3-D map, :class:`CurvatureCorrected` on one
        too small for the harmonic fits, the linear interpolant on a planar one; harmonic:
        :class:`NodeExactHarmonic`, refused on a planar map; linear: the linear interpolant.

    Returns
    -------
    model : NodeExactHarmonic, CurvatureCorrected or LinearInterpolator
    kind : {'harmonic', 'curved', 'linear'}
    why : str
        Why the model was chosen (for the notes); empty when asked for by name.
    """
    from ...models.interpolation import LinearInterpolator

    lin = LinearInterpolator(fm)
    if field_model == "linear":
        return lin, "linear", ""
    try:
        return NodeExactHarmonic(fm, lin), "harmonic", ""
    except CfmInputError as e:
        if field_model == "harmonic":
            raise
        if lin.mesh.dim < 3:  # a plane: no differences across it
            return lin, "linear", f"read linearly between nodes: {e}"
        return CurvatureCorrected(fm, lin), "curved", str(e)
