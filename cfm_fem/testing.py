"""Plain-numpy twins of the numba kernels in `cfm_fem._kernels` (slow, obvious), and analytic
cases with closed-form answers.

Each twin gives the kernel's numbers by the most direct code, for tests: the package's own and
users' (a kernel and its twin agree to rounding, most of them bit for bit). The analytic cases
(`linear_field_map`, `gauss_linear_std`) are fields whose sweep statistics are known exactly.
"""

from __future__ import annotations

import math

import numpy as np
import scipy.spatial

from . import _kernels
from . import _kernels as K
from .models.bench import ERROR_NAMES, Bench
from .models.field import FieldMap
from .models.harmonic_basis import field_basis, monomial_exponents, n_basis
from .models.kinematics.geometry import _keys, kernel_geometry
from .models.mc import coverage_count, ppf_numpy, shortest_interval, symmetric_interval

M64 = (1 << 64) - 1
GAMMA = 0x9E3779B97F4A7C15
STREAM_SWEEP = 0x53574550
STREAM_FALLBACK = 0x46414C4C
KN, WN, FN = _kernels.ziggurat_tables()
LAYER_MASK = _kernels.ZIG_LAYERS - 1
ZIG_R = _kernels.rng._ZIG_R


def mix64(z: int) -> int:
    z &= M64
    z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) & M64
    z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & M64
    return z ^ (z >> 31)


def stream_key(seed: int, stream: int) -> int:
    return mix64(mix64(seed * GAMMA + 1) ^ stream)


def trial_key(key: int, index: int) -> int:
    return mix64(mix64(key + index * GAMMA))


def draw(key: int, counter: int) -> int:
    return mix64(key + counter * GAMMA)


def uniform53(h: int) -> float:
    return min(((h >> 11) + 0.5) / 9007199254740992.0, 1.0 - 2.0**-53)


def int32(v: int) -> float:
    v &= 0xFFFFFFFF
    return float(v - (1 << 32) if v >= 1 << 31 else v)


def zig_fallback(hz: float, iz: int, fkey: int) -> float:
    c = 0
    while True:
        x = hz * WN[iz]
        if iz == 0:
            while True:
                c += 1
                x = -np.log(uniform53(draw(fkey, c))) / ZIG_R
                c += 1
                y = -np.log(uniform53(draw(fkey, c)))
                if y + y >= x * x:
                    break
            return ZIG_R + x if hz > 0 else -ZIG_R - x
        c += 1
        if FN[iz] + uniform53(draw(fkey, c)) * (FN[iz - 1] - FN[iz]) < np.exp(-0.5 * x * x):
            return x
        c += 1
        h = draw(fkey, c)
        hz, iz = int32(h), (h >> 32) & (_kernels.ZIG_LAYERS - 1)
        if abs(hz) < KN[iz]:
            return hz * WN[iz]


def normal_from_bits(value32: int, layer: int, fkey: int, fb: int) -> float:
    hz = int32(value32)
    if abs(hz) < KN[layer]:
        return hz * WN[layer]
    return zig_fallback(hz, layer, mix64(fkey ^ (fb & M64)))


def three_normals(tkey: int, fkey: int, index: int):
    """Twin of `_kernels._three_normals`: two hashes, three ziggurat normals."""
    c = index * 4
    h1, h2 = draw(tkey, c), draw(tkey, c + 1)
    fb = tkey + c * GAMMA
    return (
        normal_from_bits(h1 & 0xFFFFFFFF, (h2 >> 32) & LAYER_MASK, fkey, fb),
        normal_from_bits(h1 >> 32, (h2 >> 42) & LAYER_MASK, fkey, fb + 1),
        normal_from_bits(h2 & 0xFFFFFFFF, (h2 >> 52) & LAYER_MASK, fkey, fb + 2),
    )


def node_key(point) -> int:
    """`cfm_fem.workflows.sweep.problem.node_keys` of one node (x, y, z) mm: SplitMix64 over
    its coordinates' float64 bits (-0.0 as 0.0), halved to fit int64."""
    key = 0
    for v in point:
        bits = int(np.float64(float(v) + 0.0).view(np.uint64))
        key = mix64(((key ^ bits) + GAMMA) & M64)
    return key >> 1


def node_keys(points) -> list[int]:
    """`node_key` of each row of ``points`` (n, 3) mm."""
    return [node_key(p) for p in np.asarray(points, dtype=np.float64)]


def sweep_normals(seed: int, node: int, n_trials: int) -> np.ndarray:
    """The (n_trials, 3) standard normals the sweep kernel draws for ``node``."""
    key = trial_key(stream_key(seed, STREAM_SWEEP), node)
    fkey = stream_key(seed, STREAM_FALLBACK)
    return np.array([three_normals(key, fkey, t) for t in range(n_trials)])


