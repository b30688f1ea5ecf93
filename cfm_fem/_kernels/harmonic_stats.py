"""Statistics of a node's field changes at several U_p values under its harmonic model.

Under the linear interpolant a trial's component errors scale exactly with U_p, so their order
statistics are computed once. A polynomial's do not: at U_p = s the change of component c is
s e_c(s) with e_c(s) = L_c + s R_c(s), L_c the first-order part. The tails of e_c are still
those of L_c up to the remainder: if every trial's |e_c - L_c| <= D, the h smallest values of
e_c are among the trials with L_c <= v + 2 D, v any value with at least h trials of L_c below
it. So each tail of L_c is gathered once per node, and at each U_p only its candidates are
read. Of those, only the values up to a threshold with at least h values below it are sorted:
s (v + D) always qualifies; the previous U_p's h-th value, scaled, is tighter and is taken
when the count confirms it. |B| is handled the same way with the first-order change of |B|
as its L. The bound D comes from the largest displacement and the norms of the coefficients
per degree (`harmonic_bounds`); where it is too loose for the gathered tail (a field whose
first-order part vanishes, large U_p against the field's curvature length), the statistic is
computed from the whole sample, so every number is exact either way.

The field changes are computed per block of trials (`PART_BLOCK`, parts in rows of a constant
pitch, `PART_PITCH`) by a loop LLVM vectorises, straight into one row per U_p and quantity.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from .harmonic_bounds import BOUND_SAFETY
from .harmonic_parts import PART_PITCH
from .options import FJIT, JIT, SJIT
from .order_stats import (
    TAIL_PILOT,
    _intervals,
    sample_stats,
    select_inplace,
    sort_in_range,
    sort_values,
)

#: Tails of the first-order part beyond its mean -+ this many std are gathered (~16 % each):
#: room for the candidates of the 5 % tails the 95 % intervals need when the field bends.
GATHER_SIGMAS = 1.0

#: Values beyond the h-th of a tail whose threshold guides the next U_p, besides h / 32: room
#: for the reordering between two U_p values, so that the guess rarely falls short.
GUIDE_PAD = 4


@nb.njit(**SJIT)
def changes_block(parts, m, s, b0, abs0, out, t0, shift, sums):
    """Field changes at U_p = ``s`` of a block of trials from its parts (`homogeneous_parts`),
    and their shifted sums.

    Parameters
    ----------
    parts : ndarray, shape (>= N_SLOTS * PART_PITCH,), T
    m : int
        Trials in the block.
    s : float, mm
        U_p; the parts are per unit displacement scale, so part q is weighted by s^q.
    b0 : ndarray, shape (3,), T
        The model's field at the node.
    abs0 : float
        |b0|, T.
    out : ndarray, shape (4, >= t0 + m), T
        ``out[c, t0 + t]``: change of B_c (c < 3), and of |B| (c = 3), of the block's trial t.
    t0 : int
        The block's first trial.
    shift : ndarray, shape (4,), T
        Per quantity, a value near its changes (the first trial's): the sums keep the
        precision of the variance.
    sums : ndarray, shape (4, 2), T
        Per quantity, the sums of (change - shift) and of its square are added here.
    """
    bx = b0[0]
    by = b0[1]
    bz = b0[2]
    out_x = out[0, t0 : t0 + m]  # 1-D views: the loop below stays vectorised
    out_y = out[1, t0 : t0 + m]
    out_z = out[2, t0 : t0 + m]
    out_b = out[3, t0 : t0 + m]
    fx, fy, fz, fb = shift[0], shift[1], shift[2], shift[3]
    ax = ay = az = ab = 0.0
    qx = qy = qz = qb = 0.0
    for t in range(m):
        ex = parts[12 * PART_PITCH + t] * s + parts[9 * PART_PITCH + t]
        ey = parts[13 * PART_PITCH + t] * s + parts[10 * PART_PITCH + t]
        ez = parts[14 * PART_PITCH + t] * s + parts[11 * PART_PITCH + t]
        ex = ex * s + parts[6 * PART_PITCH + t]
        ey = ey * s + parts[7 * PART_PITCH + t]
        ez = ez * s + parts[8 * PART_PITCH + t]
        ex = ex * s + parts[3 * PART_PITCH + t]
        ey = ey * s + parts[4 * PART_PITCH + t]
        ez = ez * s + parts[5 * PART_PITCH + t]
        ex = (ex * s + parts[t]) * s
        ey = (ey * s + parts[PART_PITCH + t]) * s
        ez = (ez * s + parts[2 * PART_PITCH + t]) * s
        x0 = bx + ex
        x1 = by + ey
        x2 = bz + ez
        den = math.sqrt(x0 * x0 + x1 * x1 + x2 * x2) + abs0
        num = 2.0 * (bx * ex + by * ey + bz * ez) + ex * ex + ey * ey + ez * ez
        eb = num / den if den > 0.0 else 0.0
        out_x[t] = ex
        out_y[t] = ey
        out_z[t] = ez
        out_b[t] = eb
        ax += ex - fx
        qx += (ex - fx) ** 2
        ay += ey - fy
        qy += (ey - fy) ** 2
        az += ez - fz
        qz += (ez - fz) ** 2
        ab += eb - fb
        qb += (eb - fb) ** 2
    sums[0, 0] += ax
    sums[0, 1] += qx
    sums[1, 0] += ay
    sums[1, 1] += qy
    sums[2, 0] += az
    sums[2, 1] += qz
    sums[3, 0] += ab
    sums[3, 1] += qb


@nb.njit(**FJIT)
def first_order_abs(parts, m, b_hat, dst):
    """First-order change of |B| per unit s of a block's trials: b_hat . part 1, into dst[:m]."""
    bx = b_hat[0]
    by = b_hat[1]
    bz = b_hat[2]
    for t in range(m):
        dst[t] = bx * parts[t] + by * parts[PART_PITCH + t] + bz * parts[2 * PART_PITCH + t]


@nb.njit(**JIT)
def tail_quantile_z(n, q):
    """z with P(Z < -z) = 1.25 h / n (h = n - q, Z standard normal): the first-order parts are
    normal samples, so about 1.25 h of them lie below mean - z std, enough to hold the h
    smallest (`gather_tails` counts them; the statistics are exact either way). 0 if the
    tails are not small."""
    f = 1.25 * (n - q) / max(n, 1)
    if not 0.0 < f < 0.5:
        return 0.0
    lo = 0.0
    hi = 40.0
    for _ in range(64):  # bisection on the normal tail
        mid = 0.5 * (lo + hi)
        if 0.5 * math.erfc(mid / math.sqrt(2.0)) > f:
            lo = mid
        else:
            hi = mid
    return lo


@nb.njit(**JIT)
def _select_in_tail(val, count, low_side, g, h, work):
    """The h-th value of one tail of a gathered list: the h-th smallest of ``val[:count]``
    at or below ``g`` (``low_side``), or the h-th largest at or above it."""
    k = 0
    for i in range(count):
        v = val[i]
        if (v <= g) if low_side else (v >= g):
            work[k] = v
            k += 1
    pos = h - 1 if low_side else k - h
    select_inplace(work, np.int64(0), k - 1, pos)
    return work[pos]


@nb.njit(**JIT)
def candidate_margin(v_lo, v_hi, bound):
    """Margin of the candidates beyond v_lo and v_hi under a remainder ``bound``
    (`tail_stats`): twice the bound, and a relative safety for rounding."""
    return 2.0 * bound + BOUND_SAFETY * (abs(v_lo) + abs(v_hi) + bound)


@nb.njit(**JIT)
def tail_pilot(lin, m, z_h, limits):
    """Where `gather_tails` gathers, from the leading values ``lin[:m]`` (m <= `TAIL_PILOT`):
    limits[:] = g_lo, g_hi, v_lo, v_hi. False (and infinite limits) if nothing is gathered."""
    pm = 0.0
    for t in range(m):
        pm += lin[t]
    pm /= max(m, 1)
    pv = 0.0
    for t in range(m):
        pv += (lin[t] - pm) ** 2
    ps = math.sqrt(pv / max(m - 1, 1))
    g_lo = pm - GATHER_SIGMAS * ps
    g_hi = pm + GATHER_SIGMAS * ps
    if not (g_lo < g_hi and z_h > 0.0):  # the whole-sample path
        limits[0] = -np.inf
        limits[1] = np.inf
        limits[2] = -np.inf
        limits[3] = np.inf
        return False
    limits[0] = g_lo
    limits[1] = g_hi
    limits[2] = min(pm - z_h * ps, g_lo)
    limits[3] = max(pm + z_h * ps, g_hi)
    return True


@nb.njit(**JIT)
def gather_block(lin, m, t0, limits, val, idx, k):
    """Append the values of lin[:m] at most g_lo or at least g_hi (``limits``), with their
    trial index t0 + t, to val[k:] and idx[k:]; returns the new length."""
    g_lo = limits[0]
    g_hi = limits[1]
    j = np.uint64(k)  # unsigned: no negative-index wraparound in the loop
    for t in range(m):  # branch-free: one list, one counter
        v = lin[t]
        val[j] = v
        idx[j] = t0 + t
        j += np.uint64((v <= g_lo) | (v >= g_hi))
    return np.int64(j)


@nb.njit(**JIT)
def finish_tails(val, k, h, limits, counts, work):
    """Counts of a gathered list of k values into ``counts``, and v_lo / v_hi selected where
    the pilot misplaced them (`gather_tails`)."""
    g_lo = limits[0]
    n_lo = 0
    c_lo = 0
    c_hi = 0
    for i in range(k):
        v = val[i]
        n_lo += v <= g_lo
        c_lo += v <= limits[2]
        c_hi += v >= limits[3]
    if c_lo < h <= n_lo:  # the pilot misplaced v: select it (rare; exact either way)
        limits[2] = _select_in_tail(val, k, True, g_lo, h, work)
        c_lo = h
    if c_hi < h <= k - n_lo:
        limits[3] = _select_in_tail(val, k, False, limits[1], h, work)
        c_hi = h
    counts[0] = k
    counts[1] = n_lo
    counts[2] = c_lo
    counts[3] = c_hi


@nb.njit(**JIT)
def gather_tails(lin, n, z_h, h, val, idx, limits, counts, work):
    """Trials in the two tails of a first-order part, in one list: `tail_pilot` on the
    leading `TAIL_PILOT` values, `gather_block`, `finish_tails` (the sweep runs these per
    block of trials, while the block's parts are at hand).

    Parameters
    ----------
    lin : ndarray, shape (>= n,)
        The first-order part per trial.
    n : int
    z_h : float
        `tail_quantile_z`.
    h : int
        Order statistics needed in each tail (n - q).
    val, idx : ndarray, shape (>= n,)
        Output: values <= g_lo or >= g_hi with their trial index, in trial order
        (g = mean -+ `GATHER_SIGMAS` std of the leading `TAIL_PILOT` values).
    limits : ndarray, shape (4,)
        Output: g_lo, g_hi and v_lo = mean - z_h std, v_hi = mean + z_h std (clipped to g);
        where fewer than h values lie beyond one of those (the pilot's mean or std off, a
        first-order part far from normal), that v is the h-th value of its tail, selected.
    counts : ndarray, shape (4,), int64
        Output: values gathered, values <= g_lo, and values <= v_lo and >= v_hi.
    work : ndarray, shape (>= n,)
        Work space.
    """
    counts[:] = 0
    if tail_pilot(lin, min(n, TAIL_PILOT), z_h, limits):
        k = gather_block(lin, n, 0, limits, val, idx, 0)
        finish_tails(val, k, h, limits, counts, work)


@nb.njit(**JIT)
def keep_candidates(tails, counts, limits, bound):
    """Keep, of a gathered list (in place, in order), the entries that are candidates under
    ``bound``, the largest of the node's U_p values (`tail_stats`): the thresholds of a
    smaller bound are tighter, so every U_p finds its candidates among them."""
    val, idx = tails
    margin = candidate_margin(limits[2], limits[3], bound)
    thr_lo = limits[2] + margin
    thr_hi = limits[3] - margin
    if not (thr_lo <= limits[0] and thr_hi >= limits[1]):
        return
    k = 0
    for i in range(counts[0]):  # branch-free
        v = val[i]
        val[k] = v
        idx[k] = idx[i]
        k += (v <= thr_lo) | (v >= thr_hi)
    counts[0] = k
    limits[0] = thr_lo  # every value up to here is still listed
    limits[1] = thr_hi


@nb.njit(**JIT)
def _candidates(x, tails, count, thr_lo, thr_hi, low, high):
    """Changes of the trials of a gathered list beyond the thresholds of its first-order part:
    low[:k] (at most thr_lo) and high[:m] (at least thr_hi); returns k, m."""
    val, idx = tails
    k = np.uint64(0)  # unsigned: no negative-index wraparound
    m = np.uint64(0)
    for i in range(count):  # branch-free; k and m depend on the list, not on the loads of x
        v = val[i]
        xi = x[idx[i]]
        low[k] = xi
        k += np.uint64(v <= thr_lo)
        high[m] = xi
        m += np.uint64(v >= thr_hi)
    return np.int64(k), np.int64(m)


@nb.njit(**JIT)
def _keep_up_to(a, k, tau, sign):
    """Keep, in place and in order, the values of a[:k] with sign * value <= sign * tau.

    Returns their count, their largest sign * value (to bound a sort's range) and whether a
    value is NaN."""
    j = np.uint64(0)
    far = -np.inf
    nan = False
    for i in range(k):
        v = a[i]
        a[j] = v
        j += np.uint64(sign * v <= sign * tau)
        far = max(far, -sign * v)
        nan |= v != v
    return np.int64(j), far, nan


@nb.njit(**JIT)
def tail_stats(x, n, q, s, bound, tails, limits, counts, guide, stats, low, high, sums, work):
    """Statistics (`sample_stats` order) of the field changes ``x[:n]`` at U_p = ``s`` from
    the candidates of the gathered tails of their first-order part; False if the bound does
    not confine the candidates to the gathered tails (the caller then takes the whole sample).

    The h = n - q smallest changes are among the trials whose first-order part is at most
    v_lo + 2 bound: at least h trials lie below v_lo, their changes per unit s are at most
    v_lo + bound, and any trial beyond has a larger one. Of those candidates only the changes
    at most tau are sorted, tau any value with at least h changes at or below it:
    s (v_lo + bound), or tighter, ``guide``'s guess when at least h candidates confirm it.

    Parameters
    ----------
    x : ndarray, shape (>= n,), T
        Changes at U_p = s.
    n, q : int
        Trials, coverage count.
    s : float, mm
        U_p, > 0.
    bound : float
        Upper bound of |change / s - first-order part| over every trial, in the first-order
        part's units.
    tails : tuple
        (val, idx) of `gather_tails`.
    limits, counts : ndarray, shape (4,)
        Of `gather_tails`.
    guide : ndarray, shape (2,)
        In: per unit s, guesses of a change a little beyond the h-th smallest and the h-th
        largest (NaN: none); out: this U_p's (`GUIDE_PAD`), for the next one.
    stats : ndarray, shape (6,)
        Output.
    low, high : ndarray, shape (>= counts[0],)
        Work space.
    sums : ndarray, shape (3,)
        Shift, sum of (x - shift) and of its square over x[:n] (`changes_block`).
    work : tuple
        `radix_work` (n).
    """
    h = n - q
    if n < 2 or h < 1 or counts[2] < h or counts[3] < h or not bound < np.inf:
        return False
    margin = candidate_margin(limits[2], limits[3], bound)
    thr_lo = limits[2] + margin
    thr_hi = limits[3] - margin
    if not (thr_lo <= limits[0] and thr_hi >= limits[1]):  # candidates beyond the list
        return False
    # at least h changes per unit s at most v_lo + bound (at least v_hi - bound)
    sure_lo = s * (limits[2] + 0.5 * margin)
    sure_hi = s * (limits[3] - 0.5 * margin)
    tau_lo = min(s * guide[0], sure_lo) if guide[0] == guide[0] else sure_lo
    tau_hi = max(s * guide[1], sure_hi) if guide[1] == guide[1] else sure_hi
    # a change at most tau needs a first-order part at most tau / s + bound: fewer to copy
    k_all, m_all = _candidates(x, tails, counts[0], min(thr_lo, tau_lo / s + 0.5 * margin),
                               max(thr_hi, tau_hi / s - 0.5 * margin), low, high)  # fmt: skip
    k, neg_min, nan_lo = _keep_up_to(low, k_all, tau_lo, 1.0)
    m, x_max, nan_hi = _keep_up_to(high, m_all, tau_hi, -1.0)
    if nan_lo or nan_hi:
        return False
    if k < h or m < h:  # a guess too tight (the list was overwritten): the sure thresholds
        tau_lo = sure_lo
        tau_hi = sure_hi
        k_all, m_all = _candidates(x, tails, counts[0], thr_lo, thr_hi, low, high)
        k, neg_min, _ = _keep_up_to(low, k_all, tau_lo, 1.0)
        m, x_max, _ = _keep_up_to(high, m_all, tau_hi, -1.0)
        if k < h or m < h:  # cannot happen when the bound holds: the whole sample decides
            return False
    sort_in_range(low[:k], -neg_min, tau_lo, work)
    sort_in_range(high[:m], tau_hi, x_max, work)
    pad = GUIDE_PAD + h // 32
    guide[0] = low[min(h - 1 + pad, k - 1)] / s
    guide[1] = high[max(m - h - pad, 0)] / s
    shift, s1, s2 = sums[0], sums[1], sums[2]
    stats[0] = shift + s1 / n
    stats[1] = math.sqrt(max(s2 - s1 * s1 / n, 0.0) / (n - 1))
    _intervals(low[:h], high[m - h : m], n, q, stats)
    return True


@nb.njit(**JIT)
def _values_beyond(x, n, tau_lo, tau_hi, low, high):
    """Values of x[:n] at most tau_lo into low[:k] and at least tau_hi into high[:m], in
    order; returns k, m, the smallest and largest value, and whether one is NaN."""
    k = np.uint64(0)
    m = np.uint64(0)
    one = np.uint64(1)
    mn = np.inf
    mx = -np.inf
    nan = False
    for i in range(n):
        v = x[i]
        if v <= tau_lo:  # rarely taken: cheaper than a count that waits for every load
            low[k] = v
            k += one
        if v >= tau_hi:
            high[m] = v
            m += one
        mn = min(mn, v)
        mx = max(mx, v)
        nan |= v != v
    return np.int64(k), np.int64(m), mn, mx, nan


@nb.njit(**JIT)
def _sort_bounded(a, lo, hi, work):
    """Sort ``a`` (values in [lo, hi]) in place: `sort_in_range`, or `sort_values` for long
    lists (its 24-bit key)."""
    if a.shape[0] > 4096:
        sort_values(a)
    else:
        sort_in_range(a, lo, hi, work)


@nb.njit(**JIT)
def whole_sample_stats(x, n, q, s, z_h, guide, stats, low, high, sums, work, scratch):
    """Statistics (`sample_stats` order) of the changes ``x[:n]`` at U_p = ``s`` where the
    first-order part's tails do not confine them (`tail_stats` False).

    One pass takes the values beyond thresholds with at least h = n - q values beyond each:
    ``guide``'s (`tail_stats`), else mean -+ z_h std, where a normal sample has about 1.25 h
    (`tail_quantile_z`); a count that falls short leaves the sample to `sample_stats`. Exact
    either way; ``guide`` is updated as by `tail_stats` (NaN after `sample_stats`).
    ``x`` may be reordered; ``sums`` as in `tail_stats`."""
    h = n - q
    shift, s1, s2 = sums[0], sums[1], sums[2]
    mean = shift + s1 / n
    std = math.sqrt(max(s2 - s1 * s1 / n, 0.0) / (n - 1)) if n > 1 else 0.0
    for attempt in range(2):
        if attempt == 0 and guide[0] == guide[0] and guide[1] == guide[1]:
            tau_lo = s * guide[0]
            tau_hi = s * guide[1]
        elif attempt == 1 and z_h > 0.0 and std > 0.0:
            tau_lo = mean - z_h * std
            tau_hi = mean + z_h * std
        else:
            continue
        k, m, mn, mx, nan = _values_beyond(x, n, tau_lo, tau_hi, low, high)
        if nan:
            break
        if k >= h and m >= h and h >= 1:
            _sort_bounded(low[:k], mn, tau_lo, work)
            _sort_bounded(high[:m], tau_hi, mx, work)
            pad = GUIDE_PAD + h // 32
            guide[0] = low[min(h - 1 + pad, k - 1)] / s
            guide[1] = high[max(m - h - pad, 0)] / s
            stats[0] = mean
            stats[1] = std
            _intervals(low[:h], high[m - h : m], n, q, stats)
            return
    guide[:] = np.nan
    sample_stats(x, n, q, stats, scratch)


__all__ = [
    "BOUND_SAFETY",
    "GATHER_SIGMAS",
    "GUIDE_PAD",
    "changes_block",
    "first_order_abs",
    "finish_tails",
    "gather_block",
    "gather_tails",
    "candidate_margin",
    "keep_candidates",
    "tail_pilot",
    "tail_quantile_z",
    "tail_stats",
    "whole_sample_stats",
]
