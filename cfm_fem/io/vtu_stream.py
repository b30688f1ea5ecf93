"""Write ``.vtu`` maps that share one mesh, array by array, in VTK's own XML format.

The sweep writes one map per U_p value on the same points and cells. `MeshBlock` encodes
the points and cells once; `write_mesh_vtu` then writes each map's field and point data and
that block straight into its file, one array at a time. The files are what VTK's XML writer
makes with `cfm_fem.io.vtk.write_vtu`'s settings (inline base64 binary, zlib at level 1 in
blocks of 32 KiB, a UInt32 header; connectivity and offsets as Int32 below 2^31 ids), read by
VTK, ParaView, pyvista and meshio alike; no copy of a whole map is held in memory.

The point data's blocks are deflated by ISA-L (`isal`), whose zlib streams at level 1 are as
small as zlib's and made about nine times faster (Monte Carlo statistics in float32, whose bytes
barely repeat, are zlib's slowest case); where it is not installed, by zlib. The points and
cells, encoded once per sweep, are deflated by zlib, which packs the cells' offsets (an
arithmetic sequence) to half of ISA-L's size.
"""

from __future__ import annotations

import base64
import zlib
from pathlib import Path
from xml.sax.saxutils import quoteattr

import numpy as np

from ._atomic import atomic_path, check_free_space
from .vtk import TEXT_SUFFIX, text_field

try:  # the same zlib streams; releases the GIL as zlib does
    from isal import isal_zlib as fast_zlib
except ImportError:  # pragma: no cover - a platform without its wheels
    fast_zlib = zlib

__all__ = ["EncodedArray", "MeshBlock", "write_mesh_vtu"]

#: Uncompressed bytes per zlib block (VTK's default).
BLOCK = 1 << 15
#: Deflate level: Monte Carlo statistics barely compress further than at level 1.
LEVEL = 1

_TYPES = {
    np.dtype(np.float64): "Float64", np.dtype(np.float32): "Float32",
    np.dtype(np.int64): "Int64", np.dtype(np.int32): "Int32",
    np.dtype(np.uint8): "UInt8", np.dtype(np.int8): "Int8",
    np.dtype(np.uint32): "UInt32", np.dtype(np.uint64): "UInt64",
    np.dtype(np.int16): "Int16", np.dtype(np.uint16): "UInt16",
}  # fmt: skip
#: VTK cell types of tetrahedra, triangles and vertices.
_TETRA, _TRIANGLE, _VERTEX = 10, 5, 1


def _encoded(values: np.ndarray, pool=None, deflate=None) -> bytes:
    """The base64 text of one array as VTK's zlib compressor writes it: a UInt32 header
    (blocks, block size, size of a partial last block, compressed size of each block) and the
    compressed blocks, each base64-encoded on its own. ``values`` is C-contiguous and
    little-endian; ``pool`` (an executor) compresses the blocks side by side (zlib releases
    the GIL), with the same bytes; ``deflate`` is the module whose ``compress`` makes them
    (default `fast_zlib`)."""
    deflate = fast_zlib if deflate is None else deflate
    raw = memoryview(values).cast("B")
    n = len(raw)
    parts = [raw[i : i + BLOCK] for i in range(0, n, BLOCK)]
    if pool is None:
        blocks = [deflate.compress(b, LEVEL) for b in parts]
    else:
        blocks = list(pool.map(lambda b: deflate.compress(b, LEVEL), parts))
    header = np.array([len(blocks), BLOCK, n % BLOCK, *map(len, blocks)], dtype="<u4")
    return base64.b64encode(header.tobytes()) + base64.b64encode(b"".join(blocks))


def _range(values: np.ndarray) -> str:
    """VTK's RangeMin and RangeMax attributes: of the values, or of each tuple's norm for
    arrays of several components; NaN ignored; empty if no value is finite."""
    v = values.astype(np.float64, copy=False)
    if v.ndim > 1:
        v = np.sqrt(np.einsum("ij,ij->i", v, v))
    finite = v[np.isfinite(v)]
    if finite.size == 0:
        return ""
    return f' RangeMin="{float(finite.min())!r}" RangeMax="{float(finite.max())!r}"'


def _array(
    name: str, values, indent: str, count: str = "NumberOfComponents", pool=None,
    deflate=None,
) -> bytes:  # fmt: skip
    """One ``<DataArray>`` element of ``values`` (shape (n,) or (n, k)), encoded (``pool``,
    ``deflate``: `_encoded`)."""
    a = np.ascontiguousarray(values)
    if a.dtype.byteorder == ">":
        a = a.astype(a.dtype.newbyteorder("<"))
    if a.dtype == np.bool_:
        a = a.astype(np.uint8)
    kind = _TYPES.get(a.dtype)
    if kind is None:
        raise TypeError(f"array {name!r} of dtype {a.dtype} has no VTK type here")
    if count == "NumberOfTuples":
        extra = f' NumberOfTuples="{a.size}"'
    else:
        extra = f' NumberOfComponents="{a.shape[1]}"' if a.ndim > 1 and a.shape[1] > 1 else ""
    head = (f'{indent}<DataArray type="{kind}" Name={quoteattr(name)}{extra} format="binary"'
            f"{_range(a)}>\n{indent}  ")  # fmt: skip
    text = _encoded(a, pool, deflate)
    return head.encode("ascii") + text + f"\n{indent}</DataArray>\n".encode("ascii")


