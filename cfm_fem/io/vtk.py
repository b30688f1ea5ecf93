"""VTK outputs for ParaView: ``.vtu`` datasets (via meshio) and ``.pvd`` collections."""

from __future__ import annotations

from pathlib import Path
from xml.sax.saxutils import quoteattr

import numpy as np

from ._atomic import atomic_path, check_free_space, write_text

__all__ = ["write_vtu", "write_pvd", "TEXT_SUFFIX", "text_field", "read_text_field"]

#: Suffix of the name under which `write_vtu` stores a text field-data value.
TEXT_SUFFIX = "_utf8"

#: Characters of a map's XML text (ASCII: one byte each) encoded and written at a time.
_WRITE_CHUNK = 1 << 22


def text_field(value: str) -> np.ndarray:
    """A text as the field-data array `write_vtu` stores: its UTF-8 bytes, shape (k,), uint8
    (every VTK reader, meshio included, reads it; a VTK string array stops meshio)."""
    return np.frombuffer(str(value).encode("utf-8"), dtype=np.uint8).copy()


def read_text_field(field_data, name: str) -> str:
    """The text ``name`` of a map's field data (``field_data`` as meshio, pyvista or VTK's
    numpy support give it), stored by `write_vtu` as ``<name>_utf8`` bytes.

    Raises
    ------
    KeyError
        The field data hold no text ``name``.
    """
    values = np.asarray(field_data[name + TEXT_SUFFIX]).ravel()
    return values.astype(np.uint8).tobytes().decode("utf-8")


def write_vtu(path, points, cells=None, point_data=None, field_data=None) -> None:
    """Write an unstructured grid ``.vtu`` atomically with VTK's XML writer (binary, zlib;
    connectivity and offsets as Int32 where the counts allow, Int64 beyond).

    Parameters
    ----------
    path : path-like
    points : ndarray, shape (n, 3), mm
    cells : ndarray, shape (m, 4) or (m, 3), int, optional
        Tetrahedra or triangles; None writes one vertex cell per point (a point cloud).
    point_data : dict of str -> ndarray, shape (n,) or (n, k), optional
        Arrays are written with their own dtype (float32 keeps large maps small).
    field_data : dict of str -> number or str, optional
        Dataset-level metadata (B_ref, U_p, seed, ...). A number is a Float64 array of one
        value; a string ``s`` under ``name`` is written as ``name_utf8``, the UTF-8 bytes of
        ``s`` as a UInt8 array (`text_field`; `read_text_field` turns it back): meshio, pyvista
        and ParaView read every array of the file (meshio stops at a VTK string array).
    """
    import pyvista as pv  # here: the sweep's maps are written by `vtu_stream`, without it
    from pyvista import CellType

    points = np.asarray(points, dtype=np.float64)
    n = len(points)
    if cells is None:
        grid = pv.UnstructuredGrid({CellType.VERTEX: np.arange(n, dtype=np.int64)[:, None]}, points)
    else:
        cells = np.asarray(cells, dtype=np.int64)
        kind = CellType.TETRA if cells.shape[1] == 4 else CellType.TRIANGLE
        grid = pv.UnstructuredGrid({kind: cells}, points)
    cell_array = grid.GetCells()
    if max(n, cell_array.GetNumberOfConnectivityIds()) < 2**31:  # every id and offset fits
        cell_array.ConvertTo32BitStorage()  # zlib packs the Int64 zeros well: ~2 % smaller
    for name, values in (point_data or {}).items():
        grid.point_data[name] = np.ascontiguousarray(values)
    for name, value in (field_data or {}).items():
        if isinstance(value, str):
            grid.field_data[name + TEXT_SUFFIX] = text_field(value)
        else:
            grid.field_data[name] = np.atleast_1d(np.asarray(value, dtype=np.float64))
    from vtkmodules.vtkIOXML import vtkXMLUnstructuredGridWriter

    writer = vtkXMLUnstructuredGridWriter()
    writer.SetInputData(grid)
    # inline base64 binary, as pyvista writes it: raw appended data can hold byte sequences
    # that meshio's XML parsing trips over (data-dependent, hence intermittent)
    writer.SetDataModeToBinary()
    # zlib, not LZ4: LZ4 writes faster but meshio (and so cfm_fem's own reader) cannot read it;
    # level 1: Monte Carlo statistics barely compress further, and level 5 takes 1.5x longer
    writer.SetCompressorTypeToZLib()
    writer.SetCompressionLevel(1)
    # into memory, then to disk from Python: VTK's own file output aborts or crashes the
    # process when the disk fills up; here that is an OSError, and the space is checked first
    writer.WriteToOutputStringOn()
    if writer.Write() != 1:
        raise OSError(f"VTK could not write {path}")
    text = writer.GetOutputString()  # inline base64: ASCII, one byte a character
    del writer, grid  # VTK's copy of the text goes: maps written side by side share the memory
    check_free_space(Path(path).parent, len(text), Path(path).name)
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        for i in range(0, len(text), _WRITE_CHUNK):  # no bytes copy of the whole text
            f.write(text[i : i + _WRITE_CHUNK].encode("ascii"))


def write_pvd(path, entries, provenance: dict | None = None) -> None:
    """Write a ParaView collection: ParaView shows ``timestep`` as the time axis.

    Parameters
    ----------
    path : path-like
    entries : sequence of (float, path-like)
        (timestep, dataset file); dataset paths are written relative to ``path``'s folder.
    provenance : dict, optional
        What produced the outputs (`cfm_fem.io.provenance.provenance`), written as an XML
        comment after the declaration (ParaView's reader skips comments); read it back with
        `cfm_fem.io.provenance.read_xml_provenance`.
    """
    from .provenance import xml_comment

    path = Path(path)
    rows = []
    for t, f in entries:
        rel = Path(f).name if Path(f).parent == path.parent else str(Path(f))
        rows.append(
            f'    <DataSet timestep="{float(t)!r}" group="" part="0" file={quoteattr(rel)}/>'
        )
    text = (
        '<?xml version="1.0"?>\n'
        + (xml_comment(provenance) + "\n" if provenance is not None else "")
        + '<VTKFile type="Collection" version="0.1" byte_order="LittleEndian">\n'
        "  <Collection>\n" + "\n".join(rows) + "\n  </Collection>\n</VTKFile>\n"
    )
    write_text(path, text)