def sample_stats(a, p=0.95):
    """mean, std, symmetric low/high, shortest low/high by full sorting (JCGM 101 7.7)."""
    a = np.asarray(a, dtype=np.float64)
    lo, hi = symmetric_interval(a, p)
    slo, shi = shortest_interval(a, p)
    return np.array([a.mean(), a.std(ddof=1), lo, hi, slo, shi])


def gauss_sweep(
    points,
    B,
    up_mm,
    n_trials,
    seed,
    axis=(1.0, 1.0, 1.0),
    p=0.95,
    grad=None,
    nodes=None,
    interp=None,
):
    """Twin of `cfm_fem._kernels.gauss_sweep` for a 3-D map: the interpolant ``interp`` (a
    callable (k, 3) mm -> (k, 3) T, NaN outside; default scipy's LinearNDInterpolator on the
    Delaunay of ``points``, see `mesh_interpolant` for a mesh's own cells) and full sorting.
    Returns stats (len(nodes), n_up, 4, 6), n_out. ``grad`` (n, 3, 3), T/mm: points outside take
    B_g + grad_g . delta (else left out). ``nodes``: the nodes to sweep (default all), each
    drawing the normals of its own index."""
    if interp is None:
        from scipy.interpolate import LinearNDInterpolator

        interp = LinearNDInterpolator(scipy.spatial.Delaunay(points), B)
    nodes = np.arange(len(points)) if nodes is None else np.asarray(nodes)
    n_up = len(up_mm)
    stats = np.full((len(nodes), n_up, 4, 6), np.nan)
    n_out = np.zeros((len(nodes), n_up), dtype=np.int64)
    for i, g in enumerate(nodes):
        z = sweep_normals(seed, int(g), n_trials)
        for k, s in enumerate(up_mm):
            delta = s * z * np.asarray(axis)
            stats[i, k], n_out[i, k] = error_stats(
                interp(points[g] + delta), B[g], delta, None if grad is None else grad[g], p
            )
    return stats, n_out


def error_stats(Bm, b0, delta, grad=None, p=0.95):
    """Statistics (4, 6) of the errors Bm - b0 of the trials (k, 3) and the number of trials
    outside (Bm NaN). Those are left out, or with ``grad`` (3, 3), T/mm, take the node's Taylor
    expansion b0 + grad . delta (delta (k, 3), mm). NaN statistics for fewer than 2 values."""
    Bm = np.array(Bm, dtype=np.float64)
    ok = np.isfinite(Bm[:, 0])
    n_out = int((~ok).sum())
    if grad is not None:
        Bm[~ok] = b0 + delta[~ok] @ grad.T
        ok[:] = True
    err = Bm[ok] - b0
    absb = np.linalg.norm(Bm[ok], axis=1) - np.linalg.norm(b0)
    out = np.full((4, 6), np.nan)
    if ok.sum() >= 2:
        for c in range(3):
            out[c] = sample_stats(err[:, c], p)
        out[3] = sample_stats(absb, p)
    return out, n_out


def locate_all(mesh, q, pad=1e-6):
    """Twin of `find_cell` for many points at once, brute force over the mesh's own (not
    Delaunay's) cells: per point of ``q`` (k, d) the cell holding it where it lies deepest
    (every coordinate >= -BARY_EPS) or -1, and its barycentric coordinates (k, d + 1). Only
    the cells whose bounding box, padded by ``pad`` (mm), meets that of the points are tried:
    no other can hold one of them (and the test stays fast)."""
    d = mesh.dim
    v = mesh.coords[mesh.simplices]
    near = ((v.min(1) - pad <= q.max(0)) & (v.max(1) + pad >= q.min(0))).all(1)
    cells = np.flatnonzero(near)
    if len(cells) == 0:
        return np.full(len(q), -1), np.full((len(q), d + 1), np.nan)
    T = mesh.transform[cells]
    # lam[j] = T_j . (x - T_d), (k, m) per coordinate j: one matrix product each
    lam = [q @ T[:, j].T - (T[:, j] * T[:, d]).sum(1) for j in range(d)]
    lam.append(1.0 - sum(lam))
    lmin = np.minimum.reduce(lam)
    ok = lmin >= -_kernels.BARY_EPS
    best = np.argmax(np.where(ok, lmin, -np.inf), axis=1)
    hit = ok.any(1)
    cell = np.where(hit, cells[best], -1)
    rows = np.arange(len(q))
    bary = np.where(hit[:, None], np.stack([x[rows, best] for x in lam], 1), np.nan)
    return cell, bary


