"""Probe position errors of the coupled field Monte Carlo (paper eq. 12-14).

The errors of a block of (trial, point) pairs come from exactly the kinematics kernels
(`axis_noise_mm`, `probe_error_mm`), so the coupled model sees the same E_p samples as
`cfm-fem kinematics` for the same (seed, trial, point index). Plain-numpy twin:
`cfm_fem.models.kinematics.probe_errors_for_bench` with `point_noise`.
"""

from __future__ import annotations

import numba as nb
import numpy as np

from .htm import probe_error_mm
from .options import PJIT
from .rng import axis_noise_mm


@nb.njit(**PJIT)
def coupled_probe_errors(params, t0, q_cmd, pidx, nkey, fkey, geo, out):
    """Probe position errors E_p of trials t0..t0+m-1 at the given points, bench frame, mm.

    Parameters
    ----------
    params : ndarray, shape (m, 21)
        Error amplitudes of the trials (rows of ``kinematics.draw_error_sets``).
    t0 : int
        Trial index of ``params[0]`` (selects the noise stream of each trial).
    q_cmd : ndarray, shape (n, 3), mm
        Commanded axis positions.
    pidx : ndarray, shape (n,), int64
        Point index of each row of ``q_cmd`` in the noise stream (``axis_noise_mm``).
    nkey, fkey : uint64
        ``kinematics.noise_keys(seed)``.
    geo : KernelGeometry
        ``cfm_fem.models.kinematics.kernel_geometry(bench)``: the bench geometry of
        `probe_error_mm` and the noise model of `axis_noise_mm`.
    out : ndarray, shape (m, n, 3), mm
        Receives E_p = P_actual - P_nominal.
    """
    stack, mounts, tool = geo.stack, geo.mounts, geo.tool
    strokes, profiles = geo.strokes, geo.profiles
    sig, speed, tau_code, tau_par = geo.sig, geo.speed, geo.tau_code, geo.tau_par
    m = params.shape[0]
    n = q_cmd.shape[0]
    for t in nb.prange(m):
        dq = np.empty(3)
        e = np.empty(3)
        for i in range(n):
            axis_noise_mm(nkey, fkey, t0 + t, pidx[i], sig, speed, tau_code, tau_par, dq)
            probe_error_mm(params[t], q_cmd[i], dq, stack, mounts, tool, strokes, profiles, e)
            out[t, i, 0] = e[0]
            out[t, i, 1] = e[1]
            out[t, i, 2] = e[2]
