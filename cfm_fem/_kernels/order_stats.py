"""Order statistics without a full sort (O(n) per node instead of O(n log n))."""

from __future__ import annotations

import numba as nb
import numpy as np

from .options import JIT, RJIT


@nb.njit(**JIT)
def select_inplace(a, lo, hi, k):
    """Partially order ``a[lo:hi+1]`` so that ``a[k]`` is its (k-lo)-th smallest value.

    Hoare partitioning (Wirth's select) with a median-of-three pivot: linear on average and
    robust to ties. Afterwards ``a[lo:k] <= a[k] <= a[k+1:hi+1]``.
    """
    while hi > lo:
        mid = (lo + hi) // 2
        x0, x1, x2 = a[lo], a[mid], a[hi]
        if x0 > x1:
            x0, x1 = x1, x0
        if x1 > x2:
            x1 = x2
            if x0 > x1:
                x1 = x0
        x = x1
        i, j = lo, hi
        while i <= j:
            while a[i] < x:
                i += 1
            while x < a[j]:
                j -= 1
            if i <= j:
                a[i], a[j] = a[j], a[i]
                i += 1
                j -= 1
        if j < k:
            lo = i
        if k < i:
            hi = j


@nb.njit(**JIT)
def _insertion_sort_inplace(a):
    """Sort ``a`` in place by insertion; exact, fast when ``a`` is nearly sorted or short, and
    no allocation (for short arrays a copy's allocation costs as much as the sort)."""
    for i in range(1, a.shape[0]):
        x = a[i]
        j = i
        while j > 0 and a[j - 1] > x:
            a[j] = a[j - 1]
            j -= 1
        a[j] = x


@nb.njit(**JIT)
def _insertion_sort(a, src):
    """a[:len(src)] = sorted(src), ``src`` an array other than ``a``."""
    n = src.shape[0]
    for i in range(n):
        a[i] = src[i]
    _insertion_sort_inplace(a[:n])


@nb.njit(**JIT)
def sort_values(a):
    """Sort a float64 array in place (NaN last, as `numpy.sort`).

    Comparison sorts stall on mispredicted branches (numba's quicksort: ~80 ns per element for
    500 values). Here the values are first ordered by a key quantised over [min, max] with an
    LSD radix sort (branch-free passes of 8 bits), then an insertion pass orders values sharing
    a key exactly:

    - up to 4,096 values (the tails of 10,000 trials), a 16-bit key in two passes: few values
      share a key, so the insertion pass moves little and its branches are predictable
      (~4.5 ns per element for 500 to 1,200 values in random order; even a sample whose
      values all share one key costs at most a few ms);
    - above, a 24-bit key (3 passes).
    """
    n = a.shape[0]
    if n < 48:
        _insertion_sort_inplace(a)
        return
    lo = a[0]
    hi = a[0]
    nan = False
    for i in range(n):
        lo = min(lo, a[i])
        hi = max(hi, a[i])
        nan |= a[i] != a[i]
    if nan:  # a trial that met a slab's halo sentinel (NaN field): its key would index out
        # of the counting arrays. NaN go last, as numpy's; the node's statistics are NaN anyway.
        k = 0  # (not np.sort: its quicksort would add ~3 s to every first run's compile)
        for i in range(n):
            v = a[i]
            if v == v:
                a[k] = v
                k += 1
        a[k:] = np.nan
        if k < 48:
            _insertion_sort_inplace(a[:k])
            return
        n = k
        lo = a[0]
        hi = a[0]
        for i in range(n):
            lo = min(lo, a[i])
            hi = max(hi, a[i])
    _sort_finite(a[:n], lo, hi)