def mesh_interpolant(mesh, B):
    """The linear interpolant of ``B`` (n, 3) in the mesh's own cells (`locate_all`): a callable
    (k, d) mesh coordinates -> (k, 3) T, NaN for points in no cell."""

    def interp(q):
        cell, bary = locate_all(mesh, np.atleast_2d(q))
        out = np.full((len(cell), 3), np.nan)
        inside = cell >= 0
        out[inside] = np.einsum("pj,pjc->pc", bary[inside], B[mesh.simplices[cell[inside]]])
        return out

    return interp


def coverage_q(n, p=0.95):
    return coverage_count(n, p)


def node_gradients(mesh, B):
    """Twin of `cfm_fem.workflows.sweep.problem.node_gradients` (numpy: einsum over cells, np.add.at
    per node)."""
    d = mesh.dim
    n = len(mesh.coords)
    T = mesh.transform[:, :d, :]  # rows are grad(lambda_j), j < d
    grad_lam = np.concatenate([T, -T.sum(axis=1, keepdims=True)], axis=1)  # (m, d+1, d)
    cell_grad = np.einsum("mjc,mjk->mck", B[mesh.simplices], grad_lam)  # (m, 3, d)
    vol = np.abs(1.0 / np.linalg.det(T))  # proportional to the simplex measure
    cell_grad *= vol[:, None, None]
    acc = np.zeros((n, 3, d))
    wsum = np.zeros(n)
    for j in range(d + 1):
        np.add.at(acc, mesh.simplices[:, j], cell_grad)
        np.add.at(wsum, mesh.simplices[:, j], vol)
    return (acc / wsum[:, None, None]) @ mesh.basis.T


def barycentric_all(mesh, p):
    """Barycentric coordinates (m, d + 1) of point ``p`` (d,) in every cell of ``mesh``."""
    d = mesh.dim
    T = mesh.transform
    lam = np.einsum("mjk,mk->mj", T[:, :d], p - T[:, d])
    return np.c_[lam, 1.0 - lam.sum(1)]


def find_cell(mesh, p):
    """Twin of `cfm_fem._kernels.find_cell`, brute force over all cells: of the cells holding
    ``p`` (every coordinate >= -BARY_EPS) the one where it lies deepest; -1 if none."""
    lmin = barycentric_all(mesh, p).min(1)
    ok = lmin >= -_kernels.BARY_EPS
    if not ok.any():
        return -1
    return int(np.flatnonzero(ok)[np.argmax(lmin[ok])])


def face_excess(mesh):
    """Twin of `cfm_fem.models.mesh.face_excess`: for each border face, the largest minus
    barycentric coordinate of its face over all nodes, brute force (no hull)."""
    d = mesh.dim
    out = np.zeros(mesh.neighbors.shape)
    nodes = np.unique(mesh.simplices)
    for s, j in zip(*np.nonzero(mesh.neighbors < 0), strict=True):
        T = mesh.transform[s]
        lam = (mesh.coords[nodes] - T[d]) @ T[:d].T
        lam = np.c_[lam, 1.0 - lam.sum(1)][:, j]
        ex = max(0.0, -lam.min())
        out[s, j] = ex if ex > _kernels.EXCESS_TOL else 0.0
    return out


def node_reach(mesh, nodes, cap):
    """Twin of `cfm_fem._kernels.node_reach`, brute force over all cells: per node, the least
    over the cells not incident to it whose bounding box comes within ``cap`` of it of the
    larger of the distance to the box and the largest distance of the node beyond one of the
    cell's face planes (at most ``cap``). Each sum in the kernel's order, so equal bit for bit
    to a kernel that finds the nearest cells (the least does not depend on the order)."""
    d = mesh.dim
    T = mesh.transform
    gn = np.c_[(T[:, :d] ** 2).sum(2), (T[:, :d].sum(1) ** 2).sum(1)]  # |grad lam_j|^2
    v = mesh.coords[mesh.simplices]
    lo, hi = v.min(1), v.max(1)
    out = np.empty(len(nodes))
    for i, (g, r) in enumerate(zip(nodes, cap, strict=True)):
        x = mesh.coords[g]
        gap = (np.maximum(np.maximum(lo - x, 0.0), x - hi) ** 2).sum(1)
        near = (gap <= r * r) & ~(mesh.simplices == g).any(1)
        lam = (T[near, :d] * (x - T[near, d])[:, None, :]).sum(2)
        lam = np.c_[lam, 1.0 - lam.sum(1)]
        lb = np.where(lam < 0.0, -lam / np.sqrt(gn[near]), 0.0).max(1)
        out[i] = min(r, np.maximum(lb, np.sqrt(gap[near])).min()) if near.any() else r
    return out


