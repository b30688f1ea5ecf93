"""Gaussian perturbation sweep (paper eq. 16), statistics streamed per node."""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from .interpolate import _STAR_TAG, _bits_from_float, _deepest_cells, _interp_in
from .locate import BARY_EPS, MAX_STAR, OUTSIDE, WALK_FAILED, locate_exact, settle_walk
from .options import JIT
from .order_stats import _merged_stats, coverage_count, sample_stats, sort_values, sums_and_tails
from .rng import STREAM_FALLBACK, STREAM_SWEEP, normals_by_index, stream_key, trial_key
from .star import (
    BEYOND_REACH,
    BIN_LEVELS,
    LEAVES_MESH,
    STAR_HASH,
    build_star,
    direction_bin,
    star_behind,
    star_bin_starts,
    star_exact,
    star_exit,
    star_locate,
    star_locate3,
    star_recheck,
)

#: Layout of the last axis of the statistics array.
STAT_NAMES = ("mean", "std", "sym_lo", "sym_hi", "short_lo", "short_hi")


#: Layout of the component axis: the three components and |B|.
COMPONENTS = ("Bx", "By", "Bz", "absB")


@nb.njit(inline="always", **JIT)
def _lam3(lmat, s, d0, d1, d2):
    """Barycentric coordinates of the star cell s's vertices other than g at displacement d."""
    return (
        lmat[s, 0, 0] * d0 + lmat[s, 0, 1] * d1 + lmat[s, 0, 2] * d2,
        lmat[s, 1, 0] * d0 + lmat[s, 1, 1] * d1 + lmat[s, 1, 2] * d2,
        lmat[s, 2, 0] * d0 + lmat[s, 2, 1] * d1 + lmat[s, 2, 2] * d2,
    )


@nb.njit(inline="always", **JIT)
def _err3(dmat, s, l0, l1, l2):
    """B - B_g in star cell s at barycentric coordinates lam (the scalar path's order)."""
    return (
        0.0 + dmat[s, 0, 0] * l0 + dmat[s, 0, 1] * l1 + dmat[s, 0, 2] * l2,
        0.0 + dmat[s, 1, 0] * l0 + dmat[s, 1, 1] * l1 + dmat[s, 1, 2] * l2,
        0.0 + dmat[s, 2, 0] * l0 + dmat[s, 2, 1] * l1 + dmat[s, 2, 2] * l2,
    )


@nb.njit(inline="always", **JIT)
def _unit_disp(w, z, t, a):
    """Component a of trial t's displacement per unit U_p: sum_c w[c, a] z[c, t], summed in the
    order `star_errors3` uses (the same bits on every path)."""
    return 0.0 + w[0, a] * z[0, t] + w[1, a] * z[1, t] + w[2, a] * z[2, t]


