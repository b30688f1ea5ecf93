"""Finite-difference derivatives of a reference field: gradient, Hessian, third derivatives.

A Hall map's model expands the reference about each reading (the bench's move of the probe,
the magnet's pose): these are the derivatives it takes, by central differences over a step of
the caller's choosing (a reference map's node spacing reads node values only).
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "field_jacobian",
    "field_hessian_diag",
    "field_hessian",
    "field_third",
    "field_derivatives",
    "debiased_jacobian",
]


def field_jacobian(f, p, h: float = 0.5) -> np.ndarray:
    """Finite-difference Jacobian dB_i/dx_j of a field function, shape (n, 3, 3), T/mm.

    Central differences; one-sided ones at points on the border of a reference map, where one
    neighbour lies outside it (``f`` gives NaN there); 0 where neither neighbour is inside.
    """
    b0 = None
    out = np.empty((len(p), 3, 3))
    for j in range(3):
        e = np.zeros(3)
        e[j] = h
        fp, fm = f(p + e), f(p - e)
        d = (fp - fm) / (2 * h)
        bad = ~np.isfinite(d).all(1)
        if bad.any():
            b0 = f(p) if b0 is None else b0
            fwd = (fp - b0) / h
            bwd = (b0 - fm) / h
            ok_f = np.isfinite(fwd).all(1)
            d[bad] = np.where(ok_f[bad, None], fwd[bad], bwd[bad])
            d[~np.isfinite(d).all(1)] = 0.0
        out[:, :, j] = d
    return out


def field_hessian_diag(f, p, h: float = 1.0) -> np.ndarray:
    """d^2 B_i / dx_j^2 by fourth-order central differences, shape (n, 3, 3) [i, j], T/mm^2.

    Five-point stencil: exact for fields polynomial up to degree 5 along each axis, so the
    Laplace identity sum_j d^2 B_i / dx_j^2 = 0 of a harmonic reference holds to rounding (the
    averaging signatures rely on it)."""
    b0 = f(p)
    out = np.empty((len(p), 3, 3))
    for j in range(3):
        e = np.zeros(3)
        e[j] = h
        out[:, :, j] = (-f(p + 2 * e) + 16 * f(p + e) - 30 * b0 + 16 * f(p - e) - f(p - 2 * e)) / (
            12 * h**2
        )
    return out


def field_hessian(f, p, h: float = 0.5) -> np.ndarray:
    """d^2 B_i / dx_j dx_k by central differences of step ``h``, shape (n, 3, 3, 3), T/mm^2.

    Only the points p + h (+-e_j +-e_k) are used: on a map with nodes h either side of each
    point the second differences read node values only. Where a neighbour lies outside a map
    (NaN), the entry is 0."""
    b0 = f(p)
    out = np.zeros((len(p), 3, 3, 3))
    eye = np.eye(3) * h
    for j in range(3):
        out[:, :, j, j] = (f(p + eye[j]) - 2.0 * b0 + f(p - eye[j])) / h**2
        for k in range(j + 1, 3):
            d = (
                f(p + eye[j] + eye[k])
                - f(p + eye[j] - eye[k])
                - f(p - eye[j] + eye[k])
                + f(p - eye[j] - eye[k])
            ) / (4.0 * h**2)
            out[:, :, j, k] = out[:, :, k, j] = d
    out[~np.isfinite(out)] = 0.0
    return out


def field_third(f, p, h: float = 0.5) -> np.ndarray:
    """d^3 B_i / dx_j dx_k dx_l by central differences of step ``h``, shape (n, 3, 3, 3, 3),
    T/mm^3 (:func:`field_derivatives`)."""
    return field_derivatives(f, p, h)[1]


def field_derivatives(f, p, h: float = 0.5):
    """The Hessian (n, 3, 3, 3) T/mm^2 and third derivatives (n, 3, 3, 3, 3) T/mm^3 of ``f``
    at ``p`` by central differences of step ``h``, from 33 evaluations of ``f``.

    The Hessian is :func:`field_hessian`'s (points p + h (+-e_j +-e_k)); the third
    derivatives add p +- 2 h e_j and p + h (+-e_x +-e_y +-e_z): on a map with nodes h apart
    around each point all are nodes. Where a neighbour lies outside a map (NaN), the entry is
    0."""
    memo = {}

    def at(*off):
        key = tuple(int(v) for v in np.sum(off, axis=0)) if off else (0, 0, 0)
        if key not in memo:
            memo[key] = f(p + h * np.asarray(key, dtype=float))
        return memo[key]

    e = [np.eye(3, dtype=int)[j] for j in range(3)]
    n = len(p)
    H = np.zeros((n, 3, 3, 3))
    T = np.zeros((n, 3, 3, 3, 3))
    b0 = at()
    for j in range(3):
        H[:, :, j, j] = (at(e[j]) - 2.0 * b0 + at(-e[j])) / h**2
        T[:, :, j, j, j] = (at(2 * e[j]) - 2.0 * at(e[j]) + 2.0 * at(-e[j]) - at(-2 * e[j])) / (
            2.0 * h**3
        )
        for k in range(3):
            if k == j:
                continue
            if k > j:
                d = (at(e[j], e[k]) - at(e[j], -e[k]) - at(-e[j], e[k]) + at(-e[j], -e[k])) / (
                    4.0 * h**2
                )
                H[:, :, j, k] = H[:, :, k, j] = d
            # d/dx_k of the second difference along x_j
            up = at(e[j], e[k]) - 2.0 * at(e[k]) + at(-e[j], e[k])
            dn = at(e[j], -e[k]) - 2.0 * at(-e[k]) + at(-e[j], -e[k])
            d3 = (up - dn) / (2.0 * h**3)
            for idx in ((j, j, k), (j, k, j), (k, j, j)):
                T[:, :, idx[0], idx[1], idx[2]] = d3
    acc = 0.0
    for sx in (1, -1):
        for sy in (1, -1):
            for sz in (1, -1):
                acc = acc + sx * sy * sz * at(sx * e[0], sy * e[1], sz * e[2])
    d3 = acc / (8.0 * h**3)
    for idx in ((0, 1, 2), (0, 2, 1), (1, 0, 2), (1, 2, 0), (2, 0, 1), (2, 1, 0)):
        T[:, :, idx[0], idx[1], idx[2]] = d3
    H[~np.isfinite(H)] = 0.0
    T[~np.isfinite(T)] = 0.0
    return H, T


def debiased_jacobian(f, p, h, T=None):
    """The gradient (n, 3, 3) T/mm of ``f`` at ``p`` by central differences of step ``h``,
    less their leading error h^2 / 6 d^3 B_i / dx_j^3 when the third derivatives ``T``
    (n, 3, 3, 3, 3) T/mm^3 are known. On an octupole's axis the gradient vanishes while a
    difference quotient reads k h^2 (B = k x^3): times a move of a hundred um, several uT."""
    G = field_jacobian(f, p, h)
    if T is None:
        return G
    return G - h**2 / 6.0 * np.einsum("nijjj->nij", T)
