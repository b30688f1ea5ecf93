"""Shared parsing for the text field-map readers: lines, column names and units, number blocks.

The readers (:mod:`.comsol`, :mod:`.opera`, :mod:`.table`) differ only in how they find the header;
everything after that (which column is x or Bx, which unit applies, turning the data block into
numbers, placeholder rows, building the `FieldMap`) happens here, once.
"""

from __future__ import annotations

import csv
import re
import warnings
from dataclasses import dataclass

import numpy as np

from ..errors import CfmInputError, CfmInputWarning, shown
from ..models.field import FieldMap
from ..units import FIELD_TO_T, LENGTH_TO_MM, field_scale, length_scale
from ._files import open_regular

COORDS = ("x", "y", "z")
FIELDS = ("Bx", "By", "Bz")
ROLES = COORDS + FIELDS
ZERO_ROWS_CHOICES = ("warn", "drop", "keep")

#: Command-line spelling of the reader arguments (option, metavar), for messages that tell how
#: to set one: a ``cfm-fem`` user and a Python caller each find their own (`option_hint`).
CLI_OPTIONS = {
    "zero_rows": ("--zero-rows", "RULE"),
    "length_unit": ("--length-unit", "UNIT"),
    "field_unit": ("--field-unit", "UNIT"),
    "fmt": ("--format", "FMT"),
    "solution": ("--solution", "TAG"),
    "r_ref_mm": ("--r-ref", "MM"),
    "b_ref_T": ("--b-ref", "T"),
    "field_model": ("--field-model", "MODEL"),
}


def option_hint(name: str, value=None) -> str:
    """How to set reader argument ``name``, in both spellings, for messages.

    ``option_hint("zero_rows", "drop")`` gives ``--zero-rows drop (zero_rows='drop' from
    Python)``; without a value, ``option_hint("length_unit")`` gives ``--length-unit UNIT
    (length_unit= from Python)``.
    """
    option, metavar = CLI_OPTIONS[name]
    if value is None:
        return f"{option} {metavar} ({name}= from Python)"
    return f"{option} {value} ({name}={value!r} from Python)"


def zero_rows_dropped(what: str) -> str:
    """The note for rows of exactly 0 0 0 dropped on request; ``what`` counts them."""
    return f"{what}: dropped as placeholders, as asked by {option_hint('zero_rows', 'drop')}"


# --------------------------------------------------------------------------- text


def check_utf16(raw: bytes, path) -> None:
    """Refuse UTF-16/UTF-32 text (Windows "Unicode text", PowerShell's default).

    Read as UTF-8 or Latin-1 it gives column names full of NUL bytes and mojibake; the readers
    (also the streaming one, which cuts blocks at line-end bytes) work on UTF-8 bytes, so ask
    for UTF-8 rather than decode it here. ``raw``: the start of the file."""
    if raw.startswith((b"\xff\xfe\x00\x00", b"\x00\x00\xfe\xff")):
        kind = "UTF-32"
    elif raw.startswith((b"\xff\xfe", b"\xfe\xff")):
        kind = "UTF-16"
    else:
        check_binary(raw, path)
        head = raw[:64]  # UTF-16 without a BOM: every other byte of ASCII text is 0
        zeros = sorted((head[0::2].count(0), head[1::2].count(0)))
        if len(head) < 8 or zeros[1] < len(head) // 4 or zeros[0] > len(head) // 16:
            return
        kind = "UTF-16 (no BOM)"
    raise CfmInputError(f"the file is {kind} text; save it as UTF-8 and read it again", file=path)


#: Bytes that text files do not hold (C0 controls but tab, line feed, form feed and carriage
#: return, and DEL); a file whose start has more than `BINARY_SHARE` of them is binary.
_CONTROL_BYTES = bytes(b for b in range(32) if b not in b"\t\n\x0c\r") + b"\x7f"
BINARY_SHARE = 0.05


def check_binary(raw: bytes, path) -> None:
    """Refuse a binary file (an image, an archive, a file of zeros) by its first 4 KiB, naming
    what it looks like and where the first byte that text does not hold is."""
    head = raw[:4096]
    if not head:
        return
    if head.count(0) == len(head):
        raise CfmInputError(
            f"the file starts with {len(head)} NUL bytes (zeros), not text; expected a text "
            "file (damaged by a crash or a disk fault?)",
            file=path,
        )
    bad = sum(head.count(b) for b in _CONTROL_BYTES)
    zeros = sorted((head[0::2].count(0), head[1::2].count(0)))
    utf16 = zeros[1] >= len(head) // 4 and zeros[0] <= len(head) // 16
    if bad > BINARY_SHARE * len(head) and not utf16:
        first = next(i for i, b in enumerate(head) if b in _CONTROL_BYTES)
        raise CfmInputError(
            f"this is a binary file, not text: {bad} of its first {len(head)} bytes are control "
            f"bytes (the first, 0x{head[first]:02x}, at byte {first}); expected a text file",
            file=path,
        )