@nb.njit(**JIT)
def star_errors3(z, n, w, smax, lmat, dmat, nbr, n_star, err, dl, tag, rest, code):
    """Field errors of n trials located in the star tables of a 3-D node, in blocks.

    Trial t moves the probe by ``delta = smax * (w.T @ z[:, t])``, computed in a vectorised
    loop. Every trial is then tested against every cell of the star, in vectorised loops over
    the trials (`interpolate_groups`' cone test: the deepest cell kept as a float tagged with
    its index), and its error written from that cell when it lies inside; the rest walk the
    star from that cell (`star_locate3`), which gives the reason. Same cells, so the same
    errors, as walking every trial (but for trials within rounding of a face between two
    cells, where the walk may stop in either).

    Parameters
    ----------
    z : ndarray, shape (3, >= n)
        Standard normals per trial.
    w : ndarray, shape (3, 3)
        Row c: the mesh-frame displacement per unit normal c (basis[c] * sigma_axes[c]);
        components summed as in `_unit_disp`.
    smax : float, mm
    lmat, dmat, nbr, n_star : star tables (`build_star`), n_star <= MAX_STAR.
    err : ndarray, shape (3, >= n), T
        Output: B(x + delta) - B(x) of each trial found in the star (others left as they are).
    dl : ndarray, shape (3, >= n); tag : ndarray, shape (>= n,)
        Work space.
    rest, code : ndarray, shape (>= n,), int64
        Output: the trials not in the star, in increasing order, and why: LEAVES_MESH, or -1
        (beyond the star).

    Returns
    -------
    int
        Number of trials in ``rest``.
    """
    for t in range(n):
        dl[0, t] = smax * _unit_disp(w, z, t, 0)
        dl[1, t] = smax * _unit_disp(w, z, t, 1)
        dl[2, t] = smax * _unit_disp(w, z, t, 2)
    d0s = dl[0]
    d1s = dl[1]
    d2s = dl[2]
    _deepest_cells(lmat.reshape((lmat.shape[0], 9)), n_star, d0s, d1s, d2s, n, tag)
    nf = 0
    for t in range(n):
        d0 = d0s[t]
        d1 = d1s[t]
        d2 = d2s[t]
        s = np.uint64(_bits_from_float(tag[t]) & _STAR_TAG)
        s = s if s < np.uint64(n_star) else np.uint64(0)  # unsigned: no index wrap-around
        l0, l1, l2 = _lam3(lmat, s, d0, d1, d2)
        inside = min(min(l0, l1), min(l2, 1.0 - (l0 + l1 + l2))) >= -BARY_EPS
        err[0, t], err[1, t], err[2, t] = _err3(dmat, s, l0, l1, l2)
        rest[nf] = t  # branch-free compaction of the trials still to place
        nf += not inside
    n_rest = 0
    for f in range(nf):
        t = rest[f]
        d0 = d0s[t]
        d1 = d1s[t]
        d2 = d2s[t]
        start = np.int64(_bits_from_float(tag[t]) & _STAR_TAG)
        s, l0, l1, l2 = star_locate3(start if start < n_star else 0, lmat, nbr, n_star,
                                     d0, d1, d2)  # fmt: skip
        if s >= 0:
            err[0, t], err[1, t], err[2, t] = _err3(dmat, s, l0, l1, l2)
        else:
            rest[n_rest] = t  # n_rest <= f: overwrites only entries already read
            code[n_rest] = s
            n_rest += 1
    return n_rest


@nb.njit(inline="always", **JIT)
def _taylor(grad, g, c, d0, d1, d2):
    """Component c of grad[g] . delta (d = 3): the first-order change of B at node g."""
    return 0.0 + grad[g, c, 0] * d0 + grad[g, c, 1] * d1 + grad[g, c, 2] * d2


@nb.njit(inline="always", **JIT)
def _abs_change(b0, e0, e1, e2, abs0):
    """|b0 + e| - |b0| without cancellation: (2 b0.e + |e|^2) / (|b0 + e| + |b0|)."""
    x0 = b0[0] + e0
    x1 = b0[1] + e1
    x2 = b0[2] + e2
    den = math.sqrt(x0 * x0 + x1 * x1 + x2 * x2) + abs0
    if den == 0.0:
        return 0.0
    return (2.0 * (b0[0] * e0 + b0[1] * e1 + b0[2] * e2) + e0 * e0 + e1 * e1 + e2 * e2) / den


