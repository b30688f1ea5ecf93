"""The exact field source: a segmented permanent-magnet quadrupole computed with magpylib.

Sixteen rectangular blocks (radial thickness 8 mm, tangential width that closes the ring at the
11 mm bore, length 250 mm) around the z axis, each magnetised at three times its azimuth less 90
deg (a Halbach-type quadrupole, By = G x, Bx = G y inside). The polarisation is chosen so that
the gradient at the centre is about 55 T/m. Both ends are real 3-D ends: the field falls to zero
over a few bore radii, so a scan over |z| <= 300 mm crosses both into field-free space.

Lengths in mm and fields in T at this module's interface (magpylib works in SI).
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from .common import circle_harmonics

__all__ = [
    "BORE_MM",
    "LENGTH_MM",
    "GRADIENT_T_M",
    "quadrupole",
    "field",
    "fringe_edges",
    "profile_derivatives",
    "harmonics_2d",
]

BORE_MM = 11.0  # inner radius of the block ring
THICK_MM = 8.0  # radial thickness of a block
LENGTH_MM = 250.0
N_BLOCKS = 16
POLARIZATION_T = 0.946  # gives ~55 T/m at the centre with this geometry
GRADIENT_T_M = 55.0  # design gradient


@lru_cache(maxsize=1)
def quadrupole():
    """The magpylib collection of the quadrupole (centre at the origin, axis along z)."""
    import magpylib as magpy
    from scipy.spatial.transform import Rotation

    ri, t, L = BORE_MM * 1e-3, THICK_MM * 1e-3, LENGTH_MM * 1e-3
    w = 2.0 * ri * np.tan(np.pi / N_BLOCKS)
    rc = ri + 0.5 * t
    coll = magpy.Collection()
    for k in range(N_BLOCKS):
        phi = 2.0 * np.pi * k / N_BLOCKS
        # the block is turned by phi: its local polarisation at 2 phi - pi/2 points at
        # 3 phi - pi/2 globally (a normal quadrupole, By = G x)
        coll.add(
            magpy.magnet.Cuboid(
                dimension=(t, w, L),
                polarization=POLARIZATION_T * np.array([np.sin(2 * phi), -np.cos(2 * phi), 0.0]),
                position=(rc * np.cos(phi), rc * np.sin(phi), 0.0),
                orientation=Rotation.from_rotvec((0.0, 0.0, phi)),
            )
        )
    return coll


def field(points_mm, chunk: int = 20000) -> np.ndarray:
    """Exact field of the quadrupole at rest at the origin.

    Parameters
    ----------
    points_mm : array_like, shape (n, 3), mm

    Returns
    -------
    ndarray, shape (n, 3), T
    """
    p = np.atleast_2d(np.asarray(points_mm, dtype=float)) * 1e-3
    coll = quadrupole()
    out = np.empty_like(p)
    for s in range(0, len(p), chunk):
        out[s : s + chunk] = np.atleast_2d(coll.getB(p[s : s + chunk]))
    return out


def _enge(z, z_entry, z_exit, lam):
    fi = 0.5 * (1.0 + np.tanh(0.5 * (z - z_entry) / lam))
    fo = 0.5 * (1.0 + np.tanh(0.5 * (z_exit - z) / lam))
    return fi * fo


@lru_cache(maxsize=1)
def fringe_edges() -> tuple:
    """Effective edges and fringe length of the ends (mm): the soft-edge profile
    f((z - z_entry)/lam) f((z_exit - z)/lam), f(u) = 1 / (1 + exp(-u)), fitted by least squares
    to the on-axis gradient profile G(z) / G(0), G = dBy/dx at x = y = 0 (a central difference
    over x = +-0.5 mm: the r^2 terms of the ends are below 1e-4 of it there).

    Returns
    -------
    (z_entry, z_exit, lam) : tuple of float, mm
    """
    from scipy.optimize import least_squares

    z = np.linspace(-300.0, 300.0, 1201)
    p = np.zeros((len(z), 3))
    p[:, 0], p[:, 2] = 0.5, z
    q = p * [-1.0, 1.0, 1.0]
    centre = field([[0.5, 0.0, 0.0], [-0.5, 0.0, 0.0]])[:, 1]
    g = (field(p)[:, 1] - field(q)[:, 1]) / (centre[0] - centre[1])
    half = 0.5 * LENGTH_MM
    fit = least_squares(lambda th: _enge(z, *th) - g, [-half, half, 5.0])
    return tuple(float(v) for v in fit.x)


def _axis_gradient(z, half_widths=(0.25, 0.5, 0.75, 1.0)):
    """G(z) = dBy/dx on the axis (T/mm): the odd part of By along x at each z,
    (By(x) - By(-x)) / (2 x) = G - G'' x^2 / 12 + ..., fitted as a polynomial in x^2."""
    x = np.asarray(half_widths, dtype=float)
    z = np.asarray(z, dtype=float)
    p = np.zeros((len(z), len(x), 3))
    p[:, :, 0], p[:, :, 2] = x, z[:, None]
    q = p * [-1.0, 1.0, 1.0]
    odd = (field(p.reshape(-1, 3))[:, 1] - field(q.reshape(-1, 3))[:, 1]).reshape(len(z), -1)
    odd /= 2.0 * x
    vander = np.vander(x**2, 3, increasing=True)
    return np.linalg.lstsq(vander, odd.T, rcond=None)[0][0]


def profile_derivatives(z_mm, h: float = 0.2) -> np.ndarray:
    """The exact profile of the ends, g(z) = G(z) / G(0) on the axis, and its first two
    z-derivatives (1/mm, 1/mm^2) by five-point differences over +-2 ``h`` mm.

    Returns
    -------
    ndarray, shape (3, len(z_mm))
    """
    z = np.atleast_1d(np.asarray(z_mm, dtype=float))
    offs = np.arange(-2, 3) * h
    g = _axis_gradient((z[:, None] + offs).reshape(-1)).reshape(len(z), 5)
    g /= _axis_gradient([0.0])[0]
    d1 = (-g[:, 4] + 8 * g[:, 3] - 8 * g[:, 1] + g[:, 0]) / (12 * h)
    d2 = (-g[:, 4] + 16 * g[:, 3] - 30 * g[:, 2] + 16 * g[:, 1] - g[:, 0]) / (12 * h * h)
    return np.stack([g[:, 2], d1, d2])


def harmonics_2d(r_ref_mm: float = 10.0, n_max: int = 40, z_mm: float = 0.0) -> np.ndarray:
    """2-D multipole coefficients of the body field at ``z_mm`` (the magnet's centre).

    B_y + i B_x = sum_n (B_n + i A_n) ((x + i y) / r_ref)^(n - 1), from the field on a circle
    of radius ``r_ref_mm`` (Fourier analysis, 256 points; the 16 blocks allow n = 2, 18, 34).

    Returns
    -------
    ndarray, shape (n_max, 3)
        Rows (n, B_n, A_n), T at r_ref.
    """
    return circle_harmonics(field, r_ref_mm, n_max, z_mm)