def decode_text(raw: bytes, path, first_line: int = 1, warn: bool = True) -> str:
    """Text of ``raw``: UTF-8 (a BOM skipped), else Latin-1 when every byte that is not UTF-8
    is a printable Latin-1 character (a legacy export: ``µT``, ``°C``), with a
    `CfmInputWarning` naming the first one's line and column.

    Raises
    ------
    CfmInputError
        Bytes that are neither UTF-8 nor printable Latin-1 (a damaged file): the first one's
        line and column (``first_line`` is the line ``raw`` starts on).
    """
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        start = exc.start
    line = (
        first_line
        + raw.count(b"\n", 0, start)
        + raw.count(b"\r", 0, start)
        - raw.count(b"\r\n", 0, start)
    )
    column = start - max(raw.rfind(b"\n", 0, start), raw.rfind(b"\r", 0, start))
    where = f"byte 0x{raw[start]:02x} at column {column}"
    if any(0x80 <= b < 0xA0 for b in raw):  # C1 controls: not Latin-1 text either
        raise CfmInputError(
            f"the file is not UTF-8 text: {where} is not valid UTF-8; save the file as UTF-8",
            file=path,
            line=line,
        )
    if warn:
        warnings.warn(
            f"{path}:{line}: not UTF-8 ({where}); the file is read as Latin-1: if that "
            "character is not what the file means, save it as UTF-8",
            CfmInputWarning,
            stacklevel=3,
        )
    return raw.decode("latin-1")


def check_nul(lines, path, first_line: int = 1) -> None:
    """Refuse NUL bytes in text (a binary file, or one cut short by a crash): messages would
    quote them raw onto the terminal. ``lines[i]`` is line ``first_line + i``."""
    for i, s in enumerate(lines):
        if "\x00" in s:
            raise CfmInputError(
                "NUL bytes in the text; expected a text file (binary, or damaged by a crash?)",
                file=path,
                line=first_line + i,
            )


def read_lines(path, max_bytes: int | None = None, what: str = "a field map") -> list[str]:
    """Lines of a text file without line ends; ``lines[i]`` is line ``i + 1``.

    UTF-8 (with or without BOM), falling back to Latin-1; CR, LF and CRLF ends all accepted.
    Only these three count as line ends, so line numbers match what an editor shows.
    ``max_bytes`` reads only the start of the file (to guess its format). ``what`` the file
    should hold, for the message on an empty file. UTF-16/32 text and NUL bytes are refused.
    """
    try:
        with open_regular(path, what) as stream:
            raw = stream.read(-1 if max_bytes is None else max_bytes)
    except OSError as exc:
        raise CfmInputError(f"cannot read the file: {exc.strerror or exc}", file=path) from None
    check_utf16(raw, path)
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        # a multi-byte character cut at max_bytes is not a reason to leave UTF-8
        cut = max_bytes is not None and exc.start >= len(raw) - 3
        if cut or max_bytes is not None:  # a look at the start, to guess the format: quietly
            text = raw[: exc.start].decode("utf-8-sig") if cut else raw.decode("latin-1")
        else:
            text = decode_text(raw, path)
    if not text.strip():
        raise CfmInputError(f"the file is empty; expected {what}", file=path)
    lines = text.replace("\r\n", "\n").replace("\r", "\n").split("\n")
    if "\x00" in text:
        check_nul(lines, path)
    return lines


def data_rows(lines, start: int, comment_chars: str = "#%"):
    """Non-blank, non-comment lines from index ``start`` on.

    Returns
    -------
    rows : list of str
    row_lines : ndarray, shape (n,), int64
        1-based line number of each row.
    """
    end = len(lines)
    while end > start and not lines[end - 1].strip():
        end -= 1
    rows = lines[start:end]
    skip = re.compile(rf"^[^\S\n]*(?:[{re.escape(comment_chars)}]|$)", re.MULTILINE)
    if not skip.search("\n".join(rows)):  # the usual case: one data row per line, checked in C
        return rows, np.arange(start + 1, start + 1 + len(rows), dtype=np.int64)
    keep = [i for i in range(start, end) if _is_data(lines[i], comment_chars)]
    return [lines[i] for i in keep], np.asarray(keep, dtype=np.int64) + 1


def _is_data(line: str, comment_chars: str) -> bool:
    s = line.lstrip()
    return bool(s) and s[0] not in comment_chars


def detect_delimiter(header: str, first_row: str | None):
    """The delimiter (``,`` ``;`` or tab) used by the header and first data row; None for blanks."""
    for delim in (",", ";", "\t"):
        if delim in header and (first_row is None or delim in first_row):
            return delim
    return None


def split_fields(line: str, delimiter) -> list[str]:
    """Fields of one line: blank-separated, or delimited with ``"`` quoting (CSV rules)."""
    if delimiter is None:
        return line.split()
    return next(csv.reader([line], delimiter=delimiter))