@nb.njit(inline="always", **JIT)
def _star_pass3(g, n_trials, smax, kmax, n_star, n_cand, n_free, exact, extrapolate, exit_grad,
                simplices, excess, reach, buffers, delta, lam):  # fmt: skip
    """3-D: place every trial of node g in its star at the largest U_p (`star_errors3`); the
    in-star component errors go to the front of comp[kmax] in trial order, the others are
    listed in ``rest`` (with ``code``, ``r_in``, ``r_out``). Returns (n_in, n_rest, n_exit)."""
    (comp, absb, scratch, zbuf, okbuf, cells, lmat, dmat, nbr, htab, bin_start, work, dl, tag,
     rest, code, wmat, r_in, r_out, cand, free) = buffers  # fmt: skip
    n_in = 0
    n_exit = 0
    n_rest = star_errors3(zbuf, n_trials, wmat, smax, lmat, dmat, nbr, n_star, comp[kmax],
                          dl, tag, rest, code)  # fmt: skip
    kept = 0
    for r in range(n_rest):
        t = rest[r]
        r_in[kept] = 0.0
        r_out[kept] = np.inf
        if code[r] == LEAVES_MESH and not exact:  # no proof by itself at this node
            for a in range(3):
                delta[a] = dl[a, t]
            s, r_in[kept], r_out[kept] = star_exit(lmat, reach[g], cand, n_cand, free,
                                                   n_free, delta, lam)  # fmt: skip
            if s == BEYOND_REACH:
                s, r_in[kept], r_out[kept] = star_recheck(
                    g, cells, n_star, lmat, nbr, simplices, excess, reach[g], delta, lam
                )
            if s >= 0:  # an in-star trial after all
                comp[kmax, 0, t], comp[kmax, 1, t], comp[kmax, 2, t] = _err3(
                    dmat, s, lam[0], lam[1], lam[2]
                )
                continue
            code[r] = s
        rest[kept] = t  # kept <= r: overwrites only entries already read
        code[kept] = code[r]
        kept += 1
    n_rest = kept
    if extrapolate:  # exits at the node: the Taylor expansion, linear in U_p (in-star)
        kept = 0
        for r in range(n_rest):
            t = rest[r]
            if code[r] == LEAVES_MESH:
                for c in range(3):
                    comp[kmax, c, t] = _taylor(exit_grad, g, c, dl[0, t], dl[1, t], dl[2, t])
                n_exit += 1
            else:
                rest[kept] = t  # kept <= r: overwrites only entries already read
                code[kept] = code[r]
                r_in[kept] = r_in[r]
                r_out[kept] = r_out[r]
                kept += 1
        n_rest = kept
    if n_rest > 0:  # in-star errors to the front, in trial order
        r = 0
        for t in range(n_trials):
            if r < n_rest and rest[r] == t:
                r += 1
                continue
            for c in range(3):
                comp[kmax, c, n_in] = comp[kmax, c, t]
            n_in += 1
    else:
        n_in = n_trials
    return n_in, n_rest, n_exit


@nb.njit(inline="always", **JIT)
def _walk_pass(g, n_trials, smax, kmax, d, n_star, n_cand, n_free, exact, extrapolate, exit_grad,
               simplices, excess, reach, buffers, delta, lam):  # fmt: skip
    """`_star_pass3` for 1-D and 2-D maps and nodes without a star: each trial walks the
    star from the start cell of its direction bin (`star_locate`). Returns (n_in, n_rest,
    n_exit)."""
    (comp, absb, scratch, zbuf, okbuf, cells, lmat, dmat, nbr, htab, bin_start, work, dl, tag,
     rest, code, wmat, r_in, r_out, cand, free) = buffers  # fmt: skip
    n_in = 0
    n_exit = 0
    n_rest = 0
    for t in range(n_trials):
        for a in range(d):
            delta[a] = smax * _unit_disp(wmat, zbuf, t, a)
        s = -1
        r_lo = 0.0
        r_hi = np.inf
        if n_star > 0:
            s = star_locate(bin_start[direction_bin(delta, d)], lmat, nbr, n_star, delta, lam)
            if s == LEAVES_MESH and not exact:  # no proof by itself at this node
                s, r_lo, r_hi = star_exit(lmat, reach[g], cand, n_cand, free, n_free,
                                          delta, lam)  # fmt: skip
                if s == BEYOND_REACH:
                    s, r_lo, r_hi = star_recheck(g, cells, n_star, lmat, nbr, simplices,
                                                 excess, reach[g], delta, lam)  # fmt: skip
        taylor = extrapolate and s == LEAVES_MESH  # linear in U_p, as an in-star trial
        if s >= 0 or taylor:
            mat, row, vec = (exit_grad, g, delta) if taylor else (dmat, s, lam)
            for c in range(3):
                e = 0.0
                for a in range(d):
                    e += mat[row, c, a] * vec[a]
                comp[kmax, c, n_in] = e
            n_in += 1
            n_exit += taylor
        else:
            rest[n_rest] = t
            code[n_rest] = s
            r_in[n_rest] = r_lo
            r_out[n_rest] = r_hi
            n_rest += 1
    return n_in, n_rest, n_exit