def star_height(transform, simplices, n_nodes):
    """Twin of the heights of `cfm_fem._kernels.star_sizes`, over every cell of every node:
    per node, its largest height over the face opposite it in one of its cells, mm."""
    d = transform.shape[2]
    grad = np.concatenate([transform[:, :d], -transform[:, :d].sum(axis=1, keepdims=True)], 1)
    out = np.zeros(n_nodes)
    np.maximum.at(out, simplices.ravel(), 1.0 / np.linalg.norm(grad, axis=2).ravel())
    return out


def padded_ranges(boxes, box, dims):
    """Twin of `cfm_fem._kernels.locate._padded_range` for every cell: (i0, span), shape (m, d)."""
    lo, hi = boxes[:, 0], boxes[:, 1]
    pad = 1e-8 * (hi - lo).max(axis=1, keepdims=True)
    i0 = np.clip(np.floor((lo - pad - box[0]) * box[1]).astype(np.int64), 0, dims - 1)
    i1 = np.clip(np.floor((hi + pad - box[0]) * box[1]).astype(np.int64), 0, dims - 1)
    return i0, i1 - i0 + 1


def cell_buckets(coords, simplices, per_bucket=4.0, max_entries=48.0):
    """Twin of `cfm_fem.models.mesh.cell_buckets` in numpy (its code before the kernels)."""
    m, dp1 = simplices.shape
    d = dp1 - 1
    v = coords[simplices]
    lo, hi = v.min(1), v.max(1)
    pad = 1e-8 * (hi - lo).max(axis=1, keepdims=True)
    g_lo, g_hi = (lo - pad).min(axis=0), (hi + pad).max(axis=0)
    ext = g_hi - g_lo
    while True:
        step = (np.prod(ext) / max(m / per_bucket, 1.0)) ** (1.0 / d)
        dims = np.maximum(np.ceil(ext / step), 1).astype(np.int64)
        box = np.stack([g_lo, dims / ext])
        i0, span = padded_ranges(np.stack([lo, hi], axis=1), box, dims)
        if np.prod(span, axis=1).sum() <= max_entries * m or dims.prod() == 1:
            break
        per_bucket *= 4.0
    bstart, bcells = bucket_lists(i0, span, dims)
    return box, dims, bstart, bcells.astype(np.int32)


def bucket_lists(i0, span, dims):
    """Twin of `cfm_fem._kernels.bucket_lists` in numpy: every (cell, bucket) entry listed,
    then sorted by bucket (stable: cells stay increasing)."""
    count = np.prod(span, axis=1)
    cell = np.repeat(np.arange(len(i0), dtype=np.int64), count)
    rank = np.arange(len(cell), dtype=np.int64) - np.repeat(np.cumsum(count) - count, count)
    flat = np.zeros(len(cell), dtype=np.int64)
    for a in range(i0.shape[1] - 1, -1, -1):  # rank -> offsets along each axis
        w = span[cell, a]
        flat += (i0[cell, a] + rank % w) * np.prod(dims[a + 1 :], dtype=np.int64)
        rank //= w
    bstart = np.zeros(int(dims.prod()) + 1, dtype=np.int64)
    np.cumsum(np.bincount(flat, minlength=int(dims.prod())), out=bstart[1:])
    return bstart, cell[np.argsort(flat, kind="stable")]


# ---------------------------------------------------------------------------------------------
# Bench kinematics: the random keys and the samples of the pilot pass
# ---------------------------------------------------------------------------------------------
def trial_keys(nkey: int, t0: int, n: int) -> np.ndarray:
    """Twin of `cfm_fem._kernels.trial_keys`: `trial_key` of trials t0 .. t0+n-1, uint64."""
    return np.array([trial_key(nkey, t0 + k) for k in range(n)], dtype=np.uint64)


def chain(terms, k: int, q, n) -> tuple:
    """Twin of `cfm_fem._kernels.kinematics_passes._chain`: E_x, E_y, E_z, |E| (mm) of row k
    of the collapsed chain ``terms`` at commanded position q and axis noise n, each sum left to
    right as in the kernel (the same bits)."""
    t = [float(x) for x in terms[k]]
    q0, q1, q2 = (float(x) for x in q)
    n0, n1, n2 = (float(x) for x in n)
    e = [t[c] + q0 * t[3 + c] + q1 * t[6 + c] + q2 * t[9 + c]
         + n0 * t[12 + c] + n1 * t[15 + c] + n2 * t[18 + c] for c in range(3)]  # fmt: skip
    return e[0], e[1], e[2], math.sqrt(e[0] * e[0] + e[1] * e[1] + e[2] * e[2])


