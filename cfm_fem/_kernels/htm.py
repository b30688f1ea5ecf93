"""HTM chain of the bench kinematics: 21 geometric errors of the stacked axes to the probe error.

Hot loop (constant error profiles): per trial the 21 errors are common to all points, so the
chain collapses exactly (no approximation) to E = C + sum_a q_a G_a + sum_a n_a D_a, with
D_a = (product of the rotations below axis a) d_a, G_a = D_a - e_a and C the offset. The 21
numbers (C, G, D) are computed once per trial (`trial_terms`); each (point, trial) then costs 3
normals and 18 multiply-adds. Plain-numpy twin: `cfm_fem.models.kinematics.probe_errors_for_bench`.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from .options import JIT, PJIT


@nb.njit(inline="always", **JIT)
def _cos_sin(x):
    """cos x, sin x (rad): Taylor polynomials within 1 ulp for |x| <= 1/16 (bench error angles
    are ~1e-5 rad: there they equal libm's bits, at a tenth of the cost), libm beyond."""
    if abs(x) > 0.0625:
        return math.cos(x), math.sin(x)
    x2 = x * x
    c = 1.0 + x2 * (-0.5 + x2 * (1.0 / 24.0 + x2 * (-1.0 / 720.0 + x2 * (
        1.0 / 40320.0 - x2 / 3628800.0))))  # fmt: skip
    s = x + x * x2 * (-1.0 / 6.0 + x2 * (1.0 / 120.0 + x2 * (-1.0 / 5040.0 + x2 / 362880.0)))
    return c, s


@nb.njit(inline="always", **JIT)
def rotation_zyx_into(phi, theta, psi, r):
    """Paper eq. 4 into ``r`` (3, 3): Rz(psi) Ry(theta) Rx(phi)."""
    cf, sf = _cos_sin(phi)
    ct, st = _cos_sin(theta)
    cp, sp = _cos_sin(psi)
    r[0, 0] = cp * ct
    r[0, 1] = cp * sf * st - cf * sp
    r[0, 2] = sf * sp + cf * cp * st
    r[1, 0] = ct * sp
    r[1, 1] = cf * cp + sf * sp * st
    r[1, 2] = cf * sp * st - cp * sf
    r[2, 0] = -st
    r[2, 1] = ct * sf
    r[2, 2] = cf * ct


@nb.njit(inline="always", **JIT)
def _squareness_into(stack, a_xy, a_xz, a_yz, ang):
    """Zyx angles per bench axis (ang[a, :]) for the squareness convention of
    `cfm_fem.models.kinematics.chain`."""
    for a in range(3):
        for c in range(3):
            ang[a, c] = 0.0
    level = np.empty(3, np.int64)
    for j in range(3):
        level[stack[j]] = j
    for col in range(3):
        if col == 0:
            a, b, alpha = 0, 1, a_xy
        elif col == 1:
            a, b, alpha = 0, 2, a_xz
        else:
            a, b, alpha = 1, 2, a_yz
        if level[a] > level[b]:
            up, lo = a, b
        else:
            up, lo = b, a
        c = 3 - a - b
        cyclic = (up == 0 and lo == 1) or (up == 1 and lo == 2) or (up == 2 and lo == 0)
        ang[up, c] += alpha if cyclic else -alpha


@nb.njit(**JIT)
def _tilt(stack, a, a_xy, a_xz, a_yz):
    """Zyx angles (phi, theta, psi) tilting axis a's travel direction (``_squareness_into``)."""
    lx = 0
    ly = 0
    lz = 0
    for j in range(3):
        if stack[j] == 0:
            lx = j
        elif stack[j] == 1:
            ly = j
        else:
            lz = j
    ang0 = 0.0
    ang1 = 0.0
    ang2 = 0.0
    # pair (x, y) -> about z; (x, z) -> about y; (y, z) -> about x; the upper axis is tilted
    for col in range(3):
        if col == 0:
            p, q, alpha, lp, lq = 0, 1, a_xy, lx, ly
        elif col == 1:
            p, q, alpha, lp, lq = 0, 2, a_xz, lx, lz
        else:
            p, q, alpha, lp, lq = 1, 2, a_yz, ly, lz
        up, lo = (p, q) if lp > lq else (q, p)
        if up != a:
            continue
        c = 3 - p - q
        cyclic = (up == 0 and lo == 1) or (up == 1 and lo == 2) or (up == 2 and lo == 0)
        sgn = alpha if cyclic else -alpha
        if c == 0:
            ang0 += sgn
        elif c == 1:
            ang1 += sgn
        else:
            ang2 += sgn
    return ang0, ang1, ang2


@nb.njit(inline="always", **JIT)
def _rot_apply(phi, theta, psi, v0, v1, v2):
    """R(phi, theta, psi) of eq. 4 applied to (v0, v1, v2), without building the matrix."""
    cf, sf = _cos_sin(phi)
    ct, st = _cos_sin(theta)
    cp, sp = _cos_sin(psi)
    w0 = cp * ct * v0 + (cp * sf * st - cf * sp) * v1 + (sf * sp + cf * cp * st) * v2
    w1 = ct * sp * v0 + (cf * cp + sf * sp * st) * v1 + (cf * sp * st - cp * sf) * v2
    w2 = -st * v0 + ct * sf * v1 + cf * ct * v2
    return w0, w1, w2


@nb.njit(inline="always", **JIT)
def _horner(profiles, k, u):
    p = 0.0
    for c in range(profiles.shape[1] - 1, -1, -1):
        p = p * u + profiles[k, c]
    return p


@nb.njit(inline="always", **JIT)
def probe_error_mm(params, q_cmd, dq, stack, mounts, tool, strokes, profiles, out):
    """Probe position error of one (point, trial): exact HTM chain (eq. 4, 5, 8, 10), bench frame.

    Callable from the user's own ``@njit`` code, once per (node, trial).

    Parameters
    ----------
    params : ndarray, shape (21,)
        Error amplitudes of this trial (mm, rad) in ``cfm_fem.models.bench.ERROR_NAMES`` order: one
        row of ``cfm_fem.models.kinematics.geometry.draw_error_sets``.
    q_cmd : ndarray, shape (3,), mm
        Commanded positions of the x, y, z axes (``Bench.axis_positions_for``).
    dq : ndarray, shape (3,), mm
        Vibration + delay added to the commanded positions (``axis_noise_mm``), or zeros.
    stack : ndarray, shape (3,), int64
        Bench axis index (0=x, 1=y, 2=z) of bodies 1, 2, 3 from the foundation.
    mounts : ndarray, shape (3, 3), mm
        Mount offsets in stack order.
    tool : ndarray, shape (3,), mm
        Probe offset in the top carriage frame.
    strokes : ndarray, shape (3,), mm
        Strokes of the x, y, z axes (normalise the profile argument).
    profiles : ndarray, shape (21, n_coef)
        Polynomial profile coefficients of the errors.
    out : ndarray, shape (3,), mm
        Receives E = P_actual - P_nominal.
    """
    # Walk the chain from the tool down: v <- m_j + (q+n) d_j + delta_j + R_j v (no allocation:
    # this runs once per (node, trial) inside the caller's loops).
    v0 = tool[0]
    v1 = tool[1]
    v2 = tool[2]
    for jj in range(2, -1, -1):
        a = stack[jj]
        d0, d1, d2 = _travel_direction(stack, a, params)
        v0, v1, v2 = _body_step(params, q_cmd, dq, jj, a, d0, d1, d2, mounts, strokes, profiles,
                                v0, v1, v2)  # fmt: skip
    _minus_nominal(v0, v1, v2, q_cmd, mounts, tool, out)


@nb.njit(inline="always", **JIT)
def _travel_direction(stack, a, params):
    """Travel direction of axis a, tilted by the squareness errors params[18:21] (unit vector)."""
    t0, t1, t2 = _tilt(stack, a, params[18], params[19], params[20])
    return _rot_apply(
        t0, t1, t2, 1.0 if a == 0 else 0.0, 1.0 if a == 1 else 0.0, 1.0 if a == 2 else 0.0
    )


@nb.njit(inline="always", **JIT)
def _body_step(params, q_cmd, dq, jj, a, d0, d1, d2, mounts, strokes, profiles, v0, v1, v2):
    """One body of the chain: m_j + (q + n) d_j + delta_j(q) + R_j(q) v, for body jj (axis a,
    travel direction d)."""
    base = 6 * a
    u = q_cmd[a] / strokes[a]
    ex = params[base + 3] * _horner(profiles, base + 3, u)
    ey = params[base + 4] * _horner(profiles, base + 4, u)
    ez = params[base + 5] * _horner(profiles, base + 5, u)
    w0, w1, w2 = _rot_apply(ex, ey, ez, v0, v1, v2)
    s = q_cmd[a] + dq[a]
    return (
        mounts[jj, 0] + s * d0 + params[base] * _horner(profiles, base, u) + w0,
        mounts[jj, 1] + s * d1 + params[base + 1] * _horner(profiles, base + 1, u) + w1,
        mounts[jj, 2] + s * d2 + params[base + 2] * _horner(profiles, base + 2, u) + w2,
    )


@nb.njit(inline="always", **JIT)
def _minus_nominal(v0, v1, v2, q_cmd, mounts, tool, out):
    """out = the probe position v minus the nominal one (mounts + q + tool)."""
    out[0] = v0 - (mounts[0, 0] + mounts[1, 0] + mounts[2, 0] + q_cmd[0] + tool[0])
    out[1] = v1 - (mounts[0, 1] + mounts[1, 1] + mounts[2, 1] + q_cmd[1] + tool[1])
    out[2] = v2 - (mounts[0, 2] + mounts[1, 2] + mounts[2, 2] + q_cmd[2] + tool[2])


@nb.njit(inline="always", **JIT)
def _probe_error_directed(params, q_cmd, dq, dirs, stack, mounts, tool, strokes, profiles, out):
    """`probe_error_mm` with the trial's travel directions given (dirs (9,): axis a's at
    3a .. 3a+2, `trial_directions`): the same numbers, without recomputing them per point."""
    v0 = tool[0]
    v1 = tool[1]
    v2 = tool[2]
    for jj in range(2, -1, -1):
        a = stack[jj]
        v0, v1, v2 = _body_step(params, q_cmd, dq, jj, a, dirs[3 * a], dirs[3 * a + 1],
                                dirs[3 * a + 2], mounts, strokes, profiles, v0, v1, v2)  # fmt: skip
    _minus_nominal(v0, v1, v2, q_cmd, mounts, tool, out)


@nb.njit(**PJIT)
def trial_directions(params, stack, out):
    """Travel directions of the x, y, z axes of each trial (``_travel_direction``) into out
    (m, 9): axis a's at 3a .. 3a+2."""
    for t in nb.prange(params.shape[0]):
        for a in range(3):
            out[t, 3 * a], out[t, 3 * a + 1], out[t, 3 * a + 2] = _travel_direction(
                stack, a, params[t]
            )


@nb.njit(**PJIT)
def trial_terms(params, stack, mounts, tool, out):
    """Per-trial constants of the collapsed chain (constant profiles only), into out (m, 21).

    out[t] = (C, G_x, G_y, G_z, D_x, D_y, D_z) with E = C + sum_a q_a G_a + sum_a n_a D_a exactly
    (module docstring). Same math as ``probe_error_mm``.
    """
    m = params.shape[0]
    nchunk = 64  # fixed layout: scratch arrays once per chunk, not per trial
    per = (m + nchunk - 1) // nchunk
    for ch in nb.prange(nchunk):
        r = np.empty((3, 3))
        rs = np.empty((3, 3))
        a_acc = np.empty((3, 3))
        tmp = np.empty((3, 3))
        ang = np.empty((3, 3))
        cc = np.empty(3)
        for t in range(ch * per, min(m, (ch + 1) * per)):
            p = params[t]
            for i in range(3):
                cc[i] = 0.0
                for k in range(3):
                    a_acc[i, k] = 1.0 if i == k else 0.0
            _squareness_into(stack, p[18], p[19], p[20], ang)
            for j in range(3):
                a = stack[j]
                base = 6 * a
                rotation_zyx_into(ang[a, 0], ang[a, 1], ang[a, 2], rs)
                # D_a = A_j d_a (A_j: product of the error rotations below body j)
                for i in range(3):
                    d = a_acc[i, 0] * rs[0, a] + a_acc[i, 1] * rs[1, a] + a_acc[i, 2] * rs[2, a]
                    out[t, 12 + 3 * a + i] = d
                    out[t, 3 + 3 * a + i] = d - (1.0 if i == a else 0.0)
                # C += A_j (m_j + delta_j) - m_j
                v0 = mounts[j, 0] + p[base]
                v1 = mounts[j, 1] + p[base + 1]
                v2 = mounts[j, 2] + p[base + 2]
                for i in range(3):
                    cc[i] += a_acc[i, 0] * v0 + a_acc[i, 1] * v1 + a_acc[i, 2] * v2 - mounts[j, i]
                rotation_zyx_into(p[base + 3], p[base + 4], p[base + 5], r)
                for i in range(3):
                    for k in range(3):
                        tmp[i, k] = (
                            a_acc[i, 0] * r[0, k] + a_acc[i, 1] * r[1, k] + a_acc[i, 2] * r[2, k]
                        )
                for i in range(3):
                    for k in range(3):
                        a_acc[i, k] = tmp[i, k]
            # the tool through all three rotations, minus the nominal tool
            for i in range(3):
                out[t, i] = (
                    cc[i]
                    + a_acc[i, 0] * tool[0]
                    + a_acc[i, 1] * tool[1]
                    + a_acc[i, 2] * tool[2]
                    - tool[i]
                )