@nb.njit(inline="always", **JIT)
def _out_of_star(g, n_rest, n_trials, kmax, d, coords, values, simplices, transform, neighbors,
                 start_cells, scales, ratio, b0, abs0, extrapolate, exit_grad, search, buffers,
                 n_out, m_out):  # fmt: skip
    """Trials of ``rest``: outside at every U_p (counted), or the global walk at each U_p,
    their errors stored per U_p (comp[k], or the back of comp[kmax]) with their |B| change
    (back of absb[k]); ``m_out[k]`` counts them."""
    (comp, absb, scratch, zbuf, okbuf, cells, lmat, dmat, nbr, htab, bin_start, work, dl, tag,
     rest, code, wmat, r_in, r_out, cand, free) = buffers  # fmt: skip
    n_up = scales.shape[0]
    disp = np.empty(d)
    pt = np.empty(d)
    bary = np.empty(d + 1)
    bi = np.empty(3)
    err = np.empty(3)
    for r in range(n_rest):
        t = rest[r]
        if code[r] == LEAVES_MESH:  # outside the map at every U_p: counted, left out
            for k in range(n_up):
                if scales[k] > 0.0:
                    n_out[k] += 1
            continue
        # left the star: the global walk at each U_p (stored from the back of comp[kmax], so
        # |B| of in-star trials is filled in below)
        octant = 0
        for a in range(d):
            disp[a] = _unit_disp(wmat, zbuf, t, a)
            if disp[a] < 0.0:
                octant |= 1 << a
        start = start_cells[g, octant]
        cell = start
        for k in range(n_up):
            if scales[k] == 0.0:
                continue
            for a in range(d):
                pt[a] = coords[g, a] + scales[k] * disp[a]
            if ratio[k] < r_in[r] or ratio[k] > r_out[r]:  # proven (`star_recheck`)
                s = OUTSIDE
            else:
                s = locate_exact(pt, cell if cell >= 0 else start, transform, neighbors, bary,
                                 search)  # fmt: skip
                if s == WALK_FAILED:  # rare: a walk that cycled (non-Delaunay meshes only)
                    s = settle_walk(pt, transform, search, bary)
            if s == OUTSIDE:
                n_out[k] += 1
                if not extrapolate:
                    continue
                for c in range(3):  # the Taylor expansion at the node
                    e = 0.0
                    for a in range(d):
                        e += exit_grad[g, c, a] * (scales[k] * disp[a])
                    err[c] = e
            else:
                cell = s
                _interp_in(s, bary, simplices, values, bi)
                for c in range(3):
                    err[c] = bi[c] - b0[c]
            mk = m_out[k]
            col = n_trials - 1 - mk if k == kmax else mk
            for c in range(3):
                comp[k, c, col] = err[c]
            absb[k, n_trials - 1 - mk] = _abs_change(
                b0, err[0], err[1], err[2], abs0
            )  # from the back: the front takes the in-star trials below
            m_out[k] = mk + 1


@nb.njit(inline="always", **JIT)
def _node_stats(n_star, n_exit, n_in, n_trials, kmax, scales, ratio, b0, abs0, extrapolate, p,
                buffers, n_out, m_out, n_abs, stats):  # fmt: skip
    """Statistics of the node's samples into ``stats``: components merged from the scaled
    in-star values and the out-of-star ones (`_merged_stats`), or all scaled when every
    trial stayed in the star; |B| per U_p. Returns whether every trial stayed in the star."""
    (comp, absb, scratch, zbuf, okbuf, cells, lmat, dmat, nbr, htab, bin_start, work, dl, tag,
     rest, code, wmat, r_in, r_out, cand, free) = buffers  # fmt: skip
    n_up = scales.shape[0]
    all_star = n_star > 0
    for k in range(n_up):
        if scales[k] > 0.0:
            n_out[k] += n_exit
        # with extrapolation every trial has a value: exits are in-star or in m_out
        if m_out[k] > 0 or (n_out[k] > 0 and not extrapolate):
            all_star = False
    # |B| per U_p: in-star trials at the front, out-of-star ones already at the back
    for k in range(n_up):
        if scales[k] == 0.0:
            continue
        r = ratio[k]
        for j in range(n_in):
            absb[k, j] = _abs_change(
                b0, r * comp[kmax, 0, j], r * comp[kmax, 1, j], r * comp[kmax, 2, j], abs0
            )
        mk = m_out[k]
        for j in range(mk):  # close the gap
            absb[k, n_in + j] = absb[k, n_trials - mk + j]
        n_abs[k] = n_in + mk
    # components
    if all_star:
        for c in range(3):
            sample_stats(comp[kmax, c], n_in, coverage_count(n_in, p), stats[kmax, c], scratch)
            for k in range(n_up):
                if k != kmax:
                    for j in range(6):
                        stats[k, c, j] = ratio[k] * stats[kmax, c, j]
    else:
        low = work[0]
        high = work[1]
        full = work[2]
        ybuf = work[3]
        for c in range(3):
            x = comp[kmax, c]
            # in-star sums and tails (the tails sorted, kept in scratch)
            shift, s1, s2, n_lo, n_hi = sums_and_tails(x, n_in, scratch, n_trials)
            if n_in < 2 or not s2 - s1 * s1 / n_in > 0.0:
                n_lo = 0  # degenerate: take the exact whole-sample path
                n_hi = 0
            lo_tail = scratch[:n_lo]
            hi_tail = scratch[n_trials - n_hi : n_trials]
            sort_values(lo_tail)
            sort_values(hi_tail)
            for k in range(n_up):
                if scales[k] == 0.0:
                    continue
                mk = m_out[k]
                for j in range(mk):
                    ybuf[j] = comp[k, c, n_trials - mk + j] if k == kmax else comp[k, c, j]
                sort_values(ybuf[:mk])
                _merged_stats(x, n_in, shift, s1, s2, lo_tail, hi_tail, ratio[k], ybuf, mk, p,
                              stats[k, c], low, high, full, work[4])  # fmt: skip
    for k in range(n_up):
        if scales[k] == 0.0:
            continue
        nk = n_abs[k]
        sample_stats(absb[k], nk, coverage_count(nk, p) if nk > 1 else 1, stats[k, 3], scratch)
    return all_star


