"""Evaluation of local harmonic field models (`cfm_fem.models.harmonic_basis`).

A node's model is B(x) = sum_j coef[j] F_j(u), u = (x - x_node) / scale, with F_j the harmonic
basis fields. `expand_node` turns the coefficients into monomial coefficients per component
once per node; a trial then costs the monomials of u and one multiply-add per monomial and
component, with no cell to locate.
"""

from __future__ import annotations

import numba as nb
import numpy as np

from .options import FJIT, JIT


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


@nb.njit(**FJIT)
def poly_errors(cexp, n_mono, exps, u, n, pw, err):
    """Field change B(u) - B(0) of an expanded model at ``n`` scaled displacements, T.

    Vectorised over the displacements: monomials one at a time, each for every trial.

    Parameters
    ----------
    cexp : ndarray, shape (3, >= n_mono), T
    n_mono : int
    exps : ndarray, shape (M, 3), int64
    u : ndarray, shape (3, >= n)
        Scaled displacements.
    n : int
    pw : ndarray, shape (3, 6, >= n)
        Work space: powers 0..5 of each coordinate.
    err : ndarray, shape (3, >= n), T
        Output.
    """
    for a in range(3):
        for t in range(n):
            pw[a, 0, t] = 1.0
        for q in range(1, 6):
            for t in range(n):
                pw[a, q, t] = pw[a, q - 1, t] * u[a, t]
    for c in range(3):
        for t in range(n):
            err[c, t] = 0.0
    for m in range(1, n_mono):
        i, j, k = exps[m, 0], exps[m, 1], exps[m, 2]
        c0, c1, c2 = cexp[0, m], cexp[1, m], cexp[2, m]
        px, py, pz = pw[0, i], pw[1, j], pw[2, k]
        for t in range(n):
            v = px[t] * py[t] * pz[t]
            err[0, t] += c0 * v
            err[1, t] += c1 * v
            err[2, t] += c2 * v


@nb.njit(**FJIT)
def poly_parts(cexp, degree, exps, u, n, pw, parts):
    """Homogeneous parts of an expanded model's field change at ``n`` displacements u.

    B(s u) - B(0) = sum_q s^q parts[q - 1] for q = 1 .. degree: the field change at any
    multiple s of u (every U_p of a sweep) from one evaluation.

    Parameters
    ----------
    cexp : ndarray, shape (3, >= n_monomials(degree)), T
    degree : int
    exps : ndarray, shape (M, 3), int64
    u : ndarray, shape (3, >= n)
    n : int
    pw : ndarray, shape (3, 6, >= n)
        Work space: powers 0..5 of each coordinate.
    parts : ndarray, shape (>= degree, 3, >= n), T
        Output.
    """
    for a in range(3):
        for t in range(n):
            pw[a, 0, t] = 1.0
        for q in range(1, degree + 1):
            for t in range(n):
                pw[a, q, t] = pw[a, q - 1, t] * u[a, t]
    m = 1
    for q in range(1, degree + 1):
        for c in range(3):
            for t in range(n):
                parts[q - 1, c, t] = 0.0
        m_end = (q + 1) * (q + 2) * (q + 3) // 6
        while m < m_end:
            i, j, k = exps[m, 0], exps[m, 1], exps[m, 2]
            c0, c1, c2 = cexp[0, m], cexp[1, m], cexp[2, m]
            px, py, pz = pw[0, i], pw[1, j], pw[2, k]
            p0, p1, p2 = parts[q - 1, 0], parts[q - 1, 1], parts[q - 1, 2]
            for t in range(n):
                v = px[t] * py[t] * pz[t]
                p0[t] += c0 * v
                p1[t] += c1 * v
                p2[t] += c2 * v
            m += 1