@nb.njit(**JIT)
def _sort_finite(a, lo, hi):
    """`sort_values` for 48 or more finite values in [lo, hi]."""
    n = a.shape[0]
    if not hi > lo:
        return
    if n <= 4096:
        _radix16_sort(a, n, lo, hi)
        return
    scale = 16777215.0 / (hi - lo)
    src_v = a.copy()
    dst_v = np.empty(n)
    src_k = np.empty(n, dtype=np.uint32)
    dst_k = np.empty(n, dtype=np.uint32)
    for i in range(n):
        src_k[i] = np.uint32(min((src_v[i] - lo) * scale, 16777215.0))
    counts = np.empty(256, dtype=np.int64)
    for sh in range(0, 24, 8):
        counts[:] = 0
        for i in range(n):
            counts[(src_k[i] >> sh) & 255] += 1
        tot = 0
        for b in range(256):
            c = counts[b]
            counts[b] = tot
            tot += c
        for i in range(n):
            b = (src_k[i] >> sh) & 255
            j = counts[b]
            counts[b] = j + 1
            dst_v[j] = src_v[i]
            dst_k[j] = src_k[i]
        src_v, dst_v = dst_v, src_v
        src_k, dst_k = dst_k, src_k
    _insertion_sort(a, src_v)


@nb.njit(**JIT)
def _radix16_sort(a, n, lo, hi):
    """`sort_values` for 48 <= n <= 4096 values in [lo, hi], lo < hi."""
    sort_in_range(a[:n], lo, hi, radix_work(n))


@nb.njit(**JIT)
def radix_work(n):
    """Work arrays of `sort_in_range` for up to ``n`` values."""
    return (np.empty(n, dtype=np.uint16), np.empty(n), np.empty(n, dtype=np.uint16),
            np.empty(n), np.empty((2, 257), dtype=np.uint64))  # fmt: skip


@nb.njit(**JIT)
def sort_in_range(a, lo, hi, work):
    """Sort finite values ``a`` known to lie in [lo, hi] in place, with the work arrays of
    `radix_work`: no allocation and no pass for the range, for callers that sort many short
    lists and know their bounds.

    An LSD radix sort on a 16-bit key quantised over [lo, hi] (two branch-free passes of 8
    bits, stable), then the exact insertion pass, which only moves values sharing a key
    (~4 ns per element for 500 to 1,200 values in random order; a range too wide for the key,
    all values sharing one key, costs the insertion sort's n^2 / 4 moves but stays exact).
    """
    n = a.shape[0]
    if n < 48:
        _insertion_sort_inplace(a)
        return
    if not hi > lo:  # every value equal
        return
    keys, by_low, low_keys, by_key, start = work
    scale = 65535.0 / (hi - lo)  # 0 if the range overflows
    if not scale < np.inf:  # a range below 65535 denormals: one key (0 * inf would be NaN)
        scale = 0.0
    for i in range(n):
        keys[i] = np.uint16(min(max((a[i] - lo) * scale, 0.0), 65535.0))
    start[:] = 0
    low_start = start[0]
    high_start = start[1]
    one = np.uint64(1)  # unsigned positions: no negative-index wraparound in the scatters
    for i in range(n):
        k = keys[i]
        low_start[(k & 255) + 1] += one
        high_start[(k >> 8) + 1] += one
    for b in range(256):
        low_start[b + 1] += low_start[b]
        high_start[b + 1] += high_start[b]
    for i in range(n):
        k = keys[i]
        j = low_start[k & 255]
        low_start[k & 255] = j + one
        by_low[j] = a[i]
        low_keys[j] = k
    for i in range(n):
        k = low_keys[i] >> 8
        j = high_start[k]
        high_start[k] = j + one
        by_key[j] = by_low[i]
    _insertion_sort(a, by_key[:n])


#: Tails beyond mean -+ TAIL_SIGMAS * std are gathered first; 1.3 holds ~10 % of a normal sample,
#: twice the 5 % the intervals need. Fewer than needed falls back to the whole sample (exact).
TAIL_SIGMAS = 1.3


#: Leading values whose mean and std place the tail thresholds (`sums_and_tails`).
TAIL_PILOT = 512


