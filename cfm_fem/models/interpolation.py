"""Piecewise-linear interpolation of a `FieldMap` on its simplicial mesh (`cfm_fem.models.mesh`).

`interpolate_points` walks from given cells, `interpolate_groups` serves points grouped around
nodes (the perturbation sweep's access pattern), `LinearInterpolator` is B(x) at any points.
"""

from __future__ import annotations

import itertools

import numpy as np

from .. import _kernels
from .field import FieldMap

__all__ = ["interpolate_points", "interpolate_groups", "LinearInterpolator"]
from .mesh import SimplexMesh, build_mesh


def interpolate_points(mesh: SimplexMesh, values, points, start):
    """Piecewise-linear values at points of the mesh frame, walking from given simplices.

    Parameters
    ----------
    mesh : SimplexMesh
    values : ndarray, shape (n, c)
        Values at the mesh nodes (T for a field).
    points : ndarray, shape (k, d), mm, in the mesh frame (`SimplexMesh.to_local`)
    start : ndarray, shape (k,), int64
        Simplex each walk starts from: one near the point saves steps (see
        `cfm_fem._kernels.octant_cells` for points drawn around nodes).

    Returns
    -------
    out : ndarray, shape (k, c)
        NaN where the point is outside the mesh (never extrapolated).
    cell : ndarray, shape (k,), int64
        Containing simplex, or -1 (outside) / -2 (walk failed).
    """
    points = np.ascontiguousarray(points, dtype=np.float64)
    values = np.ascontiguousarray(values, dtype=np.float64)
    out = np.empty((len(points), values.shape[1]))  # numpy's allocation: see the kernel
    cell = np.empty(len(points), dtype=np.int64)
    _kernels.interpolate_points(
        points, np.ascontiguousarray(start, dtype=np.int64), mesh.simplices, mesh.transform,
        mesh.neighbors, values, out, cell,
    )  # fmt: skip
    return out, cell


def interpolate_groups(mesh: SimplexMesh, values, points, group_start, group_node):
    """Piecewise-linear values at points drawn around nodes, grouped by node.

    The access pattern of a perturbation sweep: group q holds the points
    ``points[group_start[q]:group_start[q + 1]]``, displaced from node ``group_node[q]``. In
    3-D each point is placed in the star of its node by a vectorised test of every cell of
    the star (`cfm_fem._kernels.interpolate_groups`); points outside the star, and every point
    of a planar map, are walked as in `interpolate_points`. A group may be of any size, and
    its points anywhere: a far point only costs a walk.

    Parameters
    ----------
    mesh, values, points
        As for `interpolate_points`: the mesh, the (n, c) values at its nodes, the (k, d)
        points (mm, mesh frame).
    group_start : ndarray, shape (n_groups + 1,), int
        Offsets: increasing, from 0 to k.
    group_node : ndarray, shape (n_groups,), int
        The node each group is drawn around.

    Returns
    -------
    out : ndarray, shape (k, c)
        NaN where the point is outside the mesh (never extrapolated) or not finite. As with
        `interpolate_points`, a walk blocked by a notch of a non-convex mesh reads as outside
        (`LinearInterpolator.field_at` retries those).
    walked : int
        How many points needed the walk.
    """
    points = np.ascontiguousarray(points, dtype=np.float64)
    values = np.ascontiguousarray(values, dtype=np.float64)
    group_start = np.ascontiguousarray(group_start, dtype=np.int64)
    group_node = np.ascontiguousarray(group_node, dtype=np.int64)
    k = len(points)
    if (
        len(group_start) != len(group_node) + 1
        or (len(group_start) and (group_start[0] != 0 or group_start[-1] != k))
        or np.any(np.diff(group_start) < 0)
    ):
        raise ValueError("group_start must rise from 0 to len(points), one more than group_node")
    if len(group_node) and (group_node.min() < 0 or group_node.max() >= len(mesh.coords)):
        raise ValueError("group_node holds indices outside the mesh's nodes")
    if mesh.dim != 3:
        start = np.repeat(mesh.node_cell[group_node], np.diff(group_start))
        out, cell = interpolate_points(mesh, values, points, start)
        return out, k
    out = np.empty((k, values.shape[1]))  # numpy's allocation: see `interpolate_points`
    star_start, star = mesh.node_stars()
    walked = _kernels.interpolate_groups(
        points, group_start, group_node, mesh.simplices, mesh.transform, mesh.neighbors,
        mesh.coords, values, star_start, star, out,
    )  # fmt: skip
    return out, int(walked)


