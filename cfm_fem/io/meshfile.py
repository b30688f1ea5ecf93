"""Mesh files through meshio (VTU, VTK, Gmsh ``.msh``, XDMF, ...): field as point data.

The field is point data ``B`` with 3 components, or ``Bx``, ``By``, ``Bz`` (also ``mf.B``,
``magnetic_flux_density``, ``B [T]``, ... when only one candidate exists). The export's own
cells are kept when they are linear tetrahedra (or the corners of quadratic ones), or triangles
of a planar map; other cells are dropped and the interpolator falls back to a Delaunay
triangulation of the nodes.
"""

from __future__ import annotations

import re
import struct
import zlib
from pathlib import Path

import numpy as np

from ..errors import CfmInputError
from ..models.field import FieldMap
from ._atomic import atomic_path
from ._files import check_regular
from ._parse import (
    DELAUNAY_NOTE,
    Column,
    build_fieldmap,
    describe_column,
    option_hint,
    resolve_unit,
)

__all__ = ["read_meshfile", "write_meshfile", "meshio_format"]

#: Normalised point-data names taken as the flux density vector.
_VECTOR_NAMES = {"b", "bfield", "magneticfluxdensity", "fluxdensity"}
#: Extensions meshio would guess wrongly or that we read as text first.
_FORMAT_OF_SUFFIX = {".msh": "gmsh"}


def meshio_format(path, file_format=None) -> str:
    """meshio format name for ``path`` (``'vtu'``, ``'gmsh'``, ...), or a `CfmInputError`."""
    import meshio

    if file_format:
        return file_format
    suffix = Path(path).suffix.lower()
    if suffix in _FORMAT_OF_SUFFIX:
        return _FORMAT_OF_SUFFIX[suffix]
    formats = meshio.extension_to_filetypes.get(suffix)
    if not formats:
        known = ", ".join(sorted(meshio.extension_to_filetypes))
        raise CfmInputError(
            f"unknown mesh file extension '{suffix}'; expected one of {known}, or pass the "
            f"format: {option_hint('fmt')}",
            file=path,
        )
    return formats[0]


def read_meshfile(
    path, *, file_format=None, length_unit=None, field_unit=None, zero_rows="warn"
) -> FieldMap:
    """Read a field map from a mesh file.

    Parameters
    ----------
    path : path-like
    file_format : str, optional
        meshio format name; guessed from the extension otherwise.
    length_unit : str, optional
        Unit of the node coordinates. Mesh files carry none, so mm is assumed (and noted).
    field_unit : str, optional
        Unit of the field; taken from the point-data name (``B [T]``) if it has one, else T is
        assumed (and noted).
    zero_rows : {'warn', 'drop', 'keep'}
        What to do with nodes whose field is exactly 0 0 0 (``'drop'`` also drops their cells).

    Returns
    -------
    FieldMap
        ``points`` (n, 3) mm (2-D coordinates get z = 0), ``B`` (n, 3) T, ``cells`` (m, 4)
        tetrahedra, (m, 3) triangles of a planar map, or None; ``lines`` is None.
    """
    file = str(path)
    if Path(path).is_dir():
        raise CfmInputError("this is a folder; expected a field-map file", file=file)
    if not Path(path).exists():
        raise CfmInputError("cannot read the file: it does not exist", file=file)
    check_regular(path, "a field-map file")
    fmt = meshio_format(path, file_format)
    try:
        mesh = _meshio_read(path, fmt)
    except Exception as exc:  # meshio raises many types (ReadError, KeyError, struct.error, ...)
        raise CfmInputError(
            f"cannot read as a '{fmt}' mesh file: {library_reason(exc, fmt, path)}", file=file
        ) from None
    notes: list[str] = []
    points = np.asarray(mesh.points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] not in (2, 3) or len(points) == 0:
        raise CfmInputError(
            f"expected node coordinates of shape (n, 2) or (n, 3); found {points.shape}", file=file
        )
    if points.shape[1] == 2:
        points = np.column_stack([points, np.zeros(len(points))])
        notes.append("2-D node coordinates: z = 0 at every node")
    B, used, field_notes = _flux_density(mesh.point_data, len(points), file)
    notes += field_notes
    mm, unit_notes = resolve_unit(
        "length",
        [Column("node coordinates", 0, None, None, None, None)],
        option=length_unit,
        fallback=None,
        assumed=(
            "mm",
            f"mesh files carry no length unit; if not mm, pass {option_hint('length_unit')}",
        ),
        file=file,
        line=None,
    )
    notes += unit_notes
    field_columns = [describe_column(name, 0, None) for name in used]
    tesla, unit_notes = resolve_unit(
        "field",
        field_columns,
        option=field_unit,
        fallback=None,
        assumed=(
            "T",
            f"the point data name gives no unit; if not T, pass {option_hint('field_unit')}",
        ),
        file=file,
        line=None,
    )
    notes += unit_notes
    points = points * mm
    cells = _usable_cells(mesh.cells, points, notes)
    return build_fieldmap(
        points,
        B * tesla,
        source=file,
        lines=None,
        notes=notes,
        columns=("x", "y", "z", *_component_names(used)),
        cells=cells,
        zero_rows=zero_rows,
    )


