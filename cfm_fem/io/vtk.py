"""VTK outputs for ParaView: ``.vtu`` datasets (via meshio) and ``.pvd`` collections."""

from __future__ import annotations

from pathlib import Path
from xml.sax.saxutils import quoteattr

import meshio
import numpy as np

from ._atomic import atomic_path, write_text

__all__ = ["write_vtu", "write_pvd"]

_CELL_TYPES = {2: "triangle", 3: "tetra"}


def write_vtu(path, points, cells=None, point_data=None, field_data=None) -> None:
    """Write an unstructured grid ``.vtu`` (binary, zlib) atomically.

    Parameters
    ----------
    path : path-like
    points : ndarray, shape (n, 3), mm
    cells : ndarray, shape (m, 4) or (m, 3), int, optional
        Tetrahedra or triangles; None writes one vertex cell per point (a point cloud).
    point_data : dict of str -> ndarray, shape (n,) or (n, k), optional
    field_data : dict of str -> str or number, optional
        Dataset-level metadata (B_ref, U_p, seed, ...); strings are stored as character arrays.
    """
    points = np.asarray(points, dtype=np.float64)
    if cells is None:
        cell_blocks = [("vertex", np.arange(len(points), dtype=np.int64)[:, None])]
    else:
        cells = np.asarray(cells, dtype=np.int64)
        cell_blocks = [(_CELL_TYPES[cells.shape[1] - 1], cells)]
    pdata = {k: np.ascontiguousarray(v) for k, v in (point_data or {}).items()}
    fdata = {}
    for k, v in (field_data or {}).items():
        # VTK field data must be arrays; strings go in as bytes so ParaView shows them.
        fdata[k] = (
            np.frombuffer(str(v).encode(), dtype=np.uint8)
            if isinstance(v, str)
            else (np.atleast_1d(np.asarray(v, dtype=np.float64)))
        )
    mesh = meshio.Mesh(points, cell_blocks, point_data=pdata, field_data=fdata)
    with atomic_path(path) as tmp:
        meshio.write(tmp, mesh, file_format="vtu", binary=True, compression="zlib")


def write_pvd(path, entries) -> None:
    """Write a ParaView collection: ParaView shows ``timestep`` as the time axis.

    Parameters
    ----------
    path : path-like
    entries : sequence of (float, path-like)
        (timestep, dataset file); dataset paths are written relative to ``path``'s folder.
    """
    path = Path(path)
    rows = []
    for t, f in entries:
        rel = Path(f).name if Path(f).parent == path.parent else str(Path(f))
        rows.append(
            f'    <DataSet timestep="{float(t)!r}" group="" part="0" file={quoteattr(rel)}/>'
        )
    text = (
        '<?xml version="1.0"?>\n'
        '<VTKFile type="Collection" version="0.1" byte_order="LittleEndian">\n'
        "  <Collection>\n" + "\n".join(rows) + "\n  </Collection>\n</VTKFile>\n"
    )
    write_text(path, text)
