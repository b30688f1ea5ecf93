"""Tracker recordings and Hall maps in and out (the CSV contract, stated here).

Comma separated, one header row, ``#`` comment lines anywhere, column names case-insensitive and in
any order:

=========  ====================================================================  =======
kind       required columns                                                      units
=========  ====================================================================  =======
tracker    ``point_id,rep,x_cmd,y_cmd,z_cmd,x_meas,y_meas,z_meas``                mm
hall       ``point_id,rep,x_cmd,y_cmd,z_cmd,Bx,By,Bz``                            mm, T
=========  ====================================================================  =======

Optional: ``t_s`` (s), ``dir_x,dir_y,dir_z`` (each axis's own last approach direction: -1, +1;
an axis that stood still keeps the direction of its earlier move; 0 when unknown; a missing one of
the three is 0), ``speed`` (mm/s of the move at acquisition, >= 0, 0 for stop-and-go),
``v_x,v_y,v_z`` (signed axis velocities at acquisition, mm/s; the three together), ``temp_C``.
Other columns are kept in ``Recording.extra`` and ignored.

Rejected with a `CfmInputError` naming file, line and column: a missing required column, a
repeated column, a field that is not a number, NaN or infinity, a non-integer ``point_id``/``rep``,
a repeated (point_id, rep), a direction outside -1/0/+1, a negative speed, a row with the wrong
number of fields, no data rows.
"""

from __future__ import annotations

import csv
import warnings

import numpy as np

from ..errors import CfmInputError, CfmInputWarning, shown
from ..models.recordings import Recording
from ._atomic import atomic_path
from ._finite import check_finite
from ._parse import (
    MAX_FIELD_T,
    check_cut_row,
    data_rows,
    parse_number,
    read_lines,
    unterminated,
)

__all__ = [
    "TRACKER_COLUMNS",
    "HALL_COLUMNS",
    "OPTIONAL_COLUMNS",
    "read_tracker",
    "read_hall_map",
    "read_recording",
    "write_tracker",
    "write_hall_map",
    "write_recording",
]

_KEY = ("point_id", "rep", "x_cmd", "y_cmd", "z_cmd")
TRACKER_COLUMNS = _KEY + ("x_meas", "y_meas", "z_meas")
HALL_COLUMNS = _KEY + ("Bx", "By", "Bz")
OPTIONAL_COLUMNS = ("t_s", "dir_x", "dir_y", "dir_z", "speed", "v_x", "v_y", "v_z", "temp_C")
_REQUIRED = {"tracker": TRACKER_COLUMNS, "hall": HALL_COLUMNS}
_WHAT = {"tracker": "a laser-tracker recording", "hall": "a Hall map"}
#: Two rows of one point whose commands differ by more than this (mm) trigger a warning.
CMD_TOLERANCE_MM = 1e-3
#: Largest magnitude a value may have, by column (larger is damage or a unit mix-up: 1e300 mm
#: made the fits fail to converge, 1e308 overflowed): positions 1e6 mm (1 km), fields
#: `MAX_FIELD_T`, time 1e10 s (three centuries), speed 1e6 mm/s.
LIMITS = {
    **{c: (1e6, "mm") for c in ("x_cmd", "y_cmd", "z_cmd", "x_meas", "y_meas", "z_meas")},
    **{c: (MAX_FIELD_T, "T") for c in ("Bx", "By", "Bz")},
    "t_s": (1e10, "s"),
    "speed": (1e6, "mm/s"),
    "temp_C": (1e4, "degC"),
}
#: A point_id or rep is an integer of int64 (read exactly, never through a float).
_INT_DIGITS = 18


# --------------------------------------------------------------------------- reading


def read_tracker(path) -> Recording:
    """Read a laser-tracker recording.

    Parameters
    ----------
    path : str or path-like
        CSV with ``point_id,rep,x_cmd,y_cmd,z_cmd,x_meas,y_meas,z_meas`` (mm) and optional columns.

    Returns
    -------
    Recording
        ``kind="tracker"``, ``meas`` in mm (bench frame).

    Raises
    ------
    CfmInputError
        ``"<file>:<line>: column 'x_meas' must be a number; found 'abc'"`` and the like.
    """
    return _read(path, "tracker")


def read_hall_map(path) -> Recording:
    """Read a Hall-probe field map recording.

    Parameters
    ----------
    path : str or path-like
        CSV with ``point_id,rep,x_cmd,y_cmd,z_cmd,Bx,By,Bz`` (mm in the magnet frame, T).

    Returns
    -------
    Recording
        ``kind="hall"``, ``B`` in T.

    Raises
    ------
    CfmInputError
        As `read_tracker`.
    """
    return _read(path, "hall")


