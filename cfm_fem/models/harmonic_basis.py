"""Curl- and divergence-free polynomial fields: gradients of harmonic polynomials.

In a current-free region the magnetic field is B = grad(Phi) with Laplace's equation for Phi,
so a local polynomial model of B that is exactly div- and curl-free is the gradient of a
harmonic polynomial. For Phi of degree n the harmonic polynomials form a space of dimension
2n + 1; a field of polynomial degree L needs Phi of degrees 1 .. L + 1, (L + 1)(L + 3) basis
functions in all.

The basis is built exactly from Cauchy data on the plane x = 0 (the harmonic extension in x):
for f(y, z) homogeneous of degree n, Phi_f = sum_k (-1)^k x^{2k} / (2k)! Lap_yz^k f, and for
g(y, z) homogeneous of degree n - 1, Phi_g = sum_k (-1)^k x^{2k+1} / (2k+1)! Lap_yz^k g, with f
and g the monomials y^a z^b. Each basis field is scaled to unit RMS magnitude over a fixed set
of points on the unit sphere, so that the columns of a fit in coordinates scaled to about unit
size have comparable norms.

Orders (the kernels rely on both): the field basis by the degree of Phi, so the basis of field
degree L is the first `n_basis(L)` functions; monomials by total degree, then by descending
power of x, then of y, so the monomials of degree <= L are the first `n_monomials(L)`.
"""

from __future__ import annotations

from functools import cache
from math import factorial

import numpy as np

__all__ = [
    "MAX_DEGREE",
    "n_basis",
    "n_monomials",
    "monomial_exponents",
    "field_basis",
]

#: Highest polynomial degree of the field model.
MAX_DEGREE = 5


def n_basis(degree: int) -> int:
    """Number of harmonic basis fields of polynomial degree <= ``degree`` ((L + 1)(L + 3))."""
    return (degree + 1) * (degree + 3)


def n_monomials(degree: int) -> int:
    """Number of monomials x^i y^j z^k with i + j + k <= ``degree``."""
    return (degree + 1) * (degree + 2) * (degree + 3) // 6


@cache
def _exponents(degree: int) -> tuple:
    return tuple(
        (i, j, n - i - j)
        for n in range(degree + 1)
        for i in range(n, -1, -1)
        for j in range(n - i, -1, -1)
    )


def monomial_exponents(degree: int = MAX_DEGREE) -> np.ndarray:
    """Exponents (i, j, k) of the monomials x^i y^j z^k of degree <= ``degree``, in kernel order.

    Returns
    -------
    ndarray, shape (n_monomials(degree), 3), int64
    """
    return np.array(_exponents(degree), dtype=np.int64).reshape(-1, 3)


def _lap_yz(poly: dict) -> dict:
    """Laplacian in (y, z) of a polynomial {(i, j, k): coefficient}."""
    out: dict = {}
    for (i, j, k), c in poly.items():
        if j >= 2:
            key = (i, j - 2, k)
            out[key] = out.get(key, 0.0) + c * j * (j - 1)
        if k >= 2:
            key = (i, j, k - 2)
            out[key] = out.get(key, 0.0) + c * k * (k - 1)
    return out


def _extension(a: int, b: int, odd: int) -> dict:
    """Harmonic polynomial with Cauchy data y^a z^b at x = 0 (value if ``odd`` = 0, normal
    derivative if ``odd`` = 1)."""
    phi: dict = {}
    term = {(0, a, b): 1.0}
    k = 0
    while term:
        scale = (-1.0) ** k / factorial(2 * k + odd)
        for (_i, j, kk), c in term.items():
            key = (2 * k + odd, j, kk)
            phi[key] = phi.get(key, 0.0) + scale * c
        term = _lap_yz(term)
        k += 1
    return phi


def _potentials(degree: int) -> list[dict]:
    """Harmonic potentials of degrees 1 .. degree + 1, in basis order."""
    out = []
    for n in range(1, degree + 2):
        for a in range(n, -1, -1):
            out.append(_extension(a, n - a, 0))
        for a in range(n - 1, -1, -1):
            out.append(_extension(a, n - 1 - a, 1))
    return out


def _sphere_points(n: int = 256) -> np.ndarray:
    """Fibonacci points on the unit sphere: fixed, so the scaling is reproducible."""
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    r = np.sqrt(1.0 - z * z)
    phi = np.pi * (1.0 + 5.0**0.5) * i
    return np.c_[r * np.cos(phi), r * np.sin(phi), z]


@cache
def _basis(degree: int) -> np.ndarray:
    exps = _exponents(degree)
    index = {e: m for m, e in enumerate(exps)}
    nb = n_basis(degree)
    g = np.zeros((3, len(exps), nb))
    for j, phi in enumerate(_potentials(degree)):
        for (i, jj, k), c in phi.items():
            for comp, e in enumerate(((i, jj, k), (jj, i, k), (k, i, jj))):
                if e[0] == 0:
                    continue
                # d/dx_comp of x^i y^jj z^k
                ex = [i, jj, k]
                ex[comp] -= 1
                g[comp, index[tuple(ex)], j] += c * e[0]
    pts = _sphere_points()
    mono = np.prod(pts[:, None, :] ** monomial_exponents(degree)[None], axis=2)
    field = np.einsum("pm,cmj->pcj", mono, g)
    g /= np.sqrt(np.mean(np.sum(field**2, axis=1), axis=0))
    g.setflags(write=False)
    return g


def field_basis(degree: int = MAX_DEGREE) -> np.ndarray:
    """Monomial coefficients of the harmonic basis fields of polynomial degree <= ``degree``.

    Returns
    -------
    ndarray, shape (3, n_monomials(degree), n_basis(degree)), read-only
        ``[c, m, j]``: coefficient of monomial m (`monomial_exponents`) in component c of basis
        field j; field j is the gradient of a harmonic polynomial, so every combination is
        div- and curl-free.
    """
    return _basis(int(degree))
