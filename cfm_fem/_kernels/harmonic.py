"""Evaluation of local harmonic field models (`cfm_fem.models.harmonic_basis`).

A node's model is B(x) = sum_j coef[j] F_j(u), u = (x - x_node) / scale, with F_j the harmonic
basis fields. `expand_node` turns the coefficients into monomial coefficients per component
once per node; a point then costs the monomials of u and one multiply-add per monomial and
component, with no cell to locate (`poly_points`; the sweep's many trials per node use the
unrolled `harmonic_parts`).
"""

from __future__ import annotations

import numba as nb
import numpy as np

from .options import JIT


@nb.njit(**JIT)
def sparse_basis(gmat):
    """Non-zero entries of ``gmat`` (3, M, NB) by component, then basis field: (start of the
    entries of component c and field j at ``start[c, j]``, their monomials, their values).
    About 3 % of `field_basis`'s entries are non-zero."""
    nbf = gmat.shape[2]
    start = np.empty((3, nbf + 1), dtype=np.int64)
    count = 0
    for c in range(3):
        for j in range(nbf):
            for m in range(gmat.shape[1]):
                if gmat[c, m, j] != 0.0:
                    count += 1
    mono = np.empty(count, dtype=np.int64)
    val = np.empty(count)
    e = 0
    for c in range(3):
        start[c, 0] = e
        for j in range(nbf):
            for m in range(gmat.shape[1]):
                if gmat[c, m, j] != 0.0:
                    mono[e] = m
                    val[e] = gmat[c, m, j]
                    e += 1
            start[c, j + 1] = e
    return start, mono, val


@nb.njit(**JIT)
def expand_node(coef, n_basis, basis, n_mono, out):
    """Monomial coefficients of one node's field model.

    Parameters
    ----------
    coef : ndarray, shape (>= n_basis,), T
        Coefficients of the basis fields (`field_basis` order).
    n_basis, n_mono : int
        Basis fields and monomials of the node's degree (`n_basis`, `n_monomials`).
    basis : tuple
        `sparse_basis` of `field_basis` of the highest degree.
    out : ndarray, shape (3, >= n_mono), T
        Output: coefficient of monomial m in component c, the sum over the basis fields j of
        their entry times coef[j], added in the order of j (only the non-zero entries: the
        same sum, term by term, as over every entry).
    """
    start, mono, val = basis
    for c in range(3):
        for m in range(n_mono):
            out[c, m] = 0.0
        for j in range(n_basis):
            cj = coef[j]
            for e in range(start[c, j], start[c, j + 1]):
                m = mono[e]
                if m < n_mono:
                    out[c, m] += val[e] * cj


@nb.njit(**JIT)
def poly_points(cexp, which, exps, u, out):
    """Fields of expanded models (`expand_node`) at scaled displacements, T.

    Parameters
    ----------
    cexp : ndarray, shape (k, 3, M), T
        Monomial coefficients of k nodes' models.
    which : ndarray, shape (m,), int64
        Model of each point (row of ``cexp``).
    exps : ndarray, shape (M, 3), int64
        `monomial_exponents` of the degree of ``cexp``.
    u : ndarray, shape (m, 3)
        Scaled displacement of each point from its model's node.
    out : ndarray, shape (m, 3), T
        Output.
    """
    n_mono = cexp.shape[2]
    top = 0
    for mm in range(n_mono):
        top = max(top, exps[mm, 0], exps[mm, 1], exps[mm, 2])
    pw = np.empty((3, top + 1))
    for i in range(which.shape[0]):
        for a in range(3):
            pw[a, 0] = 1.0
            for q in range(1, top + 1):
                pw[a, q] = pw[a, q - 1] * u[i, a]
        c = cexp[which[i]]
        b0 = 0.0
        b1 = 0.0
        b2 = 0.0
        for mm in range(n_mono):
            v = pw[0, exps[mm, 0]] * pw[1, exps[mm, 1]] * pw[2, exps[mm, 2]]
            b0 += c[0, mm] * v
            b1 += c[1, mm] * v
            b2 += c[2, mm] * v
        out[i, 0] = b0
        out[i, 1] = b1
        out[i, 2] = b2
