"""The volume each node of a map stands for, and percentiles weighted by it.

A percentile over nodes counts every node once, so it tells where the nodes are as much as what
the field does: a mesh refined at the magnet ends, or a grid that reaches far into the
field-free fringe, moves it. Weighted by the volume each node stands for (its dual cell), a
percentile is one of the map's volume instead, and does not depend on the node density.

- Cells (a native mesh, a Delaunay triangulation, a grid with missing points): each simplex
  gives an equal share of its volume (area for a planar map) to each of its d + 1 nodes; the
  node weights sum to the meshed volume.
- A complete rectilinear grid: the product over the axes of the node's half-spacings,
  (x_{i+1} - x_{i-1}) / 2, one-sided at the grid's faces; they sum to the grid's box.
"""

from __future__ import annotations

import numpy as np

from .mesh import signed_measures

__all__ = ["node_volumes", "volume_rule", "weighted_percentiles", "CELL_RULE", "GRID_RULE"]

CELL_RULE = "an equal share (1/(d+1)) of the volume of each cell around the node"
GRID_RULE = "the product of the node's half-spacings along the grid's axes"


def _grid_axes(coords):
    """Per axis the sorted distinct values and each node's index among them, when the nodes
    fill a complete rectilinear grid; else None."""
    n, d = coords.shape
    span = float(np.ptp(coords, axis=0).max()) or 1.0
    values, index = [], []
    for k in range(d):
        key = np.round(coords[:, k] / (span * 1e-9))
        uniq, inv = np.unique(key, return_inverse=True)
        if len(uniq) < 2:
            return None
        first = np.zeros(len(uniq), dtype=np.int64)
        first[inv[::-1]] = np.arange(n)[::-1]  # one node per distinct value
        values.append(coords[first, k])
        index.append(inv)
    if np.prod([len(v) for v in values], dtype=np.float64) != n:
        return None
    return values, index


def _half_spacings(x: np.ndarray) -> np.ndarray:
    """Half-spacing of each grid value, (x[i+1] - x[i-1]) / 2, one-sided at the ends."""
    padded = np.concatenate([x[:1], x, x[-1:]])
    return (padded[2:] - padded[:-2]) / 2.0


def volume_rule(mesh) -> str:
    """The rule `node_volumes` applies to ``mesh`` (`GRID_RULE` or `CELL_RULE`)."""
    coords = np.asarray(mesh.coords, dtype=np.float64)
    if getattr(mesh, "kind", None) == "grid" and _grid_axes(coords) is not None:
        return GRID_RULE
    return CELL_RULE


def node_volumes(mesh) -> tuple[np.ndarray, str]:
    """Volume each node stands for (its dual cell).

    Parameters
    ----------
    mesh : cfm_fem.models.mesh.SimplexMesh
        ``coords`` (n, d) mm and ``simplices`` (m, d + 1) are used.

    Returns
    -------
    volumes : ndarray, shape (n,), mm^3 (mm^2 for a planar map)
        0 for a node in no cell.
    rule : str
        How they were found (`GRID_RULE` or `CELL_RULE`).
    """
    coords = np.asarray(mesh.coords, dtype=np.float64)
    if getattr(mesh, "kind", None) == "grid":
        axes = _grid_axes(coords)
        if axes is not None:
            vol = np.ones(len(coords))
            for values, idx in zip(*axes, strict=True):
                vol *= _half_spacings(values)[idx]
            return vol, GRID_RULE
    simplices = np.asarray(mesh.simplices)
    share = np.abs(signed_measures(coords, simplices)) / simplices.shape[1]
    vol = np.zeros(len(coords))
    for j in range(simplices.shape[1]):
        vol += np.bincount(simplices[:, j], weights=share, minlength=len(coords))
    return vol, CELL_RULE


def weighted_percentiles(values, weights, qs) -> list[float | None]:
    """Percentiles of ``values`` weighted by ``weights``: for q in ``qs`` (0-100), the smallest
    value v such that the values <= v hold at least q % of the total weight (the inverse of the
    weighted empirical distribution; with equal weights, numpy's ``inverted_cdf`` percentile).
    q = 100 gives the largest value of positive weight.

    Parameters
    ----------
    values : ndarray, shape (n,)
    weights : ndarray, shape (n,), >= 0
    qs : sequence of float

    Returns
    -------
    list of float or None
        None for every q when no value has a positive weight.
    """
    values = np.asarray(values, dtype=np.float64)
    weights = np.asarray(weights, dtype=np.float64)
    keep = weights > 0
    values, weights = values[keep], weights[keep]
    if values.size == 0:
        return [None for _ in qs]
    order = np.argsort(values, kind="stable")
    cum = np.cumsum(weights[order])
    total = cum[-1]
    out = []
    for q in qs:
        # a relative tolerance: the target q/100 * total must not miss a node by rounding
        i = int(np.searchsorted(cum, q / 100.0 * total * (1.0 - 1e-12), side="left"))
        out.append(float(values[order[min(i, len(order) - 1)]]))
    return out