def read_recording(path) -> Recording:
    """Read either kind, chosen from the header (``x_meas`` -> tracker, ``Bx`` -> Hall map)."""
    lines = read_lines(path, what="a recording")
    hline, names = _header(lines, path, "a recording")
    low = {n.lower() for n in names}
    if "bx" in low and "x_meas" not in low:
        kind = "hall"
    elif "x_meas" in low and "bx" not in low:
        kind = "tracker"
    else:
        raise CfmInputError(
            "cannot tell a tracker recording (x_meas,y_meas,z_meas) from a Hall map (Bx,By,Bz): "
            f"the header names {', '.join(names)}",
            file=path,
            line=hline + 1,
        )
    return _read(path, kind, lines=lines)


def _header(lines, path, what):
    for i, text in enumerate(lines):
        s = text.strip()
        if s and not s.startswith("#"):
            return i, [n.strip() for n in next(csv.reader([text]))]
    raise CfmInputError(
        f"no header row; expected {what} with a header row of column names", file=path
    )


def _read(path, kind, lines=None) -> Recording:
    source = str(path)
    lines = read_lines(path, what="a recording") if lines is None else lines
    hidx, names = _header(lines, path, _WHAT[kind])
    hline = hidx + 1
    index = _column_index(names, kind, path, hline)
    rows, row_lines = data_rows(lines, hidx + 1, comment_chars="#")
    if not rows:
        raise CfmInputError(
            f"no data rows after the header (line {hline}); expected one row per acquisition",
            file=path,
            line=hline,
        )
    table = _split(rows, row_lines, names, path)  # list of columns of str
    if unterminated(lines, row_lines):
        check_cut_row(rows, row_lines, names, sorted(index.values()), delimiter=",", file=path)

    def num(col, *, finite=True):
        v = _numbers(table[index[col]], row_lines, names[index[col]], path, finite=finite)
        if col in LIMITS:
            _check_limit(v, table[index[col]], row_lines, names[index[col]], path, *LIMITS[col])
        return v

    def integer(col, lo=None, hi=None, what="an integer"):
        texts = table[index[col]]
        exact = _exact_integers(texts)
        v = num(col) if exact is None else exact
        bad = (v != np.round(v)) | (np.abs(v) > 2**53) if exact is None else np.zeros(len(v), bool)
        if lo is not None:
            bad |= (v < lo) | (v > hi)
        if bad.any():
            i = int(np.argmax(bad))
            raise CfmInputError(
                f"column '{names[index[col]]}' must be {what}; found {shown(texts[i].strip())}",
                file=path,
                line=int(row_lines[i]),
                column=names[index[col]],
            )
        return v.astype(np.int64)

    point_id = integer("point_id")
    rep = integer("rep")
    _check_unique(point_id, rep, row_lines, path)
    cmd = np.column_stack([num(c) for c in ("x_cmd", "y_cmd", "z_cmd")])
    vals = np.column_stack([num(c) for c in _REQUIRED[kind][5:]])

    def opt(col):
        return num(col) if col in index else None

    direction = None
    if any(c in index for c in ("dir_x", "dir_y", "dir_z")):
        zero = np.zeros(len(rows), dtype=np.int64)
        direction = np.column_stack(
            [
                integer(c, -1, 1, "-1, 0 or +1 (approach direction)") if c in index else zero
                for c in ("dir_x", "dir_y", "dir_z")
            ]
        ).astype(np.int8)
    speed = opt("speed")
    if speed is not None and np.any(speed < 0):
        i = int(np.argmax(speed < 0))
        found = table[index["speed"]][i].strip()  # as written: not "np.float64(-1.0)"
        raise CfmInputError(
            f"column '{names[index['speed']]}' must be a speed >= 0 mm/s; found {found}",
            file=path,
            line=int(row_lines[i]),
            column=names[index["speed"]],
        )
    vel = None
    if any(c in index for c in ("v_x", "v_y", "v_z")):
        missing = [c for c in ("v_x", "v_y", "v_z") if c not in index]
        if missing:
            raise CfmInputError(
                f"columns v_x, v_y, v_z come together (signed axis velocities, mm/s); "
                f"missing {', '.join(missing)}",
                file=path,
                line=hline,
            )
        vel = np.column_stack([num(c) for c in ("v_x", "v_y", "v_z")])
    known = set(index.values())
    extra = {}
    for j, name in enumerate(names):
        if j not in known:
            try:
                extra[name] = np.asarray(table[j], dtype=np.float64)
            except ValueError:
                extra[name] = np.asarray([s.strip() for s in table[j]])
    rec = Recording(
        kind=kind,
        point_id=point_id,
        rep=rep,
        cmd=cmd,
        meas=vals if kind == "tracker" else None,
        B=vals if kind == "hall" else None,
        t_s=opt("t_s"),
        dir=direction,
        speed=speed,
        vel=vel,
        temp_C=opt("temp_C"),
        extra=extra,
        source=source,
        lines=row_lines,
    )
    _warn_inconsistent_cmd(rec, path)
    return rec