def axis_noise(nkey: int, fkey: int, trial: int, point: int, sig, speed, tau_code, tau_par):
    """Twin of `cfm_fem._kernels.axis_noise_mm` (mm, shape (3,)): three normals at positions
    4 * point, 4 * point + 1 of the trial's sequence, times ``sig``; plus ``speed`` x tau, tau
    from the uniform at position 4 * point + 2 (none for tau_code < 0)."""
    tkey = trial_key(nkey, trial)
    z = three_normals(tkey, fkey, point)
    out = [float(sig[a]) * z[a] for a in range(3)]
    if tau_code >= 0:
        u = uniform53(draw(tkey, 4 * point + 2))
        tau = float(ppf_numpy(int(tau_code), tau_par, np.array([u]))[0])
        out = [out[a] + float(speed[a]) * tau for a in range(3)]
    return np.array(out)


def kinematics_values(model, t0: int, n: int, q, pidx) -> np.ndarray:
    """Twin of `cfm_fem._kernels.pass_pilot` (and of `fill_values` per point): E_x, E_y, E_z,
    |E| of trials t0 .. t0+n-1 at the points q, shape (npts, 4, n), mm.

    ``model`` as the kernel's (`cfm_fem.models.kinematics.monte_carlo._Engine.model`): row k of its
    terms and params serves trial t0 + k. The noise of (trial, point) is `axis_noise` keyed by the
    point's index pidx[i] (the twin derives the trial keys itself; the model's are not read).
    Collapsed chain (`chain`) when the model is linear, else the numpy HTM chain
    `cfm_fem.models.kinematics.chain.probe_errors` (equal to the kernel's to rounding only).
    """
    from .models.kinematics.chain import probe_errors

    linear, terms, params, sig, speed, tau_code, tau_par, nkey, _, fkey = model[:10]
    stack, mounts, tool, strokes, profiles = model[10:15]
    npts = len(q)
    dq = np.array([[axis_noise(int(nkey), int(fkey), t0 + k, int(pidx[i]), sig, speed,
                               tau_code, tau_par) for i in range(npts)]
                   for k in range(n)])  # fmt: skip
    out = np.empty((npts, 4, n))
    if linear:
        for i in range(npts):
            for k in range(n):
                out[i, :, k] = chain(terms, k, q[i], dq[k, i])
        return out
    e = probe_errors(params[:n], q, dq, stack, mounts, tool, strokes, profiles)  # (n, npts, 3)
    out[:, :3] = e.transpose(1, 2, 0)
    out[:, 3] = np.sqrt((e * e).sum(-1)).T
    return out


def pilot_brackets(values, kth, bins: int = 2048) -> np.ndarray:
    """Twin of `cfm_fem._kernels.pass_pilot_quantiles` given the pilot's values (npts, 4, n):
    per point and quantity, brackets of the order statistics kth[:4] (0-based) read from a
    ``bins``-bin histogram of [min, max] (a lower bracket, even j, the lower edge of the bin
    holding it, an upper bracket its upper edge), then min, max and mean; shape (npts, 4, 7)."""
    out = np.empty(values.shape[:2] + (7,))
    for i, c in np.ndindex(*values.shape[:2]):
        v = values[i, c]
        vmin, vmax = v.min(), v.max()
        out[i, c, 4:] = vmin, vmax, v.mean()
        width = (vmax - vmin) / bins
        if not width > 0.0:  # every value equal
            out[i, c, :4] = vmin
            continue
        b = np.minimum(((v - vmin) * (1.0 / width)).astype(np.int64), bins - 1)
        cum = np.cumsum(np.bincount(b, minlength=bins))
        for j in range(4):
            first = np.searchsorted(cum, kth[j] + 1)  # first bin whose count reaches the rank
            out[i, c, j] = vmin + (first + j % 2) * width
    return out


# ---------------------------------------------------------------------------------------------
# Stars of the sweep (the cells incident to a node, `cfm_fem._kernels.build_star` tables)
# ---------------------------------------------------------------------------------------------
def _ordered_sum(x) -> float:
    s = 0.0
    for v in x:
        s += float(v)
    return s


def star_lam(lmat, i: int, delta) -> np.ndarray:
    """``lmat[i] @ delta`` summed left to right as the star kernels do (the same bits): the
    barycentric coordinates, in star cell i of node g, of x_g + delta of the cell's vertices
    other than g."""
    lam = np.zeros(lmat.shape[1])
    for b in range(len(delta)):
        lam = lam + lmat[i, :, b] * delta[b]
    return lam


def star_locate(start, lmat, nbr, n_star, delta):
    """Twin of `cfm_fem._kernels.star_locate`: from star cell ``start``, cross the face opposite
    the most negative coordinate (the first of equal ones) until every coordinate of the other
    vertices is >= -BARY_EPS. Returns (cell, lam): the cell if g's coordinate 1 - sum(lam) is
    >= -BARY_EPS too, else -1; LEAVES_MESH on crossing a border face (nbr < 0); -1 after
    n_star + 4 steps."""
    eps = _kernels.BARY_EPS
    s = start
    lam = np.zeros(lmat.shape[1])
    for _ in range(n_star + 4):
        lam = star_lam(lmat, s, delta)
        if lam.min() >= -eps:
            return (s if 1.0 - _ordered_sum(lam) >= -eps else -1), lam
        s = nbr[s, int(np.argmin(lam))]
        if s < 0:
            return _kernels.LEAVES_MESH, lam
    return -1, lam


