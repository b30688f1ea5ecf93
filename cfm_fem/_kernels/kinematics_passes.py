"""Monte Carlo passes of the kinematics over (point, trial), with streamed order statistics.

Parallel over points; each point sees the trials of a block in increasing order, so sums and
counts are bit-identical whatever the number of threads. Per (point, block): fill the values
E_x, E_y, E_z, |E| of the block's trials (the hot loop), then reduce them in separate loops
(vectorisable sums and counts, rare window work).
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from .htm import _probe_error_directed
from .options import JIT, PJIT, RJIT
from .order_stats import select_inplace
from .rng import (
    _DEBRUIJN,
    _DEBRUIJN_INDEX,
    _noise_of_trial,
    _three_normals,
    _zig_fast3,
    normals_by_key,
)

N_QTY = 4  # quantities per point: E_x, E_y, E_z, |E|


@nb.njit(**JIT)
def fill_values(model, t0, n, q, i, pi, ev):
    """Values of point i (index pi) for trials t0..t0+n-1 into ev (4, >= n): E_x, E_y, E_z, |E|.

    model: the tuple of ``_Engine.model`` (linear, terms, params, sig, speed, tau_code, tau_par,
    nkey, tkeys, fkey, stack, mounts, tool, strokes, profiles, dirs), rows 0 .. n-1 of terms,
    params, tkeys and dirs (`trial_directions`, non-linear models) being trials t0 .. t0+n-1.
    ``linear`` with ``tau_code < 0`` is the hot path (collapsed chain, three normals); otherwise
    ``probe_error_mm`` (with the trial's directions) / the collapsed chain with the noise of
    ``axis_noise_mm``. Both give the same numbers for the same (seed, trial, point).
    """
    linear, terms, params, sig, speed, tau_code, tau_par, _, tkeys, fkey = model[:10]
    if linear and tau_code < 0:
        s0 = sig[0]
        s1 = sig[1]
        s2 = sig[2]
        q0 = q[i, 0]
        q1 = q[i, 1]
        q2 = q[i, 2]
        # the normals first (vectorised fast path, same numbers as `_three_normals`), then the
        # chain in a loop without calls (vectorised too)
        z = np.empty((3, n))
        normals_by_key(tkeys, fkey, pi, n, z, np.empty(n, dtype=np.bool_))
        for k in range(n):
            ev[0, k], ev[1, k], ev[2, k], ev[3, k] = _chain(
                terms, k, q0, q1, q2, s0 * z[0, k], s1 * z[1, k], s2 * z[2, k]
            )
    else:
        stack, mounts, tool, strokes, profiles, dirs = model[10:]
        e = np.empty(3)
        dq = np.empty(3)
        qi = q[i]
        for k in range(n):
            _noise_of_trial(tkeys[k], fkey, pi, sig, speed, tau_code, tau_par, dq)
            if linear:
                e[0], e[1], e[2], _ = _chain(terms, k, qi[0], qi[1], qi[2], dq[0], dq[1], dq[2])
            else:
                _probe_error_directed(params[k], qi, dq, dirs[k], stack, mounts, tool, strokes,
                                      profiles, e)  # fmt: skip
            ev[0, k] = e[0]
            ev[1, k] = e[1]
            ev[2, k] = e[2]
            ev[3, k] = math.sqrt(e[0] * e[0] + e[1] * e[1] + e[2] * e[2])


@nb.njit(**RJIT)
def _sums_below(v, n, shift, lo0, lo1):
    """sum (v - shift), sum (v - shift)^2, #(v < lo0), #(v < lo1) over v[:n]."""
    s = 0.0
    s2 = 0.0
    b0 = 0
    b1 = 0
    for k in range(n):
        d = v[k] - shift
        s += d
        s2 += d * d
        b0 += v[k] < lo0
        b1 += v[k] < lo1
    return s, s2, b0, b1


@nb.njit(inline="always", **JIT)
def _slot(v, lo, inv):
    """Window slot of v (the same expression in both passes): floor((v - lo) * inv)."""
    return (v - lo) * inv


@nb.njit(**JIT)
def _hits(v, a, b, lo0, hi0, lo1, hi1):
    """Number of v[a:b] inside [lo0, hi0] or [lo1, hi1] (a vectorised pre-scan)."""
    h = 0
    for k in range(a, b):
        x = v[k]
        h += ((x >= lo0) & (x <= hi0)) | ((x >= lo1) & (x <= hi1))
    return h


@nb.njit(**JIT)
def _count_windows(v, n, lo0, inv0, lo1, inv1, wh0, wh1):
    """Add the v[:n] that fall in the slots of window 0 (low end) or 1 (high end)."""
    nw = wh0.shape[0]
    top0 = lo0 + (nw + 1) / inv0  # above this, window 0 cannot be hit (one slot of slack)
    for k in range(n):
        x = v[k]
        if x < top0:
            y = _slot(x, lo0, inv0)
            if y >= 0.0 and y < nw:
                wh0[np.int64(y)] += 1
        if x >= lo1:
            y = _slot(x, lo1, inv1)
            if y >= 0.0 and y < nw:
                wh1[np.int64(y)] += 1


@nb.njit(**PJIT)
def pass_pilot(model, t0, n, q, pidx, out):
    """Values of trials t0..t0+n-1 into out (npts, 4, n); ``model`` as `fill_values`."""
    for i in nb.prange(q.shape[0]):
        fill_values(model, t0, n, q, i, pidx[i], out[i])


@nb.njit(**PJIT)
def pass_pilot_quantiles(model, t0, n, q, pidx, kth, out):
    """Order statistics ``kth`` (0-based, sorted) of trials t0..t0+n-1 per point and quantity,
    into out (npts, 4, len(kth)), plus the mean in out[..., -1] (one point's values at a time,
    so a large pilot needs no trials x points memory); ``model`` as `fill_values`."""
    npts = q.shape[0]
    nchunk = min(npts, 64)  # one scratch array per chunk of points, not per point
    per = (npts + nchunk - 1) // nchunk
    for ch in nb.prange(nchunk):
        ev = np.empty((4, n))
        for i in range(ch * per, min(npts, (ch + 1) * per)):
            _pilot_point(model, t0, n, q, i, pidx[i], kth, out, ev)


@nb.njit(**JIT)
def _pilot_point(model, t0, n, q, i, pi, kth, out, ev):
    """Pilot order statistics and mean of point i (scratch ev (4, n) reused across points)."""
    fill_values(model, t0, n, q, i, pi, ev)
    # kth = (low end: lower, upper bracket; high end: lower, upper; 0; n - 1). The brackets only
    # place windows, so a histogram of the pilot with conservative bin edges is enough (a
    # selection per bracket costs several times more).
    nb_ = 2048
    counts = np.empty(nb_, np.int64)
    for c in range(4):
        v = ev[c]
        vmin = v[:n].min()
        vmax = v[:n].max()
        out[i, c, 4] = vmin
        out[i, c, 5] = vmax
        out[i, c, 6] = v[:n].mean()
        width = (vmax - vmin) / nb_
        if not width > 0.0:
            for j in range(4):
                out[i, c, j] = vmin
            continue
        counts[:] = 0
        inv = 1.0 / width
        for k in range(n):
            b = min(np.int64((v[k] - vmin) * inv), nb_ - 1)
            counts[b] += 1
        for j in range(4):
            r = kth[j] + 1  # 1-based rank
            cum = 0
            b = 0
            while cum + counts[b] < r:
                cum += counts[b]
                b += 1
            # lower brackets take the bin's lower edge, upper brackets its upper edge
            out[i, c, j] = vmin + (b if j % 2 == 0 else b + 1) * width


@nb.njit(**PJIT)
def pass_window(model, t0, n, q, pidx, shift, wlo, winv, acc, below, whist):
    """Pass 1 of the generic path: shifted sums, and counts around each interval end, over
    trials t0..t0+n-1.

    acc (npts, 4, 2): sum of (v - shift) and of (v - shift)**2 per quantity (shift: a pilot
    mean, which keeps the variance free of cancellation). For each point, quantity c and
    interval end s, a window of W slots [wlo, wlo + W / winv): below[i, c, s] counts values under
    it, whist[i, c, s, k] values in slot k (floor((v - wlo) * winv) == k). ``model`` as
    `fill_values`.
    """
    for i in nb.prange(q.shape[0]):
        ev = np.empty((4, n))
        fill_values(model, t0, n, q, i, pidx[i], ev)
        for c in range(4):
            a, b, c0, c1 = _sums_below(ev[c], n, shift[i, c], wlo[i, c, 0], wlo[i, c, 1])
            acc[i, c, 0] += a
            acc[i, c, 1] += b
            below[i, c, 0] += c0
            below[i, c, 1] += c1
            _count_windows(
                ev[c],
                n,
                wlo[i, c, 0],
                winv[i, c, 0],
                wlo[i, c, 1],
                winv[i, c, 1],
                whist[i, c, 0],
                whist[i, c, 1],
            )


@nb.njit(**JIT)
def _keep(v, n, i, c, vlo, vhi, wlo, winv, target, offset, fill, buf):
    """Append to buf the v[:n] in the target slot of either interval end of quantity c."""
    lo0 = vlo[i, c, 0]
    hi0 = vhi[i, c, 0]
    lo1 = vlo[i, c, 1]
    hi1 = vhi[i, c, 1]
    for a in range(0, n, 256):  # most stretches of 256 values hold no candidate at all
        b = min(n, a + 256)
        if _hits(v, a, b, lo0, hi0, lo1, hi1) == 0:
            continue
        for k in range(a, b):
            x = v[k]
            # range pre-tests; the slot index, computed as in pass 1, decides
            if x >= lo0 and x <= hi0:
                y = _slot(x, wlo[i, c, 0], winv[i, c, 0])
                if y >= 0.0 and np.int64(y) == target[i, c, 0]:
                    buf[offset[i, c, 0] + fill[i, c, 0]] = x
                    fill[i, c, 0] += 1
            if x >= lo1 and x <= hi1:
                y = _slot(x, wlo[i, c, 1], winv[i, c, 1])
                if y >= 0.0 and np.int64(y) == target[i, c, 1]:
                    buf[offset[i, c, 1] + fill[i, c, 1]] = x
                    fill[i, c, 1] += 1


@nb.njit(**PJIT)
def pass_capture(model, t0, n, q, pidx, wlo, winv, target, vlo, vhi, offset, fill, buf):
    """Pass 2: keep the values in window slot target[i, c, s] (exact order statistics).

    vlo, vhi (npts, 4, 2): that slot's value range widened by a few ulps (pre-test);
    offset (npts, 4, 2): start of each capture in buf; fill: values stored so far. ``model`` as
    `fill_values`.
    """
    for i in nb.prange(q.shape[0]):
        ev = np.empty((4, n))
        fill_values(model, t0, n, q, i, pidx[i], ev)
        for c in range(4):
            _keep(ev[c], n, i, c, vlo, vhi, wlo, winv, target, offset, fill, buf)


# ------------------------------------------------------------------------------------------
# Hot path of the kinematics (constant profiles, normal noise): one pass over the trials, fused
# per point and sub-block of SUB trials (the 21 chain terms of a sub-block stay in cache while a
# chunk of points uses them). Per (point, sub-block): the values (one vectorised loop; the ~1.3 %
# of samples with a slow-path normal are redone exactly), then sums, counts below each
# interval-end window and a flag per sample inside some window (one vectorised loop), then the
# flagged values are kept in their windows' stores. The point loop is one function with the
# value loop inlined: a call per (point, sub-block) cost ~0.5 ns per sample. Loops index with
# unsigned integers where a signed index costs a wrap-around test that stops vectorisation.
# ------------------------------------------------------------------------------------------
#: Trials per sub-block of the fused pass.
SUB = 512


#: Points per parallel chunk; the chunking does not change any number.
_N_CHUNKS = 64


#: Bit 0 of each byte: a bool array read eight entries at a time.
_BYTE_ONES = np.uint64(0x0101010101010101)


@nb.njit(inline="always", **JIT)
def _chain(terms, k, q0, q1, q2, n0, n1, n2):
    """E_x, E_y, E_z, |E| of trial row k of ``terms`` at commanded q and axis noise n (mm).

    The one expression of the collapsed chain: every path must produce the same bits for the
    same sample (no FMA contraction: fastmath is off)."""
    e0 = (terms[k, 0] + q0 * terms[k, 3] + q1 * terms[k, 6] + q2 * terms[k, 9]
          + n0 * terms[k, 12] + n1 * terms[k, 15] + n2 * terms[k, 18])  # fmt: skip
    e1 = (terms[k, 1] + q0 * terms[k, 4] + q1 * terms[k, 7] + q2 * terms[k, 10]
          + n0 * terms[k, 13] + n1 * terms[k, 16] + n2 * terms[k, 19])  # fmt: skip
    e2 = (terms[k, 2] + q0 * terms[k, 5] + q1 * terms[k, 8] + q2 * terms[k, 11]
          + n0 * terms[k, 14] + n1 * terms[k, 17] + n2 * terms[k, 20])  # fmt: skip
    return e0, e1, e2, math.sqrt(e0 * e0 + e1 * e1 + e2 * e2)


@nb.njit(inline="always", **JIT)
def _bit_index(low):
    """Index of the single set bit of ``low`` (a power of two, uint64)."""
    return _DEBRUIJN_INDEX[np.int64((low * _DEBRUIJN) >> np.uint64(58))]


@nb.njit(**JIT)
def _redo_sample(terms, tkeys, k, q0, q1, q2, s0, s1, s2, fkey, pi, ev, j):
    """Exact values (slow-path normals included) of trial row k of point pi into ev[:, j]."""
    z0, z1, z2 = _three_normals(tkeys[k], fkey, pi)
    ev[0, j], ev[1, j], ev[2, j], ev[3, j] = _chain(terms, k, q0, q1, q2, s0 * z0, s1 * z1, s2 * z2)


@nb.njit(inline="always", **JIT)
def _values_run(terms, tkeys, k0, m, q0, q1, q2, s0, s1, s2, fkey, pi, ev, ok, okw):
    """Values of point pi for the trial rows k0 .. k0+m-1 into ev (4, SUB): E_x, E_y, E_z, |E|.

    One vectorised loop takes the ziggurat's fast path (`_zig_fast3`); the samples with a
    slow-path normal (~1.3 %) are found eight flags at a time through ``okw`` (``ok``'s bytes as
    uint64, SUB // 8) and redone exactly: the numbers of ``fill_values``."""
    c = np.uint64(pi) * np.uint64(4)
    e0 = ev[0]  # row views: stores through the 2-D array kept the loop scalar
    e1 = ev[1]
    e2 = ev[2]
    e3 = ev[3]
    for j in range(m):
        k = np.uint64(k0) + np.uint64(j)
        z0, z1, z2, good = _zig_fast3(tkeys[k], c)
        e0[j], e1[j], e2[j], e3[j] = _chain(terms, k, q0, q1, q2, s0 * z0, s1 * z1, s2 * z2)
        ok[j] = good
    for w in range((m + 7) >> 3):
        bad = ~okw[w] & _BYTE_ONES
        while bad != 0:
            low = bad & (~bad + np.uint64(1))
            bad ^= low
            j = (w << 3) + (_bit_index(low) >> 3)
            if j < m:
                _redo_sample(terms, tkeys, k0 + j, q0, q1, q2, s0, s1, s2, fkey, pi, ev, j)


@nb.njit(**RJIT)
def _sums_flags(ev, m, i, shift, lo, hi, out, flag):
    """Sums, counts below each window and window flags of ev[:, :m] (one vectorised loop).

    For point i: shift (npts, 4); lo, hi (npts, 4, 2): window (c, e) is [lo, hi]. Adds to out
    (4, 4), per quantity c: sum (v - shift), sum (v - shift)^2, #(v < lo[i, c, 0]),
    #(v < lo[i, c, 1]). flag[j] (uint8): bit 2c + e set when sample j lies in window (c, e).
    """
    e0 = ev[0]
    e1 = ev[1]
    e2 = ev[2]
    e3 = ev[3]
    a0 = a1 = a2 = a3 = 0.0
    b0 = b1 = b2 = b3 = 0.0
    c00 = c01 = c10 = c11 = c20 = c21 = c30 = c31 = 0
    h0, h1, h2, h3 = shift[i, 0], shift[i, 1], shift[i, 2], shift[i, 3]
    l00, l01, l10, l11 = lo[i, 0, 0], lo[i, 0, 1], lo[i, 1, 0], lo[i, 1, 1]
    l20, l21, l30, l31 = lo[i, 2, 0], lo[i, 2, 1], lo[i, 3, 0], lo[i, 3, 1]
    u00, u01, u10, u11 = hi[i, 0, 0], hi[i, 0, 1], hi[i, 1, 0], hi[i, 1, 1]
    u20, u21, u30, u31 = hi[i, 2, 0], hi[i, 2, 1], hi[i, 3, 0], hi[i, 3, 1]
    for j in range(m):
        x0 = e0[j]
        x1 = e1[j]
        x2 = e2[j]
        x3 = e3[j]
        d0 = x0 - h0
        d1 = x1 - h1
        d2 = x2 - h2
        d3 = x3 - h3
        a0 += d0
        a1 += d1
        a2 += d2
        a3 += d3
        b0 += d0 * d0
        b1 += d1 * d1
        b2 += d2 * d2
        b3 += d3 * d3
        c00 += x0 < l00
        c01 += x0 < l01
        c10 += x1 < l10
        c11 += x1 < l11
        c20 += x2 < l20
        c21 += x2 < l21
        c30 += x3 < l30
        c31 += x3 < l31
        flag[j] = (
            np.uint8((x0 >= l00) & (x0 <= u00))
            | np.uint8((x0 >= l01) & (x0 <= u01)) << np.uint8(1)
            | np.uint8((x1 >= l10) & (x1 <= u10)) << np.uint8(2)
            | np.uint8((x1 >= l11) & (x1 <= u11)) << np.uint8(3)
            | np.uint8((x2 >= l20) & (x2 <= u20)) << np.uint8(4)
            | np.uint8((x2 >= l21) & (x2 <= u21)) << np.uint8(5)
            | np.uint8((x3 >= l30) & (x3 <= u30)) << np.uint8(6)
            | np.uint8((x3 >= l31) & (x3 <= u31)) << np.uint8(7)
        )  # fmt: skip
    out[0, 0] += a0
    out[1, 0] += a1
    out[2, 0] += a2
    out[3, 0] += a3
    out[0, 1] += b0
    out[1, 1] += b1
    out[2, 1] += b2
    out[3, 1] += b3
    out[0, 2] += c00
    out[0, 3] += c01
    out[1, 2] += c10
    out[1, 3] += c11
    out[2, 2] += c20
    out[2, 3] += c21
    out[3, 2] += c30
    out[3, 3] += c31


@nb.njit(inline="always", **JIT)
def _keep_flagged(ev, flagw, m, i, lo, hi, store, off, cap, fill):
    """Append each flagged value to the stores of the windows its flag names.

    ``flagw``: the flags (`_sums_flags`) eight at a time as uint64. Window (i, c, e) owns
    store[off : off + cap + 1] and counts its values in fill, stored while fill <= cap (fill >
    cap: overflow, the window is lost); a value is written at the next free place, the spare
    last one once full (no branch on the capacity)."""
    for w in range((m + 7) >> 3):
        hits = flagw[w]
        while hits != 0:
            low = hits & (~hits + np.uint64(1))
            sh = np.uint64(_bit_index(low) & ~7)  # the byte of the first flagged sample
            mk = (hits >> sh) & np.uint64(255)
            hits ^= mk << sh
            j = (w << 3) + np.int64(sh >> np.uint64(3))
            if j >= m:  # bytes past the sub-block's end hold an earlier point's flags
                break
            while mk != 0:
                lb = mk & (~mk + np.uint64(1))
                mk ^= lb
                b = _bit_index(lb)
                c = b >> 1
                e = b & 1
                f = fill[i, c, e]
                store[off[i, c, e] + min(f, cap[i, c, e])] = ev[c, j]
                fill[i, c, e] = f + 1


@nb.njit(inline="always", **JIT)
def _count_and_keep(ev, m, i, shift, lo, hi, acc, below, store, off, cap, fill, red, flag,
                    flagw):  # fmt: skip
    """The values ev[:, :m] of point i (a sub-block) into its sums, counts below the windows and
    window stores (`_sums_flags`, `_keep_flagged`); red (4, 4), flag / flagw: work space."""
    red[:] = 0.0
    _sums_flags(ev, m, i, shift, lo, hi, red, flag)
    for c in range(4):
        acc[i, c, 0] += red[c, 0]
        acc[i, c, 1] += red[c, 1]
        below[i, c, 0] += np.int64(red[c, 2])
        below[i, c, 1] += np.int64(red[c, 3])
    _keep_flagged(ev, flagw, m, i, lo, hi, store, off, cap, fill)


@nb.njit(**PJIT)
def pass_keep(terms, n, q, pidx, sig, tkeys, fkey, shift, lo, hi, acc, below, store, off, cap,
              fill):  # fmt: skip
    """The fused pass over trial rows 0 .. n-1 of a block (hot path).

    Parameters
    ----------
    terms : ndarray (>= n, 21), column-major
        Collapsed chain terms (`trial_terms`) of the block's trials.
    q : ndarray (npts, 3), mm; pidx : ndarray (npts,) int64
        Commanded positions and the points' indices (keys of their noise).
    sig : ndarray (3,), mm
        Normal noise std per axis.
    tkeys : ndarray (>= n,) uint64
        `trial_key` of the block's trials; fkey: the fallback stream's key.
    shift : ndarray (npts, 4)
        Shifts of the sums (a pilot mean: no cancellation in the variance).
    lo, hi : ndarray (npts, 4, 2)
        Interval-end window (c, e): values in [lo, hi] are kept, those below lo counted.
    acc : ndarray (npts, 4, 2)
        Adds sum (v - shift) and sum (v - shift)**2; below (npts, 4, 2) int64: adds #(v < lo).
    store, off, cap, fill
        The windows' stores (`_keep_flagged`).

    Each point sees the trials in increasing order in sub-blocks of SUB: sums and counts are
    the same whatever the number of threads.
    """
    npts = q.shape[0]
    nchunk = min(npts, _N_CHUNKS)
    per = (npts + nchunk - 1) // nchunk
    s0 = sig[0]
    s1 = sig[1]
    s2 = sig[2]
    for ch in nb.prange(nchunk):
        ev = np.empty((4, SUB))
        okw = np.empty(SUB // 8, dtype=np.uint64)
        ok = okw.view(np.bool_)
        flagw = np.empty(SUB // 8, dtype=np.uint64)
        flag = flagw.view(np.uint8)
        red = np.empty((4, 4))
        for k0 in range(0, n, SUB):
            m = min(SUB, n - k0)
            for i in range(ch * per, min(npts, (ch + 1) * per)):
                _values_run(terms, tkeys, k0, m, q[i, 0], q[i, 1], q[i, 2], s0, s1, s2, fkey,
                            pidx[i], ev, ok, okw)  # fmt: skip
                _count_and_keep(ev, m, i, shift, lo, hi, acc, below, store, off, cap, fill, red,
                                flag, flagw)  # fmt: skip


@nb.njit(**PJIT)
def pass_keep_model(model, t0, n, q, pidx, shift, lo, hi, acc, below, store, off, cap, fill):
    """`pass_keep` for any bench model (``model`` as `fill_values`: position-dependent errors,
    speed x tau delay): each point's values of the block by `fill_values`, then its sums,
    counts and kept values by sub-blocks of SUB trials as `pass_keep`. Arguments as
    `pass_keep`; trials t0 .. t0+n-1 are rows 0 .. n-1 of the model's arrays."""
    npts = q.shape[0]
    nchunk = min(npts, _N_CHUNKS)
    per = (npts + nchunk - 1) // nchunk
    for ch in nb.prange(nchunk):
        ev = np.empty((4, n))
        sub = np.empty((4, SUB))
        flagw = np.empty(SUB // 8, dtype=np.uint64)
        flag = flagw.view(np.uint8)
        red = np.empty((4, 4))
        for i in range(ch * per, min(npts, (ch + 1) * per)):
            fill_values(model, t0, n, q, i, pidx[i], ev)
            for k0 in range(0, n, SUB):
                m = min(SUB, n - k0)
                for c in range(4):
                    for j in range(m):
                        sub[c, j] = ev[c, k0 + j]
                _count_and_keep(sub, m, i, shift, lo, hi, acc, below, store, off, cap, fill,
                                red, flag, flagw)  # fmt: skip


#: Histogram bins of a window's values when it narrows (`narrow_windows`).
NARROW_BINS = 256


@nb.njit(**PJIT)
def narrow_windows(store, off, cap, fill, below, lo, hi, klo, khi):
    """Shrink each window to the values that can still hold its order statistic (flat arrays
    over the windows, shape (nw,)).

    A window holds in store[off : off + fill] the values in [lo, hi] of the trials seen so far
    and counts in ``below`` those under lo. Ranks klo <= khi (1-based, among the trials seen)
    must stay inside: the new lo is the smallest stored value of the histogram bin holding rank
    klo, the new hi the largest of the bin holding rank khi (a rank outside the stored ones
    leaves that edge). Values outside are dropped, those under the new lo added to ``below``.
    Windows that overflowed (fill > cap) or hold nothing are left alone.
    """
    nw = fill.shape[0]
    nchunk = min(nw, 256)
    per = (nw + nchunk - 1) // nchunk
    for ch in nb.prange(nchunk):
        cnt = np.empty(NARROW_BINS, np.int64)
        vmin = np.empty(NARROW_BINS)
        vmax = np.empty(NARROW_BINS)
        for w in range(ch * per, min(nw, (ch + 1) * per)):
            f = fill[w]
            a = lo[w]
            b = hi[w]
            kl = klo[w] - below[w]
            kh = khi[w] - below[w]
            if f > cap[w] or f == 0 or not b > a or (kl <= 1 and kh >= f):
                continue
            o = off[w]
            inv = NARROW_BINS / (b - a)
            cnt[:] = 0
            vmin[:] = np.inf
            vmax[:] = -np.inf
            for t in range(f):
                v = store[o + t]
                k = min(np.int64((v - a) * inv), NARROW_BINS - 1)
                cnt[k] += 1
                vmin[k] = min(vmin[k], v)
                vmax[k] = max(vmax[k], v)
            new_lo = a
            new_hi = b
            cum = 0
            for k in range(NARROW_BINS):
                if cum < kl <= cum + cnt[k] and kl > 1:
                    new_lo = vmin[k]
                if cum < kh <= cum + cnt[k] and kh < f:
                    new_hi = vmax[k]
                cum += cnt[k]
            kept = 0
            under = 0
            for t in range(f):  # in place, branch-free: a kept value moves down or stays
                v = store[o + t]
                under += v < new_lo
                store[o + kept] = v
                kept += (v >= new_lo) & (v <= new_hi)
            fill[w] = kept
            below[w] += under
            lo[w] = new_lo
            hi[w] = new_hi


@nb.njit(**PJIT)
def select_ends(store, off, fill, cap, below, lo, hi, rank, out):
    """Order statistic of 1-based rank rank[w] among all trials, per window (flat arrays).

    It is the (rank - below)-th smallest stored value (all in [lo, hi]) when that lies among
    the stored ones and the window did not overflow; otherwise out[w] = NaN (the caller
    recomputes that point). A histogram of NARROW_BINS bins finds the bin holding the rank;
    that bin's values are moved to the front of the store and selected among (three cheap
    passes instead of a selection over all: 3x faster). The stores are overwritten."""
    nw = fill.shape[0]
    nchunk = min(nw, 256)
    per = (nw + nchunk - 1) // nchunk
    for ch in nb.prange(nchunk):
        cnt = np.empty(NARROW_BINS, np.int64)
        for w in range(ch * per, min(nw, (ch + 1) * per)):
            f = fill[w]
            k = rank[w] - below[w]
            if f > cap[w] or k < 1 or k > f:
                out[w] = np.nan
                continue
            o = off[w]
            a = lo[w]
            if not hi[w] > a:  # every value equal
                out[w] = store[o]
                continue
            inv = NARROW_BINS / (hi[w] - a)
            cnt[:] = 0
            for t in range(f):
                cnt[min(np.int64((store[o + t] - a) * inv), NARROW_BINS - 1)] += 1
            before = 0
            kb = 0
            while before + cnt[kb] < k:
                before += cnt[kb]
                kb += 1
            n = 0
            for t in range(f):  # the bin's values to the front, branch-free
                v = store[o + t]
                store[o + n] = v
                n += min(np.int64((v - a) * inv), NARROW_BINS - 1) == kb
            select_inplace(store, o, o + n - 1, o + k - before - 1)
            out[w] = store[o + k - before - 1]
