"""Star tables of a node: its cells in local barycentric form, walks and exits inside the star."""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from .locate import BARY_EPS, EXCESS_MARGIN, MAX_STAR, OUTSIDE, _bary_in
from .options import JIT
from .rng import GAMMA


@nb.njit(**JIT)
def _star_contains(simplices, s, node):
    for j in range(simplices.shape[1]):
        if simplices[s, j] == node:
            return True
    return False


#: `star_locate`: the displacement's ray leaves the mesh through a boundary face at the node.
LEAVES_MESH = -3


#: Slots of the open-addressing table that maps a cell to its index in the star (2 x MAX_STAR).
STAR_HASH = 2 * MAX_STAR


@nb.njit(inline="always", **JIT)
def _star_slot(htab, g, s, n):
    """Index of cell s in the star of g being built; inserts it as index n if absent (returns
    -1 - n then). ``htab`` (3, STAR_HASH) int64 rows: cell, index, owner node (a slot owned
    by another node is free; `build_star` clears the owners first, else a node built a second
    time would find its own entries of the first time)."""
    h = np.int64((np.uint64(s) * GAMMA) >> np.uint64(55)) & (STAR_HASH - 1)
    while htab[2, h] == g:
        if htab[0, h] == s:
            return htab[1, h]
        h = (h + 1) & (STAR_HASH - 1)
    htab[0, h] = s
    htab[1, h] = n
    htab[2, h] = g
    return -1 - n


@nb.njit(**JIT)
def build_star(g, c0, simplices, transform, neighbors, values, cells, lmat, dmat, nbr, htab):
    """Tables of the star of node ``g``: the cells incident to it, reached from ``c0`` across
    faces that contain ``g``.

    A point ``x_g + delta`` lies in star cell i when the barycentric coordinates of the cell's
    other vertices, ``lam = lmat[i] @ delta``, are >= 0 and ``1 - sum(lam) >= 0`` (that of g);
    the field there is ``B_g + dmat[i] @ lam``. Working with the small displacement instead of
    the absolute position avoids cancelling map coordinates of ~100 mm against U_p ~ 1e-2 mm.

    Parameters
    ----------
    g, c0 : int
        Node and a cell incident to it.
    simplices, transform, neighbors : `SimplexMesh` arrays (d + 1 vertices per cell)
    values : ndarray, shape (n, 3), T
    cells : ndarray, shape (MAX_STAR,), int64
        Output: global index of each star cell.
    lmat : ndarray, shape (MAX_STAR, d, d), 1/mm
        Output: row a maps delta to the barycentric coordinate of the a-th vertex other than g.
    dmat : ndarray, shape (MAX_STAR, 3, d), T
        Output: column a is B of that vertex minus B_g.
    nbr : ndarray, shape (MAX_STAR, d), int64
        Output: star index of the cell across the face opposite that vertex (the face contains
        g); -1 across the mesh boundary.
    htab : ndarray, shape (3, STAR_HASH), int64
        Work space (see `_star_slot`); its owner row is cleared here.

    Returns
    -------
    int
        Number of star cells; -1 if ``c0`` does not contain ``g``, the star exceeds MAX_STAR or
        a face with g leads to a cell without it.
    """
    d = transform.shape[2]
    if c0 < 0 or not _star_contains(simplices, c0, g):
        return -1
    htab[2, :] = -1  # 512 stores: a star built before for g (a node listed twice) is gone
    cells[0] = c0
    _star_slot(htab, g, c0, 0)
    n = 1
    i = 0
    while i < n:  # breadth-first across the faces that contain g, filling the tables
        s = cells[i]
        a = 0
        for j in range(d + 1):
            v = simplices[s, j]
            if v == g:
                continue
            ns = neighbors[s, j]
            if ns < 0:
                nbr[i, a] = -1
            else:
                k = _star_slot(htab, g, ns, n)
                if k < 0:
                    # too large; or a cell without g across a face with g: not a conforming
                    # star (the sentinel cell a slab's halo border leads to,
                    # `cfm_fem.workflows.sweep.slabs`)
                    if n == cells.shape[0] or not _star_contains(simplices, ns, g):
                        return -1
                    cells[n] = ns
                    k = n
                    n += 1
                nbr[i, a] = k
            for b in range(d):
                if j < d:
                    lmat[i, a, b] = transform[s, j, b]
                else:  # the last coordinate is 1 - the others
                    acc = 0.0
                    for m in range(d):
                        acc += transform[s, m, b]
                    lmat[i, a, b] = -acc
            for c in range(3):
                dmat[i, c, a] = values[v, c] - values[g, c]
            a += 1
        i += 1
    return n


