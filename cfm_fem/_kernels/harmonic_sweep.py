"""Sweeps with the local harmonic field model: no cell location, one polynomial per node.

Each node's model (`cfm_fem.models.harmonic`) is expanded into monomial coefficients once
(`expand_node`); every trial is then the polynomial at its scaled displacement. A trial
displaced beyond the node's reach is counted as outside (left out, or kept with
``extrapolate``: the polynomial beyond the data that support it).
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from .harmonic import expand_node, sparse_basis
from .harmonic_bounds import BOUND_SAFETY, degree_bounds, inverse_multinomials, remainder_bounds
from .harmonic_parts import N_SLOTS, PART_BLOCK, PART_PITCH, homogeneous_parts
from .harmonic_stats import (
    changes_block,
    finish_tails,
    first_order_abs,
    gather_block,
    keep_candidates,
    tail_pilot,
    tail_quantile_z,
    tail_stats,
    whole_sample_stats,
)
from .htm_sweep import _position_moments, _probe_points, htm_buffers
from .options import JIT
from .order_stats import TAIL_PILOT, coverage_count, radix_work, sample_stats
from .rng import (
    STREAM_FALLBACK,
    STREAM_SWEEP,
    normals_by_index,
    normals_by_key,
    stream_key,
    trial_key,
)
from .sweep import _abs_change, _unit_disp, sweep_outputs

#: Highest degree of the unrolled polynomial (`homogeneous_parts`).
MAX_DEG = N_SLOTS // 3


@nb.njit(inline="always", **JIT)
def _node_model(g, hcoef, hdeg, fields, cexp):
    """Expand node g's model into ``cexp`` (``fields``: `sparse_basis`); returns the number of
    monomials."""
    deg = hdeg[g]
    n_mono = (deg + 1) * (deg + 2) * (deg + 3) // 6
    expand_node(hcoef[g], (deg + 1) * (deg + 3), fields, n_mono, cexp)
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
def _scaled_displacements(w, z, n, inv, u, d2):
    """Displacements per unit U_p of n trials (`_unit_disp`) times ``inv`` into u (3, n) and
    their squared lengths before scaling into d2; returns the largest of those."""
    for t in range(n):  # straight-line body: vectorised
        d0 = _unit_disp(w, z, t, 0)
        d1 = _unit_disp(w, z, t, 1)
        d2_ = _unit_disp(w, z, t, 2)
        u[0, t] = d0 * inv
        u[1, t] = d1 * inv
        u[2, t] = d2_ * inv
        d2[t] = 0.0 + d0 * d0 + d1 * d1 + d2_ * d2_
    d2max = 0.0
    for t in range(n):
        d2max = max(d2max, d2[t])
    return d2max


@nb.njit(**JIT)
def _hot_arrays(n, n_sets):
    """Arrays of the loops over every trial, carved from one buffer so that the rows one loop
    reads lie in other cache lines than, and just above (modulo 4 KiB), the rows it writes:
    rows 4 KiB apart fall into one cache set, and a load 4 KiB below a pending store waits
    for it. The first ``n`` values of each row are the trials'.

    Returns
    -------
    parts : ndarray, shape (N_SLOTS * PART_PITCH,)
        `homogeneous_parts` of a block: lines 0 .. 14 modulo 4 KiB.
    u, z : ndarray, shape (3, >= n)
        Scaled displacements and normals, rows in consecutive lines from line 16 and 20.
    d2 : ndarray, shape (>= n,)
        Squared displacements, line 19.
    lin : ndarray, shape (PART_BLOCK,)
        |B|'s first-order parts of a block, line 63.
    vals : ndarray, shape (n_sets, 4, >= n)
        Field changes, every row at line 63.
    """
    pitch = n + (8 - n) % 512  # 4 KiB + one line apart: rows in consecutive lines
    wide = (n + 511) // 512 * 512  # rows a multiple of 4 KiB apart: all in one line
    size_parts = N_SLOTS * PART_PITCH
    lines = (0, 16, 19, 20, 63, 63)  # first line (mod 64) of parts, u, d2, z, lin, vals
    sizes = (size_parts, 3 * pitch, pitch, 3 * pitch, PART_BLOCK, n_sets * 4 * wide)
    starts = np.empty(6, dtype=np.int64)
    pos = 0
    for i in range(6):
        pos = (pos + 511) // 512 * 512 + 8 * lines[i]
        starts[i] = pos
        pos += sizes[i]
    ws = np.empty(pos)
    parts = ws[starts[0] : starts[0] + size_parts]
    u = ws[starts[1] : starts[1] + 3 * pitch].reshape((3, pitch))
    d2 = ws[starts[2] : starts[2] + pitch]
    z = ws[starts[3] : starts[3] + 3 * pitch].reshape((3, pitch))
    lin = ws[starts[4] : starts[4] + PART_BLOCK]
    vals = ws[starts[5] : starts[5] + n_sets * 4 * wide].reshape((n_sets, 4, wide))
    return parts, u, d2, z, lin, vals


@nb.njit(**JIT)
def _gauss_buffers(n_up, n_trials, n_mono):
    """Per-thread work arrays of `harmonic_gauss_sweep`."""
    n = n_trials
    parts, u, d2, z, lin, vals = _hot_arrays(n, n_up)
    return (
        z, np.empty(n, dtype=np.bool_), u, d2, parts, vals, lin,
        np.empty((4, n)), np.empty((4, n), dtype=np.int64), np.empty((4, 4)), np.empty(n),
        np.empty(n), np.zeros((4, 4), dtype=np.int64), np.empty(n), np.zeros((3, n_mono)),
    )  # fmt: skip


@nb.njit(**JIT)
def _node_changes(cexp, u, n, scales, b0, abs0, b_hat, z_h, buffers, sums, gathered):
    """Every trial's field changes at every U_p > 0 into ``vals`` (n_up, 4, n) and their sums
    into ``sums`` (n_up, 4, 3: shift, sum of (change - shift) and of its square; the shift is
    the first trial's change); the tails of the first-order parts (the components' part 1,
    |B|'s b_hat . those) gathered block by block while the block is at hand: `tail_pilot` on
    the first block (its leading `TAIL_PILOT` values, as `gather_tails`), `gather_block` on
    each, into ``tail_val``, ``tail_idx``, ``limits`` and ``counts[:, 0]``; ``gathered[j]``
    False where quantity j gathers nothing."""
    (z, ok, u_, d2, parts, vals, lin, tail_val, tail_idx, limits, low, high, counts, scratch,
     cexp_) = buffers  # fmt: skip
    n_up = scales.shape[0]
    counts[:, 0] = 0
    for t0 in range(0, n, PART_BLOCK):
        m = min(PART_BLOCK, n - t0)
        homogeneous_parts(cexp, u, t0, m, parts)
        first_order_abs(parts, m, b_hat, lin)
        for j in range(4):
            row = lin[:m] if j == 3 else parts[j * PART_PITCH : j * PART_PITCH + m]
            if t0 == 0:
                gathered[j] = tail_pilot(row, min(m, TAIL_PILOT), z_h, limits[j])
            if gathered[j]:
                counts[j, 0] = gather_block(row, m, t0, limits[j], tail_val[j], tail_idx[j],
                                            counts[j, 0])  # fmt: skip
        for k in range(n_up):
            if scales[k] > 0.0:
                if t0 == 0:  # the first trial's changes are the shifts of the sums
                    changes_block(parts, 1, scales[k], b0, abs0, vals[k], 0, sums[k, :, 0],
                                  sums[k, :, 1:])  # fmt: skip
                    sums[k, :, 0] = vals[k, :, 0]
                    sums[k, :, 1:] = 0.0
                changes_block(parts, m, scales[k], b0, abs0, vals[k], t0, sums[k, :, 0],
                              sums[k, :, 1:])  # fmt: skip


@nb.njit(**JIT)
def harmonic_gauss_sweep(nodes, keys, model, sigma_axes, scales, n_trials, seed, p, extrapolate):
    """Monte Carlo of B(x + N(0, U_p)) - B(x) at each node under its harmonic model.

    The same standard normals as `gauss_sweep` (same seed, same node key), so the two field
    models are compared trial by trial. Each trial's polynomial is evaluated once
    (`homogeneous_parts`), every U_p from its homogeneous parts; the order statistics come
    from the candidates of the first-order part's tails (`harmonic_stats`), exactly.

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
    n = n_trials
    stats, n_out, n_lost, star = sweep_outputs(k_nodes, n_up)
    skey = stream_key(seed, STREAM_SWEEP)
    fkey = stream_key(seed, STREAM_FALLBACK)
    buffers = _gauss_buffers(n_up, n, gmat.shape[1])
    fields = sparse_basis(gmat)
    (z, ok, u, d2, parts, vals, lin, tail_val, tail_idx, limits, low, high, counts, scratch,
     cexp) = buffers  # fmt: skip
    w = np.zeros((3, 3))
    for c in range(3):
        w[c, c] = sigma_axes[c]
    csum = np.empty((MAX_DEG, 3))
    inv_multi = inverse_multinomials(exps)
    bounds = np.empty(4)
    gathered = np.zeros(4, dtype=np.bool_)
    bound_max = np.empty(4)
    guide = np.empty((4, 2))
    sort_work = radix_work(n)
    sums = np.zeros((n_up, 4, 3))
    b_hat = np.zeros(3)
    cnt = np.zeros(1, dtype=np.int64)
    smax = 0.0
    for k in range(n_up):
        smax = max(smax, scales[k])
    q = coverage_count(n, p) if n > 1 else 1
    z_h = tail_quantile_z(n, q)
    for i in range(k_nodes):
        g = nodes[i]
        n_mono = _node_model(g, hcoef, hdeg, fields, cexp)
        cexp[:, n_mono:] = 0.0  # the unrolled polynomial is of the highest degree
        normals_by_index(trial_key(skey, keys[i]), fkey, 0, n, z, ok)
        inv = 1.0 / hscale[g]
        d2max = _scaled_displacements(w, z, n, inv, u, d2)
        rho = math.sqrt(d2max) * inv * (1.0 + BOUND_SAFETY)
        degree_bounds(cexp, exps, inv_multi, MAX_DEG, csum)
        b0 = cexp[:, 0]
        abs0 = math.sqrt(b0[0] ** 2 + b0[1] ** 2 + b0[2] ** 2)
        for c in range(3):
            b_hat[c] = b0[c] / abs0 if abs0 > 0.0 else 0.0
        _node_changes(cexp, u, n, scales, b0, abs0, b_hat, z_h, buffers, sums, gathered)
        for k in range(n_up):  # the largest bound: its candidates hold every U_p's
            remainder_bounds(scales[k], rho, csum, MAX_DEG, b_hat, abs0, bounds)
            for j in range(4):
                bound_max[j] = max(bound_max[j], bounds[j]) if k > 0 else bounds[j]
        for j in range(4):
            if gathered[j]:
                finish_tails(tail_val[j], counts[j, 0], n - q, limits[j], counts[j], scratch)
            else:
                counts[j, :] = 0
            keep_candidates((tail_val[j], tail_idx[j]), counts[j], limits[j], bound_max[j])
        guide[:] = np.nan  # no guess at the node's first U_p
        beyond_max = 0  # trials beyond the reach at the largest U_p (the most)
        if smax > 0.0:
            r2max = (hreach[g] / smax) ** 2
            for t in range(n):
                beyond_max += d2[t] > r2max
        for k in range(n_up):
            s = scales[k]
            if s == 0.0:  # no displacement: every error is exactly zero
                for c in range(4):
                    for j in range(6):
                        stats[i, k, c, j] = 0.0
                continue
            reach2 = (hreach[g] / s) ** 2
            if beyond_max > 0:
                cnt[0] = 0
                for t in range(n):
                    cnt[0] += d2[t] > reach2
                if cnt[0] > 0 and not extrapolate:  # a sample of its own per U_p
                    cnt[0] = 0
                    _stats_of_errors(n, d2, reach2, False, b0, vals[k, :3], vals[k, 3],
                                     scratch, p, stats[i, k], cnt)  # fmt: skip
                    n_out[i, k] = cnt[0]
                    continue
                n_out[i, k] = cnt[0]
            remainder_bounds(s, rho, csum, MAX_DEG, b_hat, abs0, bounds)
            for j in range(4):
                tails = (tail_val[j], tail_idx[j])
                if not tail_stats(vals[k, j], n, q, s, bounds[j], tails, limits[j], counts[j],
                                  guide[j], stats[i, k, j], low, high, sums[k, j],
                                  sort_work):  # fmt: skip
                    whole_sample_stats(vals[k, j], n, q, s, z_h, guide[j], stats[i, k, j], low,
                                       high, sums[k, j], sort_work, scratch)  # fmt: skip
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
    parts, u, d2, _, _, err = _hot_arrays(n_trials, 1)
    err = err[0]  # the components, then |B| (recomputed below)
    no_shift = np.zeros(4)
    unused_sums = np.zeros((4, 2))  # the statistics below take their own
    absb = np.empty(n_trials)
    scratch = np.empty(n_trials)
    cexp = np.empty((3, gmat.shape[1]))
    fields = sparse_basis(gmat)
    for i in range(k_nodes):
        g = nodes[i]
        if start_cells[g, 0] < 0:  # out of the bench's strokes
            continue
        n_mono = _node_model(g, hcoef, hdeg, fields, cexp)
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
        cexp[:, n_mono:] = 0.0  # the unrolled polynomial is of the highest degree
        b0 = cexp[:, 0]
        abs0 = math.sqrt(b0[0] ** 2 + b0[1] ** 2 + b0[2] ** 2)
        for t0 in range(0, n_trials, PART_BLOCK):
            m = min(PART_BLOCK, n_trials - t0)
            homogeneous_parts(cexp, u, t0, m, parts)
            changes_block(parts, m, 1.0, b0, abs0, err, t0, no_shift, unused_sums)
        _stats_of_errors(n_trials, d2, hreach[g] ** 2, extrapolate, cexp[:, 0], err[:3], absb,
                         scratch, p, stats[i, 0], n_out[i])  # fmt: skip
        _position_moments(n_trials, s1, s2, sx, pos[i])
    return stats, n_out, n_lost, pos