#: meshio's (and numpy's) messages for broken files, and what each means for the user: the
#: pattern, then the reason given (``{0}``, ``{1}``: the pattern's groups).
_LIBRARY_REASONS = [
    (r"need at least one array to concatenate",
     "the file holds no nodes or no data arrays (NumberOfPoints 0, or no Piece)"),
    (r"cannot reshape array of size (\d+) into shape \((\d+),?\s*(\d*)\)",
     "a data array holds {0} values where the file's counts ask for {1} x {2} (a count "
     "the file states, such as NumberOfPoints, POINTS or NumberOfCells, disagrees with its "
     "data)"),
    (r"index (-?\d+) is out of bounds for axis \d+ with size (\d+)",
     "a cell or tag refers to entry {0} (counted from 0) of a list of {1}: a node or element "
     "number outside the file's nodes"),
    (r"No module named '([\w.]+)'",
     "reading this format needs the Python package '{0}' (pip install {0})"),
    (r"no element found|not well-formed|mismatched tag|unclosed token|junk after document",
     "the XML is not well-formed ({msg})"),
]  # fmt: skip


def library_reason(exc: BaseException, fmt: str, path) -> str:
    """What a reading library's exception ``exc`` means, as a reason and what was expected.

    meshio passes on numpy's and its parsers' messages ("need at least one array to
    concatenate", "cannot reshape array of size 1029 into shape (999,3)", "'Version'"), which
    name neither the damage nor the fix; each known one is translated (`_LIBRARY_REASONS`), an
    unknown one kept with its type. The text ends with what a readable file holds.

    Parameters
    ----------
    exc : BaseException
    fmt : str
        The format tried (``'vtu'``, ``'gmsh'``).
    path : path-like
        The file (its size tells an empty file from a damaged one).

    Returns
    -------
    str
        One line.
    """
    msg = " ".join(str(exc).split())  # one line: library messages may hold line feeds
    expected = f"; expected a complete {fmt} file with nodes, cells and point data B"
    for pattern, reason in _LIBRARY_REASONS:
        m = re.search(pattern, msg)
        if m:
            groups = [g or "1" for g in m.groups()]
            missing_package = pattern.startswith("No module")
            return reason.format(*groups, msg=msg) + ("" if missing_package else expected)
    if isinstance(exc, KeyError):
        return f"the entry {msg} that {fmt} files must hold is missing" + expected
    if isinstance(exc, (EOFError, struct.error, zlib.error, UnicodeDecodeError)):
        return f"the file is cut short or damaged ({type(exc).__name__}: {msg})" + expected
    if not msg:  # meshio's ReadError() on an empty or cut-off file says nothing
        try:
            empty = Path(path).stat().st_size == 0
        except OSError:
            empty = False
        if empty:
            return "the file is empty" + expected
        return f"{type(exc).__name__} with no reason given; is the file cut short?" + expected
    return f"{msg} ({type(exc).__name__})" + expected


def _meshio_read(path, fmt):
    """meshio's reader for ``fmt``, called directly: ``meshio.read`` prints and calls
    ``sys.exit(1)`` when the file is broken."""
    import meshio

    module = getattr(meshio, fmt.split("-")[0].removesuffix("22"), None)
    if module is not None and hasattr(module, "read"):
        return module.read(str(path))
    try:
        return meshio.read(path, file_format=fmt)
    except SystemExit:
        raise meshio.ReadError(f"meshio could not read it as {fmt}") from None


def _flux_density(point_data, n, file):
    """(B (n, 3) in the file's unit, names used, notes) from meshio point data."""
    vectors = []
    components: dict[str, list[str]] = {"Bx": [], "By": [], "Bz": []}
    for name, values in point_data.items():
        arr = np.asarray(values)
        column = describe_column(name, 0, None)
        if column.key in _VECTOR_NAMES and arr.ndim == 2 and arr.shape[1] in (2, 3):
            vectors.append(name)
        elif column.role in components and (arr.ndim == 1 or arr.shape[1:] == (1,)):
            components[column.role].append(name)
    found = ", ".join(f"'{k}'" for k in point_data) or "no point data"
    notes = []
    if len(vectors) > 1:
        raise CfmInputError(
            f"several point data could be the flux density: {', '.join(map(repr, vectors))}; "
            f"expected exactly one (rename the others)",
            file=file,
        )
    if vectors:
        arr = np.asarray(point_data[vectors[0]], dtype=np.float64)
        if arr.shape[1] == 2:
            arr = np.column_stack([arr, np.zeros(n)])
            notes.append(f"point data '{vectors[0]}' has 2 components: Bz = 0 at every node")
        if all(len(v) == 1 for v in components.values()):
            notes.append(_vector_and_components(point_data, vectors[0], components, arr, file))
        return arr, vectors, notes
    if all(len(v) == 1 for v in components.values()):
        used = [components[c][0] for c in ("Bx", "By", "Bz")]
        arr = np.column_stack([np.asarray(point_data[u], dtype=np.float64).ravel() for u in used])
        return arr, used, notes
    raise CfmInputError(
        f"no unambiguous flux density in the point data: expected 'B' (3 components) or "
        f"'Bx', 'By', 'Bz'; found {found}",
        file=file,
    )


