"""Point location in a simplex mesh: walks, exact searches, bucket grids and star reach.

A walk goes from a known simplex to its neighbours; the exact search of a non-convex mesh
uses a bucket grid of padded cell boxes.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from .options import JIT

#: Barycentric tolerance: a point this close outside a face still counts as inside.
BARY_EPS = 1e-10


#: Longest walk before giving up (only non-Delaunay native meshes can make a walk cycle).
MAX_WALK = 10000


OUTSIDE = -1


WALK_FAILED = -2


@nb.njit(inline="always", **JIT)
def _walk(p, start, transform, neighbors, bary):
    """The walk of `locate`: (simplex or code, last simplex, face left by or -1)."""
    d = p.shape[0]
    s = start
    if s < 0:
        return OUTSIDE, s, -1
    for _ in range(MAX_WALK):
        _bary_in(p, s, transform, bary)
        jmin = 0
        for j in range(1, d + 1):
            if bary[j] < bary[jmin]:
                jmin = j
        if bary[jmin] >= -BARY_EPS:
            return s, s, -1
        nxt = neighbors[s, jmin]
        if nxt < 0:
            return OUTSIDE, s, jmin
        s = nxt
    return WALK_FAILED, s, -1


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
        ``MAX_WALK`` steps. On a non-convex mesh a walk can leave through a border face
        although ``p`` is inside (behind a notch): `locate_exact` settles those, `settle_walk`
        a failed walk.
    """
    return _walk(p, start, transform, neighbors, bary)[0]


#: `face_excess` values up to this (in heights of the cell above the face) count as 0: the face
#: is a supporting plane of the mesh, within the rounding of the barycentric coordinates.
EXCESS_TOL = 1e-9


#: Relative margin on a face excess before a point beyond it is declared outside.
EXCESS_MARGIN = 1e-9


@nb.njit(**JIT)
def find_cell(p, transform, box, dims, bstart, bcells, bary):
    """Simplex containing ``p`` by testing every simplex listed in its bucket (exact search).

    Of the simplices that contain ``p`` (all barycentric coordinates >= -BARY_EPS), the one
    where ``p`` lies deepest (largest smallest coordinate; the first listed on ties): the
    answer does not depend on the order of the list.

    Parameters
    ----------
    p : ndarray, shape (d,), mm
    transform : ndarray, shape (m, d + 1, d)
    box : ndarray, shape (2, d)
        Lower corner of the bucket grid (mm) and buckets per mm along each axis.
    dims : ndarray, shape (d,), int64
        Buckets along each axis (C order of the flat bucket index).
    bstart : ndarray, int64; bcells : ndarray, int32
        CSR lists: the simplices whose (padded) bounding box meets bucket b are
        ``bcells[bstart[b]:bstart[b + 1]]`` (`cfm_fem.models.mesh.cell_buckets`).
    bary : ndarray, shape (d + 1,)
        Output: barycentric coordinates in the returned simplex (as `locate` computes them).

    Returns
    -------
    int
        The simplex, or ``OUTSIDE``.
    """
    d = p.shape[0]
    b = 0
    for a in range(d):
        x = (p[a] - box[0, a]) * box[1, a]
        if not (x == x):  # NaN
            return OUTSIDE
        # beyond the grid: its border bucket lists every cell that reaches beyond it
        # (`cfm_fem.models.mesh.grid_extent`), or none when the grid covers every cell
        x = min(max(x, 0.0), dims[a] - 0.5)
        b = b * dims[a] + np.int64(x)
    return _deepest(p, transform, bcells, bstart[b], bstart[b + 1], bary)


@nb.njit(inline="always", **JIT)
def _deepest(p, transform, cells, lo, hi, bary):
    """The simplex holding ``p`` deepest (largest smallest barycentric coordinate) among
    ``cells[lo:hi]``, or among simplices ``lo .. hi - 1`` when ``cells`` is empty; ``OUTSIDE``
    if none holds it. ``bary``: its barycentric coordinates (as `locate` computes them)."""
    best = OUTSIDE
    best_min = 0.0
    for i in range(lo, hi):
        s = np.int64(cells[i]) if cells.shape[0] > 0 else np.int64(i)
        lmin = _depth(p, s, transform)
        if lmin >= -BARY_EPS and (best < 0 or lmin > best_min):
            best = s
            best_min = lmin
    if best >= 0:
        _bary_in(p, best, transform, bary)
    return best


