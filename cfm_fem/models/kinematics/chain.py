"""Exact HTM chain of the bench in plain numpy (paper eq. 1-10): errors to probe positions.

Full rotation matrices (eq. 4, no small-angle shortcut), 4x4 HTMs (eq. 2) multiplied along the
chain (eq. 5), the probe error as actual minus nominal probe position (eq. 8) with vibration and
reading delay added to the commanded positions (eq. 10). The numba kernels in
`cfm_fem._kernels.htm` use the same math and are tested against it.

Chain. Body j (j = 1, 2, 3 from the foundation) is the carriage of axis ``stack[j]``; with
commanded travel q_j, axis-position noise n_j, error values delta_j, eps_j (both evaluated at the
commanded q_j, as in eq. 10) and travel direction d_j::

    M_{j-1,j} = Trans(m_j + (q_j + n_j) d_j + delta_j) . Rot(eps_j)
    P_actual  = M_{0,1} M_{1,2} M_{2,3} [tool; 1]
    P_nominal = m_1 + m_2 + m_3 + q + tool          (M* = pure translations)
    E         = P_actual - P_nominal                (bench frame, mm)

Squareness. ``alpha_ab`` tilts the travel direction of the upper of the two axes a, b (the one
stacked later) towards the positive direction of the other, by a rotation about the third axis;
``alpha_ab > 0`` means the two travel directions make an angle of 90 deg - alpha_ab. The
foundation axis defines the bench frame and has no squareness term.
"""

from __future__ import annotations

import numpy as np

from ..bench import AXES, ERROR_NAMES, Bench
from ..rotations import htm, rotation_zyx

_I = {name: k for k, name in enumerate(ERROR_NAMES)}


def squareness_angles(stack, alphas) -> np.ndarray:
    """Zyx angles that tilt each axis' travel direction (module docstring convention).

    Parameters
    ----------
    stack : sequence of int, shape (3,)
        Bench axis index (0=x, 1=y, 2=z) of bodies 1, 2, 3.
    alphas : ndarray, shape (..., 3), rad
        (alpha_xy, alpha_xz, alpha_yz).

    Returns
    -------
    ndarray, shape (..., 3, 3)
        ``[..., a, :]`` = (phi, theta, psi) of bench axis a.
    """
    alphas = np.asarray(alphas, dtype=np.float64)
    out = np.zeros(alphas.shape[:-1] + (3, 3))
    level = {int(a): j for j, a in enumerate(stack)}
    for col, (a, b) in enumerate(((0, 1), (0, 2), (1, 2))):
        upper, lower = (a, b) if level[a] > level[b] else (b, a)
        c = 3 - a - b
        cyclic = (upper, lower, c) in ((0, 1, 2), (1, 2, 0), (2, 0, 1))
        out[..., upper, c] += (1.0 if cyclic else -1.0) * alphas[..., col]
    return out


def travel_directions(stack, alphas) -> np.ndarray:
    """Unit travel direction of each bench axis, shape (..., 3 axes, 3), in its parent frame."""
    ang = squareness_angles(stack, alphas)
    r = rotation_zyx(ang[..., 0], ang[..., 1], ang[..., 2])  # (..., 3, 3, 3)
    return np.stack([r[..., a, :, a] for a in range(3)], axis=-2)


def error_values(params, q_cmd, strokes, profiles) -> np.ndarray:
    """Values of the 21 errors at the commanded positions: amplitude x profile(q / stroke).

    Parameters
    ----------
    params : ndarray, shape (m, 21)
        Amplitudes (mm, rad) in ``ERROR_NAMES`` order.
    q_cmd : ndarray, shape (n, 3), mm
    strokes : ndarray, shape (3,), mm
    profiles : ndarray, shape (21, n_coef)

    Returns
    -------
    ndarray, shape (m, n, 21)
    """
    params = np.atleast_2d(np.asarray(params, dtype=np.float64))
    q = np.atleast_2d(np.asarray(q_cmd, dtype=np.float64))
    profiles = np.asarray(profiles, dtype=np.float64)
    u = q / np.asarray(strokes, dtype=np.float64)  # (n, 3)
    axis_of_error = np.array([AXES.index(n[-2]) if "(" in n else 0 for n in ERROR_NAMES])
    uk = u[:, axis_of_error]  # (n, 21)
    p = np.zeros_like(uk)
    for c in profiles.T[::-1]:  # Horner
        p = p * uk + c
    return params[:, None, :] * p[None, :, :]


