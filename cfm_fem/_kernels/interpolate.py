"""Linear interpolation of a simplex mesh at many points: block walks and star (cone) tables."""

from __future__ import annotations

import numba as nb
import numpy as np
from llvmlite import ir
from numba.core import types
from numba.extending import intrinsic

from ..threads import map_blocks
from .locate import BARY_EPS, MAX_WALK, OUTSIDE, WALK_FAILED, locate
from .options import FJIT, JIT, PJIT


@nb.njit(inline="always", **JIT)
def _walk_step3(p0, p1, p2, s, transform):
    """One step of the d = 3 walk in simplex ``s``: the barycentric coordinates of p, the face
    to cross (the first most negative coordinate, chosen by selects: at every step its outcome
    is a coin toss, so a branch would mispredict) and whether p is inside."""
    x0 = p0 - transform[s, 3, 0]
    x1 = p1 - transform[s, 3, 1]
    x2 = p2 - transform[s, 3, 2]
    b0 = 0.0 + transform[s, 0, 0] * x0 + transform[s, 0, 1] * x1 + transform[s, 0, 2] * x2
    b1 = 0.0 + transform[s, 1, 0] * x0 + transform[s, 1, 1] * x1 + transform[s, 1, 2] * x2
    b2 = 0.0 + transform[s, 2, 0] * x0 + transform[s, 2, 1] * x1 + transform[s, 2, 2] * x2
    b3 = 1.0 - b0 - b1 - b2
    m01 = min(b0, b1)
    m23 = min(b2, b3)
    j01 = np.uint64(1) if b1 < b0 else np.uint64(0)
    j23 = np.uint64(3) if b3 < b2 else np.uint64(2)
    jmin = j23 if m23 < m01 else j01
    return b0, b1, b2, b3, jmin, min(m01, m23) >= -BARY_EPS


@nb.njit(inline="always", **JIT)
def _interp_in(s, bary, simplices, values, out):
    """out = sum_j bary[j] * values[simplices[s, j]]."""
    for c in range(out.shape[0]):
        out[c] = 0.0
    for j in range(simplices.shape[1]):
        w = bary[j]
        v = simplices[s, j]
        for c in range(out.shape[0]):
            out[c] += w * values[v, c]


#: Points per block of the batched walk: its work space stays in the L1/L2 cache.
WALK_BLOCK = 1024


@nb.njit(**JIT)
def walk_block3(points, i0, n, start, transform, neighbors, cur, act, bary):
    """`locate` of points ``i0 .. i0 + n - 1`` (d = 3), one step of every unfinished walk per round.

    Each round tests the current cell of every walk still going, in a loop without branches
    that depend on the data: a point-by-point walk ends with a mispredicted branch at a
    random step, and the CPU throws away the work it had in flight for the next points. Same
    cells, same sums and the same face crossed at every step as `locate`, so the same results.

    Parameters
    ----------
    points : ndarray, shape (k, 3), mm
    i0, n : int
        The block: points i0 .. i0 + n - 1, n <= len(cur).
    start : ndarray, shape (>= n,), int64
        Starting simplex of the walk of point i0 + j at j.
    cur : ndarray, shape (>= n,), int64
        Output: containing simplex of point i0 + j, or ``OUTSIDE`` / ``WALK_FAILED``.
    act : ndarray, shape (>= n,), int64
        Work space.
    bary : ndarray, shape (>= n, 4)
        Output: barycentric coordinates in ``cur[j]`` (meaningful where cur[j] >= 0).
    """
    m = 0
    for j in range(n):
        s = start[j]
        cur[j] = s if s >= 0 else OUTSIDE
        act[m] = j
        m += s >= 0
    for _ in range(MAX_WALK):
        if m == 0:
            return
        m_next = 0
        for t in range(m):
            j = act[t]
            i = i0 + j
            s = np.uint64(cur[j])  # unsigned: no wrap-around code for the gathers
            b0, b1, b2, b3, jmin, inside = _walk_step3(
                points[i, 0], points[i, 1], points[i, 2], s, transform
            )
            bary[j, 0] = b0
            bary[j, 1] = b1
            bary[j, 2] = b2
            bary[j, 3] = b3
            nxt = neighbors[s, jmin]  # OUTSIDE when the walk leaves the mesh
            # the cell a walk goes on with, by arithmetic: LLVM turns a select here into a
            # branch, whose outcome (inside or not) is a coin toss (a two-slot array, as before,
            # was 4-6 % slower)
            ins = np.int64(inside)
            cur[j] = nxt + (np.int64(s) - nxt) * ins
            act[m_next] = j  # branch-free compaction of the walks still going
            m_next += (1 - ins) & np.int64(nxt >= 0)
        m = m_next
    for t in range(m):
        cur[act[t]] = WALK_FAILED