def star_find(mesh, cells, p):
    """Twin of `cfm_fem._kernels.star_find` from the mesh alone: the first of the star cells
    ``cells`` whose barycentric coordinates of ``p`` (`barycentric_all`) are all >= -BARY_EPS,
    with those coordinates; (OUTSIDE, None) if none."""
    bary = barycentric_all(mesh, p)[cells]
    ok = np.flatnonzero(bary.min(1) >= -_kernels.BARY_EPS)
    if len(ok) == 0:
        return _kernels.OUTSIDE, None
    return int(cells[ok[0]]), bary[ok[0]]


def star_recheck(g, cells, n_star, lmat, nbr, simplices, excess, reach, delta):
    """Twin of `cfm_fem._kernels.star_recheck`. Returns (cell, r_in, r_out, lam): the first
    star cell holding x_g + delta (`star_lam` >= -BARY_EPS, g's coordinate too), with 0, inf
    and its coordinates; else -1, r_in = reach / |delta| unless delta is in some star cell's
    cone (coordinates of the other vertices >= -BARY_EPS; then 0), and r_out the least over
    the border faces (nbr < 0) whose plane x_g + delta is beyond (lam_a < -BARY_EPS) of
    (excess * (1 + EXCESS_MARGIN) + BARY_EPS) / -lam_a (inf if none)."""
    eps = _kernels.BARY_EPS
    r_out = np.inf
    cone = False
    for i in range(n_star):
        lam = star_lam(lmat, i, delta)
        if lam.min() >= -eps:
            if 1.0 - _ordered_sum(lam) >= -eps:
                return i, 0.0, np.inf, lam
            cone = True
        s = cells[i]
        others = [j for j in range(simplices.shape[1]) if simplices[s, j] != g]
        for a, j in enumerate(others):
            if nbr[i, a] < 0 and lam[a] < -eps:
                ex = float(excess[s, j])  # float32 in the search arrays; the kernel widens it
                r_out = min(r_out, (ex * (1.0 + _kernels.EXCESS_MARGIN) + eps) / -lam[a])
    r_in = 0.0 if cone else reach / math.sqrt(_ordered_sum(np.asarray(delta) ** 2))
    return -1, r_in, r_out, None


def _splitmix_numpy(key, counters):
    z = (np.uint64(key) + counters.astype(np.uint64) * K.GAMMA).astype(np.uint64)
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return z ^ (z >> np.uint64(31))


def draw_error_sets_numpy(bench: Bench, n_trials: int, seed: int, start: int = 0) -> np.ndarray:
    """Plain-numpy twin of :func:`draw_error_sets` (scipy's ndtri for the normals); for tests."""
    ekey, _, _ = _keys(seed)
    t = np.arange(start, start + n_trials, dtype=np.uint64)[:, None]
    ctr = t * np.uint64(32) + np.arange(len(ERROR_NAMES), dtype=np.uint64)[None, :]
    with np.errstate(over="ignore"):
        h = _splitmix_numpy(ekey, ctr)
    u = ((h >> np.uint64(11)).astype(np.float64) + 0.5) * 2.0**-53
    g = kernel_geometry(bench)
    return np.stack([ppf_numpy(g.codes[k], g.pars[k], u[:, k]) for k in range(u.shape[1])], -1)


#: Gradient (T/mm, row i = grad B_i) and value at the origin (T) of `linear_field_map`.
LINEAR_GRADIENT = np.array([[0.3, -0.1, 0.02], [0.05, 0.2, -0.4], [0.0, 0.1, 0.7]])
LINEAR_OFFSET = np.array([0.1, -0.2, 0.5])


def linear_field_map(n=9, h=1.0, centred=False, field=None, gradient=LINEAR_GRADIENT,
                     offset=LINEAR_OFFSET) -> FieldMap:  # fmt: skip
    """A cubic grid map of n^3 nodes, step h (mm), of the linear field B = G x + B0 (T).

    Parameters
    ----------
    n : int
        Nodes per axis.
    h : float, mm
        Grid step.
    centred : bool
        Grid centred on the origin (else its corner is).
    field : callable(ndarray (m, 3) mm) -> ndarray (m, 3) T, optional
        Another field on the same grid.
    gradient : ndarray, shape (3, 3), T/mm
    offset : ndarray, shape (3,), T
    """
    ax = np.arange(n) * h - ((n - 1) * h / 2 if centred else 0.0)
    pts = np.stack(np.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3)
    B = pts @ np.asarray(gradient).T + offset if field is None else field(pts)
    return FieldMap.from_arrays(pts, B)


