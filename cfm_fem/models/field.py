"""`FieldMap`: nodes (mm) carrying a flux density (T), with the export's cells if it has them."""

from __future__ import annotations

import bisect
import warnings
from dataclasses import dataclass, field

import numpy as np

from ..errors import CfmInputError, CfmInputWarning

__all__ = ["FieldMap"]

#: Nodes closer than this (mm) are the same node.
DUPLICATE_TOL_MM = 1e-9


@dataclass
class FieldMap:
    """A sampled magnetic field.

    Build it with :meth:`FieldMap.from_arrays`, which checks the data; readers in
    :mod:`cfm_fem.io` do that for you.

    Attributes
    ----------
    points : ndarray, shape (n, 3), float64, mm
        Node coordinates in the magnet (map) frame.
    B : ndarray, shape (n, 3), float64, T
        Flux density (Bx, By, Bz) at the nodes.
    cells : ndarray, shape (m, 4) or (m, 3), int64, or None
        Linear tetrahedra (or triangles for a planar map) of the export, as indices into
        ``points``; None when the export is a bare point cloud.
    source : str
        File the map came from (used in messages and recorded in outputs).
    notes : list of str
        What the reader did that a user should know (dropped rows, header mismatches, ...).
    lines : ndarray, shape (n,), int64, or None
        1-based line number of each node in ``source``, for messages.
    """

    points: np.ndarray
    B: np.ndarray
    cells: np.ndarray | None = None
    source: str = "<memory>"
    notes: list[str] = field(default_factory=list)
    lines: np.ndarray | None = None

    @property
    def n_nodes(self) -> int:
        return int(self.points.shape[0])

    @property
    def b_max(self) -> float:
        """Largest |B| over the nodes, T (the default B_ref)."""
        return float(np.sqrt((self.B**2).sum(axis=1)).max())

    def line_of(self, i: int) -> int | None:
        """Source line of node ``i``, or None if unknown."""
        return None if self.lines is None else int(self.lines[i])

    @classmethod
    def from_arrays(
        cls,
        points,
        B,
        *,
        cells=None,
        source: str = "<memory>",
        lines=None,
        notes=None,
        columns=("x", "y", "z", "Bx", "By", "Bz"),
    ) -> FieldMap:
        """Check and assemble a field map.

        Parameters
        ----------
        points : array_like, shape (n, 3), mm
        B : array_like, shape (n, 3), T
        cells : array_like of int, shape (m, 4) or (m, 3), optional
        source : str
            File name for messages.
        lines : array_like of int, shape (n,), optional
            1-based source line of each node, for messages.
        notes : list of str, optional
        columns : sequence of 6 str
            Names of the coordinate and field columns as the file spells them, for messages.

        Raises
        ------
        CfmInputError
            Wrong shapes, no nodes, a NaN or infinite value, or two nodes at the same place with
            different fields. Identical duplicate nodes are merged with a `CfmInputWarning`.
        """
        points = np.asarray(points, dtype=np.float64)
        B = np.asarray(B, dtype=np.float64)
        lines = None if lines is None else np.asarray(lines, dtype=np.int64)
        notes = list(notes or [])
        if points.ndim != 2 or points.shape[1] != 3 or B.shape != points.shape:
            raise CfmInputError(
                f"points must have shape (n, 3) and B the same; instead received {points.shape}"
                f" and {B.shape}",
                file=source,
            )
        if points.shape[0] == 0:
            raise CfmInputError(
                "the file holds no data rows; expected at least 4 nodes", file=source
            )
        for arr, names in ((points, columns[:3]), (B, columns[3:])):
            bad = ~np.isfinite(arr)
            if bad.any():
                i, j = np.argwhere(bad)[0]
                line = None if lines is None else int(lines[i])
                raise CfmInputError(
                    f"column '{names[j]}' must be a finite number; found {float(arr[i, j])}",
                    file=source,
                    line=line,
                    column=names[j],
                )
        if cells is not None:
            cells = np.asarray(cells, dtype=np.int64)
            if cells.ndim != 2 or cells.shape[1] not in (3, 4) or len(cells) == 0:
                raise CfmInputError(
                    f"cells must be triangles (m, 3) or tetrahedra (m, 4); instead received "
                    f"shape {cells.shape}",
                    file=source,
                )
            if cells.min() < 0 or cells.max() >= len(points):
                bad = int(np.argmax((cells < 0).any(axis=1) | (cells >= len(points)).any(axis=1)))
                raise CfmInputError(
                    f"cell {bad} refers to node(s) {cells[bad].tolist()}, outside the "
                    f"{len(points)} nodes of the file; expected node numbers 0 to "
                    f"{len(points) - 1} (counted from 0)",
                    file=source,
                )
        points, B, cells, lines = _merge_duplicates(points, B, cells, lines, source, notes)
        return cls(points=points, B=B, cells=cells, source=str(source), notes=notes, lines=lines)


