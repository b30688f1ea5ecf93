"""Every file format in and out. Nothing else in cfm_fem opens files.

Field maps: `read_field` / `write_field` pick the format; the per-format readers and writers are
exported too. Every reader returns a `FieldMap` in mm and T, converted once, here.

========  =====================================  ===============================
fmt       files                                  module
========  =====================================  ===============================
comsol    COMSOL text, spreadsheet, sectionwise  :mod:`cfm_fem.io.comsol`
opera     Opera-3D ``.table``                    :mod:`cfm_fem.io.opera`
table     CSV or blank-separated, header row     :mod:`cfm_fem.io.table`
meshio    VTU, VTK, Gmsh ``.msh``, XDMF, ...     :mod:`cfm_fem.io.meshfile`
========  =====================================  ===============================
"""

from __future__ import annotations

import os
from pathlib import Path

from ..errors import CfmInputError
from ..models.field import FieldMap
from ._files import check_regular
from ._parse import check_zero_rows, option_hint, read_lines
from .comsol import looks_like_comsol, read_comsol, write_comsol
from .meshfile import meshio_format, read_meshfile, write_meshfile
from .opera import looks_like_opera, read_opera, write_opera
from .table import read_table, write_table

__all__ = [
    "read_field",
    "write_field",
    "detect_format",
    "check_solution",
    "read_comsol",
    "write_comsol",
    "read_opera",
    "write_opera",
    "read_table",
    "write_table",
    "read_meshfile",
    "write_meshfile",
]

_TEXT_READERS = {"comsol": read_comsol, "opera": read_opera, "table": read_table}
_TEXT_WRITERS = {"comsol": write_comsol, "opera": write_opera, "table": write_table}
_ALIASES = {"csv": "table", "mesh": "meshio", "txt": "comsol"}
#: Extensions whose content decides between COMSOL, Opera and a plain table.
_SNIFFED = {".txt", ".dat", ".csv", ".tsv"}
_TECPLOT_START = ("title", "variables", "zone")


def detect_format(path) -> str:
    """Format of a field-map file for reading: ``'comsol'``, ``'opera'``, ``'table'`` or a meshio
    format name (``'vtu'``, ``'gmsh'``, ...).

    ``.table`` is Opera; ``.txt``, ``.dat``, ``.csv``, ``.tsv`` are decided by content: ``%``
    header lines mean COMSOL, the Opera header (counts, ``1 <NAME> [<UNIT>]`` lines, a line
    ``0``) means Opera, a Tecplot header (``.dat``) goes to meshio, anything else is a table.
    Other extensions go to meshio.
    """
    if os.fspath(path) in ("", b""):  # Path("") is the current folder
        raise CfmInputError("an empty file name; expected a field-map file", file=path)
    if Path(path).is_dir():  # else "unknown mesh file extension ''" for a folder
        raise CfmInputError("this is a folder; expected a field-map file", file=path)
    if not Path(path).exists():  # before the extension: a typo'd name has the wrong one
        raise CfmInputError("cannot read the file: it does not exist", file=path)
    check_regular(path, "a field-map file")
    suffix = Path(path).suffix.lower()
    if suffix == ".table":
        return "opera"
    if suffix not in _SNIFFED:
        return meshio_format(path)
    lines = read_lines(path, max_bytes=1 << 16)
    if looks_like_comsol(lines):
        return "comsol"
    if looks_like_opera(lines):
        return "opera"
    first = next(s.strip().lower() for s in lines if s.strip())
    if suffix == ".dat" and first.startswith(_TECPLOT_START):
        return "tecplot"
    return "table"