@nb.njit(**PJIT)
def interpolate_points(points, start, simplices, transform, neighbors, values, out, cell):
    """Piecewise-linear values at ``points``; NaN where outside the mesh.

    In 3-D the walks of a block of points advance together (`walk_block3`); in other
    dimensions each point walks on its own (`locate`). Both give the same cells and values.

    Parameters
    ----------
    points : ndarray, shape (k, d), mm, in the mesh frame
    start : ndarray, shape (k,), int64
        Starting simplex of each walk (e.g. the simplex of the nearest node, or its
        `octant_cells` entry for the point's side, which saves most of the steps).
    values : ndarray, shape (n, c)
    out : ndarray, shape (k, c)
        Output: the values.
    cell : ndarray, shape (k,), int64
        Output: containing simplex, or -1 (outside) / -2 (walk failed).

    Notes
    -----
    The caller allocates the outputs (`cfm_fem.models.interpolation.interpolate_points`): numpy asks
    for transparent huge pages for large arrays, so their first touch costs fewer page faults
    (here, 5e6 points: 0.02-0.03 s instead of 0.04 s, within the noise of a whole call).
    """
    k = points.shape[0]
    d = points.shape[1]
    nc = values.shape[1]
    block = WALK_BLOCK  # work space once per block of points, not per point
    for b in nb.prange((k + block - 1) // block):
        i0 = b * block
        n = min(block, k - i0)
        cur = np.empty(block, dtype=np.int64)
        bary = np.empty((block, d + 1))
        if d == 3:
            act = np.empty(block, dtype=np.int64)
            walk_block3(points, i0, n, start[i0 : i0 + n], transform, neighbors, cur, act, bary)
            # `_interp_in` written out for four vertices, without array views per point: 37 ->
            # 23 ns per point of one-step walks (the same sums in the same order)
            for j in range(n):
                s = cur[j]
                i = i0 + j
                cell[i] = s
                if s >= 0:
                    v0, v1 = simplices[s, 0], simplices[s, 1]
                    v2, v3 = simplices[s, 2], simplices[s, 3]
                    w0, w1, w2, w3 = bary[j, 0], bary[j, 1], bary[j, 2], bary[j, 3]
                    for c in range(nc):
                        out[i, c] = (
                            0.0 + w0 * values[v0, c] + w1 * values[v1, c] + w2 * values[v2, c]
                        ) + w3 * values[v3, c]
                else:
                    for c in range(nc):
                        out[i, c] = np.nan
        else:
            for j in range(n):
                cur[j] = locate(points[i0 + j], start[i0 + j], transform, neighbors, bary[j])
            for j in range(n):
                s = cur[j]
                cell[i0 + j] = s
                if s >= 0:
                    _interp_in(s, bary[j], simplices, values, out[i0 + j])
                else:
                    for c in range(nc):
                        out[i0 + j, c] = np.nan


def octant_cells(coords, node_cell, transform, neighbors, eps):
    """Per node, the simplex that contains node + eps * (+-1, +-1[, +-1]) for each sign pattern.

    A walk for a displacement starts from the cell of its octant (bit a of the index set when
    component a is negative, as in `octant_starts`), which cuts the walk across the node's star
    to about one step. In 3-D the eight walks of a block of nodes advance together
    (`walk_block3`). Blocks of nodes run on numba's number of threads (`cfm_fem.threads`): a
    numba parallel loop would compile the walk kernels once more on first use (~1 s).

    Returns
    -------
    ndarray, shape (n, 2**d), int64
        Start simplex per node and octant (the node's own cell where the probe leaves the mesh).
    """

    def work(g0, g1):
        return (_octant_rows(coords, node_cell, transform, neighbors, eps, g0, g1),)

    return map_blocks(work, len(coords), 2048)[0]


@nb.njit(**JIT)
def _octant_rows(coords, node_cell, transform, neighbors, eps, n0, n1):
    """Rows n0 .. n1-1 of `octant_cells`."""
    d = coords.shape[1]
    n_oct = 1 << d
    out = np.empty((n1 - n0, n_oct), dtype=np.int64)
    per = WALK_BLOCK // n_oct  # nodes per block
    for b in range((n1 - n0 + per - 1) // per):
        g0 = n0 + b * per
        g1 = min(n1, g0 + per)
        m = (g1 - g0) * n_oct
        p = np.empty((m, d))
        st = np.empty(m, dtype=np.int64)
        for g in range(g0, g1):
            for o in range(n_oct):
                r = (g - g0) * n_oct + o
                st[r] = node_cell[g]
                for a in range(d):
                    p[r, a] = coords[g, a] + (-eps if (o >> a) & 1 else eps)
        found = np.empty(m, dtype=np.int64)
        if d == 3:
            act = np.empty(m, dtype=np.int64)
            bary = np.empty((m, 4))
            walk_block3(p, 0, m, st, transform, neighbors, found, act, bary)
        else:
            bary1 = np.empty(d + 1)
            for r in range(m):
                found[r] = locate(p[r], st[r], transform, neighbors, bary1)
        for g in range(g0, g1):
            for o in range(n_oct):
                s = found[(g - g0) * n_oct + o]
                out[g - n0, o] = s if s >= 0 else node_cell[g]
    return out


@nb.njit(**PJIT)
def octant_starts(points, node, coords, start_cells):
    """Walk start of each point from the `octant_cells` row of the node it was drawn around.

    Parameters
    ----------
    points : ndarray, shape (k, d), mm
    node : ndarray, shape (k,), int64
        The node each point is a perturbation of.
    coords : ndarray, shape (n, d), mm
    start_cells : ndarray, shape (n, 2**d), int64

    Returns
    -------
    ndarray, shape (k,), int64
        ``start_cells[node, octant]``, bit a of the octant set where the point is below the
        node in coordinate a.
    """
    k, d = points.shape
    out = np.empty(k, dtype=np.int64)
    for i in nb.prange(k):
        g = node[i]
        o = 0
        for a in range(d):
            o |= np.int64(points[i, a] < coords[g, a]) << a
        out[i] = start_cells[g, o]
    return out


#: Most cells in a node's star that `interpolate_groups` handles with its vectorised cone test
#: (their index goes into the low bits of a float); a larger star (a degenerate fan) walks.
STAR_MAX_CELLS = 256


_STAR_TAG = np.uint64(STAR_MAX_CELLS - 1)


@intrinsic
def _bits_from_float(typingctx, x):
    """The IEEE-754 bits of ``x``: a float64 as a uint64, a float32 as a uint32 (a cast that
    vectorises)."""
    if x not in (types.float64, types.float32):
        return None
    width = x.bitwidth

    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.IntType(width))

    return getattr(types, f"uint{width}")(x), codegen


@intrinsic
def _with_bits(typingctx, like, bits):
    """The float of ``like``'s type whose IEEE-754 bits are the low bits of the integer
    ``bits`` (a cast that vectorises)."""
    if like not in (types.float64, types.float32) or not isinstance(bits, types.Integer):
        return None
    width = like.bitwidth

    def codegen(context, builder, signature, args):
        b = args[1]
        if bits.bitwidth > width:
            b = builder.trunc(b, ir.IntType(width))
        elif bits.bitwidth < width:
            b = builder.zext(b, ir.IntType(width))
        return builder.bitcast(b, context.get_value_type(like))

    return like(like, bits), codegen


@intrinsic
def _prefetch(typingctx, arr, offset):
    """Ask the CPU to start loading the cache line of element ``offset`` (flat index, C order)
    of the contiguous array ``arr``. A hint: it changes no result."""
    if not isinstance(arr, types.Array) or not isinstance(offset, types.Integer):
        return None

    def codegen(context, builder, signature, args):
        ary = context.make_array(signature.args[0])(context, builder, args[0])
        off = context.cast(builder, args[1], signature.args[1], types.intp)
        i8p = builder.bitcast(builder.gep(ary.data, [off]), ir.IntType(8).as_pointer())
        i32 = ir.IntType(32)
        fnty = ir.FunctionType(ir.VoidType(), [i8p.type, i32, i32, i32])
        fn = builder.module.declare_intrinsic("llvm.prefetch", [i8p.type], fnty)
        builder.call(fn, [i8p, i32(0), i32(3), i32(1)])  # read, keep in all cache levels, data
        return context.get_dummy_value()

    return types.void(arr, offset), codegen


@nb.njit(**JIT)
def node_cells(simplices, n_nodes):
    """The cells around each node (its star), as compressed rows.

    Parameters
    ----------
    simplices : ndarray, shape (m, d + 1), int64
    n_nodes : int

    Returns
    -------
    start : ndarray, shape (n_nodes + 1,), int64
    cells : ndarray, shape (m * (d + 1),), int32
        The cells holding node g are ``cells[start[g]:start[g + 1]]``, in increasing order.
    """
    m, k = simplices.shape
    start = np.zeros(n_nodes + 1, dtype=np.int64)
    for s in range(m):
        for j in range(k):
            start[simplices[s, j] + 1] += 1
    for g in range(n_nodes):
        start[g + 1] += start[g]
    fill = start[:-1].copy()
    cells = np.empty(m * k, dtype=np.int32)
    for s in range(m):
        for j in range(k):
            v = simplices[s, j]
            cells[fill[v]] = s
            fill[v] += 1
    return start, cells


@nb.njit(inline="always", **JIT)
def _place_in_cell(simplices, s, g):
    """The place (0 .. 3) of node g among the vertices of tetrahedron s, without branches."""
    return (
        np.int64(simplices[s, 1] == g)
        + 2 * np.int64(simplices[s, 2] == g)
        + 3 * np.int64(simplices[s, 3] == g)
    )


#: Bound on |cone test in float32 - in float64| / (max |cone entry| * sum |d_a|): the
#: rounding of d and of the cone rows to float32 and of three products summed, 5 * 2**-24,
#: with a margin of 3.
_CONE32_TOL = 1e-6


@nb.njit(**FJIT)
def _cone_tables(g, c0, ns, star, simplices, transform, values, cone, cone32, grad, far):
    """Per cell k of node g's star: ``cone[k]`` (9) the gradients of the barycentric coordinates
    of its three other vertices (their values at g + d are cone @ d, so d is in the cell's cone
    when all three are >= 0), ``cone32[k]`` the same in float32, ``far[k]`` (3) the gradient
    of g's own (g + d stays on g's side of the opposite face while 1 + far @ d >= 0) and
    ``grad[k]`` (3 per value column) the gradient of the linear interpolant in the cell.

    Returns the tolerance of the float32 cone test per unit of |d|_1 (`_CONE32_TOL` times the
    largest cone entry) and the squared distance, less 1 %, within which no displacement
    reaches a far face (0.99 / max |far|^2), both float32.
    """
    nc = values.shape[1]
    amax = 0.0
    fmax = 0.0
    for k in range(ns):
        s = np.int64(star[c0 + k])
        j = _place_in_cell(simplices, s, g)
        # rows 0-2: grad(lambda_0..2) from the transform; row 3 = -(their sum). The three
        # rows other than g's, and g's, picked with selects (no indexed work array).
        a0, a1, a2 = transform[s, 0, 0], transform[s, 0, 1], transform[s, 0, 2]
        b0, b1, b2 = transform[s, 1, 0], transform[s, 1, 1], transform[s, 1, 2]
        d0, d1, d2 = transform[s, 2, 0], transform[s, 2, 1], transform[s, 2, 2]
        h0, h1, h2 = -(a0 + b0 + d0), -(a1 + b1 + d1), -(a2 + b2 + d2)
        first = j == 0
        second = j <= 1
        third = j <= 2
        row = (
            b0 if first else a0, b1 if first else a1, b2 if first else a2,
            d0 if second else b0, d1 if second else b1, d2 if second else b2,
            h0 if third else d0, h1 if third else d1, h2 if third else d2,
        )  # fmt: skip
        for i in range(9):
            cone[k, i] = row[i]
            cone32[k, i] = np.float32(row[i])
            amax = max(amax, abs(row[i]))
        f0 = a0 if j == 0 else (b0 if j == 1 else (d0 if j == 2 else h0))
        f1 = a1 if j == 0 else (b1 if j == 1 else (d1 if j == 2 else h1))
        f2 = a2 if j == 0 else (b2 if j == 1 else (d2 if j == 2 else h2))
        far[k, 0] = f0
        far[k, 1] = f1
        far[k, 2] = f2
        fmax = max(fmax, f0 * f0 + f1 * f1 + f2 * f2)
        v0, v1, v2, v3 = simplices[s, 0], simplices[s, 1], simplices[s, 2], simplices[s, 3]
        for c in range(nc):
            w3 = values[v3, c]
            e0 = values[v0, c] - w3
            e1 = values[v1, c] - w3
            e2 = values[v2, c] - w3
            grad[k, 3 * c] = e0 * a0 + e1 * b0 + e2 * d0
            grad[k, 3 * c + 1] = e0 * a1 + e1 * b1 + e2 * d1
            grad[k, 3 * c + 2] = e0 * a2 + e1 * b2 + e2 * d2
    return np.float32(_CONE32_TOL * amax), np.float32(0.99 / fmax)


@nb.njit(inline="always", **FJIT)
def _tagged_min(c, k, x, y, z):
    """min of the three cone coordinates (``c``: the 9 numbers of `_cone_tables`' cone row)
    of displacement (x, y, z) in star cell k, its low 8 bits replaced by k: the max over the
    cells of these is the cell where the point lies deepest, tagged, in one float (of the
    type of x: in float32 the tag moves the value by at most 2**-15 of itself, never its
    sign)."""
    l0 = c[0] * x + c[1] * y + c[2] * z
    l1 = c[3] * x + c[4] * y + c[5] * z
    l2 = c[6] * x + c[7] * y + c[8] * z
    m = min(min(l0, l1), l2)
    return _with_bits(m, (_bits_from_float(m) & ~_STAR_TAG) | np.uint64(k))


@nb.njit(inline="always", **JIT)
def _cone_row(cone, k):
    """Row k of the cone table as a tuple: scalars the vectorised loops keep in registers (a
    table read inside them would be read again for every point, as it might alias the
    stores)."""
    return (cone[k, 0], cone[k, 1], cone[k, 2], cone[k, 3], cone[k, 4], cone[k, 5],
            cone[k, 6], cone[k, 7], cone[k, 8])  # fmt: skip


@nb.njit(inline="always", **JIT)
def _tag_cell(tagged, ns):
    """The star cell whose index `_tagged_min` put in the low bits of ``tagged`` (0 for the
    noise in the tag of a NaN point)."""
    k = np.int64(_bits_from_float(tagged) & _STAR_TAG)
    return k if k < ns else 0


@nb.njit(inline="always", **FJIT)
def _deepest_cell(tagged, ns, far, x, y, z):
    """The star cell of a point from its tagged max (`_tagged_min`), and whether the point
    left the star: in no cone, or beyond the cell's face opposite the node."""
    k = _tag_cell(tagged, ns)
    f = 1.0 + far[k, 0] * x + far[k, 1] * y + far[k, 2] * z
    return k, (tagged < -BARY_EPS) | (f < -BARY_EPS)


@nb.njit(**JIT)
def _prefetch_groups(q, group_node, star_start, star, coords, simplices, transform, values):
    """Start loading what the tables of the groups after q will read, one hop per group:
    group q + 4's star offsets, q + 3's star list and node, q + 2's cells, q + 1's vertex
    values. Each hop reads only what an earlier one fetched, so none waits for memory (a
    hint: it changes no result)."""
    n_groups = len(group_node)
    nc = values.shape[1]
    if q + 4 < n_groups:
        _prefetch(star_start, group_node[q + 4])
    if q + 3 < n_groups:
        g = group_node[q + 3]
        _prefetch(star, star_start[g])
        _prefetch(star, star_start[g + 1] - 1)
        _prefetch(coords, 3 * g)
    if q + 2 < n_groups:
        g = group_node[q + 2]
        for c in range(star_start[g], star_start[g + 1]):
            s = np.int64(star[c])
            _prefetch(transform, s * 12)
            _prefetch(transform, s * 12 + 11)
            _prefetch(simplices, s * 4)
    if q + 1 < n_groups:
        g = group_node[q + 1]
        for c in range(star_start[g], star_start[g + 1]):
            s = np.int64(star[c])
            for j in range(4):
                v = simplices[s, j] * nc
                _prefetch(values, v)
                _prefetch(values, v + nc - 1)


@nb.njit(inline="always", **FJIT)
def _star_cell_exact(b32, ctol, e0, e1, e2, cone, ns, far, x, y, z):
    """The star cell of a point and whether it left the star, as `_deepest_cell` finds them
    in float64, from the point's float32 tagged max ``b32``: taken from it where its sign is
    sure (beyond ``ctol * |e|_1``, the float32 rounding, and ``2 * BARY_EPS``), else the cone
    test done again in float64."""
    if abs(b32) > ctol * (abs(e0) + abs(e1) + abs(e2)) + np.float32(2 * BARY_EPS):
        k = _tag_cell(b32, ns)
        f = 1.0 + far[k, 0] * x + far[k, 1] * y + far[k, 2] * z
        return k, (b32 < 0) | (f < -BARY_EPS)
    tagged = _tagged_min(_cone_row(cone, 0), 0, x, y, z)
    for k in range(1, ns):
        tagged = max(tagged, _tagged_min(_cone_row(cone, k), k, x, y, z))
    return _deepest_cell(tagged, ns, far, x, y, z)


@nb.njit(inline="always", **FJIT)
def _value_in(res, i, values, g, grad, k, x, y, z):
    """res[i] = values[g] + grad[k] @ (x, y, z) (``grad[k]``: 3 numbers per value column)."""
    for c in range(values.shape[1]):
        res[i, c] = (values[g, c] + grad[k, 3 * c] * x + grad[k, 3 * c + 1] * y) + grad[
            k, 3 * c + 2
        ] * z


@nb.njit(**FJIT)
def _walk_group(pts, res, s0, transform, neighbors, simplices, values, bary):
    """Values of a group's points by walks from cell ``s0`` (NaN outside the mesh); returns
    how many points were walked."""
    for i in range(len(pts)):
        s = locate(pts[i], s0, transform, neighbors, bary)
        if s >= 0:
            _interp_in(s, bary, simplices, values, res[i])
        else:
            res[i, :] = np.nan
    return len(pts)


@nb.njit(**FJIT)
def _values_from_deepest(res, pf, n, g, coords, values, grad, best, ns):
    """res[i] from the gradient of the deepest cone cell of each of the n points around node g
    (``pf``: the points, flat)."""
    x0, x1, x2 = coords[g, 0], coords[g, 1], coords[g, 2]
    if values.shape[1] == 3:  # a field: three components unrolled
        rf = res.reshape(-1)
        vg0, vg1, vg2 = values[g, 0], values[g, 1], values[g, 2]
        for i in range(n):
            x = pf[3 * i] - x0
            y = pf[3 * i + 1] - x1
            z = pf[3 * i + 2] - x2
            k = _tag_cell(best[i], ns)
            rf[3 * i] = vg0 + grad[k, 0] * x + grad[k, 1] * y + grad[k, 2] * z
            rf[3 * i + 1] = vg1 + grad[k, 3] * x + grad[k, 4] * y + grad[k, 5] * z
            rf[3 * i + 2] = vg2 + grad[k, 6] * x + grad[k, 7] * y + grad[k, 8] * z
    else:
        for i in range(n):
            k = _tag_cell(best[i], ns)
            _value_in(res, i, values, g, grad, k, pf[3 * i] - x0, pf[3 * i + 1] - x1,
                      pf[3 * i + 2] - x2)  # fmt: skip


@nb.njit(**FJIT)
def _group_block(points, group_start, group_node, q0, q1, simplices, transform, neighbors,
                 coords, values, star_start, star, out, n_max, s_max):  # fmt: skip
    """Groups q0 .. q1-1 of `interpolate_groups`; returns how many points were walked."""
    nc = values.shape[1]
    cone = np.empty((s_max, 9))
    cone32 = np.empty((s_max, 9), dtype=np.float32)
    grad = np.empty((s_max, 3 * nc))
    far = np.empty((s_max, 3))
    e0 = np.empty(n_max, dtype=np.float32)
    e1 = np.empty(n_max, dtype=np.float32)
    e2 = np.empty(n_max, dtype=np.float32)
    thr = np.empty(n_max, dtype=np.float32)
    best = np.empty(n_max, dtype=np.float32)
    out_point = np.empty(n_max, dtype=np.int64)
    out_cell = np.empty(n_max, dtype=np.int64)
    out_next = np.empty(n_max, dtype=np.int64)
    bary = np.empty(4)
    eps2 = np.float32(2 * BARY_EPS)
    walked = 0
    for q in range(q0, q1):
        _prefetch_groups(q, group_node, star_start, star, coords, simplices, transform, values)
        g = group_node[q]
        i0 = group_start[q]
        n = group_start[q + 1] - i0
        c0 = star_start[g]
        ns = star_start[g + 1] - c0
        pts = points[i0 : i0 + n]
        res = out[i0 : i0 + n]
        if ns == 0 or ns > STAR_MAX_CELLS:  # a node in no cell, or a degenerate fan: walk
            s0 = np.int64(star[c0]) if ns > 0 else np.int64(0)
            walked += _walk_group(pts, res, s0, transform, neighbors, simplices, values, bary)
            continue
        ctol, r2 = _cone_tables(
            g, c0, ns, star, simplices, transform, values, cone, cone32, grad, far
        )
        x0, x1, x2 = coords[g, 0], coords[g, 1], coords[g, 2]
        # Flat views: numba's 2-D indexing keeps these loops scalar.
        pf = pts.reshape(-1)
        for i in range(n):  # displacements from g, in float32 for the cone test
            a0 = np.float32(pf[3 * i] - x0)
            a1 = np.float32(pf[3 * i + 1] - x1)
            a2 = np.float32(pf[3 * i + 2] - x2)
            e0[i] = a0
            e1[i] = a1
            e2[i] = a2
            # a tagged max above thr: inside that cell for sure, far face out of reach
            t = ctol * (abs(a0) + abs(a1) + abs(a2)) + eps2
            thr[i] = t if a0 * a0 + a1 * a1 + a2 * a2 < r2 else np.float32(np.inf)
        if q + 1 < len(group_node):  # the next group's points load during the tests
            for j in range(3 * group_start[q + 1], 3 * group_start[q + 2], 8):
                _prefetch(points, j)
        _deepest_cells(cone32, ns, e0, e1, e2, n, best)
        _values_from_deepest(res, pf, n, g, coords, values, grad, best, ns)
        n_unsure = 0
        for i in range(n):  # (thr is inf for a non-finite point: never > it)
            n_unsure += not best[i] > thr[i]
        if n_unsure == 0:
            continue
        # The rest: near a cone's border, near a far face, or outside the star. Decided as in
        # float64; the points outside are walked from the cell they came closest to, after
        # all their first steps' cells were asked for: their memory latencies overlap.
        n_out = 0
        for i in range(n):
            if best[i] > thr[i]:
                continue
            x = pf[3 * i] - x0
            y = pf[3 * i + 1] - x1
            z = pf[3 * i + 2] - x2
            if not (np.isfinite(x) and np.isfinite(y) and np.isfinite(z)):
                res[i, :] = np.nan  # a cone test at infinity can pick any cell
                continue
            k, left = _star_cell_exact(best[i], ctol, e0[i], e1[i], e2[i], cone, ns, far, x, y, z)
            if not left:
                if k != _tag_cell(best[i], ns):  # else the value written above stands
                    _value_in(res, i, values, g, grad, k, x, y, z)
                continue
            s = np.int64(star[c0 + k])
            s1 = neighbors[s, _place_in_cell(simplices, s, g)]  # across the far face
            out_point[n_out] = i
            out_cell[n_out] = s
            out_next[n_out] = s1
            n_out += 1
            if s1 >= 0:
                _prefetch(transform, s1 * 12)
                _prefetch(transform, s1 * 12 + 11)
                _prefetch(simplices, s1 * 4)
        for r in range(n_out):
            s1 = out_next[r]
            if s1 >= 0:
                for j in range(4):
                    _prefetch(values, simplices[s1, j] * nc)
        for r in range(n_out):
            i = out_point[r]
            walked += 1
            s = locate(pts[i], out_cell[r], transform, neighbors, bary)
            if s >= 0:
                _interp_in(s, bary, simplices, values, res[i])
            else:
                res[i, :] = np.nan
    return walked


@nb.njit(**dict(PJIT, fastmath={"contract"}))
def interpolate_groups(points, group_start, group_node, simplices, transform, neighbors,
                       coords, values, star_start, star, out):  # fmt: skip
    """Piecewise-linear values at points grouped around nodes (d = 3); NaN outside the mesh.

    Group q holds the points ``group_start[q] .. group_start[q + 1] - 1``, drawn around node
    ``group_node[q]`` (a perturbation sweep's trials). A point near its node lies in one of the
    cones of the node's star: every point of a group is tested against every cell of the star
    in loops without gathers or branches, which the compiler vectorises (the walk's
    table-indexed loads keep it scalar). The test runs in float32, twice the lanes; a point
    whose result is within the bound of float32 rounding of a cone's border, or that could
    reach a far face, is decided again in float64, so the cells are those of a float64 test.
    Points outside the star, or in a star of more than `STAR_MAX_CELLS` cells, are walked
    (`locate`) from the nearest cell. The same values as the walk to rounding (the
    interpolant taken as value at the node plus the cell's gradient times the
    displacement); the same cells but on faces, where either side gives the value.

    Parameters
    ----------
    points : ndarray, shape (k, 3), mm, in the mesh frame
    group_start : ndarray, shape (n_groups + 1,), int64
        Increasing offsets into ``points``, from 0 to k.
    group_node : ndarray, shape (n_groups,), int64
    simplices, transform, neighbors, coords : the mesh (`cfm_fem.models.mesh.SimplexMesh`)
    values : ndarray, shape (n, c)
    star_start, star : `node_cells` of the mesh
    out : ndarray, shape (k, c)
        Output: the values (NaN where a walk left the mesh, or the point is not finite).

    Returns
    -------
    int
        Points that were walked.
    """
    n_groups = len(group_node)
    n_max = 1
    for q in range(n_groups):
        n_max = max(n_max, group_start[q + 1] - group_start[q])
    s_max = 1
    for q in range(n_groups):
        g = group_node[q]
        s_max = max(s_max, min(star_start[g + 1] - star_start[g], STAR_MAX_CELLS))
    per = max(1, (1 << 12) // n_max)  # groups per task: ~4k points, work space reused
    walked = 0
    for b in nb.prange((n_groups + per - 1) // per):
        walked += _group_block(points, group_start, group_node, b * per,
                               min(n_groups, (b + 1) * per), simplices, transform, neighbors,
                               coords, values, star_start, star, out, n_max, s_max)  # fmt: skip
    return walked


@nb.njit(**JIT)
def cell_gradient_sums(simplices, transform, values, n_nodes):
    """Measure-weighted sums of the cell gradients of a piecewise-linear field, per node.

    Parameters
    ----------
    simplices : ndarray, shape (m, d + 1), int
    transform : ndarray, shape (m, d + 1, d)
        scipy-layout barycentric transforms: rows j < d are grad(lambda_j), 1/mm.
    values : ndarray, shape (n_nodes, 3), T
    n_nodes : int

    Returns
    -------
    acc : ndarray, shape (n_nodes, 3, d), T/mm x (1/|det T|)
        Sum over the cells incident to each node of |1/det T| (proportional to the cell's
        measure) times the cell's gradient [c, a] = dB_c/dx_a, in local coordinates.
    wsum : ndarray, shape (n_nodes,)
        Sum of those weights. A degenerate cell (NaN transform) makes its nodes' sums NaN.
    """
    m, k = simplices.shape
    d = k - 1
    acc = np.zeros((n_nodes, 3, d))
    wsum = np.zeros(n_nodes)
    cg = np.empty((3, d))
    for s in range(m):
        t = transform[s]
        if d == 3:
            det = (t[0, 0] * (t[1, 1] * t[2, 2] - t[1, 2] * t[2, 1])
                   - t[0, 1] * (t[1, 0] * t[2, 2] - t[1, 2] * t[2, 0])
                   + t[0, 2] * (t[1, 0] * t[2, 1] - t[1, 1] * t[2, 0]))  # fmt: skip
        else:
            det = t[0, 0] * t[1, 1] - t[0, 1] * t[1, 0]
        w = abs(1.0 / det)
        for c in range(3):
            last = values[simplices[s, d], c]
            for a in range(d):
                g = 0.0
                for j in range(d):  # grad(lambda_d) = -sum_j grad(lambda_j)
                    g += (values[simplices[s, j], c] - last) * t[j, a]
                cg[c, a] = g * w
        for j in range(k):
            v = simplices[s, j]
            wsum[v] += w
            for c in range(3):
                for a in range(d):
                    acc[v, c, a] += cg[c, a]
    return acc, wsum


@nb.njit(**FJIT)
def _deepest_cells(cone, n_star, d0, d1, d2, n, tag):
    """``tag[t]``: the max over star cells k < n_star of `_tagged_min` of displacement t (the
    cone rows of cell k in ``cone[k]``, 9 numbers): the deepest cell of each displacement and
    how deep, in vectorised loops over the displacements."""
    c = _cone_row(cone, 0)
    for t in range(n):
        tag[t] = _tagged_min(c, 0, d0[t], d1[t], d2[t])
    for k in range(1, n_star):
        c = _cone_row(cone, k)
        for t in range(n):
            tag[t] = max(tag[t], _tagged_min(c, k, d0[t], d1[t], d2[t]))
