"""All numba code of cfm_fem: raw kernels with no I/O and no checks.

Callers validate inputs. Every kernel has a plain-numpy twin (in the module that calls it or in the
tests) that the tests compare it with. Numba options are set once, here.
"""

from __future__ import annotations

import numba as nb
import numpy as np

#: One place for numba options. ``cache`` keeps compile time out of repeated runs.
JIT = dict(nogil=True, cache=True, fastmath=False, error_model="numpy")
PJIT = dict(JIT, parallel=True)

# ---------------------------------------------------------------------------------------------
# Counter-based random numbers: every draw is a hash of (seed, node, trial, slot), so the numbers
# do not depend on the thread count, the chunking or the order nodes are processed in.
# splitmix64's finaliser on a Weyl sequence is SplitMix64 itself (passes BigCrush).
# ---------------------------------------------------------------------------------------------
_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_NODE_GAMMA = np.uint64(0xD1B54A32D192ED03)
_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)
_INV_2_53 = 1.0 / 9007199254740992.0


@nb.njit(**JIT)
def mix64(z):
    """splitmix64 finaliser of a uint64."""
    z = (z ^ (z >> np.uint64(30))) * _M1
    z = (z ^ (z >> np.uint64(27))) * _M2
    return z ^ (z >> np.uint64(31))


@nb.njit(**JIT)
def stream_key(seed, stream):
    """Key of an independent stream (e.g. one per node) derived from the user's seed."""
    return mix64(mix64(np.uint64(seed)) + (np.uint64(stream) + np.uint64(1)) * _NODE_GAMMA)


@nb.njit(**JIT)
def uniform_at(key, counter):
    """Uniform double in [0, 1) at position ``counter`` of stream ``key`` (53-bit resolution)."""
    h = mix64(np.uint64(key) + (np.uint64(counter) + np.uint64(1)) * _GOLDEN)
    return float(h >> np.uint64(11)) * _INV_2_53


@nb.njit(**JIT)
def normal_next(key, state, spare):
    """Next standard normal of the sequential stream ``key`` (Marsaglia's polar method).

    Parameters
    ----------
    key : uint64
        Stream key from `stream_key`.
    state : ndarray, shape (2,), uint64
        [next uniform counter, 1 if ``spare`` holds an unused normal]; start from zeros.
    spare : ndarray, shape (1,), float64

    The sequence depends only on ``key`` and the number of draws made, never on threads.
    """
    key = np.uint64(key)
    if state[1] == 1:
        state[1] = 0
        return spare[0]
    while True:
        u = 2.0 * uniform_at(key, state[0]) - 1.0
        v = 2.0 * uniform_at(key, state[0] + np.uint64(1))
        v -= 1.0
        state[0] += np.uint64(2)
        s = u * u + v * v
        if 0.0 < s < 1.0:
            break
    f = np.sqrt(-2.0 * np.log(s) / s)
    spare[0] = v * f
    state[1] = 1
    return u * f


# ---------------------------------------------------------------------------------------------
# Point location by walking from a known simplex to its neighbours.
# ---------------------------------------------------------------------------------------------
#: Barycentric tolerance: a point this close outside a face still counts as inside.
BARY_EPS = 1e-10
#: Longest walk before giving up (only non-Delaunay native meshes can make a walk cycle).
MAX_WALK = 10000
OUTSIDE = -1
WALK_FAILED = -2


@nb.njit(**JIT)
def locate(p, start, transform, neighbors, bary):
    """Simplex containing ``p``, walking from ``start`` across the most violated face.

    Parameters
    ----------
    p : ndarray, shape (d,), mm
    start : int
        A simplex near ``p`` (the node's own).
    transform : ndarray, shape (m, d + 1, d)
    neighbors : ndarray, shape (m, d + 1)
    bary : ndarray, shape (d + 1,)
        Output: barycentric coordinates of ``p`` in the returned simplex.

    Returns
    -------
    int
        The simplex, ``OUTSIDE`` (-1) if the walk leaves the mesh, ``WALK_FAILED`` (-2) after
        ``MAX_WALK`` steps.
    """
    d = p.shape[0]
    s = start
    if s < 0:
        return OUTSIDE
    for _ in range(MAX_WALK):
        last = 1.0
        for j in range(d):
            c = 0.0
            for k in range(d):
                c += transform[s, j, k] * (p[k] - transform[s, d, k])
            bary[j] = c
            last -= c
        bary[d] = last
        jmin = 0
        for j in range(1, d + 1):
            if bary[j] < bary[jmin]:
                jmin = j
        if bary[jmin] >= -BARY_EPS:
            return s
        s = neighbors[s, jmin]
        if s < 0:
            return OUTSIDE
    return WALK_FAILED