def _snap_close_values(column, values):
    """Snap each value of ``column`` within `DUPLICATE_TOL_MM` of a smaller one to the first
    value of its run (sorted values each within the tolerance of the next).

    Parameters
    ----------
    column : ndarray, shape (n,)
    values : ndarray, shape (n,)
        ``column`` sorted.

    Returns
    -------
    snapped : ndarray, shape (n,), or None
        None when no two distinct values are that close (the usual case).
    hit : ndarray of int
        Indices of the changed values.
    """
    gaps = np.diff(values)
    close = (gaps > 0) & (gaps <= DUPLICATE_TOL_MM)
    if not close.any():
        return None, None
    starts = values[np.r_[0, np.flatnonzero(gaps > DUPLICATE_TOL_MM) + 1]]
    hit = np.flatnonzero(np.isin(column, values[np.flatnonzero(close) + 1]))
    out = column.copy()
    out[hit] = starts[np.searchsorted(starts, column[hit], side="right") - 1]
    return out, hit


#: More snapped nodes than this are re-sorted with one lexsort instead of being inserted one by one.
_MAX_INSERTED = 10_000


def _reinsert(order, keys, moved):
    """``order`` (a lexicographic order of the old keys) with the nodes ``moved``, whose keys
    changed, taken out and put back at their place for the new ``keys``."""
    stay = order[~np.isin(order, moved)]
    moved = moved[np.lexsort(keys[moved].T[::-1])]
    rows = keys[stay]

    class _Rows:  # a lazy sequence of row tuples for bisect
        def __len__(self):
            return len(rows)

        def __getitem__(self, i):
            return tuple(rows[i])

    at = [bisect.bisect_left(_Rows(), tuple(keys[m])) for m in moved]
    return np.insert(stay, at, moved)


def _merge_duplicates(points, B, cells, lines, source, notes):
    """Merge nodes that share a position and a field; reject those that share only a position.

    Positions are the same when every coordinate agrees within `DUPLICATE_TOL_MM`. Comparing
    neighbours in lexicographic (x, y, z) order alone misses a node whose x (or y) differs by 1e-12
    from its twin's: other nodes sort between the two. So x and y values closer than the tolerance
    to a smaller one are first snapped to the start of their run (z, the last key, needs no
    snapping), and the few snapped nodes are moved to their place in the order. Cost on 1e6
    nodes: one more sort (of y), about +0.05 s on 0.2-0.8 s; a KD-tree query took 1-2 s.
    """
    order = np.lexsort(points.T[::-1])
    keys, moved = points, []
    for k, values in ((0, points[order, 0]), (1, np.sort(points[:, 1]))):
        snapped, hit = _snap_close_values(points[:, k], values)
        if snapped is not None:
            keys = points.copy() if keys is points else keys
            keys[:, k] = snapped
            moved.append(hit)
    if moved:
        moved = np.unique(np.concatenate(moved))
        if len(moved) > _MAX_INSERTED:
            order = np.lexsort(keys.T[::-1])
        else:
            order = _reinsert(order, keys, moved)
    sp = keys[order]
    same = np.all(np.abs(np.diff(sp, axis=0)) <= DUPLICATE_TOL_MM, axis=1)
    if not same.any():
        return points, B, cells, lines
    first_of = np.empty(len(points), dtype=np.int64)  # representative (sorted position)
    rep = np.concatenate([[True], ~same])
    group = np.cumsum(rep) - 1
    starts = np.flatnonzero(rep)
    first_of[order] = np.minimum.reduceat(order, starts)[group]  # the earliest row of a group
    dup = first_of != np.arange(len(points))
    db = np.abs(B[dup] - B[first_of[dup]]).max(axis=1)
    scale = max(float(np.abs(B).max()), 1e-30)
    conflict = np.flatnonzero(dup)[db > 1e-9 * scale]
    if conflict.size:
        i = int(conflict[0])
        j = int(first_of[i])
        li = None if lines is None else int(lines[i])
        lj = None if lines is None else int(lines[j])
        # a mesh file has no lines: name the nodes (0-based, as the NaN-in-point-data message)
        also = f"also on line {lj}" if lj is not None else f"nodes {j} and {i}, 0-based"
        raise CfmInputError(
            f"duplicate node at {points[i].tolist()} mm ({also}) with a different field "
            f"{B[i].tolist()} T vs {B[j].tolist()} T; expected one field per position",
            file=source,
            line=li,
        )
    keep = ~dup
    n_dup = int(dup.sum())
    msg = f"{source}: merged {n_dup} duplicate node(s) with identical position and field"
    warnings.warn(msg, CfmInputWarning, stacklevel=3)
    notes.append(msg)
    new_index = np.cumsum(keep) - 1
    remap = new_index[first_of]
    if cells is not None:
        cells = remap[cells]
    return points[keep], B[keep], cells, (None if lines is None else lines[keep])
