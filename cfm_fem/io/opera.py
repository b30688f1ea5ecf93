"""Opera-3D ``.table`` files: point counts, one line per column, a line ``0``, then the data.

Layout::

     41 11 21 2              <- point counts (any order) and a trailing flag (ignored)
     1 X [METRE]             <- <index> <NAME> [<UNIT>], one line per column
     2 Y [METRE]
     ...
     6 BZ [TESLA]
     0                       <- end of header
     -0.2 -0.05 -0.2 -8.2e-06 1.3e-05 -8.2e-06
"""

from __future__ import annotations

import re
import warnings

import numpy as np

from ..errors import CfmInputError, CfmInputWarning
from ..models.field import FieldMap
from ._parse import (
    KNOWN_UNITS,
    data_rows,
    describe_column,
    read_lines,
    table_fieldmap,
    unterminated,
    write_rows,
)

__all__ = ["read_opera", "write_opera", "looks_like_opera"]

_DEFINITION = re.compile(r"^\s*(?P<index>\d+)\s+(?P<rest>\S.*?)\s*$")
_BRACKET_UNIT = re.compile(r"^(?P<name>.+?)\s*\[(?P<unit>[^\]]*)\]$")


def looks_like_opera(lines) -> bool:
    """True for the Opera layout: integer counts, then ``1 <NAME> ...``, ..., then a line ``0``."""
    text = [s for s in lines[:200] if s.strip()]
    if len(text) < 3 or not all(t.isdigit() for t in text[0].split()):
        return False
    return (
        _DEFINITION.match(text[1]) is not None
        and text[1].split()[0] == "1"
        and any(s.strip() == "0" for s in text[2:])
    )


def read_opera(path, *, length_unit=None, field_unit=None, zero_rows="warn") -> FieldMap:
    """Read an Opera-3D ``.table`` field map.

    Parameters
    ----------
    path : path-like
    length_unit, field_unit : str, optional
        Units for columns defined without one (``1 X`` instead of ``1 X [METRE]``); they
        override the file's units otherwise (with a `CfmInputWarning`).
    zero_rows : {'warn', 'drop', 'keep'}
        What to do with rows whose field is exactly 0 0 0.

    Returns
    -------
    FieldMap
        ``points`` (n, 3) mm, ``B`` (n, 3) T. Units METRE/M/CM/MM and TESLA/GAUSS in any case;
        extra columns (a magnitude ``B``, a potential, ...) are ignored. When the counts on
        line 1 differ from the numbers of distinct x, y, z values (compared as a multiset, since
        exports list them in different orders) a `CfmInputWarning` is issued.
    """
    file = str(path)
    lines = read_lines(path)
    first = next(i for i, s in enumerate(lines) if s.strip())
    counts = _point_counts(lines[first], file, first + 1)
    columns = []
    i = first + 1
    while True:
        if i >= len(lines):
            raise CfmInputError(
                f"the header never ends: expected a line '0' after the {len(columns)} column "
                f"definition(s) ('<index> <NAME> [<UNIT>]')",
                file=file,
                line=max(k + 1 for k, s in enumerate(lines) if s.strip()),
            )
        text = lines[i].strip()
        i += 1
        if not text:
            continue
        if text == "0":
            break
        columns.append(_definition(text, len(columns) + 1, file, i))
    if not columns:
        raise CfmInputError(
            "no column definitions ('<index> <NAME> [<UNIT>]') before the line '0'",
            file=file,
            line=i,
        )
    rows, row_lines = data_rows(lines, i)
    return table_fieldmap(
        columns,
        rows,
        row_lines,
        delimiter=None,
        file=file,
        header_line=columns[0].line,
        length_unit=length_unit,
        field_unit=field_unit,
        zero_rows=zero_rows,
        check_points=lambda points: _check_counts(counts, points, file, first + 1),
        cut=unterminated(lines, row_lines),
    )


def _point_counts(text, file, line) -> list[int]:
    tokens = text.split()
    if len(tokens) < 2 or not all(t.isascii() and t.isdigit() and len(t) < 19 for t in tokens):
        raise CfmInputError(
            f"line 1 of an Opera table must hold the point counts and a trailing flag "
            f"(e.g. '41 11 21 2'); found '{text.strip()}'",
            file=file,
            line=line,
        )
    return [int(t) for t in tokens[:-1]]


