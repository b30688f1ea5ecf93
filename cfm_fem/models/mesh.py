"""Simplicial mesh of a `FieldMap` that can be walked, and its exact-search tables.

Three ways to get the simplices, chosen by :func:`build_mesh` and always stated in the outputs:

- ``native``: the export's own linear tetrahedra (or triangles); the interpolant follows the FEM
  domain, gaps between poles stay gaps.
- ``grid``: nodes on a full rectilinear grid get the Kuhn triangulation (6 tetrahedra per voxel,
  2 triangles per square), which is conforming and free of the degenerate simplices Qhull makes on
  co-spherical grid points.
- ``delaunay``: scattered nodes get ``scipy.spatial.Delaunay``; it fills the convex hull, so it
  bridges non-convex gaps (between poles) that the FEM domain does not contain. Its hull is lined
  with flat cells spanning nodes far apart on the surface (their circumspheres bulge out of the
  hull); their interpolant has gradients far off the field's. ``hull_slivers="remove"`` takes
  them out (`hull_sliver_cells`), and the map then ends at the nodes' own surface.

Planar maps (all nodes in one plane) are triangulated in that plane; out-of-plane displacements
of the probe are then not covered, and the outputs say so.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field, replace

import numpy as np
from threadpoolctl import threadpool_limits

from .. import _kernels
from ..errors import CfmInputError
from .field import FieldMap

__all__ = ["SimplexMesh", "build_mesh", "exact_search", "no_search", "morton_order"]

#: Relative singular value below which a point set is treated as planar (or collinear).
FLAT_TOL = 1e-9
#: A Delaunay cell is a hull sliver when its circumradius exceeds this many times its shortest
#: edge and its circumcentre lies outside the convex hull of the nodes (`hull_sliver_cells`).
SLIVER_RATIO = 5.0
#: Delaunay triangulates the nodes moved by `node_jitter` times this fraction of the map's size
#: (`delaunay_coords`), always: co-spherical nodes then have one triangulation, the same in any
#: part of the map. Small against any node spacing, large enough that Qhull resolves the cells
#: it makes of collinear nodes on the hull's edges (their volume grows with its square: 1e-9
#: left some at 1e-17 of the mean cell volume on a grid). Only the nodes of cells that are
#: flat on the nodes themselves keep the move (`build_mesh`).
TIE_JITTER = 1e-6
#: What `build_mesh` does with the flat cells of a Delaunay hull.
HULL_SLIVERS = ("keep", "remove")


@dataclass
class SimplexMesh:
    """Simplices with neighbours and barycentric transforms, in local coordinates.

    Attributes
    ----------
    dim : int
        2 (planar map) or 3.
    coords : ndarray, shape (n, dim), mm
        Node coordinates in the mesh's own frame: the map frame for 3-D, in-plane coordinates
        ``(p - origin) @ basis`` for a planar map.
    simplices : ndarray, shape (m, dim + 1), int64
    neighbors : ndarray, shape (m, dim + 1), int64
        ``neighbors[s, j]`` is the simplex across the face opposite vertex ``j``; -1 on the border.
    transform : ndarray, shape (m, dim + 1, dim), float64
        scipy's layout: barycentric ``c[:dim] = T[:dim] @ (p - T[dim])``, ``c[dim] = 1 - sum``.
    node_cell : ndarray, shape (n,), int64
        One simplex incident to each node (-1 for nodes in no simplex).
    origin : ndarray, shape (3,), mm
    basis : ndarray, shape (3, dim)
        Orthonormal columns spanning the mesh frame (identity for 3-D).
    kind : str
        ``"native"``, ``"grid"`` or ``"delaunay"``.
    notes : list of str
    hull_slivers : ndarray, shape (k, dim + 1), int64, or None
        Delaunay cells removed as hull slivers (`hull_sliver_cells`), as node indices (empty
        when none were; None for a mesh not made by `build_mesh`).
    tie_nodes : ndarray, shape (n,), bool, or None
        Delaunay only: the nodes of cells that are flat on the nodes themselves (co-spherical
        nodes, a tie of the triangulation); ``coords`` holds them moved (`delaunay_coords`).
        Kept hull slivers that are flat on the nodes move none: their transform alone is that
        of the moved nodes. None for other meshes.
    """

    dim: int
    coords: np.ndarray
    simplices: np.ndarray
    neighbors: np.ndarray
    transform: np.ndarray
    node_cell: np.ndarray
    origin: np.ndarray
    basis: np.ndarray
    kind: str
    notes: list[str] = field(default_factory=list)
    hull_slivers: np.ndarray | None = None
    tie_nodes: np.ndarray | None = None
    _stars: tuple | None = field(default=None, repr=False, compare=False)

    def node_stars(self) -> tuple:
        """The cells around each node, as `cfm_fem._kernels.node_cells` returns them (start
        offsets (n + 1,) and cell indices): made on first use, then kept (4 bytes per cell
        vertex, 92 MB for a 5.8-million-cell map)."""
        if self._stars is None:
            self._stars = _kernels.node_cells(self.simplices, len(self.coords))
        return self._stars

    @property
    def description(self) -> str:
        what = {
            "native": "linear interpolation in the export's own cells",
            "grid": "linear interpolation on the Kuhn triangulation of the structured grid",
            "delaunay": "linear interpolation on the Delaunay triangulation (scipy/Qhull) of the "
            "nodes; it fills the convex hull and bridges gaps the FEM domain may not contain",
        }[self.kind]
        if self.hull_slivers is not None and len(self.hull_slivers):
            what = what.replace("it fills the convex hull and", "its hull's flat cells removed; it")
        plane = (
            " in the plane of the map (out-of-plane displacement not covered)"
            if self.dim == 2
            else ""
        )
        return f"{what}{plane}; {len(self.simplices)} simplices"

    def for_output(self) -> SimplexMesh:
        """The same mesh without what only point location needs (barycentric transforms, face
        neighbours, node stars: 128 bytes per tetrahedron, 0.74 GB for 5.8 million cells): what
        writing the maps needs, once the sweep is done. It cannot run another sweep."""
        d = self.dim
        return replace(
            self,
            transform=np.empty((0, d + 1, d)),
            neighbors=np.empty((0, d + 1), dtype=np.int64),
            _stars=None,
        )

    def to_local(self, points) -> np.ndarray:
        """Map-frame points (k, 3) mm to mesh-frame coordinates (k, dim)."""
        return (np.asarray(points, dtype=np.float64) - self.origin) @ self.basis

    def cells_3d(self) -> np.ndarray:
        """Simplices for VTK output, shape (m, dim + 1)."""
        return self.simplices


def _frame(points, source):
    """Origin, orthonormal basis (3, dim) and dim of the affine hull of ``points``."""
    n = len(points)
    if n < 3:
        raise CfmInputError(
            f"the map has {n} node(s); expected at least 4 non-coplanar nodes (or 3 in a plane)",
            file=source,
        )
    origin = points.mean(axis=0)
    _, s, vt = np.linalg.svd(points - origin, full_matrices=False)
    if s[0] == 0 or s[1] <= FLAT_TOL * s[0]:
        raise CfmInputError(
            "all nodes lie on one line (collinear); expected a 3-D volume or a plane of nodes",
            file=source,
        )
    if s[2] <= FLAT_TOL * s[0]:
        basis = vt[:2].T.copy()
        # Prefer the map's own axes when the plane is a coordinate plane (readable outputs).
        for drop in range(3):
            e = np.delete(np.eye(3), drop, axis=1)
            if np.allclose(np.abs(np.linalg.det(np.c_[e, vt[2]])), 1.0, atol=1e-12):
                basis = e
                break
        return origin, basis, 2
    return np.zeros(3), np.eye(3), 3


def _lattice(coords):
    """Lattice shape and node index per lattice point if the nodes sit on a rectilinear lattice.

    The lattice may be incomplete (measured grids with placeholder rows removed); it is accepted
    when it has at most 4 times as many points as there are nodes.

    Returns
    -------
    (shape, order) or None
        ``order[flat lattice index]`` is the node index, -1 where the lattice has no node.
    """
    n, d = coords.shape
    span = np.ptp(coords, axis=0).max()
    axes, index = [], []
    for k in range(d):
        key = np.round(coords[:, k] / (span * 1e-9))
        vals = np.unique(key)
        if len(vals) < 2:
            return None
        axes.append(vals)
        index.append(np.searchsorted(vals, key))
    shape = tuple(len(a) for a in axes)
    if np.prod(shape, dtype=np.float64) > 4.0 * n:
        return None
    flat = np.ravel_multi_index(index, shape)
    if len(np.unique(flat)) != n:
        return None
    order = np.full(int(np.prod(shape)), -1, dtype=np.int64)
    order[flat] = np.arange(n)
    return shape, order


def kuhn_simplices(shape, order) -> np.ndarray:
    """Kuhn (Freudenthal) triangulation of a grid: d! simplices per cell, conforming.

    Parameters
    ----------
    shape : tuple of int
        Number of grid values per axis (2 or 3 axes).
    order : ndarray, shape (prod(shape),)
        Node index of each grid point in C order, -1 where a node is missing; simplices touching
        a missing node are left out (the map has no field there).
    """
    d = len(shape)
    base = np.stack(
        np.meshgrid(*[np.arange(s - 1) for s in shape], indexing="ij"), axis=-1
    ).reshape(-1, d)
    out = []
    for perm in itertools.permutations(range(d)):
        corners = [base.copy()]
        cur = base.copy()
        for axis in perm:
            cur = cur.copy()
            cur[:, axis] += 1
            corners.append(cur)
        idx = np.stack([order[np.ravel_multi_index(c.T, shape)] for c in corners], axis=1)
        out.append(idx[(idx >= 0).all(axis=1)])
    return np.concatenate(out).astype(np.int64)


def _sorted_columns(a: np.ndarray) -> np.ndarray:
    """``np.sort(a, axis=1)`` for a (m, 2) or (m, 3) array, by a network of element-wise
    minima and maxima (a face's few node indices: numpy's row sort costs a call per row)."""
    if a.shape[1] == 2:
        return np.stack([np.minimum(a[:, 0], a[:, 1]), np.maximum(a[:, 0], a[:, 1])], axis=1)
    if a.shape[1] != 3:
        return np.sort(a, axis=1)
    lo, hi = np.minimum(a[:, 0], a[:, 1]), np.maximum(a[:, 0], a[:, 1])
    mid, top = np.minimum(hi, a[:, 2]), np.maximum(hi, a[:, 2])
    return np.stack([np.minimum(lo, mid), np.maximum(lo, mid), top], axis=1)


def face_neighbors(simplices, source="<mesh>") -> np.ndarray:
    """Neighbour across each face of each simplex (-1 on the border), by matching sorted faces.

    Raises
    ------
    CfmInputError
        If a face is shared by more than two simplices (non-manifold mesh).
    """
    m, k = simplices.shape
    faces = np.stack([_sorted_columns(np.delete(simplices, j, axis=1)) for j in range(k)], axis=1)
    faces = faces.reshape(-1, k - 1)
    n_bits = max(int(simplices.max()).bit_length(), 1)
    if n_bits * (k - 1) <= 63:
        key = np.zeros(len(faces), dtype=np.int64)
        for j in range(k - 1):
            key = (key << n_bits) | faces[:, j]
        order = np.argsort(key)  # a face's key is held by at most two cells: any order pairs them
        sorted_key = key[order]
        same = sorted_key[1:] == sorted_key[:-1]
    else:
        order = np.lexsort(faces.T[::-1])
        fs = faces[order]
        same = np.all(fs[1:] == fs[:-1], axis=1)
    if np.any(same[1:] & same[:-1]):
        raise CfmInputError(
            "a face is shared by more than two cells (non-manifold mesh); expected a conforming "
            "mesh of linear cells",
            file=source,
        )
    a = order[:-1][same]
    b = order[1:][same]
    nb = np.full(m * k, -1, dtype=np.int64)
    nb[a] = b // k
    nb[b] = a // k
    return nb.reshape(m, k)


def _inverse_and_det(A: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Inverses (m, d, d) and determinants (m,) of small matrices A (m, d, d), d = 2 or 3.

    The inverse is the adjugate over the determinant: a few vector operations over all m at
    once, where LAPACK's inverse factors each matrix on its own. The determinant is LAPACK's
    (exactly 0 for a simplex with a repeated node, where the adjugate's triple product keeps
    a rounding error): rows of a matrix with det 0 are NaN."""
    d = A.shape[1]
    if d == 3:
        a0, a1, a2 = A[:, :, 0], A[:, :, 1], A[:, :, 2]  # columns
        adj = np.stack([np.cross(a1, a2), np.cross(a2, a0), np.cross(a0, a1)], axis=1)
    else:
        adj = np.empty_like(A)
        adj[:, 0, 0], adj[:, 1, 1] = A[:, 1, 1], A[:, 0, 0]
        adj[:, 0, 1], adj[:, 1, 0] = -A[:, 0, 1], -A[:, 1, 0]
    with threadpool_limits(limits=1, user_api="blas"):  # small matrices: idle threads spin
        det = np.linalg.det(A)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = adj / det[:, None, None]
    inv[det == 0] = np.nan
    return inv, det