@nb.njit(**JIT)
def _node_gauss(
    g,
    gkey,
    coords,
    values,
    simplices,
    transform,
    neighbors,
    start_cells,
    basis,
    sigma_axes,
    scales,
    n_trials,
    skey,
    fkey,
    p,
    exit_grad,
    search,
    buffers,
    stats,
    n_out,
    n_lost,
):
    """All trials and statistics of node ``g`` (see `gauss_sweep`). ``buffers``: the per-thread
    work arrays of `_gauss_buffers`.

    With node gradients in ``exit_grad`` (see `gauss_sweep`), a trial that leaves the map takes
    the node's first-order Taylor expansion B_g + grad B_g . delta (counted in ``n_out`` all the
    same); one that leaves through a boundary face at the node is then linear in U_p and joins
    the in-star trials.

    Trials whose largest displacement stays in the node's star are located in the star tables
    (`build_star`; in 3-D by the block pass `star_errors3`); the field is affine there, so their
    component errors at every U_p are the largest U_p's scaled. They are stored once
    (comp[kmax]); the few trials that leave the star take the global walk at each U_p and are
    stored per U_p (comp[k], or the back of comp[kmax]).
    A trial whose star walk crosses a border face at g is outside at every U_p when that face
    is a supporting plane of the mesh (`star_exact`); on a non-convex mesh, where it may not
    be, `star_exit` places it: in a star cell, outside at every U_p (nearer to g than any other
    cell), or the global walk (`locate_exact`) at the U_p values where nothing proves it.
    Component statistics then merge the scaled in-star tails with the sorted out-of-star values
    (`_merged_stats`); |B| is not linear in U_p and gets its own sample per U_p.
    """
    (comp, absb, scratch, zbuf, okbuf, cells, lmat, dmat, nbr, htab, bin_start, work, dl, tag,
     rest, code, wmat, r_in, r_out, cand, free) = buffers  # fmt: skip
    excess, reach = search[0], search[1]
    d = coords.shape[1]
    n_up = scales.shape[0]
    kmax = 0
    for k in range(n_up):
        if scales[k] > scales[kmax]:
            kmax = k
    smax = scales[kmax]
    ratio = np.empty(n_up)
    for k in range(n_up):
        ratio[k] = scales[k] / smax if smax > 0 else 0.0
    delta = np.empty(d)
    lam = np.empty(d)
    b0 = values[g]
    abs0 = np.sqrt(b0[0] ** 2 + b0[1] ** 2 + b0[2] ** 2)
    key = trial_key(skey, gkey)  # one sequence per node: positions 4t, 4t + 1 serve trial t
    n_abs = np.zeros(n_up, dtype=np.int64)  # |B| samples per U_p
    m_out = np.zeros(n_up, dtype=np.int64)  # out-of-star component samples per U_p
    extrapolate = exit_grad.shape[0] > 0
    for k in range(n_up):
        n_out[k] = 0
        n_lost[k] = 0
    for k in range(n_up):
        if scales[k] == 0.0:  # no displacement: every error is exactly zero
            for c in range(4):
                for j in range(6):
                    stats[k, c, j] = 0.0
    if smax == 0.0:
        return False
    n_star = build_star(
        g, start_cells[g, 0], simplices, transform, neighbors, values, cells, lmat, dmat, nbr,
        htab,
    )  # fmt: skip
    if n_star > 0 and d != 3:  # per direction bin, a star cell to start walks from
        star_bin_starts(lmat, nbr, n_star, d, smax, bin_start)
    exact = star_exact(g, cells, n_star, simplices, excess)  # LEAVES_MESH is proven
    n_cand = 0
    n_free = 0
    if not exact:
        n_cand, n_free = star_behind(g, coords, cells, n_star, lmat, nbr, simplices, cand, free)
    normals_by_index(key, fkey, 0, n_trials, zbuf, okbuf)
    # place every trial in the star at the largest U_p; the others are listed in ``rest``
    for c in range(3):  # mesh-frame displacement per unit normal (projected for planar maps)
        for a in range(d):
            wmat[c, a] = basis[c, a] * sigma_axes[c]
    if d == 3 and n_star > 0:
        n_in, n_rest, n_exit = _star_pass3(
            g, n_trials, smax, kmax, n_star, n_cand, n_free, exact, extrapolate, exit_grad,
            simplices, excess, reach, buffers, delta, lam,
        )  # fmt: skip
    else:
        n_in, n_rest, n_exit = _walk_pass(
            g, n_trials, smax, kmax, d, n_star, n_cand, n_free, exact, extrapolate, exit_grad,
            simplices, excess, reach, buffers, delta, lam,
        )  # fmt: skip
    _out_of_star(
        g, n_rest, n_trials, kmax, d, coords, values, simplices, transform, neighbors,
        start_cells, scales, ratio, b0, abs0, extrapolate, exit_grad, search, buffers, n_out,
        m_out,
    )  # fmt: skip
    return _node_stats(
        n_star, n_exit, n_in, n_trials, kmax, scales, ratio, b0, abs0, extrapolate, p, buffers,
        n_out, m_out, n_abs, stats,
    )  # fmt: skip