def gauss_linear_std(up_um: float, gradient=LINEAR_GRADIENT) -> np.ndarray:
    """Exact standard deviation (T) of each component of B(x + d) - B(x) for a linear field
    and an isotropic normal displacement d of standard deviation U_p per axis (paper eq. 16):
    U_p |grad B_i|. The 95 % half-width is 1.96 times it.

    Returns
    -------
    ndarray, shape (3,), T
    """
    return up_um * 1e-3 * np.linalg.norm(np.asarray(gradient), axis=1)


def harmonic_design(u, degree: int) -> np.ndarray:
    """Design matrix of the harmonic basis of ``degree`` at scaled displacements ``u`` (m, 3):
    row 3 i + c is component c of every basis field at u[i]; shape (3 m, n_basis(degree))."""
    exps = monomial_exponents(degree)
    mono = np.prod(np.asarray(u)[:, None, :] ** exps[None], axis=2)  # (m, M)
    return np.einsum("im,cmj->icj", mono, field_basis(degree)).reshape(-1, n_basis(degree))


def harmonic_fit_twin(centers, scale, nbr, points, B, lmin: int, lmax: int) -> tuple:
    """`_kernels.harmonic_fit_block` by `np.linalg.lstsq` and explicit hat matrices.

    Per node and degree: the weighted least-squares fit (weights (1 - `FIT_TAPER` |u|^2)^4)
    with column-scaled design, its residuals and
    the leave-one-node-out residuals (I - H_ii)^-1 e_i from the 3 x 3 diagonal blocks of
    H = Q Q^T; the degree of least PRESS among those the equations and the pivots (squared
    diagonal of R in A = Q R) allow; the Laplace checks by `harmonic_fit_checks`. Returns
    (coef, degree, resid, flag, checks).
    """
    n, k = nbr.shape
    rows = 3 * k
    nbf = n_basis(lmax)
    coef = np.zeros((n, nbf))
    degree = np.full(n, lmin, dtype=np.int64)
    resid = np.full(n, np.nan)
    flag = np.zeros(n, dtype=np.int64)
    checks = np.full((n, 4), np.nan)
    lcap = max([L for L in range(lmax + 1) if rows >= K.FIT_EQ_PER_UNKNOWN * n_basis(L)],
               default=-1)  # fmt: skip
    for g in range(n):
        u = (points[nbr[g]] - centers[g]) / scale[g]
        sw = np.repeat((1.0 - K.FIT_TAPER * np.sum(u**2, axis=1)) ** 2, 3)
        b = B[nbr[g]].reshape(-1) * sw
        checks[g] = harmonic_fit_checks(u, B[nbr[g]])
        a = harmonic_design(u, lmax) * sw[:, None]
        norms = np.linalg.norm(a, axis=0)
        a = a / np.where(norms > 0, norms, 1.0)
        pivots = np.diag(np.linalg.qr(a, mode="r")) ** 2
        small = np.flatnonzero(pivots <= K.FIT_PIVOT_MIN)
        n_ok = small[0] if small.size else nbf
        lhi = max([L for L in range(lcap + 1) if n_basis(L) <= n_ok], default=-1)
        flag[g] |= K.FIT_CAPPED_EQUATIONS * (lcap < lmax) | K.FIT_CAPPED_PIVOT * (lhi < lcap)
        if lhi < lmin:
            flag[g] |= K.FIT_FAILED
            continue
        best = None
        for L in range(lmin, lhi + 1):
            al = a[:, : n_basis(L)]
            c = np.linalg.lstsq(al, b, rcond=None)[0]
            e = (al @ c - b).reshape(k, 3)
            q = np.linalg.qr(al)[0].reshape(k, 3, -1)
            eye_h = np.eye(3) - np.einsum("iaj,ibj->iab", q, q)
            if np.any(np.linalg.det(eye_h) < K.FIT_LEVERAGE_DET_MIN):
                press = np.inf
            else:
                press = np.sum(np.linalg.solve(eye_h, e[..., None]) ** 2)
            if best is None or press < best[0]:
                best = (press, L, c, np.sqrt(np.sum(e**2) / np.sum(sw**2)))
        _, degree[g], c, resid[g] = best
        coef[g, : c.size] = c / norms[: c.size]
    return coef, degree, resid, flag, checks


