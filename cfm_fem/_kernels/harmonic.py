"""Evaluation of local harmonic field models (`cfm_fem.models.harmonic_basis`).

A node's model is B(x) = sum_j coef[j] F_j(u), u = (x - x_node) / scale, with F_j the harmonic
basis fields. `expand_node` turns the coefficients into monomial coefficients per component
once per node; a trial then costs the monomials of u and one multiply-add per monomial and
component, with no cell to locate.
"""

from __future__ import annotations

import numba as nb
import numpy as np

from .options import JIT


@nb.njit(**JIT)
def expand_node(coef, n_basis, gmat, n_mono, out):
    """Monomial coefficients of one node's field model.

    Parameters
    ----------
    coef : ndarray, shape (>= n_basis,), T
        Coefficients of the basis fields (`field_basis` order).
    n_basis, n_mono : int
        Basis fields and monomials of the node's degree (`n_basis`, `n_monomials`).
    gmat : ndarray, shape (3, M, NB)
        `field_basis` of the highest degree.
    out : ndarray, shape (3, >= n_mono), T
        Output: coefficient of monomial m in component c.
    """
    for c in range(3):
        for m in range(n_mono):
            s = 0.0
            for j in range(n_basis):
                s += gmat[c, m, j] * coef[j]
            out[c, m] = s


@nb.njit(inline="always", **JIT)
def poly_field(cexp, n_mono, exps, u0, u1, u2):
    """Field of an expanded model (`expand_node`) at one scaled displacement u, T.

    ``exps``: `monomial_exponents` of the highest degree, shape (M, 3), int64.
    Returns (B_x, B_y, B_z).
    """
    px = np.empty(6)
    py = np.empty(6)
    pz = np.empty(6)
    px[0] = py[0] = pz[0] = 1.0
    for q in range(1, 6):
        px[q] = px[q - 1] * u0
        py[q] = py[q - 1] * u1
        pz[q] = pz[q - 1] * u2
    b0 = 0.0
    b1 = 0.0
    b2 = 0.0
    for m in range(n_mono):
        v = px[exps[m, 0]] * py[exps[m, 1]] * pz[exps[m, 2]]
        b0 += cexp[0, m] * v
        b1 += cexp[1, m] * v
        b2 += cexp[2, m] * v
    return b0, b1, b2