def barycentric_transforms(coords, simplices):
    """scipy-layout barycentric transforms and signed measures (volume or area) of simplices.

    Parameters
    ----------
    coords : ndarray, shape (n, d)
        Node coordinates, d = 2 or 3.
    simplices : ndarray, shape (m, d + 1)
        Node indices of each simplex.

    Returns
    -------
    T : ndarray, shape (m, d + 1, d)
        ``T[:, :d]`` maps ``p - T[:, d]`` to the first d barycentric coordinates (NaN for a
        flat simplex), ``T[:, d]`` the last vertex.
    measure : ndarray, shape (m,)
        Signed volume (area in 2-D), in the units of ``coords`` cubed (squared).
    """
    d = coords.shape[1]
    v = coords[simplices]  # (m, d+1, d)
    r = v[:, d, :]
    A = np.swapaxes(v[:, :d, :] - r[:, None, :], 1, 2)  # columns v_j - v_d
    T = np.empty((len(simplices), d + 1, d))
    T[:, :d, :], det = _inverse_and_det(A)
    T[:, d, :] = r
    return T, det / (2.0 if d == 2 else 6.0)


@threadpool_limits.wrap(limits=1, user_api="blas")  # small matrices: idle BLAS threads spin
def _grid_simplices(coords, method: str, src, notes: list):
    """Kuhn simplices of nodes on a rectilinear grid (a note when grid points are missing), or
    None when the nodes are not on one (refused for ``method`` "grid")."""
    simplices = None
    lattice = _lattice(coords)
    if lattice is not None:
        simplices = kuhn_simplices(*lattice)
        missing = int((lattice[1] < 0).sum())
        if missing:
            notes.append(
                f"nodes on a rectilinear grid with {missing} grid point(s) missing: cells "
                "touching a missing point are left out, not bridged"
            )
        if len(simplices) == 0:
            simplices = None
    if simplices is None and method == "grid":
        raise CfmInputError(
            "--interpolation grid needs nodes on a rectilinear grid; use auto or delaunay",
            file=src,
        )
    return simplices


