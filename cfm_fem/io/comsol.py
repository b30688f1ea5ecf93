"""COMSOL text export: ``%`` header lines, then one row of numbers per node.

Layout read::

    % Model:              magnet.mph
    % Dimension:          3
    % Nodes:              7840
    % Length unit:        mm
    % X       Y       Z       mf.Bx (T)      mf.By (T)      mf.Bz (T)
    -15       -15     -315    0.0012         -0.3           0.0001
    ...

The column line is the last ``%`` line that is not a ``Key: value`` line. Data may be separated by
blanks (COMSOL "text") or commas (COMSOL "spreadsheet" CSV). A "Sectionwise" export (a
``% Coordinates`` line, then ``% Elements (...)`` and ``% Data (...)`` blocks) is read by
`cfm_fem.io.comsol_sections`, with its tetrahedra as the map's cells.
"""

from __future__ import annotations

import re
import warnings
from pathlib import Path

import numpy as np

from ..errors import CfmInputError, CfmInputWarning
from ..models.field import FieldMap
from ._parse import (
    data_rows,
    detect_delimiter,
    header_names,
    read_lines,
    table_fieldmap,
    unterminated,
    write_rows,
)
from .comsol_sections import is_coordinates_line, read_sections, solution_columns

__all__ = ["read_comsol", "write_comsol", "looks_like_comsol"]

_META = re.compile(r"^(?P<key>[A-Za-z][A-Za-z ]{0,30}):\s*(?P<value>.*)$")


def looks_like_comsol(lines) -> bool:
    """True if the first non-blank line is a ``%`` header line."""
    first = next((s.lstrip() for s in lines if s.strip()), "")
    return first.startswith("%")


def read_comsol(
    path, *, length_unit=None, field_unit=None, zero_rows="warn", solution=None
) -> FieldMap:
    """Read a COMSOL text (or spreadsheet CSV) export.

    Parameters
    ----------
    path : path-like
    length_unit : str, optional
        Unit of X, Y, Z; overrides ``% Length unit`` (with a warning if they differ).
        Needed when the file has no ``% Length unit`` line.
    field_unit : str, optional
        Unit of the field columns; needed when their names carry none (``mf.Bx`` instead of
        ``mf.Bx (T)``), overrides them otherwise.
    zero_rows : {'warn', 'drop', 'keep'}
        What to do with rows whose field is exactly 0 0 0 (placeholders in some exports).
    solution : str, optional
        Which solution of a parametric or time-dependent export to read, by its tag as the
        column names write it after ``@`` (``'I0=200'``, ``'@ I0=200'``, ``'t=0.1'``; blanks
        around ``=`` and ``,`` do not matter, the values are compared as text). Needed when the
        export holds several; checked against the tag when it holds one.

    Returns
    -------
    FieldMap
        ``points`` (n, 3) mm, ``B`` (n, 3) T. Columns are mapped by name (``mf.Bx (T)``,
        ``mfnc.BZ (kG)``, any order, any case). A 2-D export (``% Dimension: 2``, columns X Y)
        gets z = 0, and Bz = 0 if it has no Bz column. A ``% Nodes`` count that differs from the
        rows is a `CfmInputWarning`, not an error.
    """
    file = str(path)
    lines = read_lines(path)
    meta: dict[str, tuple[str, int]] = {}
    column_line = None
    start = 0
    while start < len(lines) and (not lines[start].strip() or lines[start].lstrip()[0] == "%"):
        body = lines[start].strip()[1:].strip()
        m = _META.match(body)
        if m:
            meta[m["key"].strip().lower()] = (m["value"].strip(), start + 1)
        elif body:
            column_line = (body, start + 1)
        start += 1
    notes = []
    dimension = _int_or_none(meta.get("dimension", ("", 0))[0])
    length_fallback = None
    if "length unit" in meta:
        unit, line = meta["length unit"]
        length_fallback = (unit, f"from '% Length unit' on line {line}", line)
    shared = dict(  # both layouts: units, placeholder rows and the '% Nodes' count
        file=file,
        length_unit=length_unit,
        field_unit=field_unit,
        zero_rows=zero_rows,
        length_fallback=length_fallback,
        check_points=lambda points: _check_nodes(meta.get("nodes"), len(points), file),
    )
    if column_line is not None and is_coordinates_line(column_line[0]):
        return read_sections(
            lines, column_line[1] - 1, dimension=dimension, solution=solution, **shared
        )
    rows, row_lines = data_rows(lines, start)
    if column_line is None:
        raise CfmInputError(
            "no column line such as '% X Y Z mf.Bx (T) mf.By (T) mf.Bz (T)' in the '%' header; "
            "expected one before the data",
            file=file,
            line=start + 1 if start < len(lines) else None,
        )
    text, header_line = column_line
    delimiter = detect_delimiter(text, rows[0] if rows else None)
    names = header_names(text, delimiter)
    columns = solution_columns(names, [header_line] * len(names), file, notes, solution)
    optional = ("z", "Bz") if dimension == 2 else ()
    if dimension == 2:
        notes.append("2-D export ('% Dimension: 2')")
    return table_fieldmap(
        columns,
        rows,
        row_lines,
        delimiter=delimiter,
        header_line=header_line,
        optional=optional,
        notes=notes,
        cut=unterminated(lines, row_lines),
        **shared,
    )


def _int_or_none(text):
    try:
        return int(text.split()[0])
    except (ValueError, IndexError):
        return None


def _check_nodes(nodes, n_rows, file) -> list[str]:
    """Warn (once the data parsed) if ``% Nodes`` differs from the number of rows."""
    if nodes is None:
        return []
    value, line = nodes
    expected = _int_or_none(value)
    if expected is None or expected == n_rows:
        return []
    msg = (
        f"{file}:{line}: header says '% Nodes: {value}' but {n_rows} data rows follow; "
        f"the {n_rows} rows are used"
    )
    warnings.warn(msg, CfmInputWarning, stacklevel=4)
    return [msg]


def write_comsol(path, fieldmap: FieldMap) -> None:
    """Write ``fieldmap`` as a COMSOL text export in mm and T (atomically).

    Header: ``% Model``, ``% Version``, ``% Dimension: 3``, ``% Nodes``, ``% Expressions``,
    ``% Description``, ``% Length unit: mm``, then ``% X Y Z mf.Bx (T) mf.By (T) mf.Bz (T)``.
    Numbers are written exactly (shortest round-trip text).
    """
    from .. import __version__

    width = 26
    names = ["X", "Y", "Z", "mf.Bx (T)", "mf.By (T)", "mf.Bz (T)"]
    header = [
        f"% Model:              {Path(fieldmap.source).name}",
        f"% Version:            cfm_fem {__version__}",
        "% Dimension:          3",
        f"% Nodes:              {fieldmap.n_nodes}",
        "% Expressions:        3",
        "% Description:        Magnetic flux density, x component, Magnetic flux density, "
        "y component, Magnetic flux density, z component",
        "% Length unit:        mm",
        "% " + "".join(name.ljust(width) for name in names).rstrip(),
    ]
    values = np.hstack([fieldmap.points, fieldmap.B])
    write_rows(path, header, values, sep=" ", width=width - 1)
