"""Adaptive control-variate estimator of the sweep's statistics under the harmonic model.

At a node, with U_p = s, the error of quantity c (Bx, By, Bz, |B|) of a trial is
Y = F_c(x + s d) - F_c(x), d = W^T z / h (z standard normals, W the per-axis scale, h the
node's length scale). Its first-order part X = s g_c . d is normal with mean 0 and standard
deviation s sigma_c, sigma_c known exactly from the model's gradient (for |B|, g = b_hat . grad
B). On the same trials (common random numbers) Y - X is small, so each statistic is
estimated as the exact value for X plus the sample's difference of Y and X (a difference
estimator), e.g. the 2.5 % quantile

    q_Y ~ -z s sigma_c + (q^_Y - q^_X),   z = Phi^-1((1 + p) / 2),

and likewise the mean (0), the standard deviation (s sigma_c) and the shortest interval
(-+ z s sigma_c for a normal X). The estimator's standard error is the asymptotic one of a
difference of two sample quantiles, sqrt(Var(psi_Y - psi_X) / n) with
psi = (1{V <= q_V} - a) / f_V(q_V), f_X exact and f_Y from the spacing of the order statistics
around q^_Y. That variance holds once the order statistics of s X lie closer together
(1 / (n f_X)) than the remainder e = Y - s X spreads near the quantile; with fewer trials the
estimate follows the remainder of the one or few trials at the quantile, of variance
~ Var(e) / (1 + sd(e) n f_X) (`_few_trials`, Var(e) over the trials of X's tail): while sd(e) is
below 1 / (n f_X) that variance is taken, beyond it the larger of the two
(`_difference_variance`). Where the plain sample quantile has the smaller estimated variance (a
first-order part that follows Y poorly, as near a zero of |B|) the plain statistics of Y are
kept.

Trials are drawn ``pilot`` first, then doubled up to ``cap`` until the standard error of
both ends of |B|'s symmetric interval is at most ``rel_se`` of U_f = max(|low|, |high|) at
every U_p. Trial t of a node is the same whatever the node's neighbours, chunk or thread
(`normals_by_index`), and the node's trial count depends on its own trials only, so the
numbers are the same whatever the chunking.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from .harmonic import expand_node, sparse_basis
from .harmonic_parts import N_SLOTS, PART_BLOCK, PART_PITCH, homogeneous_parts
from .harmonic_stats import changes_block, first_order_abs
from .options import JIT
from .order_stats import _intervals, coverage_count, select_inplace, sort_values, sums_and_tails
from .rng import STREAM_FALLBACK, STREAM_SWEEP, normals_by_index, stream_key, trial_key
from .sweep import sweep_outputs


@nb.njit(**JIT)
def normal_quantile(prob):
    """Phi^-1(prob) of the standard normal, 0 < prob < 1 (bisection on erfc, 64 steps)."""
    lo = -40.0
    hi = 40.0
    for _ in range(64):
        mid = 0.5 * (lo + hi)
        if 0.5 * math.erfc(-mid / math.sqrt(2.0)) < prob:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


@nb.njit(**JIT)
def _copy_ends(a, n, h, low, high):
    """``low[:h] = a[:h]`` and ``high[:h] = a[n - h:n]`` (loops: a slice assignment compiles
    numba's shape-mismatch message, seconds of compile time)."""
    for t in range(h):
        low[t] = a[t]
        high[t] = a[n - h + t]


@nb.njit(**JIT)
def sample_tails(a, n, h, low, high, scratch, copy):
    """Mean, std (ddof 1) of a[:n] and its h smallest (``low[:h]``) and h largest
    (``high[:h]``) values, both ascending; ``a`` is left unchanged.

    ``scratch`` and ``copy`` (>= n) are work space: the tails beyond mean -+ 1.3 std are
    gathered (`sums_and_tails`) and the h extreme values of each selected, or, if a tail is
    thinner than h, selected from a copy of the whole sample; then sorted (`sort_values`: a
    radix pass and an insertion pass, a few ns per value whatever the order the selection
    left them in).
    """
    shift, s1, s2, n_lo, n_hi = sums_and_tails(a, n, scratch, n)
    mean = shift + s1 / n
    std = math.sqrt(max(s2 - s1 * s1 / n, 0.0) / (n - 1))
    if n_lo >= h and n_hi >= h and std > 0.0:
        select_inplace(scratch, np.int64(0), n_lo - 1, h - 1)
        select_inplace(scratch, n - n_hi, n - 1, n - h)
        _copy_ends(scratch, n, h, low, high)
    else:
        for t in range(n):
            copy[t] = a[t]
        select_inplace(copy, np.int64(0), n - 1, h - 1)
        select_inplace(copy, h, n - 1, n - h)
        _copy_ends(copy, n, h, low, high)
    sort_values(low[:h])
    sort_values(high[:h])
    return mean, std


@nb.njit(**JIT)
def _spacing(y_tail, x_tail, s, i, m, n):
    """Slope in probability of the order statistics of Y and of Y - s X around order
    statistic i of n (sorted tails ``y_tail``, ``x_tail``; 2m order statistics apart): the
    inverse density 1 / f_Y and its difference from 1 / f_X. The second comes from the
    differences of paired order statistics, which on common random numbers vary far less
    than either."""
    w = n / (2.0 * m)
    inv_fy = (y_tail[i + m] - y_tail[i - m]) * w
    d_inv = ((y_tail[i + m] - s * x_tail[i + m]) - (y_tail[i - m] - s * x_tail[i - m])) * w
    return inv_fy, d_inv


@nb.njit(**JIT)
def window_trials(xu, n, x_win, lo, hi):
    """The trials of the two tail windows of the first-order part, in index order: X <= x_win[0]
    into ``lo``, else X >= x_win[1] into ``hi`` (each shape >= n); returns their counts."""
    k_lo = 0
    k_hi = 0
    for t in range(n):  # branch-free: every trial is written, the counts say which stay
        v = xu[t]
        in_lo = v <= x_win[0]
        lo[k_lo] = t
        k_lo += in_lo
        hi[k_hi] = t
        k_hi += (v >= x_win[1]) & (not in_lo)
    return k_lo, k_hi


@nb.njit(**JIT)
def _crossings_in_windows(y, xu, s, ends, x_ends, window, tails, h):
    """`_crossings` from the tails alone, or (-1, ...) where they do not settle it.

    The trials of X's tail side (X <= x_lo, X >= x_hi) all lie in X's windows (``window``:
    `window_trials`, disjoint, the quantile ends within their edges), and those at or beyond
    Y's ends among Y's h extreme values (``tails``, ascending) unless a tie reaches a tail's
    edge; so the counts, and the window sums in the same order, come from O(h) trials, not n.
    """
    lo, hi, k_lo, k_hi = window
    low, high = tails
    y_lo, y_hi = ends
    if not (low[h - 1] > y_lo and high[0] < y_hi):  # ties across a tail's edge: all trials
        return -1, -1, np.nan, np.nan
    c_lo = 0
    c_hi = 0
    for j in range(h):
        c_lo += low[j] <= y_lo
        c_hi += high[j] >= y_hi
    s1 = 0.0
    s2 = 0.0
    for j in range(k_lo):
        t = lo[j]
        c_lo -= (y[t] <= y_lo) & (xu[t] <= x_ends[0])
        e = y[t] - s * xu[t]
        s1 += e
        s2 += e * e
    var_lo = _variance(float(k_lo), s1, s2)
    s1 = 0.0
    s2 = 0.0
    for j in range(k_hi):
        t = hi[j]
        c_hi -= (y[t] >= y_hi) & (xu[t] >= x_ends[1])
        e = y[t] - s * xu[t]
        s1 += e
        s2 += e * e
    return c_lo, c_hi, var_lo, _variance(float(k_hi), s1, s2)


@nb.njit(**JIT)
def _crossings(y, xu, n, s, ends, x_ends, x_win):
    """Trials on the tail side of Y's quantile but not of X's: Y <= y_lo with X > x_lo, and
    Y >= y_hi with X < x_hi (``ends`` = (y_lo, y_hi), ``x_ends`` = (x_lo, x_hi)); and the
    variance of the remainder Y - s X over the trials of each tail window of X, X <= x_win[0]
    and X >= x_win[1] (NaN if fewer than 2).

    Returns
    -------
    c_lo, c_hi : int
    var_lo, var_hi : float, T^2
    """
    c_lo = 0
    c_hi = 0
    k_lo = k_hi = 0.0  # per window: count, sum and sum of squares of e = Y - s X
    s1_lo = s1_hi = s2_lo = s2_hi = 0.0
    for t in range(n):
        c_lo += (y[t] <= ends[0]) & (xu[t] > x_ends[0])
        c_hi += (y[t] >= ends[1]) & (xu[t] < x_ends[1])
        e = y[t] - s * xu[t]
        if xu[t] <= x_win[0]:
            k_lo += 1.0
            s1_lo += e
            s2_lo += e * e
        elif xu[t] >= x_win[1]:
            k_hi += 1.0
            s1_hi += e
            s2_hi += e * e
    return c_lo, c_hi, _variance(k_lo, s1_lo, s2_lo), _variance(k_hi, s1_hi, s2_hi)


@nb.njit(**JIT)
def _variance(k, s1, s2):
    """Sample variance (ddof 1) from a count and the sums of values and squares; NaN if k < 2."""
    return max(s2 - s1 * s1 / k, 0.0) / (k - 1.0) if k >= 2.0 else np.nan


@nb.njit(**JIT)
def _few_trials(a, d_inv, var_e, inv_f, n):
    """n times the variance of the difference estimator while the order statistics of s X
    lie farther apart (1 / (n f_X)) than the remainder e = Y - s X spreads (sd(e) near the
    quantile, ``var_e``): the estimate then follows the remainder of the one or few trials at
    the quantile, Var ~ Var(e) / (1 + sd(e) n f_X), which the asymptotic variance (its large-n
    limit, ~sd(e) / (n f_X)) misses; plus the density term of `_variances`."""
    if not var_e >= 0.0:
        return np.inf
    spacing = abs(inv_f) / n
    sd = math.sqrt(var_e)
    small = var_e / (1.0 + sd / spacing) if spacing > 0.0 else 0.0
    return a * (1.0 - a) * d_inv * d_inv + n * small


@nb.njit(**JIT)
def _difference_variance(v_asym, v_few, var_e, inv_f, n):
    """n times the variance of the difference estimator: the few-trials one (`_few_trials`)
    while the remainder spreads less (sd(e), ``var_e``) than the order statistics of s X lie
    apart (1 / (n f_X)); else the larger of it and the asymptotic one (`_variances`).

    With so few trials the asymptotic variance's share of trials on different sides of the
    two quantiles (``p10``) is a count of 0, 1 or 2 that its expectation, about f_X E|e|,
    lies far below, and the one or few trials at the quantile move it by e, not by
    1 / f_X."""
    if var_e >= 0.0 and math.sqrt(var_e) < abs(inv_f) / n:
        return v_few
    return max(v_asym, v_few)


@nb.njit(**JIT)
def _variances(a, inv_fy, inv_fx, d_inv, p10):
    """n times the asymptotic variance of the plain sample quantile of Y and of the difference
    estimator, at probability ``a``: Var(psi_Y - psi_X) = a (1 - a) (1/f_Y - 1/f_X)^2
    + 2 p10 / (f_Y f_X), with ``d_inv`` = 1/f_Y - 1/f_X and ``p10`` the share of trials on
    the tail side of Y's quantile and not of X's."""
    v_plain = a * (1.0 - a) * inv_fy * inv_fy
    v_cv = a * (1.0 - a) * d_inv * d_inv + 2.0 * p10 * abs(inv_fy * inv_fx)
    return v_plain, v_cv


@nb.njit(**JIT)
def cv_stats(y, xu, n, q, s, sig1, zq, x_st, x_tails, window, work, out, se):
    """Statistics of one quantity at one U_p from the n trials' errors ``y`` and first-order
    parts per unit U_p ``xu``, into ``out`` (6: mean, std, symmetric low/high, shortest
    low/high, T) and the standard errors of the symmetric ends into ``se`` (2, T).

    Parameters
    ----------
    y, xu : ndarray, shape (>= n,), T and T/mm
    n, q : int
        Trials and the count of the coverage interval (`coverage_count`).
    s : float, mm
        U_p.
    sig1 : float, T/mm
        Exact standard deviation of ``xu``.
    zq : float
        Phi^-1((1 + p) / 2).
    x_st : ndarray, shape (6,)
        The same figures of the sample ``xu`` (mean, std, low, high, shortest low, shortest
        high; T/mm).
    x_tails : tuple of 2 ndarray, shape (>= n - q,)
        The n - q smallest and largest values of ``xu``, ascending.
    window : tuple (ndarray, ndarray, int, int)
        The trials of ``xu``'s tail windows at its (n - q)-th smallest and largest values
        and their counts (`window_trials`).
    work : tuple
        (low, high, scratch, copy) work arrays (>= n).
    """
    low, high, scratch, copy = work
    h = n - q
    mean, std = sample_tails(y, n, h, low, high, scratch, copy)
    out[0] = mean
    out[1] = std
    _intervals(low, high, n, q, out)
    r = h // 2 if h % 2 == 0 else (h + 1) // 2
    r = max(r, 1)
    m = min(max(r // 2, 1), r - 1, h - r)
    if m < 1:  # too few trials in a tail for a density: the plain figures, no error estimate
        se[0] = np.nan
        se[1] = np.nan
        return
    a_lo = r / n
    a_hi = (h - r + 1) / n
    ify_lo, d_lo = _spacing(low, x_tails[0], s, r - 1, m, n)
    ify_hi, d_hi = _spacing(high, x_tails[1], s, r - 1, m, n)
    ifx = s * sig1 / (math.exp(-0.5 * zq * zq) / math.sqrt(2.0 * math.pi))
    ends, x_ends = (out[2], out[3]), (x_st[2], x_st[3])
    x_win = (x_tails[0][h - 1], x_tails[1][0])
    c_lo, c_hi, ve_lo, ve_hi = -1, -1, np.nan, np.nan
    if x_win[0] < x_win[1]:  # disjoint windows (else X is all but constant)
        c_lo, c_hi, ve_lo, ve_hi = _crossings_in_windows(y, xu, s, ends, x_ends, window,
                                                         (low, high), h)  # fmt: skip
    if c_lo < 0:
        c_lo, c_hi, ve_lo, ve_hi = _crossings(y, xu, n, s, ends, x_ends, x_win)
    vp_lo, vc_lo = _variances(a_lo, ify_lo, ifx, d_lo, c_lo / n)
    vp_hi, vc_hi = _variances(a_hi, ify_hi, ifx, d_hi, c_hi / n)
    vc_lo = _difference_variance(vc_lo, _few_trials(a_lo, d_lo, ve_lo, ifx, n), ve_lo, ifx, n)
    vc_hi = _difference_variance(vc_hi, _few_trials(a_hi, d_hi, ve_hi, ifx, n), ve_hi, ifx, n)
    if vc_lo + vc_hi < vp_lo + vp_hi:  # the first-order part helps: difference estimator
        ex = s * sig1
        out[0] = mean - s * x_st[0]
        out[1] = ex + (std - s * x_st[1])
        out[2] = -zq * ex + (out[2] - s * x_st[2])
        out[3] = zq * ex + (out[3] - s * x_st[3])
        out[4] = -zq * ex + (out[4] - s * x_st[4])
        out[5] = zq * ex + (out[5] - s * x_st[5])
        se[0] = math.sqrt(vc_lo / n)
        se[1] = math.sqrt(vc_hi / n)
    else:
        se[0] = math.sqrt(vp_lo / n)
        se[1] = math.sqrt(vp_hi / n)


@nb.njit(**JIT)
def _first_order_sigmas(cexp, lin, sigma_axes, inv, b_hat, out):
    """Standard deviation per unit U_p of the first-order part of each quantity, T/mm:
    |(cexp[c, lin[a]] * sigma_axes[a] / h)_a| for the components, with b_hat . cexp for |B|."""
    for c in range(4):
        v = 0.0
        for a in range(3):
            if c < 3:
                g = cexp[c, lin[a]]
            else:
                g = b_hat[0] * cexp[0, lin[a]] + b_hat[1] * cexp[1, lin[a]]
                g += b_hat[2] * cexp[2, lin[a]]
            v += (g * sigma_axes[a] * inv) ** 2
        out[c] = math.sqrt(v)


@nb.njit(**JIT)
def _linear_monomials(exps):
    """Rows of ``exps`` (M, 3) of the monomials x, y and z."""
    lin = np.empty(3, dtype=np.int64)
    for a in range(3):
        lin[a] = 0
    for m in range(exps.shape[0]):
        if exps[m, 0] + exps[m, 1] + exps[m, 2] == 1:
            for a in range(3):
                if exps[m, a] == 1:
                    lin[a] = m
    return lin


@nb.njit(**JIT)
def _add_trials(key, fkey, t0, t1, sigma_axes, inv, cexp, b0, abs0, b_hat, scales, bufs):
    """Draw trials t0 .. t1-1 and put their errors at every U_p into ``vals`` and their
    first-order parts per unit U_p into ``xu``; returns the largest squared displacement per
    unit U_p (mm^2/mm^2)."""
    zb, ok, u, parts, vals, xu, lin_abs, shift, sums = bufs
    d2max = 0.0
    for b0_ in range(t0, t1, PART_BLOCK):
        m = min(PART_BLOCK, t1 - b0_)
        normals_by_index(key, fkey, b0_, m, zb, ok)
        for t in range(m):
            d0 = sigma_axes[0] * zb[0, t]
            d1 = sigma_axes[1] * zb[1, t]
            d2 = sigma_axes[2] * zb[2, t]
            u[0, b0_ + t] = d0 * inv
            u[1, b0_ + t] = d1 * inv
            u[2, b0_ + t] = d2 * inv
            d2max = max(d2max, d0 * d0 + d1 * d1 + d2 * d2)
        homogeneous_parts(cexp, u, b0_, m, parts)
        first_order_abs(parts, m, b_hat, lin_abs)
        for t in range(m):
            xu[0, b0_ + t] = parts[t]
            xu[1, b0_ + t] = parts[PART_PITCH + t]
            xu[2, b0_ + t] = parts[2 * PART_PITCH + t]
            xu[3, b0_ + t] = lin_abs[t]
        for k in range(scales.shape[0]):
            if scales[k] > 0.0:
                changes_block(parts, m, scales[k], b0, abs0, vals[k], b0_, shift, sums)
    return d2max


@nb.njit(**JIT)
def _node_estimates(n, p, scales, sig1, zq, vals, xu, work, x_st, x_tails, x_win, stats_i, se, c0,
                    c1):  # fmt: skip
    """The statistics of quantities c0 .. c1-1 of one node from its n trials into
    ``stats_i`` (n_up, 4, 6); returns the largest ratio of a standard error of |B|'s interval
    ends to U_f over the U_p values (0 unless c1 = 4). ``x_win``: the trials of the first-order
    parts' tail windows, (2, 4, >= n), and their counts (4, 2), set here."""
    q = coverage_count(n, p)
    h = n - q
    scratch, copy = work[2], work[3]
    win, k_win = x_win
    for c in range(c0, c1):  # the first-order parts' figures, per unit U_p (scaled below)
        mean, std = sample_tails(xu[c], n, h, x_tails[0, c], x_tails[1, c], scratch, copy)
        x_st[c, 0] = mean
        x_st[c, 1] = std
        _intervals(x_tails[0, c], x_tails[1, c], n, q, x_st[c])
        edges = (x_tails[0, c][h - 1], x_tails[1, c][0])
        k_win[c, 0], k_win[c, 1] = window_trials(xu[c], n, edges, win[0, c], win[1, c])
    worst = 0.0
    for k in range(scales.shape[0]):
        s = scales[k]
        if s == 0.0:  # no displacement: every error is exactly zero
            for c in range(4):
                for j in range(6):
                    stats_i[k, c, j] = 0.0
            continue
        for c in range(c0, c1):  # |B| last: ``se`` is then its
            x_tc = (x_tails[0, c], x_tails[1, c])
            window = (win[0, c], win[1, c], k_win[c, 0], k_win[c, 1])
            cv_stats(vals[k, c], xu[c], n, q, s, sig1[c], zq, x_st[c], x_tc, window, work,
                     stats_i[k, c], se)  # fmt: skip
        uf = max(abs(stats_i[k, 3, 2]), abs(stats_i[k, 3, 3]))
        if c1 < 4:
            continue
        if uf > 0.0:
            worst = max(worst, se[0] / uf, se[1] / uf)
        elif se[0] > 0.0 or se[1] > 0.0:
            worst = np.inf
    return worst


@nb.njit(**JIT)
def _buffers(n_up, size, p):
    """Work arrays of `harmonic_cv_sweep` for ``size`` trials per node: (the trial arrays of
    `_add_trials`, the statistics' work arrays, the first-order parts' tails and their
    windows' trials)."""
    bufs = (np.empty((3, PART_BLOCK)), np.empty(PART_BLOCK, dtype=np.bool_), np.empty((3, size)),
            np.empty(N_SLOTS * PART_PITCH), np.empty((n_up, 4, size)), np.empty((4, size)),
            np.empty(PART_BLOCK), np.empty(4), np.empty((4, 2)))  # fmt: skip
    for c in range(4):  # zeros, filled by loops: np.zeros compiles apart from np.empty
        bufs[7][c] = 0.0
        bufs[8][c, 0] = 0.0
        bufs[8][c, 1] = 0.0
    work = (np.empty(size), np.empty(size), np.empty(size), np.empty(size))
    x_win = (np.empty((2, 4, size), dtype=np.int64), np.empty((4, 2), dtype=np.int64))
    return bufs, work, np.empty((2, 4, size - coverage_count(size, p) + 1)), x_win


@nb.njit(**JIT)
def _grown(n_up, size, p, old, n):
    """`_buffers` for ``size`` trials, the first n trials of ``old`` (its trial arrays)
    carried over."""
    bufs, work, x_tails, x_win = _buffers(n_up, size, p)
    for t in range(n):  # loops: see `_copy_ends`
        for a in range(3):
            bufs[2][a, t] = old[2][a, t]
        for c in range(4):
            bufs[5][c, t] = old[5][c, t]
            for k in range(n_up):
                bufs[4][k, c, t] = old[4][k, c, t]
    return bufs, work, x_tails, x_win


@nb.njit(**JIT)
def harmonic_cv_buffers(n_up, p, plan):
    """Work arrays of `harmonic_cv_sweep` for ``n_up`` U_p values, coverage ``p`` and ``plan``
    (pilot, most trials, target), sized for a pilot's trials (grown by the kernel as a node
    needs). A caller that runs the kernel on many blocks of nodes passes the arrays each call
    returns to its next call: grown once, not once per block (megabytes for nodes that take
    tens of thousands of trials)."""
    pilot, cap, _ = plan
    return _buffers(n_up, min(4 * pilot, cap), p)


@nb.njit(**JIT)
def harmonic_cv_sweep(nodes, keys, model, sigma_axes, scales, seed, p, plan, buffers):
    """Statistics of B(x + N(0, U_p)) - B(x) at each node under its harmonic model, by the
    adaptive control-variate estimator (module docstring).

    Parameters
    ----------
    nodes, keys : ndarray, shape (k,), int64
        Node rows and random-stream ids, as in `harmonic_gauss_sweep` (the same trials).
    model : tuple
        As `harmonic_gauss_sweep`.
    sigma_axes : ndarray, shape (3,)
        Per-axis multiplier of U_p.
    scales : ndarray, shape (n_up,), mm
        U_p values.
    seed : int
    p : float
        Coverage probability.
    plan : tuple (int, int, float)
        Pilot trials, most trials, and the target standard error of U_f relative to U_f.
    buffers : tuple
        Work arrays (`harmonic_cv_buffers` for the same ``scales`` count, ``p`` and ``plan``,
        or those an earlier call returned); their content is not read.

    Returns
    -------
    stats, n_out, n_lost, star
        As `harmonic_gauss_sweep` (n_out, n_lost zero; star False).
    used : ndarray, shape (k,), int64
        Trials each node took; 0 where a trial left the node's reach (its model's support):
        such nodes have no statistics here and are left to the plain Monte Carlo.
    buffers : tuple
        The work arrays, grown where a node took more trials than they held: for the next
        call.
    """
    pilot, cap, rel_se = plan
    coords, hcoef, hdeg, hscale, hreach, gmat, exps = model
    k_nodes = nodes.shape[0]
    n_up = scales.shape[0]
    stats, n_out, n_lost, star = sweep_outputs(k_nodes, n_up)
    used = np.empty(k_nodes, dtype=np.int64)  # every node's count is set below
    skey = stream_key(seed, STREAM_SWEEP)
    fkey = stream_key(seed, STREAM_FALLBACK)
    bufs, work, x_tails, x_win = buffers
    size = bufs[2].shape[1]  # trials they hold; grown for a node that needs more
    x_st = np.empty((4, 6))
    se = np.empty(2)
    sig1 = np.empty(4)
    b_hat = np.empty(3)
    cexp = np.empty((3, gmat.shape[1]))  # every coefficient is set at each node
    lin = _linear_monomials(exps)
    basis = sparse_basis(gmat)
    zq = normal_quantile(0.5 * (1.0 + p))
    c0, c3, c4 = np.int64(0), np.int64(3), np.int64(4)  # not literals: one callee version
    smax = 0.0
    for k in range(n_up):
        smax = max(smax, scales[k])
    for i in range(k_nodes):
        g = nodes[i]
        deg = hdeg[g]
        n_mono = (deg + 1) * (deg + 2) * (deg + 3) // 6
        expand_node(hcoef[g], (deg + 1) * (deg + 3), basis, n_mono, cexp)
        for c in range(3):  # the unrolled polynomial is of the highest degree
            for m in range(n_mono, cexp.shape[1]):
                cexp[c, m] = 0.0
        b0 = cexp[:, 0]
        abs0 = math.sqrt(b0[0] ** 2 + b0[1] ** 2 + b0[2] ** 2)
        for c in range(3):
            b_hat[c] = b0[c] / abs0 if abs0 > 0.0 else 0.0
        inv = 1.0 / hscale[g]
        _first_order_sigmas(cexp, lin, sigma_axes, inv, b_hat, sig1)
        key = trial_key(skey, keys[i])
        reach2 = (hreach[g] / smax) ** 2 if smax > 0.0 else np.inf
        n = np.int64(0)  # not a literal, as above
        target = min(pilot, cap)
        while True:
            if target > size:
                size = min(2 * size, cap)
                bufs, work, x_tails, x_win = _grown(n_up, size, p, bufs, n)
            d2max = _add_trials(key, fkey, n, target, sigma_axes, inv, cexp, b0, abs0, b_hat,
                                scales, bufs)  # fmt: skip
            n = target
            if d2max > reach2:  # beyond the model's support: the plain Monte Carlo's node
                n = np.int64(0)
                break
            vals, xu = bufs[4], bufs[5]
            worst = _node_estimates(n, p, scales, sig1, zq, vals, xu, work, x_st, x_tails,
                                    x_win, stats[i], se, c3, c4)  # |B| decides  # fmt: skip
            if worst <= rel_se or n >= cap:  # then the components
                _node_estimates(n, p, scales, sig1, zq, vals, xu, work, x_st, x_tails, x_win,
                                stats[i], se, c0, c3)  # fmt: skip
                break
            target = min(2 * n, cap)
        used[i] = n
        if n == 0:
            for k in range(n_up):
                for c in range(4):
                    for j in range(6):
                        stats[i, k, c, j] = np.nan
    return stats, n_out, n_lost, star, used, (bufs, work, x_tails, x_win)
