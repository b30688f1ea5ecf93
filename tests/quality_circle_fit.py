"""The centre-plane value of the magnetic length, written for the tests apart from the code: the
main harmonic on the circle r = R_ref of a plane of a 3-D field, from a least-squares fit of
the plane's (B_x, B_y) by the in-plane gradient of a potential made of the 2-D multipoles
Re(c w^n), n = 1 .. 15, and the first pseudo-multipoles Re(c |w|^2 w^m), m = 0 .. 8.

The field of a real potential Phi(w, conj w) is B_x - i B_y = 2 dPhi/dw (Wirtinger
derivative), so F = B_y + i B_x = 2i dPhi/dw; the circle's coefficient of e^(i (n-1) theta) is
taken by the discrete Fourier transform of F on 64 points of the circle.
"""

from __future__ import annotations

import numpy as np

PURE, PSEUDO = 15, 8


def _f_columns(xy, scale):
    """F (k, M) of the potentials, complex, at points xy (k, 2) mm, w scaled by ``scale``."""
    w = (xy[:, 0] + 1j * xy[:, 1]) / scale
    wb = w.conj()
    cols = []
    for n in range(1, PURE + 1):  # Phi = Re(c w^n) = (c w^n + conj(c) wb^n) / 2
        for c in (1.0, 1j):
            cols.append(2j * (c * n * w ** (n - 1)) / 2)
    for m in range(PSEUDO + 1):  # Phi = w wb (c w^m + conj(c) wb^m) / 2
        for c in (1.0, 1j) if m > 0 else (1.0,):
            dphi = (wb * (c * w**m + np.conj(c) * wb**m) + w * wb * c * m * w ** max(m - 1, 0)) / 2
            cols.append(2j * dphi)
    return np.column_stack(cols)


def circle_operator(xy, r_fit, r_ref, order):
    """Row (2k,) taking [B_y at xy; B_x at xy] of a plane to its harmonic of ``order`` on the
    circle r = r_ref (complex, T)."""
    f = _f_columns(xy, r_fit)
    design = np.vstack([f.real, f.imag])  # rows: B_y = Re F, B_x = Im F
    th = 2 * np.pi * np.arange(64) / 64
    ring = _f_columns(r_ref * np.column_stack([np.cos(th), np.sin(th)]), r_fit)
    row = np.exp(-1j * (order - 1) * th) @ ring / 64
    return row @ np.linalg.pinv(design)
