"""Sweeps with the local harmonic field model: no cell location, one polynomial per node.

Each node's model (`cfm_fem.models.harmonic`) is expanded into monomial coefficients once
(`expand_node`); every trial is then the polynomial at its scaled displacement. A trial
displaced beyond the node's reach is counted as outside (left out, or kept with
``extrapolate``: the polynomial beyond the data that support it).
"""

from __future__ import annotations

import numba as nb
import numpy as np

from .harmonic import expand_node, poly_errors, poly_parts
from .htm_sweep import _position_moments, _probe_points, htm_buffers
from .options import JIT
from .order_stats import coverage_count, sample_stats
from .rng import (
    STREAM_FALLBACK,
    STREAM_SWEEP,
    normals_by_index,
    normals_by_key,
    stream_key,
    trial_key,
)
from .sweep import _abs_change, _unit_disp, sweep_outputs


@nb.njit(inline="always", **JIT)
def _node_model(g, hcoef, hdeg, gmat, cexp):
    """Expand node g's model into ``cexp``; returns the number of monomials."""
    deg = hdeg[g]
    n_mono = (deg + 1) * (deg + 2) * (deg + 3) // 6
    expand_node(hcoef[g], (deg + 1) * (deg + 3), gmat, n_mono, cexp)
    return n_mono


@nb.njit(inline="always", **JIT)
def _stats_of_errors(n, d2, reach2, extrapolate, b0, err, absb, scratch, p, out, n_out_k):
    """Statistics of the field changes ``err`` (3, n) into ``out`` (4, 6); trials whose squared
    displacement ``d2`` exceeds ``reach2`` are counted in ``n_out_k[0]`` and left out unless
    ``extrapolate``. ``b0``: the model's field at the node."""
    abs0 = np.sqrt(b0[0] ** 2 + b0[1] ** 2 + b0[2] ** 2)
    n_beyond = 0
    for t in range(n):
        n_beyond += d2[t] > reach2
    n_out_k[0] += n_beyond
    if n_beyond == 0 or extrapolate:  # every trial kept: one vectorised pass
        for t in range(n):
            absb[t] = _abs_change(b0, err[0, t], err[1, t], err[2, t], abs0)
        nv = n
    else:
        nv = 0
        for t in range(n):
            err[0, nv] = err[0, t]
            err[1, nv] = err[1, t]
            err[2, nv] = err[2, t]
            absb[nv] = _abs_change(b0, err[0, t], err[1, t], err[2, t], abs0)
            nv += d2[t] <= reach2
    q = coverage_count(nv, p) if nv > 1 else 1
    for c in range(3):
        sample_stats(err[c], nv, q, out[c], scratch)
    sample_stats(absb, nv, q, out[3], scratch)


@nb.njit(**JIT)
def harmonic_gauss_sweep(nodes, keys, model, sigma_axes, scales, n_trials, seed, p, extrapolate):
    """Monte Carlo of B(x + N(0, U_p)) - B(x) at each node under its harmonic model.

    The same standard normals as `gauss_sweep` (same seed, same node key), so the two field
    models are compared trial by trial.

    Parameters
    ----------
    nodes, keys : ndarray, shape (k,), int64
        Node rows and random-stream ids, as in `gauss_sweep`.
    model : tuple
        (coords (n, 3) mm, hcoef (n, NB) T, hdeg (n,) int64, hscale (n,) mm, hreach (n,) mm,
        gmat (3, M, NB), exps (M, 3) int64): the nodes, their fits
        (`cfm_fem.models.harmonic.HarmonicFit`) and the basis (`field_basis`,
        `monomial_exponents`).
    sigma_axes : ndarray, shape (3,)
        Per-axis multiplier of U_p.
    scales : ndarray, shape (n_up,), mm
        U_p values.
    n_trials : int
    seed : int
    p : float
        Coverage probability.
    extrapolate : bool
        Keep trials beyond the node's reach in the statistics (counted in ``n_out`` either way).

    Returns
    -------
    stats, n_out, n_lost, star
        As `gauss_sweep` (``n_lost`` and ``star`` all zero / False: no walks, and errors are
        not linear in U_p).
    """
    coords, hcoef, hdeg, hscale, hreach, gmat, exps = model
    k_nodes = nodes.shape[0]
    n_up = scales.shape[0]
    stats, n_out, n_lost, star = sweep_outputs(k_nodes, n_up)
    skey = stream_key(seed, STREAM_SWEEP)
    fkey = stream_key(seed, STREAM_FALLBACK)
    z = np.empty((3, n_trials))
    ok = np.empty(n_trials, dtype=np.bool_)
    unit = np.empty((3, n_trials))
    u = np.empty((3, n_trials))
    d2 = np.empty(n_trials)
    pw = np.empty((3, 6, n_trials))
    parts = np.empty((5, 3, n_trials))
    err = np.empty((3, n_trials))
    absb = np.empty(n_trials)
    scratch = np.empty(n_trials)
    cexp = np.empty((3, gmat.shape[1]))
    w = np.empty((3, 3))
    cnt = np.zeros(1, dtype=np.int64)
    for c in range(3):
        for a in range(3):
            w[c, a] = sigma_axes[c] if a == c else 0.0
    for i in range(k_nodes):
        g = nodes[i]
        _node_model(g, hcoef, hdeg, gmat, cexp)
        normals_by_index(trial_key(skey, keys[i]), fkey, 0, n_trials, z, ok)
        for t in range(n_trials):
            for a in range(3):
                unit[a, t] = _unit_disp(w, z, t, a)
        inv = 1.0 / hscale[g]
        for t in range(n_trials):
            r2 = 0.0
            for a in range(3):
                u[a, t] = unit[a, t] * inv
                r2 += unit[a, t] * unit[a, t]
            d2[t] = r2
        deg = hdeg[g]
        poly_parts(cexp, deg, exps, u, n_trials, pw, parts)  # every U_p from one evaluation
        for k in range(n_up):
            s = scales[k]
            if s == 0.0:  # no displacement: every error is exactly zero
                for c in range(4):
                    for j in range(6):
                        stats[i, k, c, j] = 0.0
                continue
            if deg == 5:  # Horner in s over the homogeneous parts, components together
                for t in range(n_trials):
                    for c in range(3):
                        acc = parts[4, c, t]
                        acc = acc * s + parts[3, c, t]
                        acc = acc * s + parts[2, c, t]
                        acc = acc * s + parts[1, c, t]
                        err[c, t] = (acc * s + parts[0, c, t]) * s
            else:
                for c in range(3):
                    for t in range(n_trials):
                        acc = parts[deg - 1, c, t]
                        for q in range(deg - 2, -1, -1):
                            acc = acc * s + parts[q, c, t]
                        err[c, t] = acc * s
            cnt[0] = 0
            _stats_of_errors(n_trials, d2, (hreach[g] / s) ** 2, extrapolate, cexp[:, 0], err,
                             absb, scratch, p, stats[i, k], cnt)  # fmt: skip
            n_out[i, k] = cnt[0]
    return stats, n_out, n_lost, star