@nb.njit(**RJIT)
def _pilot_mean_std(x, m):
    """Mean and std (ddof 1) of x[:m], m >= 1, summed in any order (vectorised): they only
    place the tail thresholds of `sums_and_tails`, never a result."""
    pm = 0.0
    for i in range(m):
        pm += x[i]
    pm /= m
    pv = 0.0
    for i in range(m):
        pv += (x[i] - pm) ** 2
    return pm, np.sqrt(pv / max(m - 1, 1))


@nb.njit(**JIT)
def sums_and_tails(x, n, scratch, end):
    """Shifted sums of x[:n] and its two tails, in one pass.

    Parameters
    ----------
    x : ndarray, shape (>= n,)
    n : int
    scratch : ndarray, shape (>= end,)
        Receives the low tail at scratch[:n_lo] and the high tail at scratch[end - n_hi:end]
        (unsorted); end >= n.
    end : int

    Returns
    -------
    shift, s1, s2 : float
        shift = x[0]; s1, s2: sums of (x - shift) and its square, in index order.
    n_lo, n_hi : int
        Sizes of the tails: values <= t_lo and >= t_hi, t = mean -+ TAIL_SIGMAS std of the first
        TAIL_PILOT values (no tails if those are constant). The thresholds only decide how much
        is gathered, never a result: a caller needing the h extreme values takes the tail path
        only when n_lo, n_hi >= h. t_lo < t_hi, so n_lo + n_hi <= n.
    """
    if n == 0:
        return 0.0, 0.0, 0.0, 0, 0
    shift = x[0]
    pm, ps = _pilot_mean_std(x, min(n, TAIL_PILOT))
    t_lo = pm - TAIL_SIGMAS * ps
    t_hi = pm + TAIL_SIGMAS * ps
    if not t_lo < t_hi:  # constant pilot: no tails (the caller's whole-sample path), and never
        t_lo = -np.inf  # a value in both tails, which would overlap in scratch
        t_hi = np.inf
    s1 = 0.0
    s2 = 0.0
    n_lo = 0
    n_hi = 0
    for i in range(n):  # branch-free gather, fused with the sums (one read of x)
        v = x[i]
        dv = v - shift
        s1 += dv
        s2 += dv * dv
        scratch[n_lo] = v
        n_lo += v <= t_lo
        scratch[end - 1 - n_hi] = v
        n_hi += v >= t_hi
    return shift, s1, s2, n_lo, n_hi


@nb.njit(**JIT)
def sample_stats(a, n, q, out, scratch):
    """Mean, std and the coverage intervals of the first ``n`` values of ``a``.

    Parameters
    ----------
    a : ndarray, shape (>= n,)
        Samples; reordered in place only on the fallback path.
    n : int
        Number of samples.
    q : int
        Samples spanned by the coverage interval, see `cfm_fem.models.mc.coverage_count`.
    out : ndarray, shape (6,)
        mean, std (ddof 1), symmetric low, symmetric high, shortest low, shortest high
        (JCGM 101 7.7); NaN when n < 2.
    scratch : ndarray, shape (>= n,)
        Work space.

    Notes
    -----
    Every order statistic the two intervals need lies among the h = n - q smallest or the h
    largest values. Those are taken from the tails beyond mean -+ 1.3 std (`sums_and_tails`;
    selection in the whole sample if a tail is too thin) and then sorted: O(n), not a full sort.
    """
    if n < 2:
        for j in range(6):
            out[j] = np.nan
        return
    # one pass, shifted by the first value so the variance keeps its precision
    shift, s1, s2, n_lo, n_hi = sums_and_tails(a, n, scratch, n)
    mean = shift + s1 / n
    std = np.sqrt(max(s2 - s1 * s1 / n, 0.0) / (n - 1))
    out[0] = mean
    out[1] = std
    h = n - q
    if n_lo >= h and n_hi >= h and std > 0.0:
        # sorting a whole gathered tail (~2h values) costs less than selecting h of them first
        lo = scratch[:n_lo]
        hi = scratch[n - n_hi : n]
        sort_values(lo)
        sort_values(hi)
        low = lo[:h]
        high = hi[n_hi - h :]
    else:
        select_inplace(a, np.int64(0), n - 1, h - 1)  # a literal 0 compiles a 2nd version
        select_inplace(a, h, n - 1, q)
        low = a[:h]
        high = a[q:n]
        sort_values(low)
        sort_values(high)
    _intervals(low, high, n, q, out)