def header_names(text: str, delimiter) -> list[str]:
    """Column names of a header line.

    Blank-separated headers cannot hold names with blanks, except a unit in brackets written
    apart from its name: ``mf.Bx (T)`` and ``x [mm]`` stay one name each, and so does COMSOL's
    solution tag: ``mf.Bx (T) @ t=0.1`` (``@ I0=100, p=2``), also written without blanks around
    the ``@`` (``mf.Bx(T)@t=0``, ``mf.Bx (T)@ t=0``, ``mf.Bx (T) @t=0``).
    """
    if delimiter is not None:
        return [name.strip() for name in split_fields(text, delimiter)]
    names: list[str] = []
    for token in text.split():
        last = names[-1] if names else ""
        tagged = " @" in last or GLUED_TAG.search(last) is not None
        if names and (
            _bracket_depth(last) > 0
            or (token[0] in "([" and not _has_unit(last))
            or token == "@"
            or GLUED_TAG.match(token) is not None  # "@t=0" after "mf.Bx (T)"
            or (last.endswith("@") and (tagged or _TAG_START.match(token) is not None))
            or (tagged and (last.endswith(",") or token[0] == ","))
        ):
            names[-1] += " " + token
        else:
            names.append(token)
    return names


#: A COMSOL solution tag glued to what comes before or after its ``@``: ``@t=0``, ``@ I0=100``
#: (an ``@`` followed by a parameter name and ``=``); `header_names` keeps it with its name.
GLUED_TAG = re.compile(r"@\s*[A-Za-z_][\w.]*\s*=")
_TAG_START = re.compile(r"[A-Za-z_][\w.]*\s*=")


def _bracket_depth(name: str) -> int:
    return name.count("(") + name.count("[") - name.count(")") - name.count("]")


def _has_unit(name: str) -> bool:
    # "x[mm]" already carries its unit; a following "(T)" starts a new (odd) name.
    return name.endswith(("]", ")"))


#: How a note ends when a reader keeps no cells of the export (meshio files, COMSOL sections).
DELAUNAY_NOTE = "interpolation will use a Delaunay triangulation of the nodes"


# --------------------------------------------------------------------------- numbers

_THOUSANDS = re.compile(r"[+-]?\d{1,3}(?:,\d{3})+(?:\.\d*)?(?:[eE][+-]?\d+)?")
# "0,125" or "-0,500": a first group of 0 is never written before a thousands separator, so the
# comma is a decimal comma. Reading it as 125 made a whole decimal-comma map 1000x too large; we
# refuse instead of reading it as 0.125 because the same file then also holds "1,250", which is
# 1250 or 1.25 depending on the writer's locale, and guessing per value would mix both readings.
_DECIMAL_COMMA = re.compile(r"[+-]?0,\d+(?:[eE][+-]?\d+)?")
# One comma between digits and no point: "-5,000000" (not a thousands group of three digits) has
# a decimal comma too; "1,066" unquoted is 1066 or 1.066, and is refused as ambiguous.
_ONE_COMMA = re.compile(r"[+-]?\d+,\d+(?:[eE][+-]?\d+)?")


def parse_number(token: str, *, column: str, file, line, was_quoted: bool = False) -> float:
    """One number as written in a file; ``"1,066.67"`` (thousands separators) is 1066.67.

    Thousands separators are accepted only where they cannot be a decimal comma: in a quoted
    field (``was_quoted``, or quotes still on ``token``) or when a decimal point follows them.
    A decimal comma that cannot be a thousands separator (``"0,125"``) is refused.

    Raises
    ------
    CfmInputError
        ``"<file>:<line>: column 'Bx' must be a number; found 'abc'"``.
    """
    s = token.strip()
    was_quoted = was_quoted or s[:1] in "\"'"
    s = s.strip("\"'").strip()
    if "_" in s or not s.isascii():  # Python's float() reads "1_000" and "١٢" (Arabic digits)
        what = "a digit separator '_'" if "_" in s else "characters other than ASCII"
        raise CfmInputError(
            f"column '{column}' must be a number; found {shown(s)}, which holds {what}",
            file=file,
            line=line,
            column=column,
        )
    try:
        return float(s)
    except ValueError:
        pass
    thousands = _THOUSANDS.fullmatch(s)
    one_comma = _ONE_COMMA.fullmatch(s)
    why = None
    if _DECIMAL_COMMA.fullmatch(s):  # before the thousands: "0,125" would match them
        why = "a thousands group never starts with 0"
    elif one_comma and not thousands:
        why = "a thousands group has three digits"
    elif thousands and (was_quoted or "." in s):
        return float(s.replace(",", ""))
    if why:
        raise CfmInputError(
            f"column '{column}' must be a number with '.' as decimal point; found '{s}', which "
            f"has a decimal comma ({why}); export the file with '.' as decimal separator",
            file=file,
            line=line,
            column=column,
        )
    found = "an empty field" if not s else f"'{s}'"
    if one_comma:  # "1,066": a thousands separator or a decimal comma
        found += (
            f", which is {s.replace(',', '')} with a thousands separator or "
            f"{s.replace(',', '.')} with a decimal comma; export the file with '.' as decimal "
            "separator and no thousands separators (or quote numbers that have them)"
        )
    raise CfmInputError(
        f"column '{column}' must be a number; found {found}", file=file, line=line, column=column
    )


def unterminated(lines, row_lines) -> bool:
    """True when the last data row is the file's last line and has no line end after it (a
    file cut short, or a writer that never ended it): `check_cut_row` then looks at it."""
    return len(row_lines) > 0 and lines[-1] != "" and int(row_lines[-1]) == len(lines)


_EXPONENT = re.compile(r"[eEdD][+-]?(\d*)$")
#: Rows before the last one that `check_cut_row` compares it with.
CUT_CONTEXT = 200


