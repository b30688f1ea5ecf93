"""Linear interpolation of a field map with its curvature corrected: second-order accurate.

Inside a simplex with vertices v_k and barycentric coordinates lambda_k of x, linear
interpolation errs by

    B_lin(x) - B(x) = 1/2 sum_k lambda_k (v_k - x)^T H(x) (v_k - x) + O(h^3)

with H the Hessian of each component: in a fringe field, whose curvature keeps one sign over
many cells, that error is no noise but a bias of one sign that looks like a gain or a shift
along the axis (about h^2 / (8 lambda^2) of the field midway between nodes h apart, lambda the
field's decay length). `CurvatureCorrected` subtracts it, with H from second differences of
the linear interpolant at the node spacing (node values on a regular grid), so a field
quadratic along each direction of a regular grid is reproduced exactly. What remains is third
order: along a direction with third difference d3 (step h), the corrected interpolant errs by
d3 t (h - t) (h - 2 t) / (6 h^3) at a distance t from a node, of mean square d3^2 / 7560 over a
cell; `CurvatureCorrected.error_var` states it from the third derivatives.
"""

from __future__ import annotations

import numpy as np

from .interpolation import LinearInterpolator

__all__ = ["CurvatureCorrected", "THIRD_ORDER_VAR"]

#: Mean square of t (h - t) (h - 2 t) / (6 h^3) over t in [0, h]: 1 / (36 * 210).
THIRD_ORDER_VAR = 1.0 / 7560.0


