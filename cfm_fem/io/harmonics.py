"""Harmonics files (``n, Bn, An``) in and out, and the bundled QFDp4 table (paper Table III).

Format: CSV, comma separated, one header row naming the columns ``n``, ``Bn``, ``An`` (any order,
case-insensitive; extra columns are ignored), ``#`` comment lines anywhere. Comment lines of the
form ``# key: value`` carry the metadata:

``r_ref_mm``
    Reference radius in mm (or ``r_ref`` with a unit, e.g. ``# r_ref: 0.01 m``).
``convention``
    ``tesla``: every coefficient in T at R_ref.
    ``paper_units``: the paper's Table III convention; rows with n <= main in T, rows with
    n > main in units of 1e-4 of the main normal coefficient B_main (signed).
``main``
    Order of the main harmonic (2 for a quadrupole); required by ``paper_units``.

The same three can be passed as arguments; an argument that disagrees with the file is an error,
as is anything missing. Orders absent from the file are zero.
"""

from __future__ import annotations

import csv
import io
from importlib import resources
from pathlib import Path

import numpy as np

from ..errors import CfmInputError
from ..models.multipole import UNIT, Multipole
from ..units import length_scale
from ._atomic import write_text
from ._files import open_regular
from ._parse import check_nul, check_utf16, decode_text, option_hint

__all__ = ["CONVENTIONS", "read_harmonics", "write_harmonics", "qfdp4_path", "read_qfdp4"]

CONVENTIONS = ("tesla", "paper_units")
#: Highest harmonic order read. Rotating coils give n <= ~30 and FEM harmonic analyses rarely go
#: past 100; every order up to the highest is stored and summed at each point, so n = 1e8 would run
#: for more than 5 minutes before any output.
MAX_ORDER = 1000
_REQUIRED = ("n", "bn", "an")
_SPELLING = {"n": "n", "bn": "Bn", "an": "An"}
_KEYS = ("r_ref_mm", "r_ref", "convention", "main")


def _parse_number(text: str, *, file, line, column, what="a number"):
    try:
        v = float(text)
    except ValueError:
        v = None
    if v is None or not np.isfinite(v):
        raise CfmInputError(
            f"column '{column}' must be {what}; found {text!r}", file=file, line=line, column=column
        )
    return v


def _meta_value(key: str, value: str, *, file, line):
    """Turn one ``# key: value`` into (canonical key, python value)."""
    if key == "r_ref_mm":
        r = _parse_number(value, file=file, line=line, column="r_ref_mm", what="a length in mm")
        return "r_ref_mm", r
    if key == "r_ref":
        parts = value.split()
        if len(parts) != 2:
            raise CfmInputError(
                f"'r_ref' must be a number and a unit such as '10 mm'; found {value!r}",
                file=file,
                line=line,
            )
        r = _parse_number(parts[0], file=file, line=line, column="r_ref", what="a length")
        return "r_ref_mm", r * length_scale(parts[1], file=file, line=line, column="r_ref")
    if key == "convention":
        c = value.strip().lower()
        if c not in CONVENTIONS:
            raise CfmInputError(
                f"'convention' must be one of {', '.join(CONVENTIONS)}; found {value!r}",
                file=file,
                line=line,
            )
        return "convention", c
    # main
    try:
        n = int(value)
    except ValueError:
        n = 0
    if n < 1:
        raise CfmInputError(
            f"'main' must be a harmonic order >= 1 (2 for a quadrupole); found {value!r}",
            file=file,
            line=line,
        )
    return "main", n


def _merge(name: str, from_file, file_line, argument, *, file):
    """File value and argument must agree when both are given (floats to 1e-12 relative)."""
    if from_file is None:
        return argument
    if argument is None:
        return from_file
    same = (
        np.isclose(from_file, argument, rtol=1e-12, atol=0)
        if isinstance(argument, float | int) and not isinstance(argument, bool)
        else from_file == argument
    )
    if not same:
        raise CfmInputError(
            f"'{name}' is {from_file!r} in the file but {argument!r} was given; expected one value",
            file=file,
            line=file_line,
        )
    return from_file