def build_mesh(
    fm: FieldMap,
    method: str = "auto",
    hull_slivers: str = "keep",
    hull_points=None,
    jitter_span: float | None = None,
) -> SimplexMesh:
    """Choose and build the simplicial mesh that interpolates ``fm``.

    Parameters
    ----------
    fm : FieldMap
    method : {"auto", "native", "grid", "delaunay"}
        ``auto`` takes the export's cells if it has them, a Kuhn triangulation for a full grid,
        and Delaunay otherwise.
    hull_slivers : {"keep", "remove"}
        Delaunay only: keep the flat cells of the convex hull, or remove them
        (`hull_sliver_cells`; said in the mesh's notes).
    hull_points : ndarray, shape (k, dim), optional
        Points whose convex hull is the whole map's (`hull_sliver_cells`); the out-of-core
        sweep triangulates a part of the map and passes the whole map's hull.
    jitter_span : float, optional
        Size of the whole map (mm) when ``fm`` is a part of it: the scale of the moves of the
        nodes that Delaunay triangulates (`delaunay_coords`), so a part moves them as the whole
        does.

    Raises
    ------
    CfmInputError
        Too few nodes, collinear nodes, degenerate or non-manifold native cells, or a method that
        does not apply to this map.
    """
    if method not in ("auto", "native", "grid", "delaunay"):
        raise CfmInputError(f"interpolation must be auto, native, grid or delaunay; got {method!r}")
    if hull_slivers not in HULL_SLIVERS:
        raise CfmInputError(f"hull slivers must be keep or remove; got {hull_slivers!r}")
    src = fm.source
    origin, basis, dim = _frame(fm.points, src)
    coords = (fm.points - origin) @ basis
    notes = []
    kind = method
    simplices = None
    slivers = np.zeros((0, dim + 1), dtype=np.int64)  # removed hull cells (Delaunay only)
    if method in ("auto", "native") and fm.cells is not None and fm.cells.shape[1] == dim + 1:
        simplices, kind = fm.cells, "native"
    elif method == "native":
        raise CfmInputError(
            f"--interpolation native needs {'triangles' if dim == 2 else 'tetrahedra'} in the "
            "export; this map has none",
            file=src,
        )
    if simplices is None and method in ("auto", "grid"):
        simplices = _grid_simplices(coords, method, src, notes)
        kind = "grid" if simplices is not None else kind
    tie = None  # Delaunay: the nodes of cells flat on the nodes, which keep their move
    lone = None  # Delaunay: kept hull slivers flat on the nodes, on their moved nodes alone
    if simplices is None:
        span = float(np.ptp(coords, axis=0).max()) if jitter_span is None else jitter_span
        simplices, kind, moved, flat, extra = _delaunay(coords, src, span)
        notes += extra
        # the moved nodes' cells are Delaunay: their circumspheres decide; the hull is the
        # nodes' own (as the out-of-core sweep's `hull_points`)
        sliver = hull_sliver_cells(moved, simplices, coords if hull_points is None else hull_points)
        if hull_slivers == "remove":
            slivers, simplices, flat = simplices[sliver], simplices[~sliver], flat[~sliver]
            lone = np.zeros(len(simplices), dtype=bool)
        else:  # kept hull slivers flat on the nodes (thin ones of scattered nodes, turned over
            # by the move) take the moved nodes' geometry alone: their nodes stay, and so does
            # the interpolant of every other cell
            lone = flat & sliver
        tie = np.zeros(len(coords), dtype=bool)
        tie[simplices[flat & ~lone]] = True
        if tie.any():  # a conforming mesh: every cell of such a node sees it moved
            coords = np.where(tie[:, None], moved, coords)
            _check_moved_cells(coords, moved, simplices, tie, src)
            notes.append(tie_note(int(tie.sum()), span))
        if hull_slivers == "remove":
            if len(slivers):
                notes.append(sliver_note(len(slivers)))
        elif sliver.any():
            notes.append(
                f"{int(sliver.sum())} flat cell(s) line the Delaunay hull (circumradius > "
                f"{SLIVER_RATIO:g} x shortest edge, centred outside the nodes' convex hull); "
                "kept: U_f and the GUM figure of nodes on the hull can be far off the field "
                "there (--hull-slivers remove, the sweep's default, takes them out)"
            )
    # cells along a Z-order curve: a node's star then sits in a few cache lines (the sweep
    # kernels are bound by memory latency, not arithmetic)
    centre = coords[simplices[:, 0]].copy()  # vertex by vertex: no (m, d + 1, d) temporary
    for j in range(1, simplices.shape[1]):
        centre += coords[simplices[:, j]]
    order = morton_order(centre)
    del centre
    simplices = simplices[order]
    T, measure = barycentric_transforms(coords, simplices)
    if lone is not None and lone.any():
        lone = lone[order]
        T[lone], measure[lone] = barycentric_transforms(moved, simplices[lone])
    scale = np.ptp(coords, axis=0).prod() / max(len(simplices), 1)
    flat = np.abs(measure) <= 1e-12 * scale
    if flat.any():
        if kind == "native":
            bad = np.flatnonzero(flat)
            s = int(bad[np.argmin(order[bad])])  # first in the export's own numbering
            first = int(order[s])
            raise CfmInputError(
                f"{int(flat.sum())} cell(s) of the export have zero volume (first: cell {first}, "
                f"nodes {simplices[s].tolist()}); expected non-degenerate linear cells",
                file=src,
            )
        raise AssertionError("degenerate simplices after triangulation")  # pragma: no cover
    neighbors = face_neighbors(simplices, src)
    node_cell = np.full(len(coords), -1, dtype=np.int64)
    for j in range(dim + 1):
        node_cell[simplices[:, j]] = np.arange(len(simplices))
    orphans = int((node_cell < 0).sum())
    if orphans:
        notes.append(f"{orphans} node(s) belong to no cell; they get no statistics (NaN)")
    return SimplexMesh(
        dim=dim,
        coords=np.ascontiguousarray(coords),
        simplices=np.ascontiguousarray(simplices, dtype=np.int64),
        neighbors=neighbors,
        transform=T,
        node_cell=node_cell,
        origin=origin,
        basis=basis,
        kind=kind,
        notes=notes,
        hull_slivers=slivers,
        tie_nodes=tie,
    )