@nb.njit(inline="always", **JIT)
def _depth(p, s, transform):
    """Smallest barycentric coordinate of ``p`` in simplex ``s`` (>= -BARY_EPS: inside)."""
    d = p.shape[0]
    last = 1.0
    lmin = np.inf
    for j in range(d):
        c = 0.0
        for k in range(d):
            c += transform[s, j, k] * (p[k] - transform[s, d, k])
        last -= c
        lmin = min(lmin, c)
    return min(lmin, last)


@nb.njit(**JIT)
def settle_walk(p, transform, search, bary):
    """Simplex containing ``p`` for a walk that failed (`WALK_FAILED`), found exactly.

    Only a walk that cycles runs out of its ``MAX_WALK`` steps: not on a Delaunay or grid
    mesh (in exact arithmetic the walk is acyclic there), rarely if ever on a native one (none in
    2,000 random non-Delaunay 2-D and 400 3-D meshes tried). Counting its trial as lost took
    the node's U_f away. With search arrays (a non-convex mesh) the bucket search `find_cell`
    answers. Without (a convex mesh: `cfm_fem.models.mesh.no_search`) every simplex is
    tested: O(m), about 2 ms per 1e5 cells, paid only for a failed walk.

    Parameters
    ----------
    p, transform, bary :
        As in `locate`.
    search : tuple
        As in `locate_exact`.

    Returns
    -------
    int
        The simplex where ``p`` lies deepest (as `find_cell`), or ``OUTSIDE`` (in none).

    Notes
    -----
    The out-of-core sweep (`cfm_fem.workflows.sweep.slabs`) appends a sentinel cell and copies of
    uncertified cells to its arrays, which this search does not tell from the mesh; its meshes
    are Delaunay or Kuhn grids, whose walks do not cycle: it does not come here.
    """
    excess, _reach, box, dims, bstart, bcells = search
    if excess.shape[0] > 0:
        return find_cell(p, transform, box, dims, bstart, bcells, bary)
    return _deepest(p, transform, bcells[:0], 0, transform.shape[0], bary)  # every simplex


@nb.njit(inline="always", **JIT)
def _bary_in(p, s, transform, bary):
    """Barycentric coordinates of p in simplex s, as `locate` computes them."""
    d = p.shape[0]
    last = 1.0
    for j in range(d):
        c = 0.0
        for k in range(d):
            c += transform[s, j, k] * (p[k] - transform[s, d, k])
        bary[j] = c
        last -= c
    bary[d] = last


@nb.njit(**JIT)
def locate_exact(p, start, transform, neighbors, bary, search):
    """`locate`, exact on non-convex meshes too.

    A walk that leaves the mesh through a border face proves ``p`` outside only when ``p`` lies
    beyond that face's plane by more than any node of the mesh does (its `face_excess`): then
    no cell can hold it. Otherwise (behind a notch, or a face left by removed hull slivers) the
    cells of ``p``'s bucket are tested (`find_cell`). On a convex mesh (empty excess table)
    this is `locate`, step for step. A ``WALK_FAILED`` is returned as is, for the caller to
    settle with `settle_walk` (that call made here took about 20 % more CPU time for the whole
    Gaussian sweep, though never run).

    Parameters
    ----------
    p, start, transform, neighbors, bary :
        As in `locate`.
    search : tuple
        ``(excess, reach, box, dims, bstart, bcells)`` (`cfm_fem.models.mesh.exact_search`):
        excess, shape (m, d + 1) or (0, d + 1), the `face_excess` of each border face in
        heights of its cell (0 elsewhere); reach, shape (n,) or (0,), `node_reach` (mm); the
        rest, the bucket lists of `find_cell`.

    Returns
    -------
    int
        As `locate`.
    """
    excess, _reach, box, dims, bstart, bcells = search
    s, last, face = _walk(p, start, transform, neighbors, bary)
    if s != OUTSIDE or face < 0 or excess.shape[0] == 0:
        return s
    if -bary[face] > excess[last, face] * (1.0 + EXCESS_MARGIN) + BARY_EPS:
        return OUTSIDE  # beyond the plane by more than every node of the mesh
    return find_cell(p, transform, box, dims, bstart, bcells, bary)