@nb.njit(**JIT)
def _intervals(low, high, n, q, out):
    """Symmetric and shortest intervals into out[2:6] from the h = n - q smallest values
    (``low``, ascending) and the h largest (``high``, ascending: high[j] is order statistic
    q + j, 0-based)."""
    h = n - q
    r = (n - q) // 2 if (n - q) % 2 == 0 else (n - q + 1) // 2
    if r < 1:
        r = 1
    out[2] = low[r - 1]
    out[3] = high[r - 1]
    best = 0
    width = high[0] - low[0]
    for j in range(1, h):
        w = high[j] - low[j]
        if w < width:  # strict: the first of equal widths
            width = w
            best = j
    out[4] = low[best]
    out[5] = high[best]


@nb.njit(**JIT)
def _merged_stats(x, n_in, shift, s1, s2, lo_tail, hi_tail, r, y, m, p, out, low, high, full,
                  scratch):  # fmt: skip
    """Statistics of the union of r * x[:n_in] (r > 0) and y[:m] (y sorted ascending).

    ``s1``, ``s2``: sums of (x - shift) and its square over x[:n_in]; ``lo_tail``/``hi_tail``:
    the smallest / largest values of x[:n_in], sorted ascending (scaling by r > 0 keeps the
    order). The union's h smallest values are among the h smallest of r * x and all of y, so
    merging two sorted lists gives the exact order statistics without touching all n values.
    Falls back to `sample_stats` on the whole union when a tail is shorter than h.
    ``low``, ``high``, ``full``, ``scratch``: work space (>= n_in + m).
    """
    n = n_in + m
    if n < 2:
        for j in range(6):
            out[j] = np.nan
        return
    q = coverage_count(n, p)
    h = n - q
    n_lo = lo_tail.shape[0]
    n_hi = hi_tail.shape[0]
    if n_lo < h or n_hi < h:
        for j in range(n_in):
            full[j] = r * x[j]
        for j in range(m):
            full[n_in + j] = y[j]
        sample_stats(full, n, q, out, scratch)
        return
    c = r * shift  # shifted sums keep the variance free of cancellation
    t1 = r * s1
    t2 = r * r * s2
    for j in range(m):
        dv = y[j] - c
        t1 += dv
        t2 += dv * dv
    out[0] = c + t1 / n
    out[1] = np.sqrt(max(t2 - t1 * t1 / n, 0.0) / (n - 1))
    i = 0
    j = 0
    for k in range(h):  # the h smallest: merge ascending
        if j < m and (i >= n_lo or y[j] < r * lo_tail[i]):
            low[k] = y[j]
            j += 1
        else:
            low[k] = r * lo_tail[i]
            i += 1
    i = n_hi - 1
    j = m - 1
    for k in range(h - 1, -1, -1):  # the h largest: merge descending
        if j >= 0 and (i < 0 or y[j] > r * hi_tail[i]):
            high[k] = y[j]
            j -= 1
        else:
            high[k] = r * hi_tail[i]
            i -= 1
    _intervals(low, high, n, q, out)


@nb.njit(**JIT)
def coverage_count(n, p):
    """Numba twin of `cfm_fem.models.mc.coverage_count`.

    Its rule (p n when within 1e-9 of an integer, else int(p n + 1/2)) gives int(p n + 1/2)
    for every p n >= 0, one conversion that compiles in a fraction of numba's rounding.
    """
    q = int(p * n + 0.5)
    return min(max(q, 1), n - 1)
