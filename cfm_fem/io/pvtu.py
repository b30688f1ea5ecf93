"""Partitioned VTK datasets: a ``.pvtu`` index that ParaView opens as one grid of ``.vtu`` pieces.

The pieces are ordinary ``.vtu`` files (`cfm_fem.io.vtk.write_vtu`); this module writes the
small XML index that names them and declares their point arrays. Written atomically.

A node shared by several pieces (a cell of one piece uses it) is written in each of them; all
copies but the owner's carry the VTK ghost flag (point array ``vtkGhostType``, `ghost_flags`),
so that VTK and ParaView count and merge it once (statistics, histograms, merging the pieces).
"""

from __future__ import annotations

from pathlib import Path
from xml.sax.saxutils import quoteattr

import numpy as np

from ._atomic import write_text
from .provenance import xml_comment

__all__ = ["GHOST_ARRAY", "DUPLICATEPOINT", "ghost_flags", "vtk_type", "write_pvtu"]

#: Name of VTK's ghost point array (vtkDataSetAttributes::GhostArrayName()).
GHOST_ARRAY = "vtkGhostType"
#: vtkDataSetAttributes::DUPLICATEPOINT: a copy of a point another piece owns.
DUPLICATEPOINT = 1

_VTK_TYPES = {
    np.dtype(np.float32): "Float32",
    np.dtype(np.float64): "Float64",
    np.dtype(np.int8): "Int8",
    np.dtype(np.uint8): "UInt8",
    np.dtype(np.int16): "Int16",
    np.dtype(np.uint16): "UInt16",
    np.dtype(np.int32): "Int32",
    np.dtype(np.uint32): "UInt32",
    np.dtype(np.int64): "Int64",
    np.dtype(np.uint64): "UInt64",
}


def ghost_flags(owned) -> np.ndarray:
    """``vtkGhostType`` values of a piece's points: 0 where the piece owns the point, else
    DUPLICATEPOINT (each point must be owned by exactly one piece).

    Parameters
    ----------
    owned : ndarray, shape (p,), bool

    Returns
    -------
    ndarray, shape (p,), uint8
    """
    return np.where(np.asarray(owned, dtype=bool), 0, DUPLICATEPOINT).astype(np.uint8)


def vtk_type(dtype) -> str:
    """VTK XML type name of a numpy dtype (``float32`` -> ``'Float32'``)."""
    return _VTK_TYPES[np.dtype(dtype)]


def write_pvtu(
    path, pieces, point_arrays: dict, comment: str | None = None, provenance: dict | None = None
) -> None:
    """Write a ``.pvtu`` index of unstructured-grid pieces.

    Parameters
    ----------
    path : path-like
    pieces : sequence of path-like
        The ``.vtu`` pieces; written relative to ``path``'s folder.
    point_arrays : dict of str -> ndarray
        One example array per point-data name (only dtype and components are used), in the
        pieces' order; points are float64.
    comment : str, optional
        Text put in an XML comment at the top (``--`` is written ``- -``).
    provenance : dict, optional
        Provenance record, written losslessly by `cfm_fem.io.provenance.xml_comment` (read it
        back with `cfm_fem.io.provenance.read_xml_provenance`).
    """
    path = Path(path)
    lines = ['<?xml version="1.0"?>']
    if comment:
        while "--" in comment:
            comment = comment.replace("--", "- -")
        lines.append(f"<!-- {comment.rstrip('-')} -->")
    if provenance is not None:
        lines.append(xml_comment(provenance))
    lines += [
        '<VTKFile type="PUnstructuredGrid" version="1.0" byte_order="LittleEndian" '
        'header_type="UInt64">',
        '  <PUnstructuredGrid GhostLevel="0">',
        "    <PPointData>",
    ]
    for name, arr in point_arrays.items():
        arr = np.asarray(arr)
        ncomp = 1 if arr.ndim < 2 else int(np.prod(arr.shape[1:]))
        lines.append(
            f"      <PDataArray type={quoteattr(vtk_type(arr.dtype))} Name={quoteattr(name)} "
            f'NumberOfComponents="{ncomp}"/>'
        )
    lines += [
        "    </PPointData>",
        "    <PPoints>",
        '      <PDataArray type="Float64" Name="Points" NumberOfComponents="3"/>',
        "    </PPoints>",
    ]
    for piece in pieces:
        piece = Path(piece)
        try:
            rel = piece.relative_to(path.parent).as_posix()
        except ValueError:
            rel = str(piece)
        lines.append(f"    <Piece Source={quoteattr(rel)}/>")
    lines += ["  </PUnstructuredGrid>", "</VTKFile>", ""]
    write_text(path, "\n".join(lines))