def _parse(text: str, source: str):
    """Rows and metadata of a harmonics file: (n, Bn, An, lines, meta, meta_lines)."""
    meta: dict = {}
    meta_lines: dict = {}
    header = None
    cols: dict[str, int] = {}
    rows = []
    for lineno, raw in enumerate(text.splitlines(), start=1):
        s = raw.strip()
        if not s:
            continue
        if s.startswith("#"):
            body = s.lstrip("#").strip()
            if ":" in body:
                key, value = body.split(":", 1)
                key = key.strip().lower()
                if key in _KEYS:
                    k, v = _meta_value(key, value.strip(), file=source, line=lineno)
                    if k in meta and meta[k] != v:
                        raise CfmInputError(
                            f"'{k}' is given twice with different values ({meta[k]!r} on line "
                            f"{meta_lines[k]} and {v!r}); expected one value",
                            file=source,
                            line=lineno,
                        )
                    meta[k] = v
                    meta_lines[k] = lineno
            continue
        fields = [f.strip() for f in next(csv.reader(io.StringIO(s)))]
        if header is None:
            header = fields
            lower = [h.lower() for h in header]
            for name in _REQUIRED:
                if name not in lower:
                    raise CfmInputError(
                        f"the header must name the columns n, Bn, An; column '{_SPELLING[name]}' "
                        f"is missing (found {', '.join(header)})",
                        file=source,
                        line=lineno,
                        column=_SPELLING[name],
                    )
                if lower.count(name) > 1:
                    raise CfmInputError(
                        f"column '{_SPELLING[name]}' appears twice in the header; expected once",
                        file=source,
                        line=lineno,
                        column=_SPELLING[name],
                    )
            cols = {name: lower.index(name) for name in _REQUIRED}
            continue
        if len(fields) != len(header):
            raise CfmInputError(
                f"expected {len(header)} comma-separated values ({', '.join(header)}); found "
                f"{len(fields)}",
                file=source,
                line=lineno,
            )
        names = {k: header[i] for k, i in cols.items()}
        n_val = _parse_number(
            fields[cols["n"]], file=source, line=lineno, column=names["n"], what="an order >= 1"
        )
        if n_val != int(n_val) or n_val < 1:
            raise CfmInputError(
                f"column '{names['n']}' must be an integer order >= 1; found {fields[cols['n']]!r}",
                file=source,
                line=lineno,
                column=names["n"],
            )
        if n_val > MAX_ORDER:
            raise CfmInputError(
                f"column '{names['n']}' must be an order <= {MAX_ORDER}; found "
                f"{fields[cols['n']]!r} (every order up to the highest is evaluated at each point)",
                file=source,
                line=lineno,
                column=names["n"],
            )
        bn = _parse_number(fields[cols["bn"]], file=source, line=lineno, column=names["bn"])
        an = _parse_number(fields[cols["an"]], file=source, line=lineno, column=names["an"])
        rows.append((int(n_val), bn, an, lineno))
    if header is None:
        raise CfmInputError(
            "no header row; expected a row naming the columns n, Bn, An", file=source
        )
    if not rows:
        raise CfmInputError("the file holds no harmonics; expected at least one row", file=source)
    return rows, meta, meta_lines


def read_harmonics(
    path,
    *,
    r_ref_mm: float | None = None,
    convention: str | None = None,
    main: int | None = None,
) -> Multipole:
    """Read a harmonics file into a `Multipole` (coefficients in T at R_ref in mm).

    Parameters
    ----------
    path : str or path-like
    r_ref_mm : float, optional
        Reference radius in mm, if the file does not say it (must agree if it does).
    convention : {"tesla", "paper_units"}, optional
        Units of the coefficients, if the file does not say it (must agree if it does).
    main : int, optional
        Order of the main harmonic; required for "paper_units", optional for "tesla" (default:
        the order with the largest |B_n + i A_n|).

    Returns
    -------
    Multipole

    Raises
    ------
    CfmInputError
        Missing or inconsistent metadata, a bad header, a row that is not three numbers, an order
        given twice, or a main harmonic that is zero (message names file, line and column).
    """
    source = str(path)
    try:
        with open_regular(path, "a harmonics table", "the harmonics file") as f:
            raw = f.read()
    except OSError as exc:
        raise CfmInputError(
            f"cannot read the harmonics file: {exc.strerror or exc}", file=source
        ) from exc
    check_utf16(raw, source)
    text = decode_text(raw, source)
    if "\x00" in text:
        check_nul(text.replace("\r\n", "\n").replace("\r", "\n").split("\n"), source)
    return parse_harmonics(text, source=source, r_ref_mm=r_ref_mm, convention=convention, main=main)