def _definition(text, expected_index, file, line):
    m = _DEFINITION.match(text)
    if m is None or int(m["index"]) != expected_index:
        raise CfmInputError(
            f"expected column definition '{expected_index} <NAME> [<UNIT>]' or the line '0' "
            f"ending the header; found '{text}'",
            file=file,
            line=line,
        )
    rest = m["rest"]
    unit = None
    bracketed = _BRACKET_UNIT.match(rest)
    words = rest.split()
    if bracketed:
        rest, unit = bracketed["name"], bracketed["unit"].strip()
    elif len(words) == 2 and words[1].lower() in KNOWN_UNITS:
        rest, unit = words  # "4 BX TESLA"
    return describe_column(rest, expected_index - 1, line, unit=unit)


def _check_counts(counts, points, file, line) -> list[str]:
    refuse_missing_rows(counts, len(points), file, line)
    distinct = [int(np.unique(points[:, k]).size) for k in range(3)]
    msg = count_mismatch(counts, distinct, len(points), file, line)
    if msg is None:
        return []
    warnings.warn(msg, CfmInputWarning, stacklevel=4)
    return [msg]


def refuse_missing_rows(counts, n_rows, file, line) -> None:
    """Refuse a table with fewer data rows than the point counts of line 1 make.

    Rows missing from an Opera grid are a file cut short (a copy or an export that stopped):
    the rows present would be used as if they were the map, without the part cut off. More
    rows than the counts, or counts that do not match the distinct values, stay a warning
    (`count_mismatch`).

    Raises
    ------
    CfmInputError
        Naming line 1, the rows expected and the rows found.
    """
    expected = int(np.prod(counts, dtype=object))
    if n_rows < expected:
        raise CfmInputError(
            f"the point counts {counts} make {expected} rows but only {n_rows} data rows follow "
            f"({expected - n_rows} missing): the file looks cut short; expected the complete "
            "table (or point counts that match its rows)",
            file=file,
            line=line,
        )


def count_mismatch(counts, distinct, n_rows, file, line) -> str | None:
    """The message for point counts on line 1 that the data do not match, or None.

    Both the numbers of distinct x, y, z values and the number of rows are compared: a file cut
    short in its last plane still has every distinct value, so only the row count shows the cut.
    Like COMSOL's ``% Nodes`` check this is a warning, not an error (the rows present are
    valid nodes, and maps with missing grid points are used elsewhere too), but it says plainly
    that rows are missing.

    Parameters
    ----------
    counts : list of int
        Point counts of line 1.
    distinct : sequence of 3 (int or None)
        Numbers of distinct x, y, z values (None: too many to count).
    n_rows : int
        Number of data rows.
    """
    expected = int(np.prod(counts, dtype=object))
    if n_rows != expected:
        cut = "the file looks cut short; " if n_rows < expected else ""
        return (
            f"{file}:{line}: the point counts {counts} do not match the {n_rows} data rows: "
            f"they make {expected} rows ({abs(expected - n_rows)} "
            f"{'missing' if n_rows < expected else 'too many'}); {cut}the {n_rows} rows are used"
        )
    if all(d is not None for d in distinct) and sorted(c for c in counts if c != 1) == sorted(
        c for c in distinct if c != 1
    ):
        return None
    shown = " x ".join("many" if d is None else str(d) for d in distinct)
    return (
        f"{file}:{line}: the point counts {counts} do not match the data, which hold "
        f"{shown} distinct x, y, z values; the data are used as they are"
    )


def write_opera(path, fieldmap: FieldMap) -> None:
    """Write ``fieldmap`` as an Opera-3D ``.table`` in metres and tesla (atomically).

    The nodes must form a full rectilinear grid (every combination of the distinct x, y and z
    values present once). Rows run with z fastest, then y, then x; line 1 lists the counts in
    that order (nz ny nx 2) like Opera's own exports.

    Raises
    ------
    CfmInputError
        The nodes are not a full rectilinear grid.
    """
    x, y, z = fieldmap.points.T
    nx, ny, nz = (int(np.unique(c).size) for c in (x, y, z))
    if nx * ny * nz != fieldmap.n_nodes:
        raise CfmInputError(
            f"an Opera .table needs nodes on a full rectilinear grid; this map has "
            f"{fieldmap.n_nodes} nodes but {nx} x {ny} x {nz} distinct x, y, z values "
            f"(= {nx * ny * nz}); write CSV, COMSOL text or VTU instead",
            file=path,
        )
    order = np.lexsort((z, y, x))
    header = [
        f" {nz} {ny} {nx} 2",
        " 1 X [METRE]",
        " 2 Y [METRE]",
        " 3 Z [METRE]",
        " 4 BX [TESLA]",
        " 5 BY [TESLA]",
        " 6 BZ [TESLA]",
        " 0",
    ]
    values = np.hstack([fieldmap.points[order] / 1000.0, fieldmap.B[order]])
    write_rows(path, header, values, sep=" ", width=24)