#: Shift-and-mask steps that spread the low bits of a uint64 apart, per dimension (the
#: classic Morton "magic numbers"): five passes over the array instead of one per bit.
_SPREAD_STEPS = {
    2: ((16, 0x0000FFFF0000FFFF), (8, 0x00FF00FF00FF00FF), (4, 0x0F0F0F0F0F0F0F0F),
        (2, 0x3333333333333333), (1, 0x5555555555555555)),
    3: ((32, 0x001F00000000FFFF), (16, 0x001F0000FF0000FF), (8, 0x100F00F00F00F00F),
        (4, 0x10C30C30C30C30C3), (2, 0x1249249249249249)),
}  # fmt: skip


def _spread_bits(v: np.ndarray, dim: int) -> np.ndarray:
    """Insert dim - 1 zero bits between the bits of v (uint64, < 2**(64 // dim))."""
    if dim == 1:
        return v.copy()
    if dim in _SPREAD_STEPS:
        out = v.copy()
        for shift, mask in _SPREAD_STEPS[dim]:
            out |= out << np.uint64(shift)
            out &= np.uint64(mask)
        return out
    out = np.zeros_like(v)
    for b in range(64 // dim):
        out |= ((v >> np.uint64(b)) & np.uint64(1)) << np.uint64(dim * b)
    return out


def morton_order(points: np.ndarray) -> np.ndarray:
    """Permutation that sorts points along a Z-order (Morton) curve.

    Parameters
    ----------
    points : ndarray, shape (n, d)

    Returns
    -------
    ndarray, shape (n,), int64
        Indices in curve order (stable, so equal codes keep their input order).
    """
    n, dim = points.shape
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    bits = 64 // dim
    lo = points.min(axis=0)
    span = float(np.ptp(points, axis=0).max()) or 1.0
    q = np.floor((points - lo) / span * (2**bits - 1)).astype(np.uint64)
    code = np.zeros(n, dtype=np.uint64)
    for a in range(dim):
        code |= _spread_bits(q[:, a], dim) << np.uint64(a)
    return np.argsort(code, kind="stable")


@threadpool_limits.wrap(limits=1, user_api="blas")  # small matrices: idle BLAS threads spin
def circumspheres(coords, simplices):
    """Circumcentres (m, d) and squared circumradii (m,) of simplices (m, d + 1), in the units
    of ``coords`` (n, d); NaN or inf for a flat simplex."""
    v = coords[simplices]  # (m, d + 1, d)
    w = v[:, 1:] - v[:, :1]  # relative to a vertex: no round-off from the map's offset
    with np.errstate(all="ignore"):
        c = np.linalg.solve(2.0 * w, (w**2).sum(-1)[..., None])[..., 0]
        return v[:, 0] + c, (c**2).sum(-1)


def convex_hull_points(points) -> np.ndarray:
    """The vertices of the convex hull of ``points`` (n, d), as rows of ``points`` in their order.

    Raises
    ------
    scipy.spatial.QhullError
        For points that span fewer than d dimensions.
    """
    import scipy.spatial

    points = np.asarray(points, dtype=np.float64)
    return points[np.sort(scipy.spatial.ConvexHull(centred(points)).vertices)]


@threadpool_limits.wrap(limits=1, user_api="blas")  # scipy's find_simplex: 3x3 solves
def hull_sliver_cells(coords, simplices, hull_points=None, cells_per_block: int = 1 << 18):
    """Flat cells on the hull of a Delaunay triangulation.

    A Delaunay cell has an empty circumsphere, so one whose circumcentre lies outside the convex
    hull of the nodes is a cell at the hull; when its circumradius also exceeds `SLIVER_RATIO`
    times its shortest edge it is flat (a regular tetrahedron has 0.61, a flat cell spanning
    nodes on the surface tens to thousands). Such cells bridge nodes far apart along the
    surface and their gradient is far off the field's, so the interpolant is wrong inside them
    (on 3,000 random nodes, U_f reached 10x the analytic figure at hull nodes before removal,
    1.4x after). A cell is kept when removing it would leave one of its nodes in no cell.
    Given the hull, the test is local to the cell: a part of the map gives its cells the answer
    the whole map gives them (the out-of-core sweep relies on that).

    Parameters
    ----------
    coords : ndarray, shape (n, d), mm
    simplices : ndarray, shape (m, d + 1), int
    hull_points : ndarray, shape (k, d), optional
        Points whose convex hull is the map's; default ``coords``.
    cells_per_block : int
        Cells per block of the computation: memory O(nodes + block).

    Returns
    -------
    ndarray, shape (m,), bool
        True for the cells to remove.
    """
    import scipy.spatial

    m, dp1 = simplices.shape
    out = np.zeros(m, dtype=bool)
    i, j = np.triu_indices(dp1, 1)
    cand, centres = [], []
    for c0 in range(0, m, cells_per_block):
        block = simplices[c0 : c0 + cells_per_block]
        centre, r2 = circumspheres(coords, block)
        v = coords[block]  # (b, d + 1, d)
        e2 = ((v[:, i] - v[:, j]) ** 2).sum(-1).min(axis=1)
        with np.errstate(invalid="ignore"):
            flat = np.flatnonzero(r2 > SLIVER_RATIO**2 * e2)
        cand.append(c0 + flat)
        centres.append(centre[flat])
    cand = np.concatenate(cand) if cand else np.zeros(0, dtype=np.int64)
    if not len(cand):
        return out
    corners = convex_hull_points(coords if hull_points is None else hull_points)
    lo, hi = corners.min(axis=0), corners.max(axis=0)
    mid, size = (lo + hi) / 2, float((hi - lo).max()) or 1.0  # the frame of `centred`
    hull = scipy.spatial.Delaunay((corners - mid) / size)
    out[cand] = hull.find_simplex((np.concatenate(centres) - mid) / size) < 0
    # a node whose every cell would go keeps them all
    left = np.bincount(simplices[~out].ravel(), minlength=len(coords))
    orphan = np.zeros(len(coords), dtype=bool)
    orphan[simplices[out].ravel()] = True
    orphan &= left == 0
    out &= ~orphan[simplices].any(axis=1)
    return out


def sliver_note(count: int) -> str:
    """The note that says ``count`` hull slivers were removed (in memory and out of core)."""
    return (
        f"{count} flat cell(s) on the Delaunay hull removed (circumradius > {SLIVER_RATIO:g} x "
        "shortest edge, centred outside the nodes' convex hull): the map ends at its nodes' "
        "surface, and trials beyond it count as outside"
    )


def _splitmix64(x):
    """SplitMix64 finaliser of uint64 arrays (wrapping arithmetic)."""
    x = x + np.uint64(0x9E3779B97F4A7C15)
    x = (x ^ (x >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    x = (x ^ (x >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return x ^ (x >> np.uint64(31))


def coordinate_keys(coords):
    """A 64-bit hash per node of its coordinates' float64 bits (-0.0 hashes as 0.0): an id of
    the node that neither the order of the rows nor the other nodes change.

    Parameters
    ----------
    coords : ndarray, shape (n, d), mm

    Returns
    -------
    ndarray, shape (n,), uint64
    """
    bits = np.ascontiguousarray(coords + 0.0).view(np.uint64)  # + 0.0: -0.0 keys as 0.0
    key = np.zeros(len(coords), dtype=np.uint64)
    for a in range(coords.shape[1]):
        key = _splitmix64(key ^ bits[:, a])
    return key


def node_jitter(coords):
    """A pseudo-random offset in [-1, 1) per node and axis, keyed by the node's coordinates
    (their float64 bits): the same for a node whatever other nodes are triangulated with it,
    so a slab of the map jitters its nodes exactly as the whole map does.

    Parameters
    ----------
    coords : ndarray, shape (n, d), mm

    Returns
    -------
    ndarray, shape (n, d)
    """
    key = coordinate_keys(coords)
    out = np.empty(coords.shape)
    for a in range(coords.shape[1]):
        h = _splitmix64(key + np.uint64(a + 1))
        out[:, a] = (h >> np.uint64(11)).astype(np.float64) * 2.0**-52 - 1.0
    return out


def centred(coords):
    """``coords`` (n, d), mm, moved to the centre of their bounding box and divided by its
    largest side: what Qhull and the circumsphere tests see, so that their round-off is the
    same wherever the map's origin is."""
    lo, hi = coords.min(axis=0), coords.max(axis=0)
    return (coords - (lo + hi) / 2) / (float((hi - lo).max()) or 1.0)


def delaunay_coords(coords, span):
    """The nodes that `build_mesh` triangulates (Delaunay): ``coords`` (n, d), mm, each moved
    by `node_jitter` times `TIE_JITTER` of ``span`` (the whole map's size, mm).

    Keyed by each node's coordinates and scaled by the whole map, the move of a node is the
    same in any part of the map. The moved nodes are in general position: their Delaunay
    triangulation is unique, so a part of the map has the whole map's cells around its nodes
    (co-spherical nodes, as on a lattice, leave a choice that Qhull makes by insertion order).
    """
    return coords + node_jitter(coords) * (TIE_JITTER * span)


def signed_measures(coords, simplices):
    """Signed volumes (areas in 2-D) of simplices (m, d + 1), as `barycentric_transforms` gives
    them, without the transforms."""
    d = coords.shape[1]
    r = coords[simplices[:, d]]
    e = [coords[simplices[:, j]] - r for j in range(d)]
    if d == 2:
        return (e[0][:, 0] * e[1][:, 1] - e[0][:, 1] * e[1][:, 0]) / 2.0
    c = np.cross(e[1], e[2])
    return np.einsum("ij,ij->i", e[0], c) / 6.0


def tie_note(count: int, span: float) -> str:
    """The note that says ``count`` nodes keep their Delaunay move (in memory and out of core)."""
    return (
        f"{count} node(s) of co-spherical sets, where Delaunay cells would be flat, jittered by "
        f"at most {TIE_JITTER:g} of the map size ({TIE_JITTER * 1e3 * span:.3g} um) to break "
        "the tie; the cells of the other nodes interpolate a linear field exactly"
    )


def _too_degenerate(source) -> CfmInputError:
    """The error for nodes whose Delaunay cells stay flat even on the moved nodes."""
    return CfmInputError(
        "the nodes are too degenerate to triangulate robustly (co-spherical sets); "
        "export the mesh cells with the field, or the nodes of a rectilinear grid",
        file=source,
    )


def _check_moved_cells(coords, moved, simplices, tie, source):
    """Refuse a mesh whose cells with a moved node (``tie``) are flat or turned over on
    ``coords`` (the nodes with those moved): they are Delaunay cells of ``moved``."""
    cells = simplices[tie[simplices].any(axis=1)]
    mix, full = signed_measures(coords, cells), signed_measures(moved, cells)
    scale = np.ptp(coords, axis=0).prod() / len(simplices)
    if np.any(mix * np.sign(full) <= 1e-12 * scale):
        raise _too_degenerate(source)


def _delaunay(coords, source, span):
    """Delaunay triangulation of the nodes moved by `delaunay_coords`.

    Returns
    -------
    simplices : ndarray, shape (m, d + 1), int64
    kind : str
        ``"delaunay"``.
    moved : ndarray, shape (n, d), mm
        The moved nodes.
    flat : ndarray, shape (m,), bool
        Cells that are flat (or turned over) on the nodes themselves: co-spherical nodes, which
        any triangulation of them leaves flat somewhere. Such a cell has less than 1e-3 of its
        volume on the moved nodes there, or less than 1e-12 of its longest edge cubed (a test of
        the cell alone, so any part of the map decides it as the whole map). Their nodes keep
        the move (`build_mesh`); the other nodes stay where they are, so a linear field is
        interpolated exactly in their cells (thin cells of scattered nodes, as on the hull,
        keep far more of their volume).
    notes : list of str
    """
    import scipy.spatial

    notes = []
    moved = delaunay_coords(coords, span)
    try:  # centred and scaled: Qhull's round-off then does not grow with the map's offset
        tri = scipy.spatial.Delaunay(centred(moved))
    except scipy.spatial.QhullError as exc:  # pragma: no cover - _frame catches flat sets first
        raise CfmInputError(
            f"cannot triangulate the nodes: {str(exc).splitlines()[0]}", file=source
        ) from None
    simplices = tri.simplices.astype(np.int64)
    own, on_moved = signed_measures(coords, simplices), signed_measures(moved, simplices)
    d = coords.shape[1]
    edge2 = np.zeros(len(simplices))  # longest edge, squared
    for i in range(d + 1):
        for j in range(i + 1, d + 1):
            e = coords[simplices[:, i]] - coords[simplices[:, j]]
            np.maximum(edge2, np.einsum("ij,ij->i", e, e), out=edge2)
    with np.errstate(invalid="ignore", divide="ignore"):
        flat = ~(own / on_moved >= 1e-3) | (
            np.abs(own) * (2 if d == 2 else 6) <= 1e-12 * edge2 ** (d / 2)
        )
    scale = np.ptp(coords, axis=0).prod() / len(simplices)
    if np.any(np.abs(on_moved) <= 1e-12 * scale):
        raise _too_degenerate(source)
    if len(tri.coplanar):
        raise CfmInputError(
            f"{len(tri.coplanar)} node(s) merge with others in the Delaunay triangulation "
            "(nodes closer than the round-off of their coordinates); expected distinct nodes",
            file=source,
        )
    return simplices, "delaunay", moved, flat, notes


def face_excess(coords, simplices, transform, neighbors):
    """How far the mesh's nodes reach beyond the plane of each border face, in heights of the
    face's cell (the barycentric coordinate of the farthest node, negated).

    A point beyond a border face's plane by more than this lies in no cell (every cell is the
    convex hull of nodes on the near side), so a walk leaving the mesh there proves it outside.
    On a convex mesh every border face is a supporting plane and the excess is 0; behind a
    notch (an L-shaped map's re-entrant edge) or on faces that removed hull slivers leave
    (`hull_sliver_cells`), it is not, and `cfm_fem._kernels.locate_exact` searches the cells.
    The maximum over the nodes is the maximum over the vertices of their convex hull, found
    by climbing its edges (`cfm_fem._kernels.hull_max`).

    Parameters
    ----------
    coords : ndarray, shape (n, d), mm
        The mesh's nodes (those of no cell are left out).
    simplices : ndarray, shape (m, d + 1), int
    transform : ndarray, shape (m, d + 1, d)
    neighbors : ndarray, shape (m, d + 1), int
        -1 across a border face.

    Returns
    -------
    ndarray, shape (m, d + 1)
        Entry (s, j): the excess of the face opposite vertex j of cell s if it is a border face,
        else 0; values up to `cfm_fem._kernels.EXCESS_TOL` (rounding) are set to 0.
    """
    import scipy.spatial

    m, dp1 = simplices.shape
    d = dp1 - 1
    out = np.zeros((m, dp1))
    s_idx, j_idx = np.nonzero(neighbors < 0)
    if not len(s_idx):
        return out
    used = np.zeros(len(coords), dtype=bool)
    used[simplices.ravel()] = True
    hull = scipy.spatial.ConvexHull(coords[used])
    pts = np.ascontiguousarray(hull.points[hull.vertices])
    T = transform[s_idx]  # (f, d + 1, d)
    # the face's barycentric coordinate lam_j(x) = grad . (x - r) (+ 1 for j = d); its
    # smallest value over the nodes is minus the largest of -lam_j
    last = j_idx == d
    grad = np.where(last[:, None], -T[:, :d].sum(axis=1), T[np.arange(len(s_idx)),
                                                           np.minimum(j_idx, d - 1)])  # fmt: skip
    shift = last.astype(np.float64) - (grad * T[:, d]).sum(axis=1)
    # the hull's edges (CSR over its vertices), and a start near each face for the climb
    local = np.full(len(hull.points), -1, dtype=np.int64)
    local[hull.vertices] = np.arange(len(hull.vertices))
    tri = local[hull.simplices]
    h = len(pts)  # an edge (v, w) as the key v * h + w: a 1-D unique, ten times faster
    pairs = [(a, b) for a in range(d) for b in range(d) if a != b]  # both directions
    key = np.unique(np.concatenate([tri[:, a] * h + tri[:, b] for a, b in pairs]))
    adj_start = np.searchsorted(key // h, np.arange(h + 1)).astype(np.int64)
    vertex = coords[simplices[s_idx, (j_idx + 1) % dp1]]  # a vertex of each face
    start = scipy.spatial.cKDTree(pts).query(vertex)[1].astype(np.int64)
    ex = _kernels.hull_max(pts, adj_start, key % h, start,
                           np.ascontiguousarray(-grad), -shift)  # fmt: skip
    ex[~(ex > _kernels.EXCESS_TOL)] = 0.0
    out[s_idx, j_idx] = ex
    return out


def cell_buckets(
    coords,
    simplices,
    per_bucket: float = 4.0,
    max_entries: float = 48.0,
    boxes=None,
):
    """Uniform grid of buckets over the cells, each listing the cells whose bounding box meets
    it (CSR), for the exact search `cfm_fem._kernels.find_cell`.

    Parameters
    ----------
    coords : ndarray, shape (n, d), mm
    simplices : ndarray, shape (m, d + 1), int
    per_bucket : float
        Cells per bucket aimed at (about m / per_bucket buckets).
    max_entries : float
        Coarser grids are taken while the lists hold more than this many entries per cell (a
        few large cells over many buckets).
    boxes : ndarray, shape (m, 2, d), mm, optional
        The cells' bounding boxes (`cfm_fem._kernels.cell_boxes`), if the caller has them.

    Returns
    -------
    box : ndarray, shape (2, d)
        Lower corner (mm) and buckets per mm of the grid.
    dims : ndarray, shape (d,), int64
        Buckets along each axis; the flat index of a bucket is in C order.
    bstart : ndarray, shape (prod(dims) + 1,), int64
    bcells : ndarray, int32
        The cells of bucket b, increasing: ``bcells[bstart[b]:bstart[b + 1]]``.
    """
    m, dp1 = simplices.shape
    d = dp1 - 1
    if boxes is None:
        boxes = _kernels.cell_boxes(coords, simplices)
    # the boxes are padded (`cfm_fem._kernels.locate._padded`), so a point a cell holds within the
    # barycentric tolerance is inside its box; per cell, on the fly: no (m, d) temporaries
    g_lo, g_hi = grid_extent(boxes, *_kernels.padded_extent(boxes))
    ext = g_hi - g_lo
    last = None
    while True:
        step = (np.prod(ext) / max(m / per_bucket, 1.0)) ** (1.0 / d)
        dims = np.maximum(np.ceil(ext / step), 1).astype(np.int64)
        if last is not None and np.array_equal(dims, last):  # no coarser grid: one bucket
            dims = np.ones(d, dtype=np.int64)
        inv = dims / ext
        box = np.ascontiguousarray(np.stack([g_lo, inv]))
        if _kernels.bucket_entries(boxes, box, dims) <= max_entries * m or dims.prod() == 1:
            break
        last = dims
        per_bucket *= 4.0
    # counted, then filled in cell order: no per-entry temporaries (a few GB on a
    # 1e6-node map), and the cells of a bucket stay increasing
    bstart, bcells = _kernels.bucket_lists(boxes, box, dims)
    return box, dims, bstart, bcells


def grid_extent(boxes, lo, hi, quantile: float = 1e-3, ratio: float = 64.0):
    """The extent of the bucket grid: the cells' padded extent (``lo``, ``hi``), shrunk along
    an axis where a few cells reach far beyond the others (a node at 1e9 mm of a map 30 mm
    wide put every other cell into one bucket, and the search took minutes).

    Along such an axis (extent over ``ratio`` times that of the cells' centres between the
    ``quantile`` and ``1 - quantile`` quantiles) the grid covers those centres with a margin of
    half their range; cells beyond it are listed in the border buckets, where
    `cfm_fem._kernels.find_cell` looks for the points beyond it.

    Returns
    -------
    lo, hi : ndarray, shape (d,), mm
    """
    centres = boxes.mean(axis=1)
    q_lo, q_hi = np.quantile(centres, [quantile, 1.0 - quantile], axis=0)
    span = q_hi - q_lo
    wide = (hi - lo) > ratio * np.maximum(span, 1e-300)
    lo = np.where(wide, np.maximum(lo, q_lo - span / 2), lo)
    hi = np.where(wide, np.minimum(hi, q_hi + span / 2), hi)
    return lo, hi


def no_search(dim: int) -> tuple:
    """The `exact_search` arrays of a convex mesh: empty (every exit is a proof)."""
    return (np.zeros((0, dim + 1), dtype=np.float32), np.zeros(0), np.zeros((2, dim)),
            np.zeros(dim, dtype=np.int64), np.zeros(1, dtype=np.int64),
            np.zeros(0, dtype=np.int32))  # fmt: skip


def exact_search(mesh: SimplexMesh) -> tuple:
    """Arrays that make the sweep kernels' outside verdicts exact on a non-convex mesh.

    Returns
    -------
    tuple
        ``(excess, reach, box, dims, bstart, bcells)``: `face_excess`, the
        `cfm_fem._kernels.node_reach` of the nodes of faces with an excess (0 elsewhere, and
        at nodes whose cells are not all face-connected, `cfm_fem._kernels.star_sizes`) and
        `cell_buckets` (`cfm_fem._kernels.locate_exact`, `cfm_fem._kernels.star_recheck`);
        `no_search` when every border face is a supporting plane of the mesh (convex: nothing
        to search).
    """
    excess = face_excess(mesh.coords, mesh.simplices, mesh.transform, mesh.neighbors)
    if not (excess > 0.0).any():
        return no_search(mesh.dim)
    # float32, rounded up (a larger excess proves fewer exits: still exact), held by the
    # kernels for the whole run: 4 bytes per face
    ex32 = excess.astype(np.float32)
    low = ex32 < excess
    ex32[low] = np.nextafter(ex32[low], np.float32(np.inf))
    excess = ex32
    boxes = _kernels.cell_boxes(mesh.coords, mesh.simplices)  # (m, 2, d), for this call only
    buckets = cell_buckets(mesh.coords, mesh.simplices, boxes=boxes)
    s_idx, j_idx = np.nonzero(excess > 0.0)
    on_face = np.ones((len(s_idx), mesh.dim + 1), dtype=bool)
    on_face[np.arange(len(s_idx)), j_idx] = False
    nodes = np.unique(mesh.simplices[s_idx][on_face])
    # a node whose cells are not all face-connected: its star (`build_star`) misses some of
    # them, which come nearer than any reach proves (0: no proof, the global search decides)
    incident = np.bincount(mesh.simplices.ravel(), minlength=len(mesh.coords))
    size, height = _kernels.star_sizes(nodes, mesh.node_cell, mesh.simplices, mesh.neighbors,
                                       mesh.transform)  # fmt: skip
    whole = size == incident[nodes]
    reach = np.zeros(len(mesh.coords))
    reach[nodes[whole]] = _kernels.node_reach(
        mesh.coords, mesh.simplices, mesh.transform, boxes, *buckets, nodes[whole], height[whole]
    )
    return (excess, reach, *buckets)