@nb.njit(**JIT)
def _interp_in(s, bary, simplices, values, out):
    """out = sum_j bary[j] * values[simplices[s, j]]."""
    for c in range(out.shape[0]):
        out[c] = 0.0
    for j in range(simplices.shape[1]):
        w = bary[j]
        v = simplices[s, j]
        for c in range(out.shape[0]):
            out[c] += w * values[v, c]


@nb.njit(**PJIT)
def interpolate_points(points, start, simplices, transform, neighbors, values):
    """Piecewise-linear values at ``points``; NaN where outside the mesh.

    Parameters
    ----------
    points : ndarray, shape (k, d), mm, in the mesh frame
    start : ndarray, shape (k,), int64
        Starting simplex of each walk (e.g. the simplex of the nearest node).
    values : ndarray, shape (n, c)

    Returns
    -------
    out : ndarray, shape (k, c)
    cell : ndarray, shape (k,), int64
        Containing simplex, or -1 (outside) / -2 (walk failed).
    """
    k = points.shape[0]
    d = points.shape[1]
    nc = values.shape[1]
    out = np.empty((k, nc))
    cell = np.empty(k, dtype=np.int64)
    for i in nb.prange(k):
        bary = np.empty(d + 1)
        s = locate(points[i], start[i], transform, neighbors, bary)
        cell[i] = s
        if s >= 0:
            _interp_in(s, bary, simplices, values, out[i])
        else:
            for c in range(nc):
                out[i, c] = np.nan
    return out, cell


@nb.njit(**PJIT)
def octant_cells(coords, node_cell, transform, neighbors, eps):
    """Per node, the simplex that contains node + eps * (+-1, +-1[, +-1]) for each sign pattern.

    A walk for a displacement starts from the cell of its octant (bit a of the index set when
    component a is negative), which cuts the walk across the node's star to about one step.

    Returns
    -------
    ndarray, shape (n, 2**d), int64
        Start simplex per node and octant (the node's own cell where the probe leaves the mesh).
    """
    n, d = coords.shape
    n_oct = 1 << d
    out = np.empty((n, n_oct), dtype=np.int64)
    for i in nb.prange(n):
        bary = np.empty(d + 1)
        p = np.empty(d)
        for o in range(n_oct):
            out[i, o] = node_cell[i]
            if node_cell[i] < 0:
                continue
            for a in range(d):
                p[a] = coords[i, a] + (-eps if (o >> a) & 1 else eps)
            s = locate(p, node_cell[i], transform, neighbors, bary)
            if s >= 0:
                out[i, o] = s
    return out


# ---------------------------------------------------------------------------------------------
# Order statistics without a full sort (O(n) per node instead of O(n log n)).
# ---------------------------------------------------------------------------------------------
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


