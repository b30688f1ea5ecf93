"""Bounds of a node's field polynomial over a ball: how far a trial's change can stray from its
first-order part, which decides the candidates of the tail statistics (`harmonic_stats`).

A tighter bound leaves fewer candidates to sort at each U_p, and sends fewer nodes to the
whole-sample statistics; either way the statistics are exact. Per degree q and component c,
|part_q,c(u)| <= b[q - 1, c] |u|^q with

- q = 2: the largest |eigenvalue| of the quadratic form's symmetric matrix (exact: the bound is
  reached on the sphere);
- otherwise: the Bombieri norm sqrt(sum_a c_a^2 a! / q!) over the monomials u^a of degree q
  (Cauchy-Schwarz against sum_a q! / a! u^(2a) = |u|^(2q)), at most the coefficients' root sum
  of squares.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from .options import JIT

#: Relative safety on the bounds (rounding).
BOUND_SAFETY = 1e-6


@nb.njit(**JIT)
def inverse_multinomials(exps):
    """a! / q! per monomial (exponents ``exps`` (M, 3) int64, q = their sum), shape (M,)."""
    out = np.empty(exps.shape[0])
    for m in range(exps.shape[0]):
        a, b, c = exps[m, 0], exps[m, 1], exps[m, 2]
        out[m] = (
            math.gamma(a + 1.0)
            * math.gamma(b + 1.0)
            * math.gamma(c + 1.0)
            / math.gamma(a + b + c + 1.0)
        )
    return out


@nb.njit(**JIT)
def symmetric3_norm(a00, a01, a02, a11, a12, a22):
    """Largest |eigenvalue| of the symmetric 3 x 3 matrix [[a00, a01, a02], [., a11, a12],
    [., ., a22]], in closed form (trigonometric solution of the characteristic cubic)."""
    q = (a00 + a11 + a22) / 3.0
    b00 = a00 - q
    b11 = a11 - q
    b22 = a22 - q
    off = a01 * a01 + a02 * a02 + a12 * a12
    p2 = b00 * b00 + b11 * b11 + b22 * b22 + 2.0 * off
    if p2 == 0.0:
        return abs(q)
    p = math.sqrt(p2 / 6.0)
    det = (
        b00 * (b11 * b22 - a12 * a12)
        - a01 * (a01 * b22 - a12 * a02)
        + a02 * (a01 * a12 - b11 * a02)
    )
    r = min(max(det / (2.0 * p * p * p), -1.0), 1.0)
    phi = math.acos(r) / 3.0
    e_max = q + 2.0 * p * math.cos(phi)
    e_min = q + 2.0 * p * math.cos(phi + 2.0 * math.pi / 3.0)
    return max(abs(e_max), abs(e_min))


@nb.njit(**JIT)
def degree_bounds(cexp, exps, inv_multi, max_deg, out):
    """Per degree q = 1 .. ``max_deg`` and component c, ``out[q - 1, c]`` with
    |part_q,c(u)| <= out[q - 1, c] |u|^q for every u (see the module docstring).

    Parameters
    ----------
    cexp : ndarray, shape (3, M), T
        Monomial coefficients (`expand_node`), graded order: degree q at
        [(q (q+1) (q+2)) / 6, ((q+1) (q+2) (q+3)) / 6).
    exps : ndarray, shape (M, 3), int64
        Their exponents (`monomial_exponents`).
    inv_multi : ndarray, shape (M,)
        `inverse_multinomials` of ``exps``.
    max_deg : int
    out : ndarray, shape (>= max_deg, 3)
        Output, T per unit |u|^q; inflated by `BOUND_SAFETY` against rounding.
    """
    m = 1
    for q in range(1, max_deg + 1):
        m_end = (q + 1) * (q + 2) * (q + 3) // 6
        for c in range(3):
            if q == 2:
                a = np.zeros((3, 3))
                for mm in range(m, m_end):
                    i = -1
                    j = -1
                    for ax in range(3):
                        for _ in range(exps[mm, ax]):
                            if i < 0:
                                i = ax
                            else:
                                j = ax
                    if i == j:
                        a[i, i] += cexp[c, mm]
                    else:
                        a[i, j] += 0.5 * cexp[c, mm]
                        a[j, i] += 0.5 * cexp[c, mm]
                b = symmetric3_norm(a[0, 0], a[0, 1], a[0, 2], a[1, 1], a[1, 2], a[2, 2])
            else:
                s = 0.0
                for mm in range(m, m_end):
                    s += cexp[c, mm] ** 2 * inv_multi[mm]
                b = math.sqrt(s)
            out[q - 1, c] = b * (1.0 + BOUND_SAFETY)
        m = m_end


@nb.njit(**JIT)
def remainder_bounds(s, rho, bnd, max_deg, b_hat, abs0, bounds):
    """Bounds of |change / s - first-order part| over every trial at U_p = s.

    Parameters
    ----------
    s : float, mm
    rho : float
        The largest scaled displacement |u| of the trials.
    bnd : ndarray, shape (>= max_deg, 3)
        `degree_bounds`.
    max_deg : int
    b_hat : ndarray, shape (3,)
        Unit vector of the field at the node (zero where it vanishes).
    abs0 : float
        |B| at the node, T.
    bounds : ndarray, shape (4,)
        Output: the components', and |B|'s (inf where none holds).
    """
    e2 = 0.0
    mix = 0.0
    for c in range(3):
        d = 0.0
        sq = rho
        for q in range(1, max_deg):
            sq *= s * rho
            d += sq * bnd[q, c]
        bounds[c] = d
        e2 += (bnd[0, c] * rho + d) ** 2
        mix += abs(b_hat[c]) * d
    # 0 <= |B0 + d| - |B0| - b.d <= |d|^2 / (2 (|B0| - |d|)) for |d| < |B0|, d = s e
    e = math.sqrt(e2)
    gap = abs0 - s * e
    bounds[3] = mix + s * e2 / (2.0 * gap) if gap > 0.0 else np.inf


__all__ = [
    "BOUND_SAFETY",
    "degree_bounds",
    "inverse_multinomials",
    "remainder_bounds",
    "symmetric3_norm",
]