def harmonic_fit_checks(u, b) -> np.ndarray:
    """The ``checks`` row of `_kernels.harmonic_fit_block` for one neighbourhood: RMS over the
    components of B - mean(B), of B, and of the residuals of the harmonic and of the
    unconstrained polynomial fits of degree `FIT_CHECK_DEGREE`, weighted (``u`` (k, 3),
    ``b`` (k, 3))."""
    L = K.FIT_CHECK_DEGREE
    out = [np.sqrt(np.mean((b - b.mean(axis=0)) ** 2)), np.sqrt(np.mean(b**2))]
    sw = (1.0 - K.FIT_TAPER * np.sum(u**2, axis=1)) ** 2
    mono = np.prod(u[:, None, :] ** monomial_exponents(L)[None], axis=2) * sw[:, None]
    harm = harmonic_design(u, L) * np.repeat(sw, 3)[:, None]
    for a, rhs in ((harm, (b * sw[:, None]).reshape(-1)), (mono, b * sw[:, None])):
        norms = np.linalg.norm(a, axis=0)
        a = a / np.where(norms > 0, norms, 1.0)
        if np.min(np.diag(np.linalg.qr(a, mode="r")) ** 2) <= K.FIT_PIVOT_MIN:
            out.append(np.nan)
            continue
        rss = np.sum((a @ np.linalg.lstsq(a, rhs, rcond=None)[0] - rhs) ** 2)
        out.append(np.sqrt(rss / (3 * np.sum(sw**2))))
    return np.array(out)


def cv_stats(y, xu, s, sig1, p=0.95):
    """Twin of `_kernels.harmonic_cv.cv_stats` by full sorts: the statistics of one quantity
    from n trials' errors ``y`` (T) and first-order parts per unit U_p ``xu`` (T/mm), U_p
    ``s`` (mm), exact standard deviation ``sig1`` of ``xu`` (T/mm).

    Returns
    -------
    out : ndarray, shape (6,), T
        mean, std, symmetric low/high, shortest low/high.
    se : ndarray, shape (2,), T
        Standard errors of the symmetric ends.
    """
    y = np.asarray(y, dtype=np.float64)
    xu = np.asarray(xu, dtype=np.float64)
    n = len(y)
    q = coverage_count(n, p)
    h = n - q
    ys, xs = np.sort(y), np.sort(xu)
    r = max(h // 2 if h % 2 == 0 else (h + 1) // 2, 1)

    def figures(srt, v):
        low, high = srt[:h], srt[n - h :]
        best = int(np.argmin(high - low))
        return np.array([v.mean(), v.std(ddof=1), low[r - 1], high[r - 1], low[best], high[best]])

    fy, fx = figures(ys, y), figures(xs, xu)
    m = min(max(r // 2, 1), r - 1, h - r)
    w = n / (2.0 * m)
    zq = float(K.normal_quantile(0.5 * (1.0 + p)))
    ifx = s * sig1 / (math.exp(-0.5 * zq * zq) / math.sqrt(2.0 * math.pi))
    a_lo, a_hi = r / n, (h - r + 1) / n
    var = {}
    for side, srt_y, srt_x, a in (
        ("lo", ys[:h], xs[:h], a_lo),
        ("hi", ys[n - h :], xs[n - h :], a_hi),
    ):
        i = r - 1
        ify = (srt_y[i + m] - srt_y[i - m]) * w
        d = ((srt_y[i + m] - s * srt_x[i + m]) - (srt_y[i - m] - s * srt_x[i - m])) * w
        if side == "lo":
            c = np.sum((y <= fy[2]) & (xu > fx[2]))
            window = xu <= xs[h - 1]  # the h trials of X's low tail
        else:
            c = np.sum((y >= fy[3]) & (xu < fx[3]))
            window = xu >= xs[n - h]
        v_cv = a * (1 - a) * d**2 + 2.0 * (c / n) * abs(ify * ifx)
        e = (y - s * xu)[window]  # the remainder near the quantile
        if len(e) >= 2:  # few trials: Var(e) / (1 + sd(e) / spacing), spacing 1 / (n f_X)
            sd_e, spacing = e.std(ddof=1), abs(ifx) / n
            small = sd_e**2 / (1.0 + sd_e / spacing) if spacing > 0 else 0.0
            v_few = a * (1 - a) * d**2 + n * small
            # the remainder spreads less than X's order statistics lie apart: the count of
            # crossings says nothing, the few-trials variance holds
            v_cv = v_few if sd_e < spacing else max(v_cv, v_few)
        else:
            v_cv = np.inf
        var[side] = (a * (1 - a) * ify**2, v_cv)
    if var["lo"][1] + var["hi"][1] < var["lo"][0] + var["hi"][0]:
        ex = s * sig1
        exact = np.array([0.0, ex, -zq * ex, zq * ex, -zq * ex, zq * ex])
        out = exact + (fy - s * fx)
        se = np.sqrt(np.array([var["lo"][1], var["hi"][1]]) / n)
    else:
        out = fy
        se = np.sqrt(np.array([var["lo"][0], var["hi"][0]]) / n)
    return out, se