class CurvatureCorrected:
    """A map's linear interpolant less its second-order error (module docstring).

    Parameters
    ----------
    linear : LinearInterpolator
    spacing_mm : float
        Node spacing h of the map (step of the second differences), mm.

    Notes
    -----
    Within a node spacing of the map's border the curvature is taken from a point one or two
    node steps inwards (:meth:`hessian`).
    """

    def __init__(self, linear: LinearInterpolator, spacing_mm: float):
        self.linear = linear
        self.h = float(spacing_mm)
        m = linear.mesh
        self._dirs = np.asarray(m.basis, dtype=float).T  # (dim, 3) unit steps of the mesh frame
        pad = 1e-9 * max(float(np.ptp(m.coords, axis=0).max()), 1.0)
        self._box = (m.coords.min(0) - pad, m.coords.max(0) + pad)

    def _lin(self, p):
        """Linear interpolant at p (k, 3) mm, NaN outside; points outside the mesh's bounding
        box are not searched for."""
        out = np.full((len(p), 3), np.nan)
        loc = self.linear.mesh.to_local(p)
        box = ((loc >= self._box[0]) & (loc <= self._box[1])).all(1)
        if box.any():
            out[box] = self.linear.field_at(p[box])[0]
        return out

    def _stencil(self) -> tuple[np.ndarray, list]:
        """Offsets (m, 3) mm of the second-difference stencil and, per entry (a, b) of the
        Hessian, the (offset index, weight) pairs that form it (weights in 1/mm^2)."""
        d, h = len(self._dirs), self.h
        e = self._dirs * h
        offs = [np.zeros(3)]
        terms = {}

        def at(v):
            offs.append(v)
            return len(offs) - 1

        for a in range(d):
            terms[a, a] = [(at(e[a]), 1.0 / h**2), (0, -2.0 / h**2), (at(-e[a]), 1.0 / h**2)]
            for b in range(a + 1, d):
                w = 1.0 / (4.0 * h**2)
                terms[a, b] = [(at(e[a] + e[b]), w), (at(e[a] - e[b]), -w),
                               (at(-e[a] + e[b]), -w), (at(-e[a] - e[b]), w)]  # fmt: skip
        return np.array(offs), terms

    def _central_hessian(self, p) -> np.ndarray:
        """Central second differences along the mesh frame's axes, (k, 3, dim, dim), NaN
        where a stencil point is outside the map (one interpolation of all stencil points)."""
        offs, terms = self._stencil()
        d = len(self._dirs)
        f = self._lin((p[:, None, :] + offs[None]).reshape(-1, 3)).reshape(len(p), len(offs), 3)
        H = np.empty((len(p), 3, d, d))
        for (a, b), tw in terms.items():
            H[:, :, a, b] = H[:, :, b, a] = sum(w * f[:, i] for i, w in tw)
        return H

    def hessian(self, points, fill: float = 0.0, shifts: bool = False):
        """Second derivatives along the mesh frame's axes, shape (k, 3, dim, dim), T/mm^2.

        Central differences of step h; where a stencil point is outside the map (within a
        node spacing of its border), those of the nearest point a node step inwards along one
        or more axes whose stencil is inside (first order in h there); ``fill`` where none is.
        With ``shifts``, also the distance (k,) mm each point's differences were moved."""
        p = np.atleast_2d(np.asarray(points, dtype=float))
        H = self._central_hessian(p)
        moved = np.zeros(len(p))
        bad = np.flatnonzero(~np.isfinite(H).all((1, 2, 3)))
        if bad.size:
            d = len(self._dirs)
            grid = np.array(np.meshgrid(*[[-1, 0, 1]] * d, indexing="ij")).reshape(d, -1).T
            grid = grid[np.argsort(np.abs(grid).sum(1), kind="stable")][1:]
            steps = grid @ self._dirs * self.h  # (g, 3), nearest first
            Hs = self._central_hessian((p[bad, None, :] + steps[None]).reshape(-1, 3))
            Hs = Hs.reshape(len(bad), len(steps), 3, d, d)
            ok = np.isfinite(Hs).all((2, 3, 4))
            first = np.argmax(ok, axis=1)
            found = ok[np.arange(len(bad)), first]
            H[bad[found]] = Hs[np.flatnonzero(found), first[found]]
            moved[bad[found]] = np.linalg.norm(steps[first[found]], axis=1)
        H[~np.isfinite(H)] = fill
        return (H, moved) if shifts else H

    def field_at(self, points) -> tuple[np.ndarray, np.ndarray]:
        """Corrected field at ``points``.

        Parameters
        ----------
        points : array_like, shape (k, 3), mm

        Returns
        -------
        B : ndarray, shape (k, 3), T
            NaN outside the map.
        inside : ndarray, shape (k,), bool
        """
        p = np.atleast_2d(np.asarray(points, dtype=float))
        B, cell, local = self.linear.locate(p)
        inside = cell >= 0
        if not inside.any():
            return B, inside
        m = self.linear.mesh
        c = cell[inside]
        x = local[inside]
        T = m.transform[c]
        dim = m.dim
        lam = np.einsum("cjk,ck->cj", T[:, :dim], x - T[:, dim])
        lam = np.concatenate([lam, 1.0 - lam.sum(1, keepdims=True)], axis=1)  # (k, dim + 1)
        D = m.coords[m.simplices[c]] - x[:, None, :]  # (k, dim + 1, dim), mesh frame
        H = self.hessian(p[inside])
        corr = 0.5 * np.einsum("cv,cva,ciab,cvb->ci", lam, D, H, D)
        B[inside] = B[inside] - corr
        return B, inside

    def error_var(self, points) -> np.ndarray:
        """Variance of the corrected interpolant's error at ``points``, T^2, shape (k, 3).

        The third derivatives T_abc of each component (central differences of :meth:`hessian`
        at step h along each mesh-frame axis, one-sided at a border) set the size of what the
        correction leaves:
        ``2 THIRD_ORDER_VAR sum_abc (h^3 T_abc)^2``: twice the mean square over a cell of
        the one-direction term, every ordered triple counted (on exponential fringes of decay
        length 2 to 6 node spacings the corrected error's mean square is 1.4 to 1.8 times the
        once-counted estimate). Where the curvature was taken inwards (:meth:`hessian`: within
        a node spacing of the border) or no third derivative can be formed, the linear
        interpolation error (h^2 H_aa)^2 / 120 of each direction
        (`cfm_fem.workflows.diagnose.noise`): an upper estimate there."""
        p = np.atleast_2d(np.asarray(points, dtype=float))
        h = self.h
        var = np.zeros((len(p), 3))
        H0, moved = self.hessian(p, fill=np.nan, shifts=True)
        for a, e in enumerate(self._dirs * h):
            Hp, Hm = self.hessian(p + e, fill=np.nan), self.hessian(p - e, fill=np.nan)
            Hp[~np.isfinite(self._lin(p + e)).all(1)] = np.nan  # outside: no difference
            Hm[~np.isfinite(self._lin(p - e)).all(1)] = np.nan
            T = (Hp - Hm) / (2.0 * h)  # (k, 3, dim, dim): d/dx_e of H
            T = np.where(np.isfinite(T), T, (Hp - H0) / h)  # one-sided at a border
            T = np.where(np.isfinite(T), T, (H0 - Hm) / h)
            third = np.nan_to_num((T * h**3) ** 2, nan=np.inf).sum((2, 3)) * 2.0 * THIRD_ORDER_VAR
            third[moved > 0] = np.inf  # curvature taken inwards: first order only
            d2 = H0[:, :, a, a] * h**2
            lin = np.where(np.isfinite(d2), d2**2 / 120.0, 0.0)
            var += np.where(np.isfinite(third), third, lin)
        return var
