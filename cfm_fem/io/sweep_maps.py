"""Read a written sweep back: its ``summary.json`` and chosen point arrays of its maps, one
``.vtu`` (or one piece of a ``.pvtu``) at a time, each node once (VTK ghost copies left out)."""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from ..errors import CfmInputError
from .pvtu import GHOST_ARRAY

__all__ = ["read_summary", "map_files", "read_map_arrays", "iter_map_nodes"]


def read_summary(out_dir) -> dict:
    """``out_dir/summary.json`` of a sweep, as a dict.

    Raises
    ------
    CfmInputError
        No readable summary (not a sweep's folder, or a run that did not finish).
    """
    path = Path(out_dir) / "summary.json"
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise CfmInputError(
            f"{path}: expected the summary.json of a finished cfm-fem sweep ({exc})"
        ) from None


def map_files(out_dir) -> list[list[Path]]:
    """The ``.vtu`` files of each map named by ``out_dir/sweep.pvd``, in its order: one file
    per map, or the pieces of its ``.pvtu`` index."""
    out = Path(out_dir)
    try:
        maps = []
        for ds in ET.parse(out / "sweep.pvd").getroot().iter("DataSet"):
            f = out / ds.get("file")
            if f.suffix == ".pvtu":
                pieces = ET.parse(f).getroot().iter("Piece")
                maps.append([f.parent / p.get("Source") for p in pieces])
            else:
                maps.append([f])
    except (OSError, ET.ParseError, TypeError) as exc:
        raise CfmInputError(
            f"{out / 'sweep.pvd'}: expected the map index of a cfm-fem sweep ({exc})"
        ) from None
    return maps


def read_map_arrays(path, names) -> tuple[np.ndarray, dict]:
    """Points and the point arrays ``names`` of one ``.vtu`` (the other arrays are not
    decompressed); nodes that are ghost copies of another piece's are left out.

    Returns
    -------
    points : ndarray, shape (m, 3), mm
    arrays : dict of str -> ndarray, shape (m, ...)
    """
    from vtkmodules.util.numpy_support import vtk_to_numpy
    from vtkmodules.vtkIOXML import vtkXMLUnstructuredGridReader

    reader = vtkXMLUnstructuredGridReader()
    reader.SetFileName(str(path))
    reader.UpdateInformation()
    selection = reader.GetPointDataArraySelection()
    selection.DisableAllArrays()
    for name in [*names, GHOST_ARRAY]:
        selection.EnableArray(name)
    reader.Update()
    grid = reader.GetOutput()
    if grid is None or grid.GetPoints() is None:
        raise CfmInputError(f"{path}: expected a map written by cfm-fem sweep")
    pd = grid.GetPointData()
    points = vtk_to_numpy(grid.GetPoints().GetData()).astype(np.float64)
    arrays = {}
    for name in names:
        arr = pd.GetArray(name)
        if arr is None:
            raise CfmInputError(f"{path}: point array {name!r} missing; expected a sweep's map")
        arrays[name] = vtk_to_numpy(arr)
    ghost = pd.GetArray(GHOST_ARRAY)
    if ghost is not None:
        own = vtk_to_numpy(ghost) == 0
        points = points[own]
        arrays = {k: v[own] for k, v in arrays.items()}
    return points, arrays


def iter_map_nodes(out_dir, names=("U_f_units", "complete")):
    """Yield ``(k, points, arrays)`` for each map ``k`` of a sweep and each of its files (one,
    or one per piece): every node once, in bounded memory (`read_map_arrays`)."""
    for k, files in enumerate(map_files(out_dir)):
        for f in files:
            points, arrays = read_map_arrays(f, names)
            yield k, points, arrays
