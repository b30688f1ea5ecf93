"""What the sweep report draws, gathered from a sweep's maps piece by piece in bounded memory.

A `SweepDigest` is fed the nodes of each map (all at once, or piece by piece for maps written
as pieces or slabs) and keeps, per column (U_p value, or mode htm's total / geometric /
vibration and delay): the U_f histogram over the nodes with a U_f figure, and the nodes nearest
the plane y = 0 (the longitudinal plane through a magnet's axis) for the slice image.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["SweepDigest", "PlaneSlice"]

#: Histogram bins per column.
BINS = 40
#: Most plane candidates kept per column (nodes nearest y = 0); bounds the memory on huge maps.
MAX_PLANE_NODES = 200_000
#: Nodes within this distance of the chosen plane level are drawn on scattered meshes, mm.
PLANE_HALF_THICKNESS_MM = 0.5
#: At most this many distinct node levels within that distance: a grid (one level is drawn).
GRID_LEVELS = 5


@dataclass
class PlaneSlice:
    """Nodes on the slice plane of one column.

    Attributes
    ----------
    y_mm : float
        The plane's y (the node level nearest y = 0).
    points : ndarray, shape (k, 3), mm
    uf : ndarray, shape (k,), units
        U_f, NaN at nodes without a U_f figure (incomplete).
    """

    y_mm: float
    points: np.ndarray
    uf: np.ndarray


@dataclass
class _Column:
    edges: np.ndarray
    counts: np.ndarray
    points: np.ndarray = field(default_factory=lambda: np.empty((0, 3)))
    uf: np.ndarray = field(default_factory=lambda: np.empty(0))


class SweepDigest:
    """Histograms and plane nodes of every column of a sweep.

    Parameters
    ----------
    uf_max : sequence of float or None
        Largest U_f per column (``summary["uf_units"]["max"]``), units: the histogram's upper
        edge (None: the column has no U_f figure).
    """

    def __init__(self, uf_max):
        self.columns = []
        for m in uf_max:
            top = float(m) if m is not None and m > 0 else 1.0
            self.columns.append(_Column(np.linspace(0.0, top, BINS + 1), np.zeros(BINS, np.int64)))

    def add(self, k: int, points, uf, complete) -> None:
        """Add nodes of column ``k`` (each node once over all calls: no ghost copies).

        Parameters
        ----------
        k : int
        points : ndarray, shape (m, 3), mm
        uf : ndarray, shape (m,), units
        complete : ndarray, shape (m,), bool
        """
        col = self.columns[k]
        points = np.asarray(points, dtype=np.float64)
        uf = np.where(np.asarray(complete, dtype=bool), np.asarray(uf, dtype=np.float64), np.nan)
        v = uf[np.isfinite(uf)]
        counts, _ = np.histogram(np.clip(v, col.edges[0], col.edges[-1]), col.edges)
        col.counts += counts
        col.points = np.concatenate([col.points, points])
        col.uf = np.concatenate([col.uf, uf])
        if len(col.uf) > 2 * MAX_PLANE_NODES:
            keep = np.argpartition(np.abs(col.points[:, 1]), MAX_PLANE_NODES)[:MAX_PLANE_NODES]
            keep.sort()
            col.points, col.uf = col.points[keep], col.uf[keep]

    @classmethod
    def of_result(cls, res, uf_max) -> SweepDigest:
        """The digest of a sweep result held in memory: the same as one fed the maps written
        from it (U_f rounded to float32, as the maps store it), without reading them back.

        Parameters
        ----------
        res : `cfm_fem.models.sweep.SweepResult` (or `cfm_fem.models.sweep.CompactSweep`)
        uf_max : sequence of float or None
            As for `SweepDigest`.
        """
        digest = cls(uf_max)
        uf = res.uf_units().astype(np.float32)
        complete = res.complete()
        points = res.fieldmap.points
        for k in range(uf.shape[1]):
            digest.add(k, points, uf[:, k], complete[:, k])
        return digest

    def histogram(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """(bin edges (BINS + 1,), units; counts (BINS,)) of U_f in column ``k``."""
        return self.columns[k].edges, self.columns[k].counts

    def plane(self, k: int) -> PlaneSlice:
        """The nodes of column ``k`` on the plane y = y0, y0 the node level nearest y = 0.

        Within `PLANE_HALF_THICKNESS_MM` of y0 a grid has a few node levels: the nodes of level
        y0 are drawn; a scattered mesh has nodes at many levels: all of those are drawn.
        """
        col = self.columns[k]
        if not len(col.uf):
            return PlaneSlice(float("nan"), np.empty((0, 3)), np.empty(0))
        y = col.points[:, 1]
        y0 = float(y[np.argmin(np.abs(y))])
        sel = np.abs(y - y0) <= PLANE_HALF_THICKNESS_MM
        if len(np.unique(y[sel])) <= GRID_LEVELS:
            sel = y == y0
        return PlaneSlice(y0, col.points[sel], col.uf[sel])