@nb.njit(**JIT)
def harmonic_htm_sweep(nodes, keys, model, start_cells, trials, geo, use_geometric, use_noise, p,
                       extrapolate):  # fmt: skip
    """Monte Carlo of B(x + E_p) - B(x), E_p from the bench model, under the harmonic model.

    The probe errors are those of `htm_sweep` (same trials, same noise), the field the node's
    polynomial (``model`` as in `harmonic_gauss_sweep`; ``start_cells`` only feeds the shared
    probe-point code). Returns (stats (k, 1, 4, 6), n_out (k, 1), n_lost (k, 1), pos (k, 3, 3))
    as `htm_sweep`.
    """
    coords, hcoef, hdeg, hscale, hreach, gmat, exps = model
    rot, q_nodes, params, terms, nkey, fkey = trials
    k_nodes = nodes.shape[0]
    n_trials = params.shape[0]
    stats, n_out, n_lost, _ = sweep_outputs(k_nodes, 1)
    pos, zero, dq, e, dm, tkeys, z, ok, pts, starts = htm_buffers(k_nodes, params, nkey, 3)
    basis = np.eye(3)
    u = np.empty((3, n_trials))
    d2 = np.empty(n_trials)
    pw = np.empty((3, 6, n_trials))
    err = np.empty((3, n_trials))
    absb = np.empty(n_trials)
    scratch = np.empty(n_trials)
    cexp = np.empty((3, gmat.shape[1]))
    for i in range(k_nodes):
        g = nodes[i]
        if start_cells[g, 0] < 0:  # out of the bench's strokes
            continue
        n_mono = _node_model(g, hcoef, hdeg, gmat, cexp)
        gk = keys[i]
        if use_noise:
            normals_by_key(tkeys, fkey, gk, n_trials, z, ok)
        s1 = np.zeros(3)
        s2 = np.zeros(3)
        sx = np.zeros(3)
        _probe_points(
            g, q_nodes[g], gk, n_trials, z, tkeys, params, terms, zero, use_geometric, use_noise,
            geo, rot, basis, coords, start_cells, dq, e, dm, s1, s2, sx, pts, starts,
        )  # fmt: skip
        inv = 1.0 / hscale[g]
        for t in range(n_trials):
            r2 = 0.0
            for a in range(3):
                da = pts[t, a] - coords[g, a]
                u[a, t] = da * inv
                r2 += da * da
            d2[t] = r2
        poly_errors(cexp, n_mono, exps, u, n_trials, pw, err)
        _stats_of_errors(n_trials, d2, hreach[g] ** 2, extrapolate, cexp[:, 0], err, absb,
                         scratch, p, stats[i, 0], n_out[i])  # fmt: skip
        _position_moments(n_trials, s1, s2, sx, pos[i])
    return stats, n_out, n_lost, pos
