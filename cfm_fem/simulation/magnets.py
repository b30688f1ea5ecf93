"""A family of exact 3-D field sources computed with magpylib: multipoles of any order and a
solenoid, permanent-magnet or current-driven.

A magnet is described by a plain dict (``spec``) so that it can be drawn from a seed and written
into a truth file:

``{"source": "pm", "order": n, "bore_mm": R, "length_mm": L, "scale_T": s}``
    A Halbach-type ring of 16 rectangular blocks (radial thickness ``0.7 R``) around the z axis,
    the block at azimuth phi magnetised at (n + 1) phi - 90 deg: a normal 2n-pole (European n:
    1 dipole, 2 quadrupole, 3 sextupole, 4 octupole; allowed harmonics n + 16 k).
``{"source": "coil", "order": n, ...}``
    A current-driven 2n-pole: saddle loops on a cylinder of radius ``R`` carrying currents
    cos(n phi) (8 conductors per pole pair), closed by arcs at both ends.
``{"source": "solenoid", "order": 0, ...}``
    60 coaxial circular loops of radius ``R`` spread over ``L``.

``scale_T`` is the modulus of the field at half the bore radius in the centre plane (the body
multipole at r = R / 2; the solenoid's axial field at its centre). Lengths in mm and fields in T
at this module's interface (magpylib works in SI).
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from .common import circle_harmonics

__all__ = [
    "ORDER_NAMES",
    "source",
    "field",
    "harmonics_2d",
    "axis_profile",
    "fringe_edges",
    "profile_derivatives",
]

#: Stratum label of each order (0: the solenoid).
ORDER_NAMES = {0: "solenoid", 1: "dipole", 2: "quadrupole", 3: "sextupole", 4: "octupole"}
N_BLOCKS = 16
N_LOOPS_SOLENOID = 60
CONDUCTORS_PER_SECTOR = 4
ARC_SEGMENTS = 6


def _key(spec: dict) -> tuple:
    return (spec["source"], int(spec["order"]), float(spec["bore_mm"]), float(spec["length_mm"]))


def _pm(order: int, bore_mm: float, length_mm: float):
    import magpylib as magpy
    from scipy.spatial.transform import Rotation

    ri, length = bore_mm * 1e-3, length_mm * 1e-3
    t = 0.7 * ri
    w = 2.0 * ri * np.tan(np.pi / N_BLOCKS)
    rc = ri + 0.5 * t
    coll = magpy.Collection()
    for k in range(N_BLOCKS):
        phi = 2.0 * np.pi * k / N_BLOCKS
        pol = np.array([np.sin(order * phi), -np.cos(order * phi), 0.0])  # block frame
        coll.add(
            magpy.magnet.Cuboid(
                dimension=(t, w, length),
                polarization=pol,
                position=(rc * np.cos(phi), rc * np.sin(phi), 0.0),
                orientation=Rotation.from_rotvec((0.0, 0.0, phi)),
            )
        )
    return coll


def _arc(r, f0, f1, z):
    f = np.linspace(f0, f1, ARC_SEGMENTS + 1)
    return np.stack([r * np.cos(f), r * np.sin(f), np.full_like(f, z)], -1)


def _coil(order: int, bore_mm: float, length_mm: float):
    """Saddle loops: forward along +z at phi, arc at the far end to phi + pi/n, back along -z,
    arc home; one loop per conductor of the positive sectors, current cos(n phi) A."""
    import magpylib as magpy

    r, h = bore_mm * 1e-3, 0.5 * length_mm * 1e-3
    coll = magpy.Collection()
    m = CONDUCTORS_PER_SECTOR
    half = np.pi / (2 * order)
    for j in range(order):
        for i in range(m):
            f = -half + (i + 0.5) * 2.0 * half / m
            cur = float(np.cos(order * f))
            f0 = f + 2.0 * np.pi * j / order
            f1 = f0 + np.pi / order
            verts = np.concatenate(
                [_arc(r, f0, f0, -h)[:1], _arc(r, f0, f1, h), _arc(r, f1, f0, -h)]
            )
            coll.add(magpy.current.Polyline(current=cur, vertices=verts))
    return coll


def _solenoid(bore_mm: float, length_mm: float):
    import magpylib as magpy

    coll = magpy.Collection()
    for z in np.linspace(-0.5, 0.5, N_LOOPS_SOLENOID) * length_mm * 1e-3:
        coll.add(magpy.current.Circle(current=1.0, diameter=2e-3 * bore_mm, position=(0, 0, z)))
    return coll


@lru_cache(maxsize=16)
def _unit_source(key: tuple):
    """(collection, factor) with ``factor`` times the collection's field of modulus 1 T at the
    normalisation point."""
    src, order, bore, length = key
    if src == "pm":
        coll = _pm(order, bore, length)
    elif src == "coil":
        coll = _coil(order, bore, length)
    elif src == "solenoid":
        coll = _solenoid(bore, length)
    else:
        raise ValueError(f"unknown magnet source {src!r}; expected 'pm', 'coil' or 'solenoid'")
    at = np.zeros(3) if order == 0 else np.array([0.5 * bore * 1e-3, 0.0, 0.0])
    b = np.linalg.norm(np.atleast_2d(coll.getB(at))[0])
    return coll, 1.0 / b


def source(spec: dict):
    """The magpylib collection of a magnet spec (centre at the origin, axis along z)."""
    return _unit_source(_key(spec))[0]


def field(spec: dict, points_mm, chunk: int = 20000) -> np.ndarray:
    """Exact field of the magnet at rest at the origin.

    Parameters
    ----------
    spec : dict
        The magnet (module docstring).
    points_mm : array_like, shape (n, 3), mm

    Returns
    -------
    ndarray, shape (n, 3), T
    """
    coll, factor = _unit_source(_key(spec))
    p = np.atleast_2d(np.asarray(points_mm, dtype=float)) * 1e-3
    out = np.empty_like(p)
    for s in range(0, len(p), chunk):
        out[s : s + chunk] = np.atleast_2d(coll.getB(p[s : s + chunk]))
    return out * (factor * float(spec["scale_T"]))


def harmonics_2d(spec: dict, r_ref_mm: float, n_max: int = 40, z_mm: float = 0.0) -> np.ndarray:
    """2-D multipole coefficients of the field on a circle of radius ``r_ref_mm`` at ``z_mm``:
    B_y + i B_x = sum_n (B_n + i A_n) ((x + i y) / r_ref)^(n - 1) (256-point Fourier analysis).

    Returns
    -------
    ndarray, shape (n_max, 3)
        Rows (n, B_n, A_n), T at r_ref.
    """
    return circle_harmonics(lambda p: field(spec, p), r_ref_mm, n_max, z_mm)


def axis_profile(spec: dict, z_mm, radii=(0.25, 0.5, 0.75, 1.0)) -> np.ndarray:
    """The body multipole's on-axis amplitude C_n(z) (T/mm^(n-1)): the normal coefficient of
    order n on small circles, divided by r^(n-1) and extrapolated to r = 0 as a polynomial in
    r^2 (the 3-D terms grow as r^2, r^4)."""
    n = int(spec["order"])
    z = np.atleast_1d(np.asarray(z_mm, dtype=float))
    m = 32
    th = 2.0 * np.pi * np.arange(m) / m
    r = np.asarray(radii, dtype=float)
    pts = np.zeros((len(z), len(r), m, 3))
    pts[..., 0] = r[None, :, None] * np.cos(th)
    pts[..., 1] = r[None, :, None] * np.sin(th)
    pts[..., 2] = z[:, None, None]
    b = field(spec, pts.reshape(-1, 3)).reshape(len(z), len(r), m, 3)
    c = (np.fft.fft(b[..., 1] + 1j * b[..., 0], axis=-1) / m)[..., n - 1].real / r ** (n - 1)
    vander = np.vander(r**2, 3, increasing=True)
    return np.linalg.lstsq(vander, c.T, rcond=None)[0][0]


def _enge(z, z_entry, z_exit, lam):
    fi = 0.5 * (1.0 + np.tanh(0.5 * (z - z_entry) / lam))
    fo = 0.5 * (1.0 + np.tanh(0.5 * (z_exit - z) / lam))
    return fi * fo


def fringe_edges(spec: dict) -> tuple:
    """Effective edges and fringe length (mm) of a multipole's ends: the soft-edge profile
    f((z - z_entry)/lam) f((z_exit - z)/lam), f(u) = 1 / (1 + exp(-u)), fitted by least squares
    to the on-axis profile C_n(z) / C_n(0) over |z| <= L / 2 + 8 R."""
    from scipy.optimize import least_squares

    half = 0.5 * float(spec["length_mm"])
    z = np.linspace(-half - 8 * spec["bore_mm"], half + 8 * spec["bore_mm"], 241)
    g = axis_profile(spec, z) / axis_profile(spec, [0.0])[0]
    fit = least_squares(lambda th: _enge(z, *th) - g, [-half, half, 0.3 * spec["bore_mm"]])
    return tuple(float(v) for v in fit.x)


def profile_derivatives(spec: dict, z_mm, h: float = 0.2) -> np.ndarray:
    """g(z) = C_n(z) / C_n(0) and its first two z-derivatives (1/mm, 1/mm^2) by five-point
    differences over +-2 ``h`` mm.

    Returns
    -------
    ndarray, shape (3, len(z_mm))
    """
    z = np.atleast_1d(np.asarray(z_mm, dtype=float))
    offs = np.arange(-2, 3) * h
    g = axis_profile(spec, (z[:, None] + offs).reshape(-1)).reshape(len(z), 5)
    g /= axis_profile(spec, [0.0])[0]
    d1 = (-g[:, 4] + 8 * g[:, 3] - 8 * g[:, 1] + g[:, 0]) / (12 * h)
    d2 = (-g[:, 4] + 16 * g[:, 3] - 30 * g[:, 2] + 16 * g[:, 1] - g[:, 0]) / (12 * h * h)
    return np.stack([g[:, 2], d1, d2])
