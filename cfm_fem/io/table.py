"""Plain tables: one header row of column names, then one row of numbers per node.

Comma-, semicolon- or tab-separated (CSV quoting rules) or blank-separated; ``#`` comment lines
anywhere. Units go in the column names (``x [mm]``, ``x (in)``, ``Bx [T]``, ``Bx_mT``,
``X [inch]``) or in the ``length_unit`` / ``field_unit`` options.
"""

from __future__ import annotations

import numpy as np

from ..errors import CfmInputError
from ..models.field import FieldMap
from ._parse import (
    data_rows,
    describe_column,
    detect_delimiter,
    header_names,
    read_lines,
    table_fieldmap,
    unterminated,
    write_rows,
)

__all__ = ["read_table", "write_table", "CSV_HEADER"]

#: Header row written by `write_table`.
CSV_HEADER = "x [mm],y [mm],z [mm],Bx [T],By [T],Bz [T]"


def read_table(path, *, length_unit=None, field_unit=None, zero_rows="warn") -> FieldMap:
    """Read a table with a header row.

    Parameters
    ----------
    path : path-like
    length_unit, field_unit : str, optional
        Units of the coordinate and field columns when the names carry none; when they do, the
        option overrides them with a `CfmInputWarning`.
    zero_rows : {'warn', 'drop', 'keep'}
        What to do with rows whose field is exactly 0 0 0.

    Returns
    -------
    FieldMap
        ``points`` (n, 3) mm and ``B`` (n, 3) T. Columns are found by name in any order; extra
        columns are ignored (they must still be present in every row). A quoted number with
        thousands separators (``"1,066.67"``) is read as 1066.67. A leading ``%`` on the header
        row is ignored.

    Raises
    ------
    CfmInputError
        No header or no data rows, a missing x/y/z/Bx/By/Bz column (the message lists the columns
        found), no unit or mixed units for x, y, z (or Bx, By, Bz), a short row, a field that is
        not a number, NaN or inf.
    """
    file = str(path)
    lines = read_lines(path)
    header_index = next(
        (i for i, s in enumerate(lines) if s.strip() and s.lstrip()[0] != "#"), None
    )
    if header_index is None:
        raise CfmInputError(
            f"the file holds only comment lines; expected a header row such as '{CSV_HEADER}'",
            file=file,
        )
    text = lines[header_index].strip().removeprefix("%").strip()
    rows, row_lines = data_rows(lines, header_index + 1)
    if _is_numeric_row(text):
        raise CfmInputError(
            f"the first row holds numbers, not column names; expected a header row such as "
            f"'{CSV_HEADER}'",
            file=file,
            line=header_index + 1,
        )
    delimiter = detect_delimiter(text, rows[0] if rows else None)
    columns = [
        describe_column(name, k, header_index + 1)
        for k, name in enumerate(header_names(text, delimiter))
    ]
    return table_fieldmap(
        columns,
        rows,
        row_lines,
        delimiter=delimiter,
        file=file,
        header_line=header_index + 1,
        length_unit=length_unit,
        field_unit=field_unit,
        zero_rows=zero_rows,
        cut=unterminated(lines, row_lines),
    )


def _is_numeric_row(text: str) -> bool:
    fields = text.replace(",", " ").replace(";", " ").split()
    try:
        [float(f) for f in fields]
    except ValueError:
        return False
    return True


def write_table(path, fieldmap: FieldMap) -> None:
    """Write ``fieldmap`` as CSV with header ``x [mm],y [mm],z [mm],Bx [T],By [T],Bz [T]``.

    Atomic; numbers are the shortest text that reads back to the same float64.
    """
    write_rows(path, [CSV_HEADER], np.hstack([fieldmap.points, fieldmap.B]), sep=",")
