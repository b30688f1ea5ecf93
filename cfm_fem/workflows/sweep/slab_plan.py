"""Slabs of the out-of-core sweep: the partition, the halo and the certification of its cells.

See `cfm_fem.workflows.sweep.slabs` for the method (halo rule, certified cells, sentinel faces).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.spatial

from ...errors import CfmInputError
from ...io.slab_files import (
    BLOCK,
    Staged,
)
from ...models.field import DUPLICATE_TOL_MM
from ...models.mesh import (
    TIE_JITTER,
    circumspheres,
    convex_hull_points,
    delaunay_coords,
)

__all__ = [
    "SlabPlan",
    "plan_slabs",
    "extract_slab",
    "certify",
    "slab_search",
    "slabs_for_memory",
    "htm_reach_mm",
]


def htm_reach_mm(bench, trials: int, seed: int, lo, hi) -> float:
    """Largest probe position error of a mode-htm sweep near a map, mm (for the slab halo).

    The geometric part at the corners and the centre of the map's box (magnet frame) for every
    trial of the run, plus 1.5 times the largest of 4,000 draws of the vibration and delay.
    A trial that still reaches the halo border is detected and counted, so this only sizes
    the halo.
    """
    from ...models.kinematics.chain import probe_errors_for_bench
    from ...models.kinematics.geometry import draw_error_sets, point_noise

    lo, hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
    corners = np.array([[(lo, hi)[(k >> a) & 1][a] for a in range(3)] for k in range(8)])
    q = bench.axis_positions_for(np.vstack([corners, (lo + hi) / 2]))
    q = np.clip(q, 0.0, bench.strokes_mm)
    params = draw_error_sets(bench, trials, seed)
    geo = np.linalg.norm(probe_errors_for_bench(bench, params, q, 0.0), axis=-1).max()
    noise = np.stack([point_noise(bench, t, range(200), seed) for t in range(20)])
    return float(geo + 1.5 * np.linalg.norm(noise, axis=-1).max())


def slabs_for_memory(n_nodes: int, budget_bytes: float, n_up: int) -> int:
    """Number of slabs for a memory budget.

    Per node of a slab (with its halo) about 1,300 bytes for the map, the Delaunay mesh and the
    walk tables plus 250 bytes per U_p value of statistics and output arrays; about 350 MB of
    interpreter, numba and VTK.
    """
    fixed = 350e6
    per_node = 1300.0 + 250.0 * n_up
    room = budget_bytes - fixed
    if room <= per_node * 2000:
        return max(1, n_nodes // 2000)
    # 1.3: the halo adds nodes to each slab
    return max(1, math.ceil(1.3 * n_nodes * per_node / room))


@dataclass
class SlabPlan:
    """Geometry of the partition.

    Attributes
    ----------
    axis : int
        Slab axis (0, 1, 2 = x, y, z): the longest side of the bounding box.
    edges : ndarray, shape (K + 1,), mm
        Slab k owns nodes with edges[k] <= x_axis < edges[k + 1] (the last one includes its
        upper edge); edges[0] and edges[K] are the map's extremes.
    halo : float, mm
    """

    axis: int
    edges: np.ndarray
    halo: float

    @property
    def n_slabs(self) -> int:
        return len(self.edges) - 1

    def owner(self, x) -> np.ndarray:
        """Slab owning each coordinate ``x`` (along the axis), shape like x."""
        return np.clip(np.searchsorted(self.edges[1:-1], x, side="right"), 0, self.n_slabs - 1)


def plan_slabs(st: Staged, n_slabs: int, halo: float) -> SlabPlan:
    axis = int(np.argmax(st.hi - st.lo))
    lo, hi = st.lo[axis], st.hi[axis]
    nb = 64 * n_slabs
    edges_h = np.linspace(lo, hi, nb + 1)
    counts = np.zeros(nb, dtype=np.int64)
    for a in range(0, len(st.rows), BLOCK):
        x = st.rows[a : a + BLOCK, axis]
        counts += np.bincount(
            np.clip(np.searchsorted(edges_h, x, side="right") - 1, 0, nb - 1), minlength=nb
        )
        st.release(a, a + BLOCK)
    cum = np.cumsum(counts)
    targets = np.arange(1, n_slabs) * (cum[-1] / n_slabs)
    inner = edges_h[np.searchsorted(cum, targets) + 1]
    edges = np.unique(np.concatenate([[lo], inner, [hi]]))
    if len(edges) < 2:
        edges = np.array([lo, hi])
    return SlabPlan(axis, edges, halo)


def extract_slab(st: Staged, plan: SlabPlan, k: int, halo: float):
    """Rows of slab k and its halo: (staged row index (m,), own mask (m,)); memory O(m)."""
    a_lo = plan.edges[k] - halo
    a_hi = plan.edges[k + 1] + halo
    idx, own = [], []
    for a in range(0, len(st.rows), BLOCK):
        x = st.rows[a : a + BLOCK, plan.axis]
        sel = np.flatnonzero((x >= a_lo) & (x <= a_hi))
        idx.append(sel + a)
        own.append(plan.owner(x[sel]) == k)
        st.release(a, a + BLOCK)
    return np.concatenate(idx), np.concatenate(own)


def merge_duplicates(st: Staged, rows, file):
    """Rows to drop as duplicates among ``rows`` (staged indices, sorted), as `FieldMap` does.

    Returns the dropped row indices; raises `CfmInputError` for two nodes at one place with
    different fields.
    """
    pts = np.asarray(st.rows[rows, :3])
    order = np.lexsort(pts.T[::-1])
    sp = pts[order]
    same = np.all(np.abs(np.diff(sp, axis=0)) <= DUPLICATE_TOL_MM, axis=1)
    if not same.any():
        return np.empty(0, dtype=np.int64)
    rep = np.concatenate([[True], ~same])
    group = np.cumsum(rep) - 1
    first_of = np.empty(len(rows), dtype=np.int64)
    first_of[order] = order[np.flatnonzero(rep)[group]]
    dup = first_of != np.arange(len(rows))
    B = np.asarray(st.rows[rows, 3:])
    db = np.abs(B[dup] - B[first_of[dup]]).max(axis=1)
    conflict = np.flatnonzero(dup)[db > 1e-9 * max(st.b_abs_max, 1e-30)]
    if conflict.size:
        i = int(conflict[0])
        j = int(first_of[i])
        raise CfmInputError(
            f"duplicate node at {pts[i].tolist()} mm (also on line {int(st.lines[rows[j]])}) with "
            f"a different field {B[i].tolist()} T vs {B[j].tolist()} T; expected one field per "
            f"position",
            file=file,
            line=int(st.lines[rows[i]]),
        )
    return rows[dup]


def lattice_keys(points, span):
    return np.round(points / (span * 1e-9))


def _circum_ok(coords, simplices, boxes, spheres=False, pad=0.0):
    """Certified Delaunay cells: the circumsphere meets no part of the map's bounding box beyond
    the slab + halo (``boxes``, each widened by ``pad``, mm: the move of the nodes that
    Delaunay triangulates), so no node left out can lie in it.

    With ``spheres``, also return the circumcentres (m, 3) and squared radii (m,), mm.
    """
    c, r2 = circumspheres(coords, simplices)
    with np.errstate(invalid="ignore", over="ignore"):
        r2 = r2 * (1.0 + 1e-9)
    ok = np.isfinite(r2)
    for lo, hi in boxes:
        lo, hi = lo - pad, hi + pad
        d2 = (np.maximum(np.maximum(lo - c, c - hi), 0.0) ** 2).sum(-1)
        ok &= d2 >= r2
    return (ok, c, r2) if spheres else ok


def _empty_spheres(st: Staged, axis, a_lo, a_hi, centers, r2, span):
    """For circumspheres that reach beyond the slab + halo: True where no staged node outside
    a_lo..a_hi along ``axis`` lies in (or on) the sphere, so the cell is the whole map's too.
    The nodes are moved as Delaunay triangulates them (`delaunay_coords`, ``span``: the whole
    map's size, mm). One scan of the staged rows; hull slivers (huge spheres bulging out of the
    map) pass here."""
    hits = np.zeros(len(centers), dtype=np.int64)
    r = np.sqrt(r2)
    for a in range(0, len(st.rows), BLOCK):
        p = np.asarray(st.rows[a : a + BLOCK, :3])
        p = delaunay_coords(p[(p[:, axis] < a_lo) | (p[:, axis] > a_hi)], span)
        st.release(a, a + BLOCK)
        if len(p):
            tree = scipy.spatial.cKDTree(p)
            hits += np.asarray(tree.query_ball_point(centers, r, return_length=True))
    return hits == 0


def hull_face_ok(coords, simplices, s, j, boxes, tol):
    """Border faces (of cell s[i], opposite its vertex j[i]) provably on the map's own hull: no
    part of the bounding box beyond the slab + halo (``boxes``) is on their outer side.

    ``tol``: mm.
    """
    out = np.ones(len(s), dtype=bool)
    if not boxes or not len(s):
        return out
    d = coords.shape[1]
    cells = simplices[s]  # (f, d + 1)
    mask = np.ones_like(cells, dtype=bool)
    mask[np.arange(len(s)), j] = False
    fv = coords[cells[mask].reshape(len(s), d)]  # (f, 3, 3): the face's vertices
    opp = coords[cells[np.arange(len(s)), j]]
    nrm = np.cross(fv[:, 1] - fv[:, 0], fv[:, 2] - fv[:, 0])
    nrm[((opp - fv[:, 0]) * nrm).sum(-1) > 0] *= -1.0  # outward
    scale = np.linalg.norm(nrm, axis=1)
    for lo, hi in boxes:
        corners = np.array([[(lo, hi)[(c >> a) & 1][a] for a in range(3)] for c in range(8)])
        side = np.einsum("fck,fk->fc", corners[None] - fv[:, :1, :], nrm)
        out &= side.max(axis=1) <= tol * scale
    return out


def certify(st: Staged, plan, k, h, coords, simplices, boxes, span):
    """Cells of slab k + halo h (m,) that are provably cells of the whole map's Delaunay
    triangulation: by the box test (`_circum_ok`), and for cells away from the cut zone that it
    could not certify, against the nodes left out (`_empty_spheres`, one scan of the rows).

    ``coords``: the slab + halo's nodes as Delaunay triangulates them (`delaunay_coords` with
    the whole map's size ``span``): the moved nodes are in general position, so the whole map
    has the one Delaunay triangulation, whose cells these tests prove.
    """
    pad = TIE_JITTER * span  # a node moves less than this along each axis
    cert, cen, r2 = _circum_ok(coords, simplices, boxes, spheres=True, pad=pad)
    near = coords[simplices, plan.axis]
    inner = (near >= plan.edges[k] - h / 2) & (near <= plan.edges[k + 1] + h / 2)
    cand = np.flatnonzero(~cert & inner.any(axis=1))
    if len(cand):
        cert[cand] = _empty_spheres(
            st, plan.axis, plan.edges[k] - h, plan.edges[k + 1] + h, cen[cand], r2[cand], span
        )
    return cert


def settled(simplices, cert):
    """Nodes of a slab + halo's Delaunay mesh (n,) in no uncertified cell: their cells are the
    whole map's (nearly always: a node on a cut face is in an uncertified cell too, whose
    circumsphere reaches beyond the cut), and so is their Delaunay move, which `build_mesh`
    keeps when one of a node's cells is flat (co-spherical nodes). The sweep leaves the cells
    of the other nodes uncertified. Faces left by removed hull slivers that cannot be certified
    (a cylinder's mantle) are accepted as halo borders (`GONE_ROWS_FACTOR`), and the moves of
    their nodes with them."""
    settled = np.ones(simplices.max(initial=-1) + 1, dtype=bool)
    settled[simplices[~cert]] = False
    return settled


def at_cut(coords, simplices, s, j, axis, map_lo, map_hi, tol):
    """Border faces (of cell s[i], opposite its vertex j[i]) of a slab + halo's Kuhn grid that
    may be cuts: with a vertex on its first or last lattice plane along ``axis`` where the map
    goes on beyond. A Kuhn cell spans one lattice step, so the map's cell across any other
    border face would have all its nodes in slab + halo, and be there: the face is the map's
    own border (a notch, a gap of the grid), not a halo border. ``tol``: mm."""
    a = coords[:, axis]
    lo, hi = a.min(), a.max()
    keep = np.ones((len(s), simplices.shape[1]), dtype=bool)
    keep[np.arange(len(s)), j] = False
    fa = a[simplices[s][keep].reshape(len(s), -1)]
    cut = np.zeros(len(s), dtype=bool)
    if lo > map_lo + tol:
        cut |= (fa <= lo + tol).any(axis=1)
    if hi < map_hi - tol:
        cut |= (fa >= hi - tol).any(axis=1)
    return cut


def faces_of(simplices, s, j, cells):
    """Whether the face of simplices[s[i]] opposite its vertex j[i] is a face of one of
    ``cells`` (k, d + 1), as a bool array like ``s``."""
    out = np.zeros(len(s), dtype=bool)
    if not len(s) or not len(cells):
        return out
    dp1 = simplices.shape[1]
    keep = np.ones((len(s), dp1), dtype=bool)
    keep[np.arange(len(s)), j] = False
    border = np.sort(simplices[s][keep].reshape(len(s), dp1 - 1), axis=1)
    faces = np.sort(np.concatenate([np.delete(cells, c, axis=1) for c in range(dp1)]), axis=1)
    _, ids = np.unique(np.concatenate([border, faces]), axis=0, return_inverse=True)
    ids = ids.ravel()
    return np.isin(ids[: len(s)], ids[len(s) :])


def hull_points(st: Staged) -> np.ndarray:
    """Vertices of the convex hull of all staged nodes (k, 3), mm, block by block (the hull of
    a union is the hull of its parts' hull vertices)."""
    keep = np.empty((0, 3))
    for a in range(0, len(st.rows), BLOCK):
        p = np.concatenate([keep, np.asarray(st.rows[a : a + BLOCK, :3])])
        st.release(a, a + BLOCK)
        try:
            keep = convex_hull_points(p)
        except scipy.spatial.QhullError:  # a flat block (one plane of nodes): kept whole
            keep = p
    return convex_hull_points(keep)


def beyond_boxes(st: Staged, axis: int, a_lo: float, a_hi: float):
    """(lo, hi) corners of the parts of the bounding box beyond a_lo..a_hi along ``axis``."""
    boxes = []
    for lo_a, hi_a in ((st.lo[axis], a_lo), (a_hi, st.hi[axis])):
        if hi_a <= lo_a:
            continue
        lo, hi = st.lo.copy(), st.hi.copy()
        lo[axis], hi[axis] = lo_a, hi_a
        boxes.append((lo, hi))
    return boxes


def slab_search(search, cert):
    """The exact-search arrays (`cfm_fem.models.mesh.exact_search`) of a slab + halo mesh
    for its two passes, the sentinel cell (index m) and copies of the uncertified cells
    (m + 1 + i for ``unc[i]``) appended to the mesh arrays.

    The face excess is the slab mesh's own: a point beyond a border face by more than every
    node of slab + halo lies in none of its cells, which is what the search would find (a cut
    face, a supporting plane of slab + halo, thus proves its exits at once). Pass 1 (suspect
    faces lead to the sentinel) lists, in place of each uncertified cell, a copy of it whose
    field is the sentinel's NaN: a point the search finds there reaches beyond the certified
    region, as a walk through a suspect face does, and poisons its node. Pass 2 (suspect
    faces closed) lists the certified cells only: the rest of slab + halo is outside.

    Returns
    -------
    search_a, search_b : tuple or None
        Pass 1 and pass 2 arrays (None: convex slab mesh, nothing to search).
    unc : ndarray, shape (k,), int64
        Uncertified cells copied (empty when there is nothing to search).
    """
    if search is None or not search[0].shape[0]:
        return None, None, np.zeros(0, dtype=np.int64)
    excess, reach, box, dims, bstart, bcells = search
    m, dp1 = excess.shape
    unc = np.flatnonzero(~cert)
    excess = np.concatenate([excess, np.zeros((1 + len(unc), dp1), dtype=excess.dtype)])
    reach = np.concatenate([reach, [0.0]])  # the sentinel node
    remap = np.arange(m, dtype=bcells.dtype)
    remap[unc] = m + 1 + np.arange(len(unc))
    bucket = np.repeat(np.arange(len(bstart) - 1), np.diff(bstart))
    keep = cert[bcells]
    start_b = np.zeros_like(bstart)
    np.cumsum(np.bincount(bucket[keep], minlength=len(bstart) - 1), out=start_b[1:])
    return ((excess, reach, box, dims, bstart, remap[bcells]),
            (excess, reach, box, dims, start_b, bcells[keep]), unc)  # fmt: skip