def _vector_and_components(point_data, vector, components, arr, file) -> str:
    """Both a vector ``B`` and components ``Bx, By, Bz``: the note when they agree (to 1e-9 of
    the largest |B|, rounding of a float32 copy included: 1e-6), else a `CfmInputError`."""
    names = [components[c][0] for c in ("Bx", "By", "Bz")]
    comp = np.column_stack([np.asarray(point_data[c], dtype=np.float64).ravel() for c in names])
    scale = max(float(np.nanmax(np.abs(arr))) if arr.size else 0.0, 1e-300)
    with np.errstate(invalid="ignore"):
        diff = np.abs(comp - arr)
    if (
        comp.shape == arr.shape
        and not (diff > 1e-6 * scale).any()
        and np.array_equal(np.isnan(comp), np.isnan(arr))
    ):
        return f"point data '{vector}' used; {', '.join(names)} agree with it"
    node, k = np.unravel_index(int(np.nanargmax(np.where(np.isnan(diff), np.inf, diff))),
                               diff.shape) if comp.shape == arr.shape else (0, 0)  # fmt: skip
    raise CfmInputError(
        f"point data '{vector}' and {', '.join(repr(c) for c in names)} disagree (node "
        f"{node}: {'xyz'[k]} component {arr[node, k]:.6g} in '{vector}', {comp[node, k]:.6g} in "
        f"'{names[k]}'); expected one flux density: remove or rename the other arrays",
        file=file,
    )


def _component_names(used):
    if len(used) == 3:
        return tuple(used)
    return tuple(f"{used[0]}[{k}]" for k in range(3))


def _usable_cells(blocks, points, notes):
    """Tetrahedra (m, 4), triangles (m, 3) of a planar map, or None; notes say which and why."""
    by_dim: dict[int, list] = {}
    for block in blocks:
        by_dim.setdefault(int(block.dim), []).append(block)
    for dim, corners, kind in ((3, 4, "tetra"), (2, 3, "triangle")):
        if dim not in by_dim:
            continue
        types = sorted({b.type for b in by_dim[dim]})
        if any(not t.startswith(kind) for t in types):
            notes.append(f"cells of type {', '.join(types)} are not used: {DELAUNAY_NOTE}")
            return None
        if dim == 2:
            plane = _constant_axis(points)
            if plane is None:
                notes.append(f"triangles of a non-planar surface are not used: {DELAUNAY_NOTE}")
                return None
            notes.append(f"planar map in the plane {plane}")
        cells = np.concatenate([np.asarray(b.data)[:, :corners] for b in by_dim[dim]])
        higher = [t for t in types if t != kind]
        if higher:
            notes.append(f"{', '.join(higher)} cells: only their {corners} corner nodes are used")
        return cells.astype(np.int64)
    notes.append(f"no volume cells: {DELAUNAY_NOTE}")
    return None


def _constant_axis(points):
    extent = np.ptp(points, axis=0)
    tol = 1e-9 * max(float(extent.max()), 1.0)
    for k in (2, 0, 1):
        if extent[k] <= tol:
            return f"{'xyz'[k]} = {float(points[0, k])!r} mm"
    return None


def write_meshfile(path, fieldmap: FieldMap, file_format=None) -> None:
    """Write ``fieldmap`` with meshio (atomically): point data ``B`` (n, 3) in T, points in mm.

    Cells are written as ``tetra`` or ``triangle`` when the map has them, otherwise one
    ``vertex`` cell per node. XDMF is written with inline XML data (no ``.h5`` side file, which
    would not survive the atomic rename).
    """
    import meshio

    fmt = meshio_format(path, file_format)
    n = fieldmap.n_nodes
    if fieldmap.cells is None:
        cells = [("vertex", np.arange(n, dtype=np.int64).reshape(-1, 1))]
    else:
        kind = "tetra" if fieldmap.cells.shape[1] == 4 else "triangle"
        cells = [(kind, fieldmap.cells)]
    mesh = meshio.Mesh(fieldmap.points, cells, point_data={"B": fieldmap.B})
    kwargs = {"data_format": "XML"} if fmt == "xdmf" else {}
    try:
        with atomic_path(path) as tmp:
            meshio.write(tmp, mesh, file_format=fmt, **kwargs)
    except ModuleNotFoundError as exc:  # meshio's XDMF writer needs h5py even for XML data
        raise CfmInputError(
            f"writing '{fmt}' needs the Python package '{exc.name}' (pip install {exc.name}); "
            f"or write .vtu instead",
            file=path,
        ) from None