def probe_positions(params, q_cmd, dq, stack, mounts, tool, strokes, profiles) -> np.ndarray:
    """Actual probe position P_r by the HTM chain (eq. 5, 10), bench frame.

    Parameters
    ----------
    params : ndarray, shape (m, 21)
        Error amplitudes per trial (mm, rad).
    q_cmd : ndarray, shape (n, 3), mm
        Commanded positions of the x, y, z axes.
    dq : ndarray, shape (m, n, 3) or broadcastable, mm
        Vibration + reading delay added to the commanded positions (eq. 10).
    stack : sequence of int, shape (3,)
    mounts : ndarray, shape (3, 3), mm
        Mount offsets in stack order.
    tool : ndarray, shape (3,), mm
    strokes : ndarray, shape (3,), mm
    profiles : ndarray, shape (21, n_coef)

    Returns
    -------
    ndarray, shape (m, n, 3), mm
    """
    params = np.atleast_2d(np.asarray(params, dtype=np.float64))
    q = np.atleast_2d(np.asarray(q_cmd, dtype=np.float64))
    m, n = params.shape[0], q.shape[0]
    dq = np.broadcast_to(np.asarray(dq, dtype=np.float64), (m, n, 3))
    ev = error_values(params, q, strokes, profiles)  # (m, n, 21)
    dirs = travel_directions(stack, params[:, 18:21])  # (m, 3, 3)
    chain = np.broadcast_to(np.eye(4), (m, n, 4, 4))
    for j, a in enumerate(stack):
        base = 6 * int(a)
        delta = ev[..., base : base + 3]
        eps = ev[..., base + 3 : base + 6]
        rot = rotation_zyx(eps[..., 0], eps[..., 1], eps[..., 2])
        travel = (q[None, :, a] + dq[..., a])[..., None] * dirs[:, None, a, :]
        chain = chain @ htm(rot, mounts[j] + travel + delta)
    tool_h = np.append(np.asarray(tool, dtype=np.float64), 1.0)
    return (chain @ tool_h)[..., :3]


def probe_errors(params, q_cmd, dq, stack, mounts, tool, strokes, profiles) -> np.ndarray:
    """Probe position error E = P_actual - P_nominal (eq. 8, 10), shape (m, n, 3), mm.

    Arguments as :func:`probe_positions`.
    """
    q = np.atleast_2d(np.asarray(q_cmd, dtype=np.float64))
    nominal = q + np.asarray(mounts, dtype=np.float64).sum(0) + np.asarray(tool, dtype=np.float64)
    return probe_positions(params, q, dq, stack, mounts, tool, strokes, profiles) - nominal


def probe_errors_for_bench(bench: Bench, params, q_cmd, dq=0.0) -> np.ndarray:
    """:func:`probe_errors` with the geometry taken from ``bench``; shape (m, n, 3), mm."""
    return probe_errors(
        params,
        q_cmd,
        dq,
        bench.stack_indices,
        bench.mounts_mm,
        bench.tool_offset_mm,
        bench.strokes_mm,
        bench.profiles,
    )


def sensitivities(bench: Bench, q_cmd, at=None, rel_step: float = 1e-3) -> np.ndarray:
    """Sensitivity coefficients dE/dX_k of the exact model (central differences).

    Parameters
    ----------
    bench : Bench
    q_cmd : ndarray, shape (n, 3), mm
    at : ndarray, shape (21,), optional
        Expansion point (mm, rad); default the means of the error PDFs.
    rel_step : float
        Step as a fraction of each error's std (absolute 1e-9 mm/rad when the std is 0).
        The model is a product of rotations, nearly linear at these scales, so the central
        difference is accurate to ~step**2 relative.

    Returns
    -------
    ndarray, shape (n, 3, 21)
        mm per mm (translations) and mm per rad (angles).
    """
    x0 = bench.error_means() if at is None else np.asarray(at, dtype=np.float64)
    h = np.where(bench.error_stds() > 0, bench.error_stds() * rel_step, 1e-9)
    k = len(x0)
    pts = np.vstack([x0 + np.diag(h), x0 - np.diag(h)])  # (2k, 21)
    e = probe_errors_for_bench(bench, pts, q_cmd)  # (2k, n, 3)
    return np.moveaxis((e[:k] - e[k:]) / (2.0 * h)[:, None, None], 0, -1)