def _column_index(names, kind, path, hline) -> dict:
    """Canonical column name -> position in the header; checks required and repeated names."""
    canon = {c.lower(): c for c in _REQUIRED[kind] + OPTIONAL_COLUMNS}
    index: dict[str, int] = {}
    seen: dict[str, int] = {}
    for j, name in enumerate(names):
        key = name.lower()
        if key in seen:
            raise CfmInputError(
                f"column '{name}' appears twice in the header (fields {seen[key] + 1} and {j + 1})",
                file=path,
                line=hline,
                column=name,
            )
        seen[key] = j
        if key in canon:
            index[canon[key]] = j
    missing = [c for c in _REQUIRED[kind] if c not in index]
    if missing:
        held = [d for d in (";", "\t") if len(names) == 1 and d in names[0]]
        hint = (  # one field holding ';' or tabs: a Excel/locale export, not a missing column
            f" (one field holding {held[0]!r}: recordings are comma-separated; save the file "
            "with ',' as the delimiter)"
            if held
            else ""
        )
        raise CfmInputError(
            f"column '{missing[0]}' is missing; {_WHAT[kind]} needs the columns "
            f"{','.join(_REQUIRED[kind])}; the header names {','.join(names)}{hint}",
            file=path,
            line=hline,
            column=missing[0],
        )
    return index


def _split(rows, row_lines, names, path) -> list[list[str]]:
    """Fields of the rows, column by column; every row must have one field per column."""
    n_names = len(names)
    fields = list(csv.reader(rows))
    for i, f in enumerate(fields):
        n = len(f)
        if n == n_names + 1 and not f[-1].strip():
            f.pop()  # a trailing comma
            n = n_names
        if n != n_names:
            if n < n_names:
                what = (
                    f"the row has {n} field(s) but the header names {n_names}; "
                    f"column '{names[n]}' is missing (truncated line?)"
                )
                col = names[n]
            else:
                what = f"the row has {n} fields but the header names only {n_names}"
                col = None
            raise CfmInputError(what, file=path, line=int(row_lines[i]), column=col)
    return [list(c) for c in zip(*fields, strict=True)]


def _exact_integers(texts):
    """The integers written in ``texts`` as int64, exactly (ids above 2**53 are not rounded
    through a float); None when one is not written as a plain integer of at most 18 digits."""
    out = np.empty(len(texts), dtype=np.int64)
    for i, t in enumerate(texts):
        s = t.strip()
        digits = s[1:] if s[:1] in "+-" else s
        if not (digits.isascii() and digits.isdigit() and len(digits) <= _INT_DIGITS):
            return None
        out[i] = int(s)
    return out


def _check_limit(v, texts, row_lines, column, path, limit, unit) -> None:
    """Refuse a value beyond ``limit`` (`LIMITS`), as written, with its line."""
    with np.errstate(invalid="ignore"):
        bad = np.abs(v) > limit
    if bad.any():
        i = int(np.argmax(bad))
        raise CfmInputError(
            f"column '{column}' must be within +-{limit:g} {unit}; found {shown(texts[i].strip())}"
            " (a unit mix-up or a damaged value?)",
            file=path,
            line=int(row_lines[i]),
            column=column,
        )


def _numbers(texts, row_lines, column, path, *, finite=True) -> np.ndarray:
    joined = "".join(texts)
    try:
        if "_" in joined or not joined.isascii():  # numpy reads "1_000"; parse_number refuses
            raise ValueError
        v = np.asarray(texts, dtype=np.float64)
    except ValueError:
        v = np.array(
            [
                parse_number(t, column=column, file=path, line=int(row_lines[i]))
                for i, t in enumerate(texts)
            ]
        )
    if finite and not np.all(np.isfinite(v)):
        i = int(np.argmax(~np.isfinite(v)))
        raise CfmInputError(
            f"column '{column}' must be a finite number; found {shown(texts[i].strip())}",
            file=path,
            line=int(row_lines[i]),
            column=column,
        )
    return v


def _check_unique(point_id, rep, row_lines, path) -> None:
    key = np.column_stack([point_id, rep])
    order = np.lexsort((rep, point_id))
    k = key[order]
    dup = np.flatnonzero(np.all(k[1:] == k[:-1], axis=1))
    if dup.size:
        a, b = sorted((int(row_lines[order[dup[0]]]), int(row_lines[order[dup[0] + 1]])))
        pid, r = k[dup[0]]
        raise CfmInputError(
            f"(point_id, rep) = ({pid}, {r}) appears twice (lines {a} and {b}); "
            "expected one row per point and repetition",
            file=path,
            line=b,
            column="rep",
        )


