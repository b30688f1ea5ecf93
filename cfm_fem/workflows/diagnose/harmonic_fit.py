"""Smooth reference field for a measured map: B = grad Phi, Phi a harmonic polynomial.

Every basis field is the gradient of a harmonic polynomial (Laplace Phi = 0), so the model has
div B = 0 and curl B = 0 exactly: what it cannot fit is either higher order than the fit or breaks
Maxwell's equations in free space: a residual that breaks div B = 0 or curl B = 0 comes from
the instrument, never from the magnet.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["HarmonicField", "fit_harmonic_field"]


def _monomials(deg):
    return [(a, b, deg - a - b) for a in range(deg + 1) for b in range(deg + 1 - a)]


def _harmonic_basis(deg):
    """Coefficient vectors (k, n_monomials) of the harmonic homogeneous polynomials of ``deg``."""
    mons = _monomials(deg)
    if deg < 2:
        return mons, np.eye(len(mons))
    low = {m: i for i, m in enumerate(_monomials(deg - 2))}
    L = np.zeros((len(low), len(mons)))
    for j, (a, b, c) in enumerate(mons):
        for k, e in enumerate((a, b, c)):
            if e >= 2:
                t = [a, b, c]
                t[k] -= 2
                L[low[tuple(t)], j] += e * (e - 1)
    _, s, vt = np.linalg.svd(L)
    rank = int((s > 1e-10 * s[0]).sum())
    return mons, vt[rank:]


@dataclass
class HarmonicField:
    """B(x) = sum_k c_k grad Phi_k((x - center) / scale); callable on (n, 3) mm -> (n, 3) T."""

    center: np.ndarray
    scale: float
    degree: int
    coef: np.ndarray
    rms_T: float = 0.0

    def design(self, points) -> np.ndarray:
        """Basis fields, shape (n, 3, k), T per unit coefficient."""
        u = (np.asarray(points, float) - self.center) / self.scale
        cols = []
        for deg in range(1, self.degree + 1):
            mons, basis = _harmonic_basis(deg)
            g = np.zeros((len(u), 3, len(mons)))
            for j, (a, b, c) in enumerate(mons):
                e = (a, b, c)
                for k in range(3):
                    if e[k] == 0:
                        continue
                    t = list(e)
                    t[k] -= 1
                    g[:, k, j] = e[k] * u[:, 0] ** t[0] * u[:, 1] ** t[1] * u[:, 2] ** t[2]
            cols.append(g @ basis.T)
        return np.concatenate(cols, axis=-1)

    def __call__(self, points) -> np.ndarray:
        return self.design(points) @ self.coef


def fit_harmonic_field(points, B, degree: int = 6) -> HarmonicField:
    """Least-squares fit of a curl- and divergence-free polynomial field of ``degree``.

    Parameters
    ----------
    points : ndarray, shape (n, 3), mm
    B : ndarray, shape (n, 3), T
    degree : int
        Degree of the scalar potential (the field has degree ``degree - 1``).
    """
    points = np.asarray(points, float)
    center = 0.5 * (points.max(0) + points.min(0))
    scale = float(np.max(np.abs(points - center))) or 1.0
    hf = HarmonicField(center, scale, int(degree), np.zeros(0))
    D = hf.design(points).transpose(0, 1, 2).reshape(-1, hf.design(points[:1]).shape[-1])
    coef, *_ = np.linalg.lstsq(D, np.asarray(B, float).reshape(-1), rcond=None)
    hf.coef = coef
    hf.rms_T = float(np.sqrt(np.mean((D @ coef - B.reshape(-1)) ** 2)))
    return hf


@dataclass
class PiecewiseHarmonic:
    """Harmonic-polynomial fits in overlapping z windows: each point uses the window centred
    nearest to it (curl- and div-free inside each window). For long maps with magnet ends."""

    centers: np.ndarray
    fits: list

    def __call__(self, points) -> np.ndarray:
        points = np.asarray(points, float)
        k = np.argmin(np.abs(points[:, 2, None] - self.centers[None, :]), axis=1)
        out = np.empty((len(points), 3))
        for j in np.unique(k):
            m = k == j
            out[m] = self.fits[j](points[m])
        return out

    @property
    def rms_T(self) -> float:
        return float(np.sqrt(np.mean([f.rms_T**2 for f in self.fits])))


def fit_piecewise_harmonic(points, B, degree: int = 5, slab_mm: float = 50.0, half_window_mm=60.0):
    """Fit :class:`HarmonicField` of ``degree`` in windows of +-``half_window_mm`` around slab
    centres every ``slab_mm`` along z."""
    points = np.asarray(points, float)
    B = np.asarray(B, float)
    z0, z1 = points[:, 2].min(), points[:, 2].max()
    n = max(1, int(np.ceil((z1 - z0) / slab_mm)))
    centers = z0 + (np.arange(n) + 0.5) * (z1 - z0) / n
    fits = []
    for c in centers:
        m = np.abs(points[:, 2] - c) <= half_window_mm
        fits.append(fit_harmonic_field(points[m], B[m], degree))
    return PiecewiseHarmonic(centers, fits)


__all__ += ["PiecewiseHarmonic", "fit_piecewise_harmonic"]