@nb.njit(**JIT)
def node_reach(coords, simplices, transform, boxes, box, dims, bstart, bcells, nodes, cap):
    """Per node g, a distance within which the only cells are g's own (its star).

    A lower bound on the distance from g to the cells not incident to g: per cell, the larger
    of the distance to its bounding box and the largest distance of g beyond one of its face
    planes (``-lam_j(g) / |grad lam_j|``), the least over the cells whose bounding box comes
    within ``cap`` of g (the others are farther than that). A point nearer to g than this is
    in the mesh if and only if it is in a star cell, however the mesh folds further away:
    `star_exit` proves trials outside with it.

    The least is found without testing every cell within ``cap``: the cells of g's own bucket
    first, then only the buckets within the distance found so far (a cell whose box is that
    near is listed in one of them), each cell once (at the first of those buckets that lists
    it) and only while its box is nearer than the distance found so far. The cells left out
    cannot lower it, so the result is that of testing them all, bit for bit (a least over a
    set does not depend on the order).

    Parameters
    ----------
    coords : ndarray, shape (n, d), mm
    simplices, transform : mesh arrays
    boxes : ndarray, shape (m, 2, d), mm
        Lower and upper corner of each cell's bounding box (`cell_boxes`).
    box, dims, bstart, bcells : bucket lists of the cells (`find_cell`), built from ``boxes``
        (`bucket_lists`)
    nodes : ndarray, shape (k,), int64
    cap : ndarray, shape (k,), mm
        Search radius per node (`star_sizes`).

    Returns
    -------
    ndarray, shape (k,), mm
        At most ``cap``; 0 where a cell not incident to g touches it (a non-conforming mesh).
    """
    d = coords.shape[1]
    out = np.empty(nodes.shape[0])
    lo = np.empty(d, dtype=np.int64)
    hi = np.empty(d, dtype=np.int64)
    own = np.empty(d, dtype=np.int64)
    c0 = np.empty(d, dtype=np.int64)
    c1 = np.empty(d, dtype=np.int64)
    gsum = np.empty(d)
    # a margin on the radius of the second pass, far above the rounding of the bucket indices
    margin = np.inf
    for a in range(d):
        margin = min(margin, 1e-6 / box[1, a])
    e = 3 - d
    n1 = dims[1 - e]
    n2 = dims[2 - e]
    idx = np.empty(d, dtype=np.int64)  # the bucket's index along each axis
    for i in range(nodes.shape[0]):
        g = nodes[i]
        r = cap[i]
        if not _reach_range(coords, g, r, box, dims, lo, hi):
            out[i] = r
            continue
        # pass 1: g's own bucket (inside the range of cap, as the index is monotonic)
        b_own = 0
        for a in range(d):
            x = np.floor((coords[g, a] - box[0, a]) * box[1, a])
            own[a] = min(max(np.int64(max(x, -1.0)), lo[a]), hi[a])
            b_own = b_own * dims[a] + own[a]
        for k in range(bstart[b_own], bstart[b_own + 1]):
            c = bcells[k]
            gap = _box_gap(coords, g, boxes, c)
            r = _reach_cell(coords, simplices, transform, g, c, gap, cap[i], r, gsum)
        # pass 2: the other buckets within r (narrowed range of cap), each cell once; three
        # nested loops as in `_bucket_pass`
        _reach_range(coords, g, min(r + margin, cap[i]), box, dims, lo, hi)
        x0 = lo[0] if e == 0 else 0
        x1 = hi[0] if e == 0 else 0
        for x in range(x0, x1 + 1):
            if e == 0:
                idx[0] = x
            for y in range(lo[1 - e], hi[1 - e] + 1):
                idx[1 - e] = y
                row = (x * n1 + y) * n2
                for z in range(lo[2 - e], hi[2 - e] + 1):
                    idx[2 - e] = z
                    b = row + z
                    if b == b_own:
                        continue
                    for k in range(bstart[b], bstart[b + 1]):
                        c = bcells[k]
                        gap = _box_gap(coords, g, boxes, c)
                        if gap > cap[i] * cap[i] or math.sqrt(gap) >= r:
                            continue  # as `_reach_cell` would: r stays
                        _padded_range(boxes, c, box, dims, c0, c1)
                        first = True  # b is the first bucket of the range that lists c
                        for a in range(d):
                            first &= max(c0[a], lo[a]) == idx[a]
                        if first:
                            r = _reach_cell(coords, simplices, transform, g, c, gap, cap[i], r,
                                            gsum)  # fmt: skip
        out[i] = r
    return out