def _warn_inconsistent_cmd(rec: Recording, path) -> None:
    ids, index = rec.point_index()
    lo = np.full((ids.size, 3), np.inf)
    hi = np.full((ids.size, 3), -np.inf)
    np.minimum.at(lo, index, rec.cmd)
    np.maximum.at(hi, index, rec.cmd)
    spread = (hi - lo).max(axis=1)
    if np.any(spread > CMD_TOLERANCE_MM):
        k = int(np.argmax(spread))
        warnings.warn(
            f"{path}: point_id {ids[k]} is commanded to positions up to {spread[k]:.4g} mm apart; "
            "its rows are treated as one point (their mean command)",
            CfmInputWarning,
            stacklevel=3,
        )


# --------------------------------------------------------------------------- writing


def write_tracker(path, rec: Recording, comments=()) -> None:
    """Write a tracker `Recording` in the 4.2 layout, atomically; `read_tracker` reads it back.

    Parameters
    ----------
    path : str or path-like
    rec : Recording
        ``kind="tracker"``.
    comments : sequence of str
        Lines written first, each prefixed with ``# ``.
    """
    if rec.kind != "tracker":
        raise CfmInputError(f"write_tracker needs a tracker Recording; got kind {rec.kind!r}")
    write_recording(path, rec, comments)


def write_hall_map(path, rec: Recording, comments=()) -> None:
    """Write a Hall-map `Recording` in the 4.2 layout, atomically; `read_hall_map` reads it back."""
    if rec.kind != "hall":
        raise CfmInputError(f"write_hall_map needs a hall Recording; got kind {rec.kind!r}")
    write_recording(path, rec, comments)


def write_recording(path, rec: Recording, comments=()) -> None:
    """Write either kind (columns: required, then the optional ones present, then ``extra``).

    Raises
    ------
    CfmInputError
        A value that is not finite or beyond what the readers take (`check_finite`): nothing
        is written.
    """
    _check_writable(path, rec)
    n = len(rec)
    cols: list[tuple[str, list[str]]] = [
        ("point_id", [str(v) for v in rec.point_id.tolist()]),
        ("rep", [str(v) for v in rec.rep.tolist()]),
    ]
    for j, c in enumerate(("x_cmd", "y_cmd", "z_cmd")):
        cols.append((c, _floats(rec.cmd[:, j])))
    for j, c in enumerate(_REQUIRED[rec.kind][5:]):
        cols.append((c, _floats(rec.values[:, j])))
    if rec.t_s is not None:
        cols.append(("t_s", _floats(rec.t_s)))
    if rec.dir is not None:
        for j, c in enumerate(("dir_x", "dir_y", "dir_z")):
            cols.append((c, [str(v) for v in rec.dir[:, j].astype(int).tolist()]))
    if rec.speed is not None:
        cols.append(("speed", _floats(rec.speed)))
    if rec.vel is not None:
        for j, c in enumerate(("v_x", "v_y", "v_z")):
            cols.append((c, _floats(rec.vel[:, j])))
    if rec.temp_C is not None:
        cols.append(("temp_C", _floats(rec.temp_C)))
    for name, v in rec.extra.items():
        v = np.asarray(v)
        cols.append((name, _floats(v) if v.dtype.kind == "f" else [str(s) for s in v.tolist()]))
    with atomic_path(path) as tmp, open(tmp, "w", encoding="utf-8", newline="") as out:
        for line in comments:
            out.write(f"# {line}\n")
        writer = csv.writer(out, lineterminator="\n")
        writer.writerow([c for c, _ in cols])
        values = [v for _, v in cols]
        writer.writerows([col[i] for col in values] for i in range(n))


def _check_writable(path, rec: Recording) -> None:
    """The finite-value contract of a recording: every number finite and within the limits
    the reader takes (`LIMITS`), so what is written reads back."""
    columns = [(c, rec.cmd[:, j]) for j, c in enumerate(("x_cmd", "y_cmd", "z_cmd"))]
    columns += [(c, rec.values[:, j]) for j, c in enumerate(_REQUIRED[rec.kind][5:])]
    columns += [(c, v) for c, v in (("t_s", rec.t_s), ("speed", rec.speed),
                                    ("temp_C", rec.temp_C)) if v is not None]  # fmt: skip
    if rec.vel is not None:
        columns += [(c, rec.vel[:, j]) for j, c in enumerate(("v_x", "v_y", "v_z"))]
    for name, values in columns:
        limit, unit = LIMITS.get(name, LIMITS["speed"])  # v_x, v_y, v_z: a speed
        check_finite(path, name, values, limit=limit, unit=unit)


def _floats(a) -> list[str]:
    return [repr(v) for v in np.asarray(a, dtype=np.float64).tolist()]