@nb.njit(inline="always", **JIT)
def star_locate(start, lmat, nbr, n_star, delta, lam):
    """Star cell containing ``x_g + delta`` by walking across faces that contain g.

    Returns the star index (``lam`` then holds the barycentric coordinates of the cell's
    vertices other than g); LEAVES_MESH if the walk crosses a boundary face of the mesh (such a
    face contains g, so every displacement along the same ray, whatever U_p, leaves the mesh
    there too); -1 if the point is beyond the star (past a face opposite g) or the walk does not
    settle.
    """
    d = lmat.shape[2]
    s = start
    for _ in range(n_star + 4):
        lmin = np.inf
        amin = 0
        tot = 0.0
        for a in range(d):
            v = 0.0
            for b in range(d):
                v += lmat[s, a, b] * delta[b]
            lam[a] = v
            tot += v
            if v < lmin:
                lmin = v
                amin = a
        if lmin >= -BARY_EPS:
            return s if 1.0 - tot >= -BARY_EPS else -1
        s = nbr[s, amin]
        if s < 0:
            return LEAVES_MESH
    return -1


@nb.njit(inline="always", **JIT)
def star_locate3(start, lmat, nbr, n_star, d0, d1, d2):
    """`star_locate` written out for d = 3 (the hot loop of 3-D maps).

    Returns (cell or code as `star_locate`, lam0, lam1, lam2): values, not an output array,
    and the face to cross chosen by selects, so the only unpredictable branch is the exit.
    """
    s = start
    for _ in range(n_star + 4):
        l0 = lmat[s, 0, 0] * d0 + lmat[s, 0, 1] * d1 + lmat[s, 0, 2] * d2
        l1 = lmat[s, 1, 0] * d0 + lmat[s, 1, 1] * d1 + lmat[s, 1, 2] * d2
        l2 = lmat[s, 2, 0] * d0 + lmat[s, 2, 1] * d1 + lmat[s, 2, 2] * d2
        m01 = min(l0, l1)
        if min(m01, l2) >= -BARY_EPS:
            return (s if 1.0 - (l0 + l1 + l2) >= -BARY_EPS else -1), l0, l1, l2
        a = 2 if l2 < m01 else (1 if l1 < l0 else 0)  # the most negative (first on ties)
        s = nbr[s, a]
        if s < 0:
            return LEAVES_MESH, l0, l1, l2
    return -1, 0.0, 0.0, 0.0


@nb.njit(inline="always", **JIT)
def _star_bary(lmat, i, delta, lam):
    """``lam[:d] = lmat[i] @ delta``: in star cell i, the barycentric coordinates of its
    vertices other than g at ``x_g + delta``; returns their sum and their minimum."""
    d = lmat.shape[2]
    tot = 0.0
    lmin = np.inf
    for a in range(d):
        v = 0.0
        for b in range(d):
            v += lmat[i, a, b] * delta[b]
        lam[a] = v
        tot += v
        lmin = min(lmin, v)
    return tot, lmin