@nb.njit(inline="always", **JIT)
def _reach_range(coords, g, r, box, dims, lo, hi):
    """Buckets within ``r`` of node g along each axis (lo..hi, clipped); False: none."""
    d = coords.shape[1]
    for a in range(d):
        x0 = np.floor((coords[g, a] - r - box[0, a]) * box[1, a])
        x1 = np.floor((coords[g, a] + r - box[0, a]) * box[1, a])
        lo[a] = np.int64(max(x0, 0.0))
        hi[a] = np.int64(min(x1, dims[a] - 1.0))
        if hi[a] < lo[a]:
            return False
    return True


@nb.njit(inline="always", **JIT)
def _box_gap(coords, g, boxes, c):
    """Squared distance from node g to cell c's bounding box, mm^2."""
    gap = 0.0
    for a in range(coords.shape[1]):
        x = coords[g, a]
        gap += max(boxes[c, 0, a] - x, 0.0, x - boxes[c, 1, a]) ** 2
    return gap


@nb.njit(inline="always", **JIT)
def _reach_cell(coords, simplices, transform, g, c, gap, cap, r, gsum):
    """`node_reach`'s distance r after cell c (squared distance ``gap`` from g to its box):
    min(r, its bound) if c is not g's and its box is within ``cap`` of g; r unchanged when the
    box is not nearer than r (no bound can be)."""
    d = coords.shape[1]
    if gap > cap * cap:
        return r
    dist = math.sqrt(gap)
    if dist >= r:
        return r
    for j in range(d + 1):
        if simplices[c, j] == g:
            return r
    lb = 0.0
    lsum = 0.0
    for a in range(d):
        gsum[a] = 0.0
    for j in range(d):
        lam = 0.0
        gn = 0.0
        for a in range(d):
            lam += transform[c, j, a] * (coords[g, a] - transform[c, d, a])
            gn += transform[c, j, a] ** 2
            gsum[a] += transform[c, j, a]
        lsum += lam
        if lam < 0.0:
            lb = max(lb, -lam / math.sqrt(gn))
    gn = 0.0
    for a in range(d):
        gn += gsum[a] ** 2
    if 1.0 - lsum < 0.0:
        lb = max(lb, -(1.0 - lsum) / math.sqrt(gn))
    return min(r, max(lb, dist))  # both bound the distance from below


@nb.njit(**JIT)
def cell_boxes(coords, simplices):
    """Bounding box of each cell.

    Parameters
    ----------
    coords : ndarray, shape (n, d), mm
    simplices : ndarray, shape (m, d + 1), int

    Returns
    -------
    ndarray, shape (m, 2, d), mm
        Lower and upper corner: the least and the largest coordinate of the cell's vertices.
    """
    m, dp1 = simplices.shape
    d = coords.shape[1]
    out = np.empty((m, 2, d))
    for c in range(m):
        for a in range(d):
            lo = coords[simplices[c, 0], a]
            hi = lo
            for j in range(1, dp1):
                x = coords[simplices[c, j], a]
                lo = min(lo, x)
                hi = max(hi, x)
            out[c, 0, a] = lo
            out[c, 1, a] = hi
    return out


@nb.njit(inline="always", **JIT)
def _padded(boxes, c):
    """The padding of cell c's box in the bucket grid: 1e-8 of its largest side, so a point
    the cell holds within the barycentric tolerance is inside the padded box."""
    side = 0.0
    for a in range(boxes.shape[2]):
        side = max(side, boxes[c, 1, a] - boxes[c, 0, a])
    return 1e-8 * side


@nb.njit(**JIT)
def padded_extent(boxes):
    """Lower and upper corner of the union of the padded cell boxes (`_padded`), mm, shape
    (2, d): the extent of the bucket grid (`cfm_fem.models.mesh.cell_buckets`)."""
    m, _, d = boxes.shape
    out = np.empty((2, d))
    out[0] = np.inf
    out[1] = -np.inf
    for c in range(m):
        pad = _padded(boxes, c)
        for a in range(d):
            out[0, a] = min(out[0, a], boxes[c, 0, a] - pad)
            out[1, a] = max(out[1, a], boxes[c, 1, a] + pad)
    return out