def read_field(
    path, *, fmt=None, length_unit=None, field_unit=None, zero_rows="warn", solution=None
) -> FieldMap:
    """Read a field map from any supported file.

    Parameters
    ----------
    path : path-like
    fmt : str, optional
        ``'comsol'``, ``'opera'``, ``'table'`` (or ``'csv'``), ``'meshio'`` or a meshio format name
        (``'vtu'``, ``'gmsh'``, ``'xdmf'``, ...); by default from `detect_format`.
    length_unit : str, optional
        Unit of the coordinates when the file does not say (``'mm'``, ``'m'``, ``'in'``, ...);
        overrides the file (with a `CfmInputWarning`) when it does. Mesh files default to mm.
    field_unit : str, optional
        Unit of the field (``'T'``, ``'mT'``, ``'G'``, ``'kG'``, ...), likewise.
    zero_rows : {'warn', 'drop', 'keep'}
        Rows whose field is exactly 0 0 0 (placeholders in some measured maps): keep with a
        warning, drop, or keep silently. Each case leaves a note with the count.
    solution : str, optional
        COMSOL exports of a parametric or time-dependent study hold one column (or ``% Data``
        block) per component and solution, named like ``mf.Bx (T) @ I0=200``: the solution to
        read, by its tag (``'I0=200'``, ``'@ I0=200'``, ``'t=0.1'``). Compared as text after
        dropping a leading ``@`` and the blanks around ``=`` and ``,`` (``'I0 = 200'`` matches
        ``@ I0=200``; ``'I0=2e2'`` does not). Needed when the export holds several solutions,
        checked against the tag when it holds one; refused for other formats.

    Returns
    -------
    FieldMap
        ``points`` (n, 3) mm, ``B`` (n, 3) T, ``cells`` or None, ``lines`` (text formats),
        ``notes`` (every unit assumption and anything dropped or suspicious).

    Raises
    ------
    CfmInputError
        One message naming file, line, column and what was expected.
    """
    check_zero_rows(zero_rows)
    kind = _checked_fmt(fmt) if fmt else detect_format(path)
    options = {"length_unit": length_unit, "field_unit": field_unit, "zero_rows": zero_rows}
    check_solution(path, kind, solution)
    if kind == "comsol":
        return read_comsol(path, solution=solution, **options)
    if kind in _TEXT_READERS:
        return _TEXT_READERS[kind](path, **options)
    file_format = None if kind == "meshio" else kind
    return read_meshfile(path, file_format=file_format, **options)


def check_solution(path, kind: str, solution) -> None:
    """Refuse ``solution`` for a file read as format ``kind`` other than COMSOL (the readers of
    the other formats, the streaming ones too, have no solution tags)."""
    if solution is None or kind == "comsol":
        return
    what = {"opera": "an Opera table", "table": "a table (CSV or blank-separated)"}.get(
        kind, f"a mesh file ({kind})"
    )
    raise CfmInputError(
        f"{option_hint('solution', solution)} applies to COMSOL exports only (the solutions of a "
        f"parametric or time-dependent study); this file is read as {what}",
        file=path,
    )


def write_field(path, fieldmap: FieldMap, fmt=None) -> None:
    """Write a field map (atomically), in mm and T except Opera (metre, tesla).

    Parameters
    ----------
    path : path-like
    fieldmap : FieldMap
    fmt : str, optional
        ``'comsol'``, ``'opera'``, ``'table'`` (or ``'csv'``), ``'meshio'`` or a meshio format
        name. By default from the extension: ``.csv`` table, ``.table`` Opera, ``.txt`` and
        ``.dat`` COMSOL text, anything else meshio (``.vtu``, ``.vtk``, ``.msh``, ``.xdmf``, ...).

    Raises
    ------
    CfmInputError
        Unknown extension or format, or an Opera table asked for nodes that are not a full grid.
    """
    kind = _checked_fmt(fmt) if fmt else _format_for_writing(path)
    if kind in _TEXT_WRITERS:
        _TEXT_WRITERS[kind](path, fieldmap)
        return
    write_meshfile(path, fieldmap, file_format=None if kind == "meshio" else kind)


def _checked_fmt(fmt: str) -> str:
    import meshio

    kind = _ALIASES.get(fmt.lower(), fmt.lower())
    mesh_formats = {f for fs in meshio.extension_to_filetypes.values() for f in fs} | {"gmsh22"}
    if kind in _TEXT_READERS or kind == "meshio" or kind in mesh_formats:
        return kind
    known = ", ".join([*_TEXT_READERS, "csv", "meshio", *sorted(mesh_formats)])
    raise CfmInputError(f"unknown format {option_hint('fmt', fmt)}; expected one of {known}")


def _format_for_writing(path) -> str:
    suffix = Path(path).suffix.lower()
    by_suffix = {".csv": "table", ".table": "opera", ".txt": "comsol", ".dat": "comsol"}
    if suffix in by_suffix:
        return by_suffix[suffix]
    try:
        return meshio_format(path)
    except CfmInputError:
        raise CfmInputError(
            f"cannot tell the format from the extension '{suffix}'; use .csv, .txt (COMSOL), "
            f".table (Opera), .vtu, .vtk, .msh, .xdmf, or pass fmt=",
            file=path,
        ) from None
