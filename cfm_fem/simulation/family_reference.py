"""The field table a Hall case gives as its reference, and that table's own error where an
analysis reads it.

A table reference holds the exact field (:func:`.magnets.field`, magnet frame, T) at the nodes of
a regular grid that pads the map's points (recording coordinates, mm):

* ``"exact"``: a grid through the map's points, with nodes 0.5 mm either side of each and one
  2 mm beyond the map, so a reading at a point is the field there;
* ``"coarse"``: an FEM-like grid, nodes 2-5 mm apart along z (a quarter of the bore) and 1/8 of
  the padded span in x and y, read between its nodes.

A coarse table read between its nodes differs from the field there, and that difference is the
same on every repetition of a point. :func:`reading_error` is the difference as a standard reader
independent of the diagnosis reads the table: the tricubic spline of
:class:`scipy.interpolate.RegularGridInterpolator` through the table's nodes and values.
"""

from __future__ import annotations

import numpy as np

from . import magnets, scans

__all__ = ["TABLE_KINDS", "grid_axes", "nodes", "table", "reading_error", "error_rms_uT"]

#: The references given as a field table (the others are 2-D harmonics).
TABLE_KINDS = ("exact", "coarse")


def _fine_axis(g) -> np.ndarray:
    """Nodes through the distinct values ``g`` (mm), 0.5 mm either side, 2 mm beyond."""
    g = np.unique(np.round(g, 6))
    return np.unique(np.concatenate([g, g - 0.5, g + 0.5, [g.min() - 2.0, g.max() + 2.0]]))


def _coarse_axis(g) -> np.ndarray:
    """Nodes 1/8 of the span apart (at least 0.5 mm) over the values ``g`` padded by 2 mm."""
    g = np.unique(np.round(g, 6))
    lo, hi = g.min() - 2.0, g.max() + 2.0
    step = max((hi - lo) / 8.0, 0.5) if len(g) > 1 or hi - lo > 4 else 1.0
    return np.arange(lo, hi + 0.5 * step, step)


def grid_axes(cfg: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The node coordinates of a table reference along x, y and z.

    Parameters
    ----------
    cfg : dict
        A Hall configuration (:func:`.family.draw_config`) whose ``reference`` is one of
        :data:`TABLE_KINDS`.

    Returns
    -------
    gx, gy, gz : ndarray, shape (nx,), (ny,), (nz,), mm
        Increasing node coordinates (recording coordinates, the magnet frame).
    """
    kind = cfg["reference"]
    if kind not in TABLE_KINDS:
        raise ValueError(f"reference {kind!r} is not a field table; expected one of {TABLE_KINDS}")
    pts = scans.map_points(cfg["scan"])
    if kind == "exact":
        return tuple(_fine_axis(pts[:, k]) for k in range(3))
    step = float(np.clip(cfg["magnet"]["bore_mm"] / 4.0, 2.0, 5.0))
    gz = np.arange(pts[:, 2].min() - 2.0 * step, pts[:, 2].max() + 2.5 * step, step)
    return _coarse_axis(pts[:, 0]), _coarse_axis(pts[:, 1]), gz


def nodes(axes) -> np.ndarray:
    """The nodes of the grid ``axes`` (x slowest, z fastest), shape (nx ny nz, 3), mm."""
    return np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)


def table(cfg: dict) -> tuple[tuple, np.ndarray]:
    """The reference table of a Hall configuration: its grid and the exact field at its nodes.

    Parameters
    ----------
    cfg : dict
        A Hall configuration whose ``reference`` is one of :data:`TABLE_KINDS`.

    Returns
    -------
    axes : tuple of ndarray
        ``(gx, gy, gz)`` of :func:`grid_axes`, mm.
    values : ndarray, shape (nx, ny, nz, 3), T
        The field at each node (magnet frame); ``values.reshape(-1, 3)`` is in the order of
        :func:`nodes`.
    """
    axes = grid_axes(cfg)
    shape = (*(len(a) for a in axes), 3)
    return axes, magnets.field(cfg["magnet"], nodes(axes)).reshape(shape)


def reading_error(cfg: dict, tab=None) -> np.ndarray:
    """The reference's own error at each of the map's points, as a standard reader reads it.

    For a coarse table: the tricubic spline of
    :class:`scipy.interpolate.RegularGridInterpolator` (``method="cubic"``) through the
    table's nodes and values, less the exact field, at each distinct point of the scan. An
    ``"exact"`` table holds the points as nodes, and 2-D harmonics are judged by their own
    test (the body's 3-D departure, :func:`.family._null_harmonics_ok`): zero for both.

    Parameters
    ----------
    cfg : dict
        A Hall configuration (:func:`.family.draw_config`).
    tab : tuple, optional
        ``(axes, values)`` of :func:`table` when already computed (the values the reference
        file holds).

    Returns
    -------
    ndarray, shape (m, 3), T
        Error of each component (magnet frame) at each distinct point, in point_id order
        (:func:`.scans.map_points`).

    Raises
    ------
    ValueError
        A point outside the grid (the grid pads the map, so the reader never extrapolates).
    """
    from scipy.interpolate import RegularGridInterpolator

    pts = scans.map_points(cfg["scan"])
    if cfg.get("reference") != "coarse":
        return np.zeros((len(pts), 3))
    axes, values = table(cfg) if tab is None else tab
    reader = RegularGridInterpolator(axes, values, method="cubic", bounds_error=True)
    return reader(pts) - magnets.field(cfg["magnet"], pts)


def error_rms_uT(error) -> list:
    """Root mean square over the points of each component of ``error`` ((m, 3), T), in uT."""
    e = np.asarray(error, dtype=float)
    return [float(v) for v in np.sqrt(np.mean(e**2, axis=0)) * 1e6]