@nb.njit(inline="always", **JIT)
def _padded_range(boxes, c, box, dims, i0, i1):
    """First and last bucket along each axis (clipped to the grid) that cell c's padded box
    meets, into i0, i1."""
    pad = _padded(boxes, c)
    for a in range(boxes.shape[2]):
        x0 = np.int64(np.floor((boxes[c, 0, a] - pad - box[0, a]) * box[1, a]))
        x1 = np.int64(np.floor((boxes[c, 1, a] + pad - box[0, a]) * box[1, a]))
        i0[a] = min(max(x0, 0), dims[a] - 1)
        i1[a] = min(max(x1, 0), dims[a] - 1)


@nb.njit(**JIT)
def bucket_entries(boxes, box, dims):
    """How many (cell, bucket) entries the lists of `bucket_lists` would hold."""
    d = boxes.shape[2]
    i0 = np.empty(d, dtype=np.int64)
    i1 = np.empty(d, dtype=np.int64)
    total = 0
    for c in range(boxes.shape[0]):
        _padded_range(boxes, c, box, dims, i0, i1)
        n = 1
        for a in range(d):
            n *= i1[a] - i0[a] + 1
        total += n
    return total


@nb.njit(inline="always", **JIT)
def _bucket_pass(boxes, box, dims, slot, out):
    """One pass of `bucket_lists`: with ``out`` empty, count the cells of each bucket into
    ``slot[b + 1]``; else write each cell at ``slot[b]`` of its buckets and advance it."""
    m, _, d = boxes.shape
    i0 = np.empty(d, dtype=np.int64)
    i1 = np.empty(d, dtype=np.int64)
    # three nested loops (a planar mesh: one bucket along a first axis of its own), twice as
    # fast as a loop over d axes
    e = 3 - d
    n1 = dims[1 - e]
    n2 = dims[2 - e]
    count = out.shape[0] == 0
    for c in range(m):
        _padded_range(boxes, c, box, dims, i0, i1)
        x0 = i0[0] if e == 0 else 0
        x1 = i1[0] if e == 0 else 0
        for x in range(x0, x1 + 1):
            for y in range(i0[1 - e], i1[1 - e] + 1):
                row = (x * n1 + y) * n2
                for b in range(row + i0[2 - e], row + i1[2 - e] + 1):  # last axis fastest
                    if count:
                        slot[b + 1] += 1
                    else:
                        out[slot[b]] = c
                        slot[b] += 1


@nb.njit(**JIT)
def bucket_lists(boxes, box, dims):
    """CSR lists of the buckets each cell's padded box meets
    (`cfm_fem.models.mesh.cell_buckets`), counted, then filled in cell order: no
    temporaries per entry or per cell.

    Parameters
    ----------
    boxes : ndarray, shape (m, 2, d), mm
        The cells' bounding boxes (`cell_boxes`), padded here (`_padded`).
    box : ndarray, shape (2, d)
        Lower corner of the grid (mm) and buckets per mm along each axis.
    dims : ndarray, shape (d,), int64
        Buckets along each axis; flat bucket index in C order.

    Returns
    -------
    bstart : ndarray, shape (prod(dims) + 1,), int64
    bcells : ndarray, int32
        The cells meeting bucket b, increasing: ``bcells[bstart[b]:bstart[b + 1]]``.
    """
    n_b = 1
    for a in range(dims.shape[0]):
        n_b *= dims[a]
    bstart = np.zeros(n_b + 1, dtype=np.int64)
    _bucket_pass(boxes, box, dims, bstart, np.empty(0, dtype=np.int32))
    for b in range(n_b):
        bstart[b + 1] += bstart[b]
    fill = bstart[:-1].copy()
    bcells = np.empty(bstart[n_b], dtype=np.int32)  # held for the run: 4 bytes per entry
    _bucket_pass(boxes, box, dims, fill, bcells)
    return bstart, bcells