def _shape(token: str):
    """(length without sign, has '.', exponent digits or None, digits after '.', is zero) of a
    number as written."""
    s = token.strip().strip("\"'").lstrip("+-")
    m = _EXPONENT.search(s)
    mantissa = s[: m.start()] if m else s
    decimals = len(mantissa) - mantissa.index(".") - 1 if "." in mantissa else 0
    zero = not mantissa.strip("0.")
    return len(s), "." in mantissa, (len(m[1]) if m else None), decimals, zero


def check_cut_row(rows, row_lines, names, usecols, *, delimiter, file) -> None:
    """Refuse a last row, written without a line end, whose numbers look cut short.

    A file cut inside its last number still parses (``-0.503488323577E-0`` for
    ``-0.503488323577E-05``, 1e5 times too large), so each value of that row is compared with
    the same column in the rows before it: shorter than every one of them, an exponent with
    fewer digits, no exponent or no decimal point where all have one, or fewer decimals than a
    column written with a fixed number of them, is taken for a cut.

    Raises
    ------
    CfmInputError
        Naming the line, the column and the value, and what the others look like.
    """
    if len(rows) < 2:
        return
    context = [split_fields(r, delimiter) for r in rows[-CUT_CONTEXT - 1 : -1]]
    last = split_fields(rows[-1], delimiter)
    for c in usecols:
        if c >= len(last) or not all(c < len(f) for f in context):
            return  # a short row: the field count check names it
        t = _shape(last[c])
        others = [_shape(f[c]) for f in context]
        # values written in the same form (with or without an exponent): "0.0" among
        # "-0.503488323577E-05" is a zero, not a cut; a non-zero value is not compared with
        # zeros (often written in a form of their own)
        same = [o for o in others if (o[2] is None) == (t[2] is None) and (o[4] <= t[4])]
        why = None
        if t[2] is None and not same:
            why = "written without the exponent the values above it have"
        elif not same:
            pass
        elif t[2] is not None and t[2] < min(o[2] for o in same):
            why = "an exponent with fewer digits than every value above it"
        elif t[0] < min(o[0] for o in same):
            why = "shorter than every value above it"
        elif not t[1] and all(o[1] for o in same):
            why = "written without the decimal point every value above it has"
        elif len({o[3] for o in same}) == 1 and t[3] < same[0][3]:
            why = f"fewer decimals than the {same[0][3]} of every value above it"
        if why:
            raise CfmInputError(
                f"column '{names[c]}': the last value {shown(last[c].strip())} is {why}, and the "
                "file ends without a line end after it: it looks cut short (a copy or a write "
                "that did not finish); if the value is complete, end the file with a line end",
                file=file,
                line=int(row_lines[-1]),
                column=names[c],
            )


def parse_block(rows, row_lines, names, usecols, *, delimiter, file, warned=None,
                cut=False) -> np.ndarray:  # fmt: skip
    """Numbers of the columns ``usecols`` of the data rows.

    Fast path: numpy parses the whole block at once. Only if that fails (a bad field, quoted
    numbers, a short line, text in an extra column) does a line-by-line scan run, which accepts what
    is acceptable and otherwise names the first bad line and column.

    Parameters
    ----------
    rows : list of str
    row_lines : ndarray, shape (n,), int
        1-based line of each row, for messages.
    names : list of str
        All column names of the header, as the file spells them.
    usecols : sequence of int
        Indices (into ``names``) of the columns to return.
    warned : set of str, optional
        The warnings already given for this file, shared by the blocks of one file read in
        blocks (`cfm_fem.io.streaming.TableStream`): each is then given once per file, not once
        per block; updated in place.
    cut : bool
        The last row ends the file without a line end (`unterminated`): `check_cut_row`.

    Returns
    -------
    ndarray, shape (n, len(usecols)), float64
    """
    if cut:
        check_cut_row(rows, row_lines, names, usecols, delimiter=delimiter, file=file)
    try:
        block = np.loadtxt(rows, delimiter=delimiter, comments=None, ndmin=2, dtype=np.float64)
    except ValueError:
        block = None
    if block is not None and block.shape[1] == len(names):
        return block[:, list(usecols)]
    return _scan_rows(rows, row_lines, names, usecols, delimiter=delimiter, file=file,
                      warned=warned)  # fmt: skip