class EncodedArray:
    """A point-data array encoded once, for every map written on the same points.

    Parameters
    ----------
    name : str
    values : ndarray, shape (n,) or (n, k)
    pool : concurrent.futures.Executor, optional
        Compresses its blocks side by side.
    """

    def __init__(self, name: str, values, pool=None):
        self.rows = len(values)
        self.nbytes = np.asarray(values).nbytes
        self.text = _array(name, values, "        ", pool=pool)


class MeshBlock:
    """The points and cells of a map, encoded once for every map written on them.

    Parameters
    ----------
    points : ndarray, shape (n, 3), mm
    cells : ndarray, shape (m, 4) or (m, 3), int, optional
        Tetrahedra or triangles; None: one vertex cell per point (a point cloud).
    pool : concurrent.futures.Executor, optional
        Compresses each array's blocks side by side (the same bytes).
    """

    def __init__(self, points, cells=None, pool=None):
        points = np.ascontiguousarray(points, dtype=np.float64)
        if cells is None:
            cells = np.arange(len(points))[:, None]
        cells = np.asarray(cells)
        self.n_points, self.n_cells = len(points), len(cells)
        per = cells.shape[1]
        # Int32 where every id and offset fits, as `write_vtu`; Int64 beyond
        ids = np.int32 if max(self.n_points, cells.size) < 2**31 else np.int64
        offsets = np.arange(per, per * self.n_cells + 1, per, dtype=ids)
        kind = {4: _TETRA, 3: _TRIANGLE, 1: _VERTEX}[per]
        ind = "        "
        self.text = b"".join((
            b"      <Points>\n",
            _array("Points", points, ind, pool=pool, deflate=zlib),
            b"      </Points>\n      <Cells>\n",
            _array("connectivity", cells.astype(ids, copy=False).reshape(-1), ind, pool=pool,
                   deflate=zlib),  # fmt: skip
            _array("offsets", offsets, ind, pool=pool, deflate=zlib),
            _array("types", np.full(self.n_cells, kind, dtype=np.uint8), ind, pool=pool,
                   deflate=zlib),  # fmt: skip
            b"      </Cells>\n",
        ))  # fmt: skip


def write_mesh_vtu(path, mesh: MeshBlock, point_data: dict, field_data: dict) -> None:
    """Write an unstructured grid ``.vtu`` on ``mesh`` atomically, one array at a time.

    Parameters
    ----------
    path : path-like
    mesh : MeshBlock
    point_data : dict of str -> ndarray, shape (n,) or (n, k), or EncodedArray
        Arrays are written with their own dtype (float32 keeps large maps small); the first
        is the map's active scalars, as pyvista makes it. An `EncodedArray` (made under the
        same name) is written as it was encoded.
    field_data : dict of str -> number or str
        As `cfm_fem.io.vtk.write_vtu`: a number is a Float64 array of one value, a string
        ``s`` under ``name`` the UTF-8 bytes of ``s`` under ``name_utf8``.

    Raises
    ------
    OSError
        Less free space than the file needs (nothing written), or a write error (the
        temporary file is removed).
    """
    fields = []
    for name, value in field_data.items():
        if isinstance(value, str):
            fields.append((name + TEXT_SUFFIX, text_field(value)))
        else:
            fields.append((name, np.atleast_1d(np.asarray(value, dtype=np.float64))))
    # base64 of zlib of data that barely compresses: 4/3 of the raw bytes and zlib's margin
    raw = sum(v.nbytes if isinstance(v, EncodedArray) else np.asarray(v).nbytes
              for v in point_data.values())  # fmt: skip
    check_free_space(Path(path).parent, int(raw * 1.34) + len(mesh.text) + (1 << 16),
                     Path(path).name)  # fmt: skip
    scalars = f" Scalars={quoteattr(next(iter(point_data)))}" if point_data else ""
    head = ('<?xml version="1.0"?>\n<VTKFile type="UnstructuredGrid" version="0.1" '
            'byte_order="LittleEndian" header_type="UInt32" compressor="vtkZLibDataCompressor">'
            "\n  <UnstructuredGrid>\n")  # fmt: skip
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        f.write(head.encode("ascii"))
        if fields:
            f.write(b"    <FieldData>\n")
            for name, value in fields:
                f.write(_array(name, value, "      ", count="NumberOfTuples"))
            f.write(b"    </FieldData>\n")
        f.write(f'    <Piece NumberOfPoints="{mesh.n_points}" NumberOfCells="{mesh.n_cells}">\n'
                f"      <PointData{scalars}>\n".encode("ascii"))  # fmt: skip
        for name, values in point_data.items():
            rows = values.rows if isinstance(values, EncodedArray) else len(values)
            if rows != mesh.n_points:
                raise ValueError(f"point data {name!r} has {rows} rows, not "
                                 f"{mesh.n_points}")  # fmt: skip
            encoded = values if isinstance(values, EncodedArray) else EncodedArray(name, values)
            f.write(encoded.text)
        f.write(b"      </PointData>\n      <CellData>\n      </CellData>\n")
        f.write(mesh.text)
        f.write(b"    </Piece>\n  </UnstructuredGrid>\n</VTKFile>\n")