@nb.njit(**JIT)
def star_sizes(nodes, start, simplices, neighbors, transform):
    """Per node g, the cells reached from ``start[g]`` across faces that contain g (its star,
    as `build_star` builds it), counted up to MAX_STAR + 1, and g's largest height over the
    face opposite it in one of them.

    Fewer than the cells incident to g: the node's cells form several face-connected parts
    (a node where removed hull slivers or a pinched mesh leave two wedges meeting at an edge or
    a point); the star then misses incident cells, and `node_reach` is no proof there.
    Otherwise the height is over all of g's cells: `node_reach`'s search radius (the cells
    across those faces are about that near, so a wider search would seldom find a larger
    reach).

    Parameters
    ----------
    nodes : ndarray, shape (k,), int64
    start : ndarray, shape (n,), int64
        A cell incident to each node (-1: none).
    simplices, neighbors : ndarray, shape (m, d + 1), int64
    transform : ndarray, shape (m, d + 1, d)

    Returns
    -------
    sizes : ndarray, shape (k,), int64
    height : ndarray, shape (k,), mm
        1 / |grad lam_j| of the cells s counted, j the vertex of s at g, largest (0 for a node
        in no cell).
    """
    dp1 = simplices.shape[1]
    out = np.zeros(nodes.shape[0], dtype=np.int64)
    height = np.zeros(nodes.shape[0])
    seen = np.empty(MAX_STAR + 1, dtype=np.int64)
    for i in range(nodes.shape[0]):
        g = nodes[i]
        if start[g] < 0:
            continue
        seen[0] = start[g]
        n = 1
        k = 0
        while k < n:  # breadth-first across the faces that contain g
            s = seen[k]
            k += 1
            for j in range(dp1):
                ns = neighbors[s, j]
                if simplices[s, j] == g:
                    height[i] = max(height[i], _node_height(transform, s, j))
                if simplices[s, j] == g or ns < 0:
                    continue
                new = True
                for q in range(n):
                    new &= seen[q] != ns
                if new and n <= MAX_STAR:
                    seen[n] = ns
                    n += 1
        out[i] = n
    return out, height


@nb.njit(inline="always", **JIT)
def _node_height(transform, s, j):
    """Height of vertex j of cell s over the opposite face, 1 / |grad lam_j|, mm (the gradient
    of the last coordinate is minus the sum of the others, summed in numpy's order)."""
    d = transform.shape[2]
    gn = 0.0
    for a in range(d):
        if j < d:
            v = transform[s, j, a]
        else:
            v = transform[s, 0, a]
            for q in range(1, d):
                v += transform[s, q, a]
        gn += v * v
    return 1.0 / math.sqrt(gn)


@nb.njit(**JIT)
def hull_max(points, adj_start, adj, start, grad, shift):
    """max over the vertices v of a convex hull of ``grad[f] . points[v] + shift[f]``, per f.

    Climbs the hull's edge graph from ``start[f]`` to a neighbour with a larger value while
    there is one: on a convex polytope a vertex no edge improves is a maximum (the simplex
    method's argument), so the answer is the brute-force maximum over all vertices
    (`cfm_fem.models.mesh.face_excess`: tens of steps per face instead of every vertex).

    Parameters
    ----------
    points : ndarray, shape (h, d), mm
        The hull's vertices.
    adj_start, adj : ndarray, int64
        CSR lists of the hull's edges: the neighbours of vertex v are
        ``adj[adj_start[v]:adj_start[v + 1]]``.
    start : ndarray, shape (f,), int64
        Vertex to climb from (one near the maximum saves steps).
    grad : ndarray, shape (f, d); shift : ndarray, shape (f,)

    Returns
    -------
    ndarray, shape (f,)
    """
    nf, d = grad.shape
    out = np.empty(nf)
    for f in range(nf):
        v = start[f]
        best = shift[f]
        for a in range(d):
            best += grad[f, a] * points[v, a]
        while True:
            nxt = -1
            for i in range(adj_start[v], adj_start[v + 1]):
                w = adj[i]
                val = shift[f]
                for a in range(d):
                    val += grad[f, a] * points[w, a]
                if val > best:
                    best = val
                    nxt = w
            if nxt < 0:
                break
            v = nxt
        out[f] = best
    return out


#: Largest star (cells incident to one node) handled by the star tables; larger stars (rare
#: in FEM meshes, about 24 tetrahedra is typical) take the global walk.
MAX_STAR = 256