def _scan_rows(rows, row_lines, names, usecols, *, delimiter, file, warned=None) -> np.ndarray:
    """Exact line-by-line parse (the slow path of `parse_block`)."""
    n_names = len(names)
    comma_quoted = delimiter == ","  # a comma inside a field of a CSV row was quoted
    out = np.empty((len(rows), len(usecols)), dtype=np.float64)
    reader = (
        (line.split() for line in rows)
        if delimiter is None
        else csv.reader(rows, delimiter=delimiter)
    )
    ambiguous = None  # (line, column, token) of the first thousands separator without a "."
    for i, fields in enumerate(reader):
        line = int(row_lines[i])
        n = len(fields)
        if n == n_names + 1 and not fields[-1].strip():
            n = n_names  # a trailing delimiter at the end of the row
        if n < n_names:
            raise CfmInputError(
                f"the row has {n} field(s) but the header names {n_names}; column "
                f"'{names[n]}' is missing (truncated line?)",
                file=file,
                line=line,
                column=names[n],
            )
        if n > n_names:
            raise CfmInputError(
                f"the row has {n} fields but the header names only {n_names} "
                f"({', '.join(names)}); expected one field per column",
                file=file,
                line=line,
            )
        for j, c in enumerate(usecols):
            out[i, j] = parse_number(
                fields[c], column=names[c], file=file, line=line, was_quoted=comma_quoted
            )
            if ambiguous is None and "," in fields[c] and "." not in fields[c]:
                ambiguous = (line, names[c], fields[c].strip())
    warned = set() if warned is None else warned
    if ambiguous is not None and "thousands" not in warned:
        warned.add("thousands")  # once per file, however many blocks it is read in
        # "1,250" with no decimal point is 1250 to an English writer and 1.25 to a decimal-comma
        # one; it is read as 1250 (a decimal-comma file is refused at its first "0,..." value),
        # but say so in case the file has no value below 1 to give it away.
        line, column, token = ambiguous
        warnings.warn(
            f"{file}:{line}: column '{column}': {token} read with ',' as thousands separator "
            f"({parse_number(token, column=column, file=file, line=line, was_quoted=True):g}); "
            "if the file uses a decimal comma, its values are 1000x too large",
            CfmInputWarning,
            stacklevel=2,
        )
    return out


# --------------------------------------------------------------------------- column names

#: Words in brackets or glued to an axis name that say which frame a coordinate is in, not its unit.
QUALIFIERS = ("magnet", "stage")
KNOWN_UNITS = set(LENGTH_TO_MM) | set(FIELD_TO_T)
_BRACKETED = re.compile(r"^(?P<base>.*?)\s*(?:\[(?P<square>[^\[\]]*)\]|\((?P<round>[^()]*)\))$")
_SUFFIXED = re.compile(r"^(?P<base>.+?)_(?P<unit>[^\s_]+)$")
_TAG = re.compile(r"^[a-z][a-z0-9]*\.(?=[a-z])")  # COMSOL physics tag: "mf.", "mfnc."
_ROLE_OF_KEY = {
    "x": "x",
    "y": "y",
    "z": "z",
    **{f"{p}{a}": f"B{a}" for p in ("b", "field", "bfield") for a in "xyz"},
}


@dataclass
class Column:
    """One column of a header.

    Attributes
    ----------
    name : str
        As the file spells it (used in every message).
    index : int
        0-based position in the row.
    line : int or None
        1-based line of the header (or of this column's definition).
    role : str or None
        ``'x'``, ``'y'``, ``'z'``, ``'Bx'``, ``'By'``, ``'Bz'`` or None (an extra column).
    unit : str or None
        Unit written in the name (``'mm'`` for ``x [mm]`` or ``x_mm``), or None.
    qualifier : str or None
        Frame word such as ``'magnet'`` (``Zmagnet``) or ``'stage'`` (``Z(stage)``).
    key : str
        The name without unit, physics tag, blanks, ``_``, ``-``, in lower case (``'bx'``).
    """

    name: str
    index: int
    line: int | None
    role: str | None
    unit: str | None
    qualifier: str | None
    key: str = ""


def describe_column(name: str, index: int, line: int | None, unit: str | None = None) -> Column:
    """Work out role, unit and qualifier from a column name.

    ``unit`` (for formats that give it apart from the name, like Opera) is used when the name
    has none. Accepted forms: ``x``, ``X [mm]``, ``x (in)``, ``x_mm``, ``Bx [T]``, ``Bx_mT``,
    ``mf.Bx (T)``, ``mfnc.BZ (kG)``, ``Field X (T)``, ``Zmagnet``, ``Z(stage)``, any case.
    """
    base = name.strip().strip("\"'").strip()
    qualifier = None
    m = _BRACKETED.match(base)
    if m and m["base"]:
        inner = (m["square"] if m["square"] is not None else m["round"]).strip()
        base = m["base"]
        if inner.lower() in QUALIFIERS:
            qualifier = inner.lower()
        else:
            unit = inner
    else:
        m = _SUFFIXED.match(base)
        if m and m["unit"].lower() in KNOWN_UNITS:
            base, unit = m["base"], m["unit"]
    key = _TAG.sub("", re.sub(r"[\s_\-]", "", base).lower())
    role = _ROLE_OF_KEY.get(key)
    if role is None:
        for q in QUALIFIERS:
            if key.endswith(q) and _ROLE_OF_KEY.get(key[: -len(q)]) in COORDS:
                role, qualifier = _ROLE_OF_KEY[key[: -len(q)]], q
    return Column(name, index, line, role=role, unit=unit, qualifier=qualifier, key=key)


