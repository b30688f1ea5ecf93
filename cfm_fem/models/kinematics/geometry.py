"""The seam between the bench model and the kernels: kernel geometry, error sets, noise keys.

``draw_error_sets`` gives the per-trial error amplitudes from the seed alone; ``kernel_geometry``
and ``noise_keys`` give the arguments of the njit functions ``_kernels.probe_error_mm`` and
``axis_noise_mm``, so every workflow sees the same probe errors for the same (seed, trial,
point index).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from ... import _kernels as K
from ...errors import check_seed
from ..bench import ERROR_NAMES, Bench


class KernelGeometry(NamedTuple):
    """Bench arrays in the layout the numba kernels take (``kernel_geometry``), a named tuple
    the kernels receive whole (`_kernels.coupled_probe_errors`, `_kernels.htm_sweep`).

    Attributes
    ----------
    stack : ndarray, shape (3,), int64
        Bench axis index (0=x, 1=y, 2=z) of bodies 1, 2, 3 from the foundation.
    mounts : ndarray, shape (3, 3), mm
        Mount offsets in stack order.
    tool : ndarray, shape (3,), mm
        Probe offset in the top carriage frame.
    strokes : ndarray, shape (3,), mm
    profiles : ndarray, shape (21, n_coef)
    codes, pars : ndarray, shape (21,) int64 and (21, 4)
        Kernel PDF codes and parameters of the error amplitudes (mm, rad).
    sig : ndarray, shape (3,), mm
        Normal std of the axis-position noise (vibration, and the delay when it is normal).
    speed : ndarray, shape (3,), mm/s
        Speeds of the eq. 9 delay (zeros when the delay is normal).
    tau_code : int
        PDF code of tau, or -1.
    tau_par : ndarray, shape (4,)
    linear : bool
        True when all profiles are constant: the per-trial collapsed chain applies.
    """

    stack: np.ndarray
    mounts: np.ndarray
    tool: np.ndarray
    strokes: np.ndarray
    profiles: np.ndarray
    codes: np.ndarray
    pars: np.ndarray
    sig: np.ndarray
    speed: np.ndarray
    tau_code: int
    tau_par: np.ndarray
    linear: bool


def kernel_geometry(bench: Bench) -> KernelGeometry:
    """Arrays of ``bench`` for the kernels (and for the user's own ``@njit`` code)."""
    codes, pars = zip(*(e.pdf.kernel_code() for e in bench.errors), strict=True)
    if bench.delay.model == "speed_tau":
        tau_code, tau_par = bench.delay.tau_pdf.kernel_code()
        speed = np.asarray(bench.delay.speed_mm_s, dtype=np.float64)
    else:
        tau_code, tau_par, speed = -1, np.zeros(4), np.zeros(3)
    return KernelGeometry(
        stack=bench.stack_indices,
        mounts=np.ascontiguousarray(bench.mounts_mm),
        tool=np.asarray(bench.tool_offset_mm, dtype=np.float64),
        strokes=bench.strokes_mm,
        profiles=np.ascontiguousarray(bench.profiles),
        codes=np.array(codes, dtype=np.int64),
        pars=np.ascontiguousarray(np.array(pars, dtype=np.float64)),
        sig=bench.noise_std_mm(),
        speed=speed,
        tau_code=int(tau_code),
        tau_par=np.asarray(tau_par, dtype=np.float64),
        linear=not bench.position_dependent,
    )


def _keys(seed: int):
    check_seed(seed)  # the one seed rule and message of every command and of the API
    s = np.uint64(int(seed))
    # numba boxes uint64 results as Python ints; keep them uint64 for the kernels
    return tuple(
        np.uint64(int(K.stream_key(s, st)))
        for st in (K.STREAM_ERRORS, K.STREAM_NOISE, K.STREAM_FALLBACK)
    )


def noise_keys(seed: int) -> tuple[np.uint64, np.uint64]:
    """Stream keys (nkey, fkey) of the per-point noise for ``seed``: the first two arguments of
    ``_kernels.axis_noise_mm``, so user kernels draw the same noise as kinematics."""
    _, nkey, fkey = _keys(seed)
    return nkey, fkey


def draw_error_sets(bench: Bench, n_trials: int, seed: int, start: int = 0) -> np.ndarray:
    """The error amplitudes of trials ``start .. start+n_trials-1``: one row per trial.

    Reproducible from ``seed`` alone: row t depends only on (seed, t), not on threads, on
    ``start`` or on how the trials are split, so ``draw_error_sets(b, 10, s)[5:]`` equals
    ``draw_error_sets(b, 5, s, start=5)``.

    Parameters
    ----------
    bench : Bench
    n_trials : int
    seed : int in [0, 2**63)
    start : int
        Index of the first trial.

    Returns
    -------
    ndarray, shape (n_trials, 21), float64
        Columns in ``cfm_fem.models.bench.ERROR_NAMES`` order; translations in mm, angles in rad
        (amplitudes: an error's value at axis position q is amplitude x profile(q / stroke)).
    """
    g = kernel_geometry(bench)
    ekey, _, _ = _keys(seed)
    out = np.empty((int(n_trials), len(ERROR_NAMES)))
    K.draw_error_params(ekey, int(start), int(n_trials), g.codes, g.pars, out)
    return out


def point_noise(bench: Bench, trial: int, points, seed: int) -> np.ndarray:
    """Axis-position noise (vibration + delay) of trial ``trial`` at point indices ``points``.

    Returns
    -------
    ndarray, shape (len(points), 3), mm
        The same numbers the Monte Carlo kernels use for (seed, trial, point).
    """
    g = kernel_geometry(bench)
    _, nkey, fkey = _keys(seed)
    out = np.empty((len(points), 3))
    for r, i in enumerate(points):
        K.axis_noise_mm(
            nkey, fkey, int(trial), int(i), g.sig, g.speed, g.tau_code, g.tau_par, out[r]
        )
    return out