def parse_harmonics(
    text: str,
    *,
    source: str = "<text>",
    r_ref_mm: float | None = None,
    convention: str | None = None,
    main: int | None = None,
) -> Multipole:
    """Like `read_harmonics`, from the file's text; ``source`` names it in messages."""
    rows, meta, meta_lines = _parse(text, source)
    if main is not None and (int(main) != main or main < 1):
        raise CfmInputError(f"main must be a harmonic order >= 1; instead received {main!r}")
    if convention is not None:
        convention = str(convention).strip().lower()
        if convention not in CONVENTIONS:
            raise CfmInputError(
                f"convention must be one of {', '.join(CONVENTIONS)}; "
                f"instead received {convention!r}"
            )
    r_ref = _merge(
        "r_ref_mm",
        meta.get("r_ref_mm"),
        meta_lines.get("r_ref_mm"),
        None if r_ref_mm is None else float(r_ref_mm),
        file=source,
    )
    conv = _merge(
        "convention", meta.get("convention"), meta_lines.get("convention"), convention, file=source
    )
    main = _merge("main", meta.get("main"), meta_lines.get("main"), main, file=source)
    if r_ref is None:
        raise CfmInputError(
            "the reference radius is not given; expected a line '# r_ref_mm: <mm>' or "
            f"{option_hint('r_ref_mm')}",
            file=source,
        )
    if not r_ref > 0:
        raise CfmInputError(
            f"the reference radius must be positive; found {r_ref} mm",
            file=source,
            line=meta_lines.get("r_ref_mm"),
        )
    if conv is None:
        raise CfmInputError(
            "the convention is not given; expected a line '# convention: tesla' (all in T at R_ref)"
            " or '# convention: paper_units' (n <= main in T, the rest in units), or the argument "
            "convention",
            file=source,
        )

    seen: dict[int, int] = {}
    for n, _, _, line in rows:
        if n in seen:
            raise CfmInputError(
                f"order n = {n} appears twice (also on line {seen[n]}); expected each order once",
                file=source,
                line=line,
                column="n",
            )
        seen[n] = line
    n_max = max(n for n, *_ in rows)
    normal = np.zeros(n_max)
    skew = np.zeros(n_max)
    for n, bn, an, _ in rows:
        normal[n - 1], skew[n - 1] = bn, an

    if main is not None and main > n_max:
        raise CfmInputError(
            f"the main order {main} has no row (highest order is {n_max}); "
            f"expected a row n = {main}",
            file=source,
            line=meta_lines.get("main"),
        )
    if conv == "paper_units":
        if main is None:
            raise CfmInputError(
                "convention 'paper_units' needs the main order; expected a line '# main: <n>' "
                "(2 for a quadrupole) or the argument main",
                file=source,
            )
        if main not in seen or normal[main - 1] == 0:
            raise CfmInputError(
                f"the main harmonic B{main} must be a non-zero field in T "
                "(units are relative to it)",
                file=source,
                line=seen.get(main),
                column="Bn",
            )
        # rows above the main order are in units of 1e-4 of B_main
        high = np.arange(1, n_max + 1) > main
        scale = UNIT * normal[main - 1]
        normal[high] *= scale
        skew[high] *= scale
    elif main is not None and normal[main - 1] == 0 and skew[main - 1] == 0:
        raise CfmInputError(
            f"the main harmonic n = {main} is zero; expected a non-zero field",
            file=source,
            line=seen.get(main),
        )
    return Multipole(normal, skew, r_ref, main, source)


def write_harmonics(path, multipole: Multipole, *, convention: str = "tesla", notes=()) -> None:
    """Write ``multipole`` as a harmonics file that `read_harmonics` reads back exactly.

    Parameters
    ----------
    path : str or path-like
    multipole : Multipole
    convention : {"tesla", "paper_units"}
        "paper_units" writes n <= main in T and the rest in units of 1e-4 of B_main.
    notes : iterable of str
        Extra comment lines written at the top.
    """
    if convention not in CONVENTIONS:
        raise CfmInputError(
            f"convention must be one of {', '.join(CONVENTIONS)}; instead received {convention!r}"
        )
    m = multipole
    b, a = m.normal.copy(), m.skew.copy()
    if convention == "paper_units":
        if b[m.main - 1] == 0:
            raise CfmInputError("paper_units needs a non-zero main normal coefficient B_main")
        high = np.arange(1, m.n_orders + 1) > m.main
        b[high] /= UNIT * b[m.main - 1]
        a[high] /= UNIT * b[m.main - 1]
    lines = [f"# {note}" for note in notes]
    lines += [
        f"# r_ref_mm: {m.r_ref!r}",
        f"# convention: {convention}",
        f"# main: {m.main}",
        "n,Bn,An",
    ]
    lines += [
        f"{n},{float(bn)!r},{float(an)!r}"
        for n, bn, an in zip(range(1, m.n_orders + 1), b, a, strict=True)
    ]
    write_text(path, "\n".join(lines) + "\n")


def qfdp4_path() -> Path:
    """Path of the bundled QFDp4 harmonics (paper Table III, R_ref assumed, see the file)."""
    return Path(str(resources.files("cfm_fem") / "data" / "qfdp4_harmonics.csv"))


def read_qfdp4() -> Multipole:
    """The SwissFEL quadrupole QFDp4 of the paper (Table III) as a `Multipole`.

    The paper does not give R_ref; the file assumes 10 mm and says why. To try another
    assumption, relabel: ``dataclasses.replace(read_qfdp4(), r_ref=...)``.
    """
    return read_harmonics(qfdp4_path())