def pick_columns(columns, *, file, line, optional=()) -> tuple[dict, list[str]]:
    """Choose the column for each of x, y, z, Bx, By, Bz.

    Several candidates for one role: a coordinate qualified ``magnet`` (the map's frame) wins,
    else the one unqualified name; anything else is ambiguous and an error.

    Parameters
    ----------
    columns : list of Column
    optional : tuple of str
        Roles that may be absent (then mapped to None), e.g. ``('z', 'Bz')`` for 2-D exports.

    Returns
    -------
    chosen : dict role -> Column or None
    notes : list of str
    """
    notes: list[str] = []
    chosen: dict = {}
    for role in ROLES:
        cands = [c for c in columns if c.role == role]
        if len(cands) <= 1:
            chosen[role] = cands[0] if cands else None
            continue
        magnet = [c for c in cands if c.qualifier == "magnet"]
        plain = [c for c in cands if c.qualifier is None]
        best = magnet if magnet else plain
        if len(best) != 1:
            listed = ", ".join(f"'{c.name}'" for c in cands)
            raise CfmInputError(
                f"several columns could be '{role}': {listed}; expected one (rename the others)",
                file=file,
                line=line,
            )
        chosen[role] = best[0]
        others = ", ".join(f"'{c.name}'" for c in cands if c is not best[0])
        why = "the magnet frame" if magnet else "the unqualified name"
        notes.append(f"'{role}' read from column '{best[0].name}' ({why}); ignored {others}")
    missing = [r for r in ROLES if chosen[r] is None and r not in optional]
    if missing:
        found = ", ".join(f"'{c.name}'" for c in columns) or "none"
        # a name holding a delimiter: the header and the data rows are split differently
        held = sorted({d for c in columns for d in (",", ";", "\t") if d in c.name})
        hint = (
            f"; a column name holds {' and '.join(repr(d) for d in held)}: the delimiter looks "
            "wrong (header and data rows must use the same one: ',', ';', tab or blanks)"
            if held
            else ""
        )
        raise CfmInputError(
            f"missing column(s) {', '.join(repr(r) for r in missing)}: expected coordinates "
            f"x, y, z and field Bx, By, Bz (any order, names like 'x [mm]' or 'Bx [T]'); "
            f"found {found}{hint}",
            file=file,
            line=line,
            column=missing[0],
        )
    return chosen, notes


def resolve_unit(
    kind: str, columns, *, option, fallback, file, line, assumed=None
) -> tuple[float, list[str]]:
    """Scale factor to mm (``kind='length'``) or T (``kind='field'``) for a group of columns.

    Precedence: the ``option`` the user passed (overrides the file, with a warning if they
    disagree), then units written in the column names (all the same, else an error), then
    ``fallback`` (e.g. COMSOL's ``% Length unit``), else an error asking for the unit.

    Parameters
    ----------
    columns : list of Column
        The x, y, z (or Bx, By, Bz) columns actually used.
    option : str or None
        ``length_unit`` / ``field_unit`` as passed by the user.
    fallback : tuple (unit, where, line) or None
        A unit the file states elsewhere, ``where`` saying where (for notes), its line.
    assumed : tuple (unit, why) or None
        The unit to assume when nothing else gives one (mesh files); noted, never an error.
    """
    to_scale = length_scale if kind == "length" else field_scale
    listed = ", ".join(f"'{c.name}'" for c in columns)
    notes: list[str] = []
    if option is not None:
        scale = to_scale(option)
        given = option_hint(f"{kind}_unit", option)
        said = [(c.unit, f"column '{c.name}'") for c in columns if c.unit is not None]
        if not said and fallback is not None:
            said = [(fallback[0], fallback[1])]
        differ = [f"'{u}' ({where})" for u, where in said if _scale_or_none(kind, u) != scale]
        if differ:
            msg = f"{file}: {given} overrides the file's {', '.join(differ)}"
            warnings.warn(msg, CfmInputWarning, stacklevel=4)
            notes.append(msg)
        notes.append(f"{kind} unit '{option}' for {listed}, as given by {given}")
        return scale, notes
    stated = [c for c in columns if c.unit is not None]
    scales = {c.name: to_scale(c.unit, file=file, line=c.line, column=c.name) for c in stated}
    if len(set(scales.values())) > 1:
        mixed = ", ".join(f"'{c.name}' ({c.unit})" for c in stated)
        raise CfmInputError(
            f"mixed {kind} units in columns {mixed}; expected one unit for {listed}",
            file=file,
            line=line,
            column=stated[0].name,
        )
    if stated:
        unit = stated[0].unit
        unstated = [c.name for c in columns if c.unit is None]
        extra = f" (applied also to {', '.join(repr(n) for n in unstated)})" if unstated else ""
        notes.append(f"{kind} unit '{unit}' from the column names{extra}")
        if fallback is not None and _scale_or_none(kind, fallback[0]) != scales[stated[0].name]:
            # the file contradicts itself (a factor of 1000 for m vs mm): say which one is used
            msg = (
                f"{file}: the column names say '{unit}' but the file states '{fallback[0]}' "
                f"({fallback[1]}); using '{unit}'; choose with {option_hint(f'{kind}_unit')}"
            )
            warnings.warn(msg, CfmInputWarning, stacklevel=4)
            notes.append(msg)
        return scales[stated[0].name], notes
    if fallback is not None:
        unit, where, fb_line = fallback
        scale = to_scale(unit, file=file, line=fb_line)
        notes.append(f"{kind} unit '{unit}' for {listed} ({where})")
        return scale, notes
    if assumed is not None:
        notes.append(f"{kind} unit '{assumed[0]}' for {listed} assumed: {assumed[1]}")
        return to_scale(assumed[0]), notes
    example = "mm" if kind == "length" else "T"
    named = "x [mm]" if kind == "length" else "Bx [T]"
    raise CfmInputError(
        f"no {kind} unit for columns {listed}: name it in the header (e.g. '{named}') or pass "
        f"it, e.g. {option_hint(f'{kind}_unit', example)}",
        file=file,
        line=line,
        column=columns[0].name,
    )


