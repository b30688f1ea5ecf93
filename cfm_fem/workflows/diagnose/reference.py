"""A reference field map read between its nodes, with an estimate of its own error there.

A diagnosis compares readings with a reference map at the readings' points, which rarely are the
map's nodes. Read linearly between nodes, a coarse map errs by the field's curvature times the
cell size squared, one sign across a whole plane: an error far above a Hall probe's noise that a
fit then takes for a probe or magnet effect. :class:`NodeExactHarmonic` reads the map as the
per-node harmonic fits of :func:`cfm_fem.models.harmonic.fit_harmonic` (a Maxwell-consistent
polynomial around each node, fitted to its nearest nodes), corrected so that it reproduces the
map exactly at every node: the harmonic fits' own residuals at the nodes are interpolated
linearly and added. Where a node's fit fails Laplace's test (currents, iron, noise in the
export) or a point lies beyond every usable fit's reach, the linear interpolant serves.

The model's error between nodes is estimated from the model itself (:meth:`error_var`): at a
point, the fits of its three nearest usable nodes all describe the field there; their largest
departure from the nearest node's fit is the size of the truncation error of the local
polynomials. It vanishes at a node (the model is exact there) and is scaled up to its full size
half a node spacing away. Where the linear interpolant serves, its error is estimated from the
map's curvature (:func:`~cfm_fem.workflows.diagnose.noise.reference_error_var`).
"""

from __future__ import annotations

import numpy as np

from ...errors import CfmInputError
from ...models.harmonic import fit_harmonic, neighbourhoods
from ...models.harmonic_basis import MAX_DEGREE, field_basis, monomial_exponents

__all__ = ["NodeExactHarmonic", "node_spacing_mm", "SPREAD_NODES"]

#: Nearest usable nodes whose fits are compared at a point to estimate the model's error.
SPREAD_NODES = 3


def node_spacing_mm(points) -> float:
    """Typical node spacing of a map (median distance to the nearest other node), mm."""
    from scipy.spatial import cKDTree

    d, _ = cKDTree(points).query(points, k=2)
    d = d[:, 1]
    return float(np.median(d[d > 0])) if np.any(d > 0) else 0.0


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

        self.fit = fit_harmonic(fm.points, fm.B, source=fm.source)
        self.linear = linear
        self.spacing_mm = node_spacing_mm(fm.points)
        self.n_fallback = int((~self.fit.use).sum())
        h, ok = self.fit.field_at(fm.points)
        resid = np.where(ok[:, None], fm.B - h, 0.0)
        self._resid = type(linear)(replace(fm, B=resid))
        self._gmat = field_basis(MAX_DEGREE)
        self._exps = monomial_exponents(MAX_DEGREE)

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
        out[ok] = h[ok] + np.where(np.isfinite(corr[ok]), corr[ok], 0.0)
        far = ~np.isfinite(out).all(1)
        idx, used, tree = self.fit._used
        if far.any() and idx.size:  # beyond the cells and every reach: the nearest fit's
            near, _ = neighbourhoods(tree, used, p[far], 1)
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
        docstring): the largest squared departure of the next usable nodes' fits from the
        nearest one's, times (2 d / spacing)^2 up to 1, d the distance to the nearest node;
        the linear interpolant's curvature estimate where it serves."""
        from scipy.spatial import cKDTree

        from .noise import reference_error_var

        p = np.asarray(points, dtype=float).reshape(-1, 3)
        idx, used, tree = self.fit._used
        var = np.zeros((len(p), 3))
        _, ok = self.fit.field_at(p)
        if idx.size >= SPREAD_NODES and ok.any():
            near, _ = neighbourhoods(tree, used, p[ok], SPREAD_NODES)
            b1 = self._eval_node(idx[near[:, 0]], p[ok])
            dev = np.zeros_like(b1)
            for j in range(1, SPREAD_NODES):
                dev = np.maximum(dev, np.abs(self._eval_node(idx[near[:, j]], p[ok]) - b1))
            var[ok] = dev**2
        if (~ok).any():
            var[~ok] = reference_error_var(self.linear_fn, p[~ok], self.spacing_mm)
        d, _ = cKDTree(self.fit.centers).query(p)
        return var * np.clip(2.0 * d / self.spacing_mm, 0.0, 1.0)[:, None] ** 2

    def linear_fn(self, points) -> np.ndarray:
        """The linear interpolant's field (NaN outside)."""
        return self.linear.field_at(points)[0]


def reference_model(fm, field_model: str):
    """The field function of a reference map for the diagnosis, and how it is read.

    Parameters
    ----------
    fm : FieldMap
    field_model : {'auto', 'harmonic', 'linear'}
        auto: :class:`NodeExactHarmonic` on a 3-D map, the linear interpolant on a planar one
        (or one too small for the harmonic fits); harmonic: :class:`NodeExactHarmonic`, refused
        on a planar map; linear: the linear interpolant.

    Returns
    -------
    model : NodeExactHarmonic or LinearInterpolator
    kind : {'harmonic', 'linear'}
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
        return lin, "linear", f"read linearly between nodes: {e}"
