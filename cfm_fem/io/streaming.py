"""Streaming readers of plain tables and Opera ``.table`` maps: a file read in blocks of rows.

The in-memory readers (:mod:`.table`, :mod:`.opera`) hold every line of the file at once. For
maps larger than memory, `open_stream` reads only the header and `TableStream.blocks` then
yields the data rows block by block, converted to mm and T, with the same validation and the
same ``file:line: column 'Bx' ...`` messages: columns and units are decided by
`cfm_fem.io._parse.table_layout` and numbers parsed by `cfm_fem.io._parse.parse_block`, the
functions the in-memory readers use. Line numbers count CR, LF and CRLF ends like
`cfm_fem.io._parse.read_lines`.

What is left to the caller (it needs all rows): placeholder rows (B = 0 0 0), duplicate nodes
and Opera's point-count check (`check_opera_counts`); `cfm_fem.workflows.sweep.slabs` does them.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import CfmInputError, CfmInputWarning
from ._files import open_regular
from ._parse import _check_finite, describe_column, detect_delimiter, header_names, parse_block
from ._parse import table_layout as _layout
from .opera import count_mismatch, refuse_missing_rows

__all__ = ["TableStream", "open_stream", "iter_lines", "check_opera_counts", "STREAMABLE"]

#: Formats (`cfm_fem.io.detect_format` names) that can be streamed.
STREAMABLE = ("table", "opera")
#: Bytes read from the file at a time.
READ_BYTES = 1 << 22


def iter_lines(path, start_line: int = 1):
    """Yield ``(line_number, text)`` of a text file without holding it in memory.

    UTF-8 (BOM skipped) with a Latin-1 fallback per block; CR, LF and CRLF line ends, so line
    numbers are those of `cfm_fem.io._parse.read_lines`. Blocks are cut after a line end, so
    neither a multi-byte character nor a CRLF pair is ever split.
    """
    from ._parse import check_nul, check_utf16, decode_text

    try:
        stream = open_regular(path, "a field map")  # closed below, also on early exit
    except OSError as exc:
        raise CfmInputError(f"cannot read the file: {exc.strerror or exc}", file=path) from None
    line = 1
    carry = b""
    first = True
    latin1 = False  # a block was read as Latin-1 (said once per file)
    try:
        while True:
            raw = stream.read(READ_BYTES)
            data = carry + raw
            if raw:
                end = len(data) - 1 if data.endswith(b"\r") else len(data)  # CR: maybe CRLF
                cut = max(data.rfind(b"\n", 0, end), data.rfind(b"\r", 0, end)) + 1
                if cut == 0:
                    carry = data  # no complete line yet
                    continue
                block, carry = data[:cut], data[cut:]
            else:
                block, carry = data, b""
            if first:
                check_utf16(block, path)
            try:
                text = block.decode("utf-8-sig" if first else "utf-8")
            except UnicodeDecodeError:
                text = decode_text(block, path, line, warn=not latin1)
                latin1 = True
            first = False
            parts = text.replace("\r\n", "\n").replace("\r", "\n").split("\n")
            if "\x00" in text:
                check_nul(parts, path, line)
            if raw:
                parts.pop()  # the block ends with a line end: the last part is empty
            for s in parts:
                if line >= start_line:
                    yield line, s
                line += 1
            if not raw:
                break
    finally:
        stream.close()


@dataclass
class TableStream:
    """Header of a streamed table and the iterator over its data rows.

    Attributes
    ----------
    file : str
    fmt : {'table', 'opera'}
    names : list of str
        Header column names as the file spells them.
    delimiter : str or None
    header_line : int
        1-based line of the header (Opera: of the first column definition).
    data_line : int
        1-based line where the data rows start.
    layout : cfm_fem.io._parse.TableLayout
        Chosen columns and unit scales.
    counts : list of int or None
        Opera's point counts (line 1).
    notes : list of str
    """

    file: str
    fmt: str
    names: list
    delimiter: object
    header_line: int
    data_line: int
    layout: object
    counts: list | None = None
    notes: list = field(default_factory=list)
    #: Data rows read so far by `blocks` (all of them once it has run to the end).
    n_rows: int = 0
    #: Warnings given for this file so far (`parse_block`): each once, not once per block.
    warned: set = field(default_factory=set)

    @property
    def spelled(self) -> list:
        """Names of the x, y, z, Bx, By, Bz columns as the file spells them."""
        return self.layout.spelled

    def blocks(self, rows_per_block: int = 65536):
        """Yield the data rows in blocks.

        Yields
        ------
        values : ndarray, shape (k, 6), float64
            x, y, z (mm) and Bx, By, Bz (T) of each row.
        lines : ndarray, shape (k,), int64
            1-based line of each row.

        Raises
        ------
        CfmInputError
            A short or long row, a field that is not a number, NaN or inf (file, line, column),
            or no data row at all.
        """
        rows, lines = [], []
        n = self.n_rows = 0
        for number, text in iter_lines(self.file, self.data_line):
            s = text.lstrip()
            if not s or s[0] in "#%":
                continue
            rows.append(text)
            lines.append(number)
            if len(rows) >= rows_per_block:
                n += len(rows)
                self.n_rows = n
                yield self._parse(rows, lines)
                rows, lines = [], []
        if rows:
            n += len(rows)
            self.n_rows = n
            yield self._parse(rows, lines, cut=_ends_with(self.file, rows[-1]))
        if n == 0:
            raise CfmInputError(
                f"no data rows after the header (line {self.header_line}); expected one row "
                f"of {len(self.names)} numbers per node",
                file=self.file,
                line=self.header_line,
            )

    def _parse(self, rows, lines, cut=False):
        row_lines = np.asarray(lines, dtype=np.int64)
        block = parse_block(
            rows, row_lines, self.names, self.layout.usecols, delimiter=self.delimiter,
            file=self.file, warned=self.warned, cut=cut,
        )  # fmt: skip
        values = self.layout.values(block)
        _check_finite(values[:, :3], values[:, 3:], self.spelled, row_lines, self.file)
        return values, row_lines


def _ends_with(path, row: str) -> bool:
    """True when the file ends with ``row`` and no line end after it (`_parse.unterminated`
    of a file read in blocks)."""
    with open_regular(path, "a field map") as f:
        size = f.seek(0, 2)
        f.seek(max(size - 4096, 0))
        tail = f.read()
    return bool(row) and not tail.endswith((b"\n", b"\r")) and tail.endswith(row.encode())


def open_stream(path, fmt: str, *, length_unit=None, field_unit=None) -> TableStream:
    """Read the header of a plain table (``fmt='table'``) or an Opera table (``'opera'``).

    Parameters
    ----------
    path : path-like
    fmt : {'table', 'opera'}
    length_unit, field_unit : str, optional
        As for `cfm_fem.io.read_field`.

    Raises
    ------
    CfmInputError
        Empty file, no header, missing columns, unknown or mixed units: the messages of the
        in-memory readers.
    """
    file = str(path)
    if fmt == "opera":
        return _open_opera(file, length_unit, field_unit)
    if fmt != "table":
        raise ValueError(f"cannot stream format {fmt!r}; streamable: {STREAMABLE}")
    from .table import CSV_HEADER, _is_numeric_row

    header = first = None
    for number, text in iter_lines(file):
        s = text.strip()
        if not s or (header is None and s[0] == "#"):
            continue
        if header is None:
            header = (number, s)
            continue
        if s[0] not in "#%":
            first = text
            break
    if header is None:
        _raise_empty_or_comments(file)
    line, text = header
    text = text.removeprefix("%").strip()
    if _is_numeric_row(text):
        raise CfmInputError(
            f"the first row holds numbers, not column names; expected a header row such as "
            f"'{CSV_HEADER}'",
            file=file,
            line=line,
        )
    delimiter = detect_delimiter(text, first)
    columns = [
        describe_column(name, k, line) for k, name in enumerate(header_names(text, delimiter))
    ]
    if first is None:
        raise CfmInputError(
            f"no data rows after the header (line {line}); expected one row of "
            f"{len(columns)} numbers per node",
            file=file,
            line=line,
        )
    layout = _layout(columns, file=file, header_line=line, length_unit=length_unit,
                     field_unit=field_unit)  # fmt: skip
    return TableStream(file, "table", [c.name for c in columns], delimiter, line, line + 1,
                       layout, notes=list(layout.notes))  # fmt: skip


def _raise_empty_or_comments(file):
    from .table import CSV_HEADER

    for _, text in iter_lines(file):
        if text.strip():
            raise CfmInputError(
                f"the file holds only comment lines; expected a header row such as '{CSV_HEADER}'",
                file=file,
            )
    raise CfmInputError("the file is empty; expected a field map", file=file)


def _open_opera(file, length_unit, field_unit) -> TableStream:
    from .opera import _definition, _point_counts

    lines = iter_lines(file)
    counts = None
    columns = []
    last = 0
    for number, text in lines:
        last = number
        s = text.strip()
        if not s:
            continue
        if counts is None:
            counts = _point_counts(text, file, number)
            continue
        if s == "0":
            break
        columns.append(_definition(s, len(columns) + 1, file, number))
    else:
        if counts is None:
            raise CfmInputError("the file is empty; expected a field map", file=file)
        raise CfmInputError(
            f"the header never ends: expected a line '0' after the {len(columns)} column "
            f"definition(s) ('<index> <NAME> [<UNIT>]')",
            file=file,
            line=last,
        )
    lines.close()
    if not columns:
        raise CfmInputError(
            "no column definitions ('<index> <NAME> [<UNIT>]') before the line '0'",
            file=file,
            line=last + 1,
        )
    header_line = columns[0].line
    layout = _layout(columns, file=file, header_line=header_line, length_unit=length_unit,
                     field_unit=field_unit)  # fmt: skip
    return TableStream(file, "opera", [c.name for c in columns], None, header_line, last + 1,
                       layout, counts=counts, notes=list(layout.notes))  # fmt: skip


def check_opera_counts(stream: TableStream, distinct) -> list[str]:
    """Opera's point-count check (`cfm_fem.io.opera.read_opera`) from distinct-value counts.

    Call it once `TableStream.blocks` has run out: the row count it read is compared too.

    Parameters
    ----------
    stream : TableStream
    distinct : sequence of 3 int or None
        Numbers of distinct x, y, z values of the rows (None: too many to count, so the counts
        cannot match a grid and the warning is given).
    """
    if stream.counts is None:
        return []
    refuse_missing_rows(stream.counts, stream.n_rows, stream.file, _first_line(stream.file))
    msg = count_mismatch(
        stream.counts, distinct, stream.n_rows, stream.file, _first_line(stream.file)
    )
    if msg is None:
        return []
    warnings.warn(msg, CfmInputWarning, stacklevel=3)
    return [msg]


def _first_line(file) -> int:
    for number, text in iter_lines(file):
        if text.strip():
            return number
    return 1  # pragma: no cover - open_stream refused an empty file


def is_streamable(path, fmt=None) -> str | None:
    """The streamable format of ``path`` (``'table'`` or ``'opera'``), or None."""
    from . import _ALIASES, detect_format

    kind = _ALIASES.get(fmt.lower(), fmt.lower()) if fmt else detect_format(Path(path))
    return kind if kind in STREAMABLE else None