def _scale_or_none(kind, unit):
    table = LENGTH_TO_MM if kind == "length" else FIELD_TO_T
    return table.get(str(unit).strip().lower())


# --------------------------------------------------------------------------- assembly


def check_zero_rows(zero_rows: str) -> None:
    """Reject a ``zero_rows`` value other than 'warn', 'drop' or 'keep'."""
    if zero_rows not in ZERO_ROWS_CHOICES:
        raise CfmInputError(
            f"zero_rows must be one of {', '.join(ZERO_ROWS_CHOICES)}; instead received "
            f"{zero_rows!r}"
        )


def table_fieldmap(
    header_columns,
    rows,
    row_lines,
    *,
    delimiter,
    file,
    header_line,
    length_unit,
    field_unit,
    zero_rows,
    length_fallback=None,
    optional=(),
    notes=(),
    check_points=None,
    cut=False,
) -> FieldMap:
    """Pick columns, resolve units, parse the block and build the `FieldMap` (all text readers).

    Parameters
    ----------
    header_columns : list of Column
        Every column of the header, in file order.
    rows, row_lines :
        From `data_rows`.
    header_line : int
        1-based line of the header, for messages about columns.
    length_fallback : tuple (unit, where, line), optional
        Length unit stated elsewhere in the file.
    optional : tuple of str
        Roles allowed to be absent (filled with 0, with a note).
    check_points : callable, optional
        ``check_points(points)`` with points (n, 3) mm of every row, returning notes; for
        format-specific checks such as Opera's point counts.
    cut : bool
        The last row has no line end after it (`unterminated`): checked by `check_cut_row`.
    """
    check_zero_rows(zero_rows)
    names = [c.name for c in header_columns]
    if not rows:
        raise CfmInputError(
            f"no data rows after the header (line {header_line}); expected one row of "
            f"{len(names)} numbers per node",
            file=file,
            line=header_line,
        )
    layout = table_layout(
        header_columns,
        file=file,
        header_line=header_line,
        length_unit=length_unit,
        field_unit=field_unit,
        length_fallback=length_fallback,
        optional=optional,
    )
    notes = list(notes) + layout.notes
    chosen = layout.chosen
    values = layout.values(parse_block(rows, row_lines, names, layout.usecols,
                                       delimiter=delimiter, file=file, cut=cut))  # fmt: skip
    for role in ROLES:
        if chosen[role] is None:
            notes.append(f"no '{role}' column: {role} = 0 at every node")
    if check_points is not None:
        notes += check_points(values[:, :3])
    spelled = layout.spelled
    return build_fieldmap(
        values[:, :3],
        values[:, 3:],
        source=file,
        lines=row_lines,
        notes=notes,
        columns=spelled,
        zero_rows=zero_rows,
    )


# --------------------------------------------------------------------------- shared by the
# in-memory and the streaming readers (cfm_fem.io.streaming): one place decides columns and units


@dataclass
class TableLayout:
    """Which header column gives each of x, y, z, Bx, By, Bz and the unit scales.

    Attributes
    ----------
    chosen : dict role -> Column or None
    usecols : list of int
        Header indices of the present roles, in `ROLES` order (the ``usecols`` of `parse_block`).
    present : list of str
        Roles with a column.
    mm, tesla : float
        Scale of the coordinate columns to mm and of the field columns to T.
    spelled : list of str
        Column names as the file spells them, per role (the role where absent), for messages.
    notes : list of str
    """

    chosen: dict
    usecols: list
    present: list
    mm: float
    tesla: float
    spelled: list
    notes: list

    def values(self, block) -> np.ndarray:
        """Parsed columns ``block`` (k, len(usecols)) to (k, 6) float64: x, y, z mm, B T."""
        values = np.zeros((len(block), 6), dtype=np.float64)
        for j, role in enumerate(self.present):
            values[:, ROLES.index(role)] = block[:, j] * (self.mm if role in COORDS else self.tesla)
        return values


def table_layout(
    header_columns,
    *,
    file,
    header_line,
    length_unit,
    field_unit,
    length_fallback=None,
    optional=(),
) -> TableLayout:
    """Pick the columns and resolve the units of a text table (see `table_fieldmap`)."""
    chosen, notes = pick_columns(header_columns, file=file, line=header_line, optional=optional)
    present = [r for r in ROLES if chosen[r] is not None]
    coords = [chosen[r] for r in COORDS if chosen[r] is not None]
    fields = [chosen[r] for r in FIELDS if chosen[r] is not None]
    mm, unit_notes = resolve_unit(
        "length", coords, option=length_unit, fallback=length_fallback, file=file,
        line=header_line,
    )  # fmt: skip
    notes += unit_notes
    tesla, unit_notes = resolve_unit(
        "field", fields, option=field_unit, fallback=None, file=file, line=header_line
    )
    notes += unit_notes
    spelled = [chosen[r].name if chosen[r] is not None else r for r in ROLES]
    return TableLayout(
        chosen, [chosen[r].index for r in present], present, mm, tesla, spelled, notes
    )