#: Tails beyond mean -+ TAIL_SIGMAS * std are gathered first; 1.3 holds ~10 % of a normal sample,
#: twice the 5 % the intervals need. Fewer than needed falls back to the whole sample (exact).
TAIL_SIGMAS = 1.3


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
        Samples spanned by the coverage interval, see `cfm_fem.mc.coverage_count`.
    out : ndarray, shape (6,)
        mean, std (ddof 1), symmetric low, symmetric high, shortest low, shortest high
        (JCGM 101 7.7); NaN when n < 2.
    scratch : ndarray, shape (>= n,)
        Work space.

    Notes
    -----
    Every order statistic the two intervals need lies among the h = n - q smallest or the h
    largest values. Those are found by selection inside the tails beyond mean -+ 1.3 std (or in
    the whole sample if a tail is too thin) and then sorted: O(n) instead of a full sort.
    """
    if n < 2:
        for j in range(6):
            out[j] = np.nan
        return
    # one pass, shifted by the first value so the variance keeps its precision
    shift = a[0]
    s1 = 0.0
    s2 = 0.0
    for i in range(n):
        x = a[i] - shift
        s1 += x
        s2 += x * x
    mean = shift + s1 / n
    std = np.sqrt(max(s2 - s1 * s1 / n, 0.0) / (n - 1))
    out[0] = mean
    out[1] = std
    h = n - q
    t_lo = mean - TAIL_SIGMAS * std
    t_hi = mean + TAIL_SIGMAS * std
    n_lo = 0
    n_hi = 0
    for i in range(n):  # branch-free: low tail at the front of scratch, high tail at the back
        x = a[i]
        scratch[n_lo] = x
        n_lo += x <= t_lo
        scratch[n - 1 - n_hi] = x
        n_hi += x >= t_hi
    if n_lo >= h and n_hi >= h and std > 0.0:
        lo = scratch[:n_lo]
        hi = scratch[n - n_hi : n]
        select_inplace(lo, 0, n_lo - 1, h - 1)
        select_inplace(hi, 0, n_hi - 1, n_hi - h)
        low = lo[:h]
        high = hi[n_hi - h :]
    else:
        select_inplace(a, 0, n - 1, h - 1)
        select_inplace(a, h, n - 1, q)
        low = a[:h]
        high = a[q:n]
    low.sort()
    high.sort()  # high[j] is order statistic q + j (0-based)
    r = (n - q) // 2 if (n - q) % 2 == 0 else (n - q + 1) // 2
    if r < 1:
        r = 1
    out[2] = low[r - 1]
    out[3] = high[r - 1]
    best = 0
    for j in range(1, h):
        if high[j] - low[j] < high[best] - low[best]:
            best = j
    out[4] = low[best]
    out[5] = high[best]


@nb.njit(**JIT)
def coverage_count(n, p):
    """Numba twin of `cfm_fem.mc.coverage_count`."""
    pm = p * n
    if abs(pm - np.round(pm)) < 1e-9:
        q = int(np.round(pm))
    else:
        q = int(pm + 0.5)
    return min(max(q, 1), n - 1)


# ---------------------------------------------------------------------------------------------
# Gaussian perturbation sweep (paper eq. 16), statistics streamed per node.
# ---------------------------------------------------------------------------------------------
#: Layout of the last axis of the statistics array.
STAT_NAMES = ("mean", "std", "sym_lo", "sym_hi", "short_lo", "short_hi")
#: Layout of the component axis: the three components and |B|.
COMPONENTS = ("Bx", "By", "Bz", "absB")


@nb.njit(**JIT)
def _star_contains(simplices, s, node):
    for j in range(simplices.shape[1]):
        if simplices[s, j] == node:
            return True
    return False


@nb.njit(**JIT)
def _node_gauss(
    g,
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
    comp,
    absb,
    scratch,
    stats,
    n_out,
    n_lost,
):
    """All trials and statistics of node ``g`` (see `gauss_sweep`). Buffers are per thread."""
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
    z = np.empty(3)
    disp = np.empty(d)
    pt = np.empty(d)
    bary = np.empty(d + 1)
    bi = np.empty(3)
    b0 = values[g]
    abs0 = np.sqrt(b0[0] ** 2 + b0[1] ** 2 + b0[2] ** 2)
    key = stream_key(seed, g)
    rstate = np.zeros(2, dtype=np.uint64)
    spare = np.empty(1)
    nvalid = np.zeros(n_up, dtype=np.int64)
    all_star = True
    for k in range(n_up):
        n_out[k] = 0
        n_lost[k] = 0
    for _ in range(n_trials):
        for c in range(3):
            z[c] = normal_next(key, rstate, spare)
        # displacement direction in the mesh frame (projection for a planar map)
        for a in range(d):
            acc = 0.0
            for c in range(3):
                acc += basis[c, a] * sigma_axes[c] * z[c]
            disp[a] = acc
        octant = 0
        for a in range(d):
            pt[a] = coords[g, a] + smax * disp[a]
            if disp[a] < 0.0:
                octant |= 1 << a
        start = start_cells[g, octant]
        s = locate(pt, start, transform, neighbors, bary) if smax > 0 else start
        if smax > 0 and s >= 0 and _star_contains(simplices, s, g):
            # Affine on a cell incident to the node: errors scale exactly with U_p.
            _interp_in(s, bary, simplices, values, bi)
            for k in range(n_up):
                r = ratio[k]
                if r == 0.0:
                    continue  # zero U_p: statistics are set to exact zeros below
                m2 = 0.0
                for c in range(3):
                    e = r * (bi[c] - b0[c])
                    comp[k, c, nvalid[k]] = e
                    m2 += (b0[c] + e) ** 2
                absb[k, nvalid[k]] = np.sqrt(m2) - abs0
                nvalid[k] += 1
            continue
        all_star = False
        cell = start
        for k in range(n_up):
            if scales[k] == 0.0:
                continue  # statistics are set to exact zeros below
            for a in range(d):
                pt[a] = coords[g, a] + scales[k] * disp[a]
            s = locate(pt, cell if cell >= 0 else start, transform, neighbors, bary)
            if s == OUTSIDE:
                n_out[k] += 1
                continue
            if s == WALK_FAILED:
                n_lost[k] += 1
                continue
            cell = s
            _interp_in(s, bary, simplices, values, bi)
            m2 = 0.0
            for c in range(3):
                comp[k, c, nvalid[k]] = bi[c] - b0[c]
                m2 += bi[c] ** 2
            absb[k, nvalid[k]] = np.sqrt(m2) - abs0
            nvalid[k] += 1
    # statistics
    if all_star and smax > 0:
        for c in range(3):
            nk = nvalid[kmax]
            sample_stats(comp[kmax, c], nk, coverage_count(nk, p), stats[kmax, c], scratch)
            for k in range(n_up):
                if k != kmax:
                    for j in range(6):
                        stats[k, c, j] = ratio[k] * stats[kmax, c, j]
    else:
        for k in range(n_up):
            if scales[k] == 0.0:
                continue  # set to zero below
            for c in range(3):
                nk = nvalid[k]
                sample_stats(
                    comp[k, c], nk, coverage_count(nk, p) if nk > 1 else 1, stats[k, c], scratch
                )
    for k in range(n_up):
        if scales[k] == 0.0:  # no displacement: every error is exactly zero
            for c in range(4):
                for j in range(6):
                    stats[k, c, j] = 0.0
            continue
        nk = nvalid[k]
        sample_stats(absb[k], nk, coverage_count(nk, p) if nk > 1 else 1, stats[k, 3], scratch)
    return all_star


@nb.njit(**PJIT)
def gauss_sweep(
    nodes,
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
    block,
):
    """Monte Carlo of B(x + N(0, U_p)) - B(x) at each node, statistics streamed per node.

    Parameters
    ----------
    nodes : ndarray, shape (k,), int64
        Node indices to process (a chunk); results do not depend on how nodes are chunked.
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
    block : int
        Nodes per parallel task (buffers are allocated once per task).

    Returns
    -------
    stats : ndarray, shape (k, n_up, 4, 6), T
        Per node, U_p value, component (Bx, By, Bz, |B|) and statistic (`STAT_NAMES`) of the
        error B_meas - B_nom over the trials that stayed inside the mesh.
    n_out : ndarray, shape (k, n_up), int64
        Trials whose perturbed point left the mesh (not extrapolated, not in the statistics).
    n_lost : ndarray, shape (k, n_up), int64
        Trials whose walk did not terminate (cyclic native meshes only).
    star : ndarray, shape (k,), bool
        True if every trial stayed in a cell incident to the node (errors exactly linear in U_p).
    """
    k_nodes = nodes.shape[0]
    n_up = scales.shape[0]
    stats = np.full((k_nodes, n_up, 4, 6), np.nan)
    n_out = np.zeros((k_nodes, n_up), dtype=np.int64)
    n_lost = np.zeros((k_nodes, n_up), dtype=np.int64)
    star = np.zeros(k_nodes, dtype=np.bool_)
    n_blocks = (k_nodes + block - 1) // block
    for b in nb.prange(n_blocks):
        comp = np.empty((n_up, 3, n_trials))
        absb = np.empty((n_up, n_trials))
        scratch = np.empty(n_trials)
        for i in range(b * block, min((b + 1) * block, k_nodes)):
            g = nodes[i]
            if start_cells[g, 0] < 0:
                continue
            star[i] = _node_gauss(
                g,
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
                comp,
                absb,
                scratch,
                stats[i],
                n_out[i],
                n_lost[i],
            )
    return stats, n_out, n_lost, star