@nb.njit(**JIT)
def _gauss_buffers(n_up, n_trials, d):
    """Per-thread work arrays of `_node_gauss`: samples (comp, absb, scratch), normals (zbuf,
    okbuf), star tables (cells, lmat, dmat, nbr, htab, bin_start), merge space (work) and the
    star pass's work space (dl, tag, rest, code, wmat; `star_errors3`) and, per trial in
    ``rest``, the fractions of its largest displacement where it is proven outside (r_in,
    r_out; `star_recheck`), and the star cells and free faces of `star_behind` (cand, free)."""
    return (
        np.empty((n_up, 3, n_trials)),
        np.empty((n_up, n_trials)),
        np.empty(n_trials),
        np.empty((3, n_trials)),
        np.empty(n_trials, dtype=np.bool_),
        np.empty(MAX_STAR, dtype=np.int64),
        np.empty((MAX_STAR, d, d)),
        np.empty((MAX_STAR, 3, d)),
        np.empty((MAX_STAR, d), dtype=np.int64),
        np.full((3, STAR_HASH), -1, dtype=np.int64),
        np.zeros((1 << d) * BIN_LEVELS ** (d - 1), dtype=np.int64),
        np.empty((5, n_trials)),
        np.empty((3, n_trials)),
        np.empty(n_trials),
        np.empty(n_trials, dtype=np.int64),
        np.empty(n_trials, dtype=np.int64),
        np.empty((3, d)),
        np.empty(n_trials),
        np.empty(n_trials),
        np.empty(MAX_STAR, dtype=np.int64),
        np.empty((2, MAX_STAR * d), dtype=np.int64),
    )


@nb.njit(**JIT)
def sweep_outputs(k_nodes, n_col):
    """Output arrays of a sweep kernel for ``k_nodes`` nodes and ``n_col`` columns: statistics
    (NaN until computed), outside and lost-trial counts (0) and the star flags (False).

    Filled by loops: np.full and np.zeros each compile apart from np.empty.
    """
    stats = np.empty((k_nodes, n_col, 4, 6))
    n_out = np.empty((k_nodes, n_col), dtype=np.int64)
    n_lost = np.empty((k_nodes, n_col), dtype=np.int64)
    star = np.empty(k_nodes, dtype=np.bool_)
    for i in range(k_nodes):
        star[i] = False
        for k in range(n_col):
            n_out[i, k] = 0
            n_lost[i, k] = 0
            for c in range(4):
                for j in range(6):
                    stats[i, k, c, j] = np.nan
    return stats, n_out, n_lost, star