def build_fieldmap(
    points, B, *, source, lines, notes, columns=ROLES, cells=None, zero_rows="warn"
) -> FieldMap:
    """Handle placeholder rows (B exactly 0, 0, 0), then `FieldMap.from_arrays`.

    ``zero_rows``: ``'warn'`` keeps them with a `CfmInputWarning`, ``'drop'`` drops them (and
    any cell using them), ``'keep'`` keeps them silently; each case leaves a note with the count.
    """
    check_zero_rows(zero_rows)
    source = str(source)
    notes = list(notes)
    _check_finite(points, B, columns, lines, source)
    zero = np.all(B == 0.0, axis=1)
    n_zero = int(zero.sum())
    if n_zero:
        first = np.flatnonzero(zero)[0]
        where = f"line {int(lines[first])}" if lines is not None else f"node {first}"
        what = f"{n_zero} row(s) have {', '.join(columns[3:])} exactly 0 0 0 (first at {where})"
        if zero_rows == "drop":
            keep = ~zero
            points, B = points[keep], B[keep]
            lines = None if lines is None else lines[keep]
            had_cells = cells is not None
            cells = _cells_without(cells, keep)
            notes.append(zero_rows_dropped(what))
            if had_cells and cells is None:
                notes.append("no cell is left without a dropped node: cells=None (Delaunay)")
        else:
            notes.append(zero_rows_kept(source, what, zero_rows, stacklevel=3))
    return FieldMap.from_arrays(
        points, B, cells=cells, source=source, lines=lines, notes=notes, columns=tuple(columns)
    )


#: Largest coordinate (mm) and field (T) a map may hold: 1e9 km and 1e6 T are beyond any
#: bench and any magnet; larger values are damage or a unit mix-up, and their squares overflow
#: float64 on the way (a value of 1e308 gave inf statistics after the outputs were written).
MAX_COORD_MM = 1e12
MAX_FIELD_T = 1e6


def _check_finite(points, B, columns, lines, source):
    """NaN, inf or an implausible magnitude (`MAX_COORD_MM`, `MAX_FIELD_T`): name the first
    one's line and column (as the file spells it)."""
    for values, names, limit, unit in ((points, columns[:3], MAX_COORD_MM, "mm"),
                                       (B, columns[3:], MAX_FIELD_T, "T")):  # fmt: skip
        with np.errstate(invalid="ignore"):
            bad = ~(np.abs(values) <= limit)
        if bad.any():
            i, j = np.argwhere(bad)[0]
            where = {"line": int(lines[i])} if lines is not None else {}
            node = "" if lines is not None else f" at node {i} (0-based)"
            v = float(values[i, j])
            what = (
                f"must be a finite number; found {v}"
                if not np.isfinite(v)
                else f"must be within +-{limit:g} {unit}; found {v:g} {unit} (a unit mix-up or "
                "a damaged value?)"
            )
            raise CfmInputError(
                f"column '{names[j]}' {what}{node}", file=source, column=names[j], **where
            )


def _cells_without(cells, keep):
    """Cells that use only kept nodes, renumbered; None if none is left."""
    if cells is None:
        return None
    cells = cells[keep[cells].all(axis=1)]
    new_index = np.cumsum(keep) - 1
    return new_index[cells] if len(cells) else None


# --------------------------------------------------------------------------- text output


def write_rows(path, header_lines, values, *, sep: str, width: int = 0) -> None:
    """Write header lines then one row per line of ``values``, atomically.

    Numbers are written as the shortest text that reads back to the same float64 (Python
    ``repr``), so a written map reads back exactly. ``width`` left-justifies each number.

    Parameters
    ----------
    values : ndarray, shape (n, k), float64
    """
    from ._atomic import atomic_path

    as_text = (lambda v: repr(v).ljust(width)) if width else repr
    with atomic_path(path) as tmp, open(tmp, "w", encoding="utf-8", newline="\n") as out:
        out.writelines(line + "\n" for line in header_lines)
        for start in range(0, len(values), 65536):
            chunk = np.asarray(values[start : start + 65536], dtype=np.float64).tolist()
            out.write("".join(sep.join(map(as_text, row)).rstrip() + "\n" for row in chunk))


def zero_rows_kept(source, what: str, zero_rows: str, stacklevel: int = 2) -> str:
    """The note for rows of exactly 0 0 0 that are kept (``zero_rows`` 'warn' or 'keep'); warns
    (`CfmInputWarning`) for 'warn'. ``what`` counts them and names the first."""
    if zero_rows == "warn":
        msg = (
            f"{source}: {what}; kept as real 0 T values. If they are placeholders, drop them "
            f"with {option_hint('zero_rows', 'drop')}"
        )
        warnings.warn(msg, CfmInputWarning, stacklevel=stacklevel + 1)
        return msg
    return f"{what}: kept, as asked by {option_hint('zero_rows', 'keep')}"