@nb.njit(**JIT)
def star_exact(g, cells, n_star, simplices, excess):
    """Whether LEAVES_MESH is a proven verdict at node g: every border face of its star (they
    all contain g) is a supporting plane of the whole mesh (zero `face_excess`).

    A displacement beyond such a face's plane leaves the mesh at every U_p. Behind a face
    with an excess (a re-entrant edge or corner at g, a notch facing it, a face left by
    removed hull slivers), the point may lie in another star cell or in a cell further away:
    `star_recheck` places those trials.

    Parameters
    ----------
    g : int
    cells : ndarray, shape (>= n_star,), int64
        The star's cells (`build_star`).
    simplices : ndarray, shape (m, d + 1), int64
    excess : ndarray, shape (m, d + 1) or (0, d + 1)
        Empty for a convex mesh (every verdict proven; nothing is read).
    """
    if excess.shape[0] == 0:
        return True
    for i in range(n_star):
        s = cells[i]
        for j in range(simplices.shape[1]):
            if simplices[s, j] != g and excess[s, j] > 0.0:
                return False
    return True


@nb.njit(**JIT)
def star_find(p, g, coords, transform, cells, n_star, lmat, delta, bary):
    """The cell of the star of g that holds ``p``, testing them all, or OUTSIDE.

    Exact for a point nearer to g than any other cell (`node_reach`): it is then in a star
    cell or outside the mesh.

    Parameters
    ----------
    p : ndarray, shape (d,), mm
    g : int
    coords, transform : mesh arrays
    cells, n_star, lmat : star tables (`build_star`)
    delta : ndarray, shape (d,)
        Work space.
    bary : ndarray, shape (d + 1,)
        Output: barycentric coordinates in the cell found (as `locate` computes them).

    Returns
    -------
    int
        The cell (mesh index), or OUTSIDE.
    """
    d = lmat.shape[2]
    for a in range(d):
        delta[a] = p[a] - coords[g, a]
    for i in range(n_star):
        tot, lmin = _star_bary(lmat, i, delta, bary)  # bary: scratch until the cell is found
        if lmin >= -BARY_EPS and 1.0 - tot >= -BARY_EPS:
            _bary_in(p, cells[i], transform, bary)
            return cells[i]
    return OUTSIDE


@nb.njit(**JIT)
def star_behind(g, coords, cells, n_star, lmat, nbr, simplices, cand, free):
    """The star cells of g that reach beyond the plane of a border face of the star (such a
    face contains g): those with a vertex strictly beyond it; and the border faces no star
    cell reaches beyond.

    A displacement the star walk finds beyond a border face's plane (LEAVES_MESH) can lie only
    in the cone of one of the cells; none (a star convex at g): in no star cell. Beyond the
    plane of a free face, it is in no star cell either (every star cell lies on its inner
    side): on a faceted curved surface, where few stars are convex at g, most exits are proven
    so, at the cost of one face test (`star_exit`).

    Parameters
    ----------
    g : int
    coords : ndarray, shape (n, d), mm
    cells, n_star, lmat, nbr : star tables (`build_star`)
    simplices : ndarray, shape (m, d + 1), int64
    cand : ndarray, shape (>= n_star,), int64
        Output: star indices of those cells.
    free : ndarray, shape (2, >= n_star * d), int64
        Output: the free border faces, as columns (i, a): star cell i, face opposite its a-th
        vertex other than g (see `build_star`).

    Returns
    -------
    n_cand, n_free : int
        How many of each.
    """
    d = lmat.shape[2]
    hit = np.zeros(n_star, dtype=np.bool_)
    n_free = 0
    for i in range(n_star):
        for a in range(d):
            if nbr[i, a] >= 0:
                continue
            face_free = True
            for i2 in range(n_star):
                s = cells[i2]
                for j in range(simplices.shape[1]):
                    v = simplices[s, j]
                    lam = 0.0
                    for b in range(d):
                        lam += lmat[i, a, b] * (coords[v, b] - coords[g, b])
                    if lam < -1e-12:  # beyond the plane (rounding: ~1e-16)
                        hit[i2] = True
                        face_free = False
            free[0, n_free] = i
            free[1, n_free] = a
            n_free += face_free
    n_cand = 0
    for i2 in range(n_star):
        cand[n_cand] = i2
        n_cand += hit[i2]
    return n_cand, n_free


