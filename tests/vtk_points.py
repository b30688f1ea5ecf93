"""Test helpers: the point data of written maps, each node once, sorted by position."""

from __future__ import annotations

import numpy as np


def by_position(grid):
    """Point data of a grid with duplicate points merged, rows sorted by position."""
    grid = grid.clean(tolerance=0.0)
    order = np.lexsort(np.asarray(grid.points).T)
    names = [k for k in grid.point_data if k != "vtkGhostType"]  # pieces only: see below
    return grid, {k: np.asarray(grid.point_data[k])[order] for k in names}


def owned_points(grid):
    """Each node once: the points of a ``.pvtu`` that are not VTK ghost copies (another piece
    owns them), sorted by position, with their point data (``vtkGhostType`` left out)."""
    ghost = np.asarray(grid.point_data["vtkGhostType"])
    assert ghost.dtype == np.uint8 and set(np.unique(ghost).tolist()) <= {0, 1}
    assert grid.GetPointGhostArray() is not None  # VTK takes it for its ghost array
    keep = ghost == 0
    pts = np.asarray(grid.points)[keep]
    order = np.lexsort(pts.T)
    data = {k: np.asarray(v)[keep][order] for k, v in grid.point_data.items()}
    return pts[order], {k: v for k, v in data.items() if k != "vtkGhostType"}


def vtk_histogram_count(grid, name):
    """Values VTK's histogram filter counts (it skips ghost points, as ParaView's does)."""
    from vtkmodules.util.numpy_support import vtk_to_numpy
    from vtkmodules.vtkFiltersStatistics import vtkExtractHistogram

    h = vtkExtractHistogram()
    h.SetInputData(grid)
    h.SetInputArrayToProcess(0, 0, 0, 0, name)
    h.Update()
    return int(vtk_to_numpy(h.GetOutput().GetRowData().GetArray("bin_values")).sum())