@nb.njit(**JIT)
def gauss_sweep(
    nodes,
    keys,
    coords,
    values,
    simplices,
    transform,
    neighbors,
    start_cells,
    basis,
    sigma_axes,
    scales,
    n_trials,
    seed,
    p,
    exit_grad,
    search,
):
    """Monte Carlo of B(x + N(0, U_p)) - B(x) at each node, statistics streamed per node.

    One thread: callers run blocks of nodes on several threads (`cfm_fem.threads`). A numba
    parallel loop here would recompile the whole kernel tree twice more on first use (~7 s).

    Parameters
    ----------
    nodes : ndarray, shape (k,), int64
        Node indices (rows of the arrays below) to process; results do not depend on how nodes
        are chunked.
    keys : ndarray, shape (k,), int64
        Random-stream id of each node (its index in the whole map): a node's numbers depend on
        its key only, so a part of a map held in its own arrays gives the whole map's numbers.
    coords : ndarray, shape (n, d), mm, mesh frame
    values : ndarray, shape (n, 3), T
    simplices, transform, neighbors : arrays of a `SimplexMesh`
    start_cells : ndarray, shape (n, 2**d), int64
        Walk start per node and octant of the displacement (`octant_cells`); -1 for nodes in
        no cell.
    basis : ndarray, shape (3, d)
        Map frame -> mesh frame (identity for 3-D).
    sigma_axes : ndarray, shape (3,)
        Per-axis multiplier of U_p (1, 1, 1 for isotropic).
    scales : ndarray, shape (n_up,), mm
        U_p values; trial t uses the same standard normals for every U_p (common random numbers).
    n_trials : int
    seed : int
    p : float
        Coverage probability (0.95).
    exit_grad : ndarray, shape (n, 3, d) or (0, 3, d), T/mm, mesh frame
        Empty: trials that leave the mesh are left out of the statistics. Else the node
        gradients (`cfm_fem.workflows.sweep.problem.node_gradients` in the mesh frame): a trial that
        leaves takes the node's first-order Taylor expansion B_g + grad B_g . delta.
    search : tuple
        Face excess and cell buckets of the mesh (`locate_exact`;
        `cfm_fem.models.mesh.exact_search`): whether a trial left the mesh is then exact on
        non-convex meshes too. Empty arrays for a convex mesh (its border faces are
        supporting planes, every exit is a proof).

    Returns
    -------
    stats : ndarray, shape (k, n_up, 4, 6), T
        Per node, U_p value, component (Bx, By, Bz, |B|) and statistic (`STAT_NAMES`) of the
        error B_meas - B_nom over the trials that stayed inside the mesh (all trials with
        ``exit_grad``).
    n_out : ndarray, shape (k, n_up), int64
        Trials whose perturbed point left the mesh (left out, or extrapolated).
    n_lost : ndarray, shape (k, n_up), int64
        Trials left without a value by a walk that did not end: 0, a walk that cycles is
        settled exactly (`settle_walk`); kept for the outputs' ``walk_failed_fraction``.
    star : ndarray, shape (k,), bool
        True if every trial stayed in a cell incident to the node (errors exactly linear in U_p).
    """
    k_nodes = nodes.shape[0]
    n_up = scales.shape[0]
    stats, n_out, n_lost, star = sweep_outputs(k_nodes, n_up)
    skey = stream_key(seed, STREAM_SWEEP)
    fkey = stream_key(seed, STREAM_FALLBACK)
    buffers = _gauss_buffers(n_up, n_trials, coords.shape[1])
    for i in range(k_nodes):
        g = nodes[i]
        if start_cells[g, 0] < 0:
            continue
        star[i] = _node_gauss(g, keys[i], coords, values, simplices, transform, neighbors,
                              start_cells, basis, sigma_axes, scales, n_trials, skey, fkey, p,
                              exit_grad, search, buffers, stats[i], n_out[i],
                              n_lost[i])  # fmt: skip
    return stats, n_out, n_lost, star