#: `star_exit`: the point is not nearer to g than every other cell; `star_recheck` places it.
BEYOND_REACH = -4


@nb.njit(inline="always", **JIT)
def star_exit(lmat, reach, cand, n_cand, free, n_free, delta, lam):
    """Place ``x_g + delta`` whose star walk crossed a border face (LEAVES_MESH), at a node
    where that proves nothing (`star_exact` False).

    Nearer to g than any other cell (``|delta| < reach``, `node_reach`), the point is in a
    star cell or outside: beyond the plane of a free face it is outside; else only the cells of
    `star_behind` can hold it. Farther, the caller tests every star cell (`star_recheck`; not
    called from here: a call that may happen makes numba count references to its array
    arguments on every call, ~100 ns).

    Parameters
    ----------
    lmat : star table (`build_star`)
    reach : float, mm
        `node_reach` of g.
    cand, n_cand, free, n_free : `star_behind` of g
    delta : ndarray, shape (d,), mm
    lam : ndarray, shape (d,)
        Output: barycentric coordinates in the star cell found.

    Returns
    -------
    cell : int
        Star index of the cell holding the point; LEAVES_MESH: outside at every fraction
        r <= 1 of ``delta``; -1: the global walk; BEYOND_REACH: `star_recheck`, with
    r_in, r_out : float
        ``x_g + r delta`` proven outside for r < r_in and r > r_out.
    """
    d = lmat.shape[2]
    n2 = 0.0
    for a in range(d):
        n2 += delta[a] * delta[a]
    if n2 >= reach * reach:
        return BEYOND_REACH, 0.0, np.inf
    for f in range(n_free):  # beyond a plane through g that every star cell stays behind
        i = free[0, f]
        a = free[1, f]
        v = 0.0
        for b in range(d):
            v += lmat[i, a, b] * delta[b]
        if v < -BARY_EPS:
            return LEAVES_MESH, 0.0, np.inf
    cone = False
    for c in range(n_cand):
        i = cand[c]
        tot = 0.0
        in_cone = True
        for a in range(d):
            v = 0.0
            for b in range(d):
                v += lmat[i, a, b] * delta[b]
            if v < -BARY_EPS:  # not in this cell's cone: the other rows are not needed
                in_cone = False
                break
            lam[a] = v
            tot += v
        if in_cone:
            if 1.0 - tot >= -BARY_EPS:
                return i, 0.0, np.inf
            cone = True  # inside for small r, beyond the cell at r = 1: the global walk
    return (-1 if cone else LEAVES_MESH), 0.0, np.inf


@nb.njit(**JIT)
def star_recheck(g, cells, n_star, lmat, nbr, simplices, excess, reach, delta, lam):
    """Place ``x_g + delta`` whose star walk crossed a border face, at a node where that is no
    proof of leaving the mesh (`star_exact` False).

    Every star cell is tested. Else the point is beyond the star, and ``x_g + r delta`` is
    proven outside for the fractions r where it either lies beyond a border face of the star
    by more than every node of the mesh (``-r lam_a > excess``), or, if ``delta`` is in no star
    cell's cone, is nearer to g than any other cell (``r |delta| < reach``, `node_reach`).

    Parameters
    ----------
    g : int
    cells, n_star, lmat, nbr : star tables (`build_star`)
    simplices : ndarray, shape (m, d + 1), int64
    excess : ndarray, shape (m, d + 1)
        `face_excess` in heights of the cell above the face.
    reach : float, mm
        `node_reach` of g.
    delta : ndarray, shape (d,), mm
    lam : ndarray, shape (d,)
        Output: barycentric coordinates in the star cell found.

    Returns
    -------
    cell : int
        Star index of the cell holding the point, or -1 (beyond the star).
    r_in, r_out : float
        With cell -1: the point ``x_g + r delta`` is outside the mesh for every r < r_in and
        every r > r_out (0 and inf where nothing proves it).
    """
    d = lmat.shape[2]
    r_out = np.inf
    cone = False  # delta in some star cell's cone: x_g + r delta is inside for small r
    norm = 0.0
    for a in range(d):
        norm += delta[a] * delta[a]
    for i in range(n_star):
        tot, lmin = _star_bary(lmat, i, delta, lam)
        if lmin >= -BARY_EPS:
            if 1.0 - tot >= -BARY_EPS:
                return i, 0.0, np.inf
            cone = True
        s = cells[i]
        a = 0
        for j in range(d + 1):
            if simplices[s, j] == g:
                continue
            if nbr[i, a] < 0 and lam[a] < -BARY_EPS:  # beyond this border face's plane
                r_out = min(r_out, (excess[s, j] * (1.0 + EXCESS_MARGIN) + BARY_EPS) / -lam[a])
            a += 1
    r_in = 0.0 if cone else reach / math.sqrt(norm)
    return -1, r_in, r_out