class LinearInterpolator:
    """Evaluate the piecewise-linear field of a map at arbitrary points.

    Parameters
    ----------
    fm : FieldMap
    method : {"auto", "native", "grid", "delaunay"}
    hull_slivers : {"keep", "remove"}
        See `build_mesh`.

    Examples
    --------
    >>> interp = LinearInterpolator(fieldmap)                      # doctest: +SKIP
    >>> B, inside = interp.field_at([[0.0, 1.0, 2.0]])             # doctest: +SKIP
    """

    def __init__(self, fm: FieldMap, method: str = "auto", hull_slivers: str = "keep"):
        self.fieldmap = fm
        self.mesh = build_mesh(fm, method, hull_slivers)
        self._tree = None
        self._spheres = None
        self._hull = None

    def field_at(self, points):
        """Interpolated B at ``points``.

        Parameters
        ----------
        points : array_like, shape (k, 3), mm

        Returns
        -------
        B : ndarray, shape (k, 3), T
            NaN where the point is outside the mesh (never extrapolated).
        inside : ndarray, shape (k,), bool
        """
        import scipy.spatial

        pts = np.atleast_2d(np.asarray(points, dtype=np.float64))
        if self._tree is None:
            self._tree = scipy.spatial.cKDTree(self.mesh.coords)
        local = np.ascontiguousarray(self.mesh.to_local(pts))
        k = min(8, len(self.mesh.coords))
        _, nearest = self._tree.query(local, k=k)
        nearest = nearest.reshape(len(local), k)
        m = self.mesh
        B, cell = interpolate_points(m, self.fieldmap.B, local, m.node_cell[nearest[:, 0]])
        # A walk can be blocked by a hole of a non-convex mesh: retry from the next nearest
        # nodes. A point outside the nodes' convex hull is in no cell: no retry (the
        # finite differences of a map's border put many points there).
        retry = cell < 0
        if retry.any():
            retry[retry] = self._in_hull(local[retry])
        for j in range(1, k):
            redo = np.flatnonzero(retry & (cell < 0))
            if redo.size == 0:
                break
            b2, c2 = interpolate_points(
                m, self.fieldmap.B, local[redo], m.node_cell[nearest[redo, j]]
            )
            B[redo], cell[redo] = b2, c2
        redo = np.flatnonzero(retry & (cell < 0))
        if redo.size:  # walks blocked by a notch of the border: search the cells around
            c2 = self._cells_around(local[redo])
            found = redo[c2 >= 0]
            cell[found] = c2[c2 >= 0]
            # a walk that starts in the containing cell takes no step
            B[found] = interpolate_points(m, self.fieldmap.B, local[found], cell[found])[0]
        return B, cell >= 0

    def _in_hull(self, local) -> np.ndarray:
        """Whether points (k, dim) of the mesh frame lie in the convex hull of its nodes, to a
        tolerance of 1e-9 of the mesh's extent (a point on a border face counts as in)."""
        import scipy.spatial

        if self._hull is None:
            c = self.mesh.coords
            tol = 1e-9 * float(np.ptp(c, axis=0).max())
            try:
                eq = scipy.spatial.ConvexHull(c).equations
            except scipy.spatial.QhullError:  # degenerate node set: test nothing out
                eq = np.zeros((0, c.shape[1] + 1))
            self._hull = (eq, tol)
        eq, tol = self._hull
        if not len(eq):
            return np.ones(len(local), bool)
        block = max(1, 4_000_000 // len(eq))  # points at a time: a few tens of MB
        out = np.empty(len(local), bool)
        for a in range(0, len(local), block):
            part = local[a : a + block] @ eq[:, :-1].T + eq[:, -1]
            out[a : a + block] = part.max(axis=1) <= tol
        return out

    def _cells_around(self, local):
        """Containing cell of each point (k, dim), -1 if none, by testing every cell whose
        bounding sphere (centroid, farthest vertex) holds it: cells are grouped by radius in
        powers of two, one KD-tree of centroids per group. Exact, for the few points whose
        walks a non-convex border blocked."""
        import scipy.spatial

        block = 4096  # points at a time: their candidate pairs stay a few MB
        if len(local) > block:
            parts = [self._cells_around(local[k : k + block]) for k in range(0, len(local), block)]
            return np.concatenate(parts)
        m = self.mesh
        if self._spheres is None:
            v = m.coords[m.simplices]
            centre = v.mean(axis=1)
            radius = np.sqrt(((v - centre[:, None]) ** 2).sum(-1).max(axis=1)) * (1 + 1e-9)
            level = np.floor(np.log2(radius)).astype(np.int64)
            groups = []
            for lv in np.unique(level):
                idx = np.flatnonzero(level == lv)
                groups.append((idx, scipy.spatial.cKDTree(centre[idx]), radius[idx].max()))
            self._spheres = (centre, radius, groups)
        centre, radius, groups = self._spheres
        best = np.full(len(local), np.iinfo(np.int64).max)
        d = m.dim
        for idx, tree, rmax in groups:
            near = tree.query_ball_point(local, rmax)
            count = np.fromiter(map(len, near), dtype=np.int64, count=len(near))
            if not count.any():
                continue
            # every (point, candidate cell) pair at once: no Python loop over the points
            i = np.repeat(np.arange(len(local)), count)
            c = idx[np.fromiter(itertools.chain.from_iterable(near), np.int64, int(count.sum()))]
            hit = ((centre[c] - local[i]) ** 2).sum(-1) <= radius[c] ** 2
            i, c = i[hit], c[hit]
            T = m.transform[c]
            lam = np.einsum("cjk,ck->cj", T[:, :d], local[i] - T[:, d])
            ok = (lam >= -_kernels.BARY_EPS).all(1) & (1 - lam.sum(1) >= -_kernels.BARY_EPS)
            np.minimum.at(best, i[ok], c[ok])
        return np.where(best == np.iinfo(np.int64).max, -1, best)