#: Levels per axis of an octahedral direction bin (`direction_bin`).
BIN_LEVELS = 4


def n_direction_bins(d: int) -> int:
    """Number of `direction_bin` values in d dimensions (128 in 3-D, 16 in 2-D)."""
    return (1 << d) * BIN_LEVELS ** (d - 1)


@nb.njit(inline="always", **JIT)
def direction_bin(delta, d):
    """Octahedral bin of a displacement direction: its sign pattern and, for each axis but the
    last, the share |delta_a| / sum_b |delta_b| in BIN_LEVELS equal steps.

    The bins are cells of a square grid on the faces of the octahedron |x| + |y| + |z| = 1, so
    every bin is a convex cone of directions. A walk started from the star cell of the bin's
    centre direction (`star_bin_starts`) ends after at most one step for ~94 % of the
    displacements of a typical 3-D Delaunay star (~27 cells). Planar maps start their star
    walks so; 3-D maps test every star cell instead (`star_errors3`).
    """
    tot = 0.0
    b = 0
    for a in range(d):
        tot += abs(delta[a])
        b = 2 * b + (1 if delta[a] < 0.0 else 0)
    inv = BIN_LEVELS / tot if tot > 0.0 else 0.0
    for a in range(d - 1):
        b = BIN_LEVELS * b + min(np.int64(abs(delta[a]) * inv), BIN_LEVELS - 1)
    return b


@nb.njit(**JIT)
def _bin_centre(b, d, scale, delta):
    """A direction inside bin b (inverse of `direction_bin`) of 1-norm ``scale``; False for the
    bins that no direction reaches (level sum >= BIN_LEVELS)."""
    rest = b
    lsum = 0
    for a in range(d - 2, -1, -1):  # the last level is the lowest digit
        delta[a] = rest % BIN_LEVELS
        lsum += rest % BIN_LEVELS
        rest //= BIN_LEVELS
    if lsum >= BIN_LEVELS:
        return False
    # the square's centre, or the centroid of its feasible corner where the face's edge cuts it
    off = 0.5 if lsum + 0.5 * (d - 1) < BIN_LEVELS else 1.0 / d
    tot = 0.0
    for a in range(d - 1):
        delta[a] = (delta[a] + off) / BIN_LEVELS
        tot += delta[a]
    delta[d - 1] = 1.0 - tot
    for a in range(d - 1, -1, -1):
        delta[a] *= -scale if rest & 1 else scale
        rest >>= 1
    return True


@nb.njit(**JIT)
def star_bin_starts(lmat, nbr, n_star, d, scale, out):
    """Start cell of every `direction_bin`: the star cell of the bin's centre direction. Each
    walk starts where the previous bin's ended (neighbouring bins, short walks)."""
    delta = np.empty(d)
    lam = np.empty(d)
    s = 0
    for b in range(out.shape[0]):
        if _bin_centre(b, d, scale, delta):
            r = star_locate(s, lmat, nbr, n_star, delta, lam)
            if r >= 0:
                s = r
        out[b] = s
