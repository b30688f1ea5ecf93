"""COMSOL "Sectionwise" data export: the nodes, the elements, then one block per expression.

Layout read (COMSOL: Export > Data, Data format: Sectionwise)::

    % Model:              magnet.mph
    % Dimension:          3
    % Nodes:              7840
    % Elements:           40211
    % Length unit:        mm
    % Coordinates
    -15 -15 -315
    ...
    % Elements (tetrahedra)
    1 2 3 4                    <- node numbers, counted from 1
    ...
    % Data (mf.Bx (T))
    0.0012                     <- one value per node, in the order of the coordinates
    ...
    % Data (mf.By (T))
    ...

The tetrahedra (triangles of a 2-D export) become the map's cells, so the field is
interpolated in the export's own mesh. Other volume elements (hexahedra, prisms, pyramids) are
not used and the interpolator triangulates the nodes instead, as for meshio files; boundary
elements of a lower dimension are ignored. Expressions are mapped to Bx, By, Bz by name and unit
as in the other text formats (`cfm_fem.io._parse.describe_column`).
"""

from __future__ import annotations

import dataclasses
import re

import numpy as np

from ..errors import CfmInputError
from ..models.field import FieldMap
from ._parse import (
    DELAUNAY_NOTE,
    FIELDS,
    build_fieldmap,
    describe_column,
    option_hint,
    parse_block,
    table_layout,
)

__all__ = ["is_coordinates_line", "read_sections", "solution_columns", "split_tag", "normal_tag"]

_SECTION = re.compile(r"^(?P<kind>coordinates|elements|data)\s*(?:\((?P<label>.*)\))?$", re.I)
#: COMSOL's element names, by dimension of the element.
_VOLUME = ("tetrahedra", "pyramids", "prisms", "hexahedra")
_SURFACE = ("triangles", "quadrilaterals", "quads")
_KNOWN = _VOLUME + _SURFACE + ("edges", "lines", "vertices", "points")
_KEPT = {3: ("tetrahedra", 4), 2: ("triangles", 3)}  # dimension -> element kept, its corners


def is_coordinates_line(body: str) -> bool:
    """True for the ``% Coordinates`` line (``body`` without its ``%``) of a sectionwise file."""
    return body.strip().lower() == "coordinates"


def read_sections(
    lines,
    start: int,
    *,
    file,
    dimension,
    length_fallback,
    length_unit,
    field_unit,
    zero_rows,
    check_points,
    solution=None,
) -> FieldMap:
    """The `FieldMap` of a sectionwise export whose ``% Coordinates`` line is ``lines[start]``.

    Parameters
    ----------
    lines : list of str
        The whole file.
    start : int
        0-based index of the ``% Coordinates`` line.
    dimension : int or None
        ``% Dimension`` of the header; None takes it from the first coordinate row.
    length_fallback : tuple (unit, where, line) or None
        ``% Length unit`` of the header.
    check_points : callable
        ``check_points(points)`` -> notes (the ``% Nodes`` count).
    solution : str, optional
        The solution to read of a parametric or time-dependent export (`solution_columns`);
        the ``% Data`` blocks of the others are not read.
    """
    sections = _split(lines, start, file)
    coords = sections[0]
    if not coords["rows"]:
        raise CfmInputError(
            "no coordinate rows after '% Coordinates'; expected one row of x y (z) per node",
            file=file,
            line=coords["line"],
        )
    dim = dimension or len(coords["rows"][0].split())
    if dim not in (2, 3):
        raise CfmInputError(
            f"a field map has 2 or 3 coordinates per node; found {dim}",
            file=file,
            line=coords["line"] + 1,
        )
    names = ["X", "Y", "Z"][:dim]
    xyz = _numbers(coords, names, file)
    n = len(xyz)
    data = [s for s in sections if s["kind"] == "data"]
    notes = ["COMSOL sectionwise export"]
    columns = solution_columns(
        names + [s["label"] for s in data], [coords["line"]] * dim + [s["line"] for s in data],
        file, notes, solution,
    )  # fmt: skip
    blocks = [xyz]
    for column, section in zip(columns[dim:], data, strict=True):
        label = section["label"]
        if _other_solution(column):  # no role: as if absent, so not read
            blocks.append(np.zeros((n, 1)))
            continue
        values = _numbers(section, [label], file)
        if len(values) != n:
            raise CfmInputError(
                f"'% Data ({label})' has {len(values)} value(s); expected {n}, one per node "
                f"of '% Coordinates' (line {coords['line']})",
                file=file,
                line=section["line"],
            )
        bad = np.flatnonzero(~np.isfinite(values[:, 0]))
        if bad.size:
            raise CfmInputError(
                f"'{label}' must be a finite number; found {float(values[bad[0], 0])}",
                file=file,
                line=int(section["row_lines"][bad[0]]),
                column=label,
            )
        blocks.append(values)
    layout = table_layout(
        columns,
        file=file,
        header_line=coords["line"],
        length_unit=length_unit,
        field_unit=field_unit,
        length_fallback=length_fallback,
        optional=("z", "Bz") if dim == 2 else (),
    )
    values = layout.values(np.hstack(blocks)[:, layout.usecols])
    if dim == 2:
        notes.append("2-D export ('% Dimension: 2'): z = 0")
    notes += layout.notes
    notes += check_points(values[:, :3])
    cells = _cells(sections, dim, n, file, notes)
    return build_fieldmap(
        values[:, :3],
        values[:, 3:],
        source=file,
        lines=coords["row_lines"],
        notes=notes,
        columns=layout.spelled,
        cells=cells,
        zero_rows=zero_rows,
    )


def solution_columns(names, lines, file, notes, solution=None) -> list:
    """Columns whose names may carry COMSOL's solution tag (``mf.Bx (T) @ t=0.1``).

    One solution: the tag is dropped for the column's role and said in a note. Several (a
    parametric or time-dependent export holds one column per component and solution): the one
    named by ``solution`` is the map, and the field columns of the others get no role (as if
    absent); without ``solution`` an error, since which one is the map is the user's choice.

    Parameters
    ----------
    names : list of str
        Column names (or ``% Data`` expressions) in file order.
    lines : list of int
        1-based line where each is written.
    solution : str, optional
        The solution to read, as the tag is written (``'I0=200'``, ``'@ I0=200'``, ``'t=0.1'``);
        compared as text after `normal_tag` (so ``'I0 = 200'`` is ``@ I0=200``), not as numbers.

    Raises
    ------
    CfmInputError
        Several solutions and no ``solution``; a ``solution`` that is none of the export's.
    """
    columns, tags, spelled = [], {}, {}
    for k, (name, line) in enumerate(zip(names, lines, strict=True)):
        base, tag = split_tag(name)
        column = dataclasses.replace(describe_column(base, k, line), name=name)
        columns.append(column)
        if tag and column.role is not None:
            key = normal_tag(tag)
            tags.setdefault(key, []).append(column)
            spelled.setdefault(key, tag.strip())
    listed = ", ".join(f"'@ {t}'" for t in spelled.values())
    if solution is not None:
        wanted = normal_tag(solution)
        if wanted not in tags:
            raise _no_such_solution(solution, tags, listed, columns, lines, file)
        if len(tags) > 1:
            for key, cs in tags.items():
                if key != wanted:
                    for c in cs:
                        columns[c.index] = dataclasses.replace(c, role=None)
            notes.append(f"COMSOL solution '@ {spelled[wanted]}' (of {len(tags)}: {listed})")
        else:
            notes.append(f"COMSOL solution '@ {spelled[wanted]}'")
        return columns
    if len(tags) > 1:
        raise CfmInputError(
            f"the export holds {len(tags)} solutions ({listed}); expected the field of one: "
            f"pass one of the tags as {option_hint('solution')}, e.g. "
            f"{_example(next(iter(tags)))}, or export a single parameter value or time from "
            "COMSOL",
            file=file,
            line=list(tags.values())[1][0].line,
        )
    if tags:
        notes.append(f"COMSOL solution '@ {next(iter(spelled.values()))}'")
    return columns


def _no_such_solution(solution, tags, listed, columns, lines, file) -> CfmInputError:
    """The error for a ``solution`` that is none of the export's ``tags`` (maybe none)."""
    given = option_hint("solution", solution)
    if not tags:
        fields = [c.line for c in columns if c.role in FIELDS]
        return CfmInputError(
            f"{given} names a solution, but no column name carries a COMSOL solution tag "
            "('@ ...'): the export holds one solution; expected no --solution for it",
            file=file,
            line=fields[0] if fields else (lines[0] if lines else None),
        )
    example = _example(next(iter(tags)))
    if len(tags) == 1:
        expects = (f"is not the export's solution ({listed}); --solution expects its tag, "
                   f"{example}, or may be left out")  # fmt: skip
    else:
        expects = (f"is none of the export's {len(tags)} solutions ({listed}); --solution "
                   f"expects one of them, e.g. {example}")  # fmt: skip
    # the line of the first tagged column: the column line, or the first tagged '% Data'
    line = min((c for cs in tags.values() for c in cs), key=lambda c: c.index).line
    return CfmInputError(f"{given} {expects}", file=file, line=line)


def _other_solution(column) -> bool:
    """True for a column of a solution that `solution_columns` did not choose: its name carries
    a solution tag, its base name a role, and it has no role."""
    base, tag = split_tag(column.name)
    return bool(tag) and column.role is None and describe_column(base, 0, None).role is not None


#: Where a COMSOL solution tag starts: `` @ `` (anything after it, as COMSOL writes it), or an
#: ``@`` without blanks around it before a parameter name and ``=`` (``mf.Bx(T)@t=0``).
_TAG_AT = re.compile(r"\s@\s|\s*@(?=\s*[A-Za-z_][\w.]*\s*=)")


def split_tag(name: str) -> tuple[str, str]:
    """``name`` without its COMSOL solution tag, and the tag (``''`` if none):
    ``'mf.Bx (T) @ t=0.1'`` gives ``('mf.Bx (T)', 't=0.1')``, ``'mf.Bx(T)@t=0'`` gives
    ``('mf.Bx(T)', 't=0')``."""
    m = _TAG_AT.search(name)
    if m is None:
        return name, ""
    return name[: m.start()], name[m.end() :].strip()


def normal_tag(tag: str) -> str:
    """A solution tag as compared: no leading ``@``, no blanks around ``=`` and ``,``, other
    runs of blanks as one; the values stay as written (``'@ I0 = 200'`` -> ``'I0=200'``)."""
    text = tag.strip().removeprefix("@")
    text = re.sub(r"\s*([=,])\s*", r"\1", text.strip())
    return re.sub(r"\s+", " ", text)


def _example(key: str) -> str:
    """``--solution TAG`` for the normalised tag ``key``, quoted for a shell if it must be."""
    import shlex

    return f"--solution {shlex.quote(key)}"


def _split(lines, start, file) -> list[dict]:
    """Sections from ``lines[start]`` on: kind, label, 1-based header line, rows and their lines."""
    sections = []
    for i in range(start, len(lines)):
        text = lines[i].strip()
        if not text:
            continue
        if text[0] == "%":
            m = _SECTION.match(text[1:].strip())
            if m is None:
                raise CfmInputError(
                    f"unknown section '{text}'; expected '% Elements (type)' or "
                    "'% Data (expression)' after '% Coordinates'",
                    file=file,
                    line=i + 1,
                )
            kind, label = m["kind"].lower(), (m["label"] or "").strip()
            if kind == "coordinates" and sections:
                raise CfmInputError(
                    "a second '% Coordinates' section; expected one per file",
                    file=file,
                    line=i + 1,
                )
            if kind != "coordinates" and not label:
                raise CfmInputError(
                    f"'{text}' names no {'element type' if kind == 'elements' else 'expression'}"
                    f"; expected '% {kind.capitalize()} (...)'",
                    file=file,
                    line=i + 1,
                )
            sections.append({"kind": kind, "label": label, "line": i + 1, "rows": [], "at": []})
            continue
        sections[-1]["rows"].append(lines[i])
        sections[-1]["at"].append(i + 1)
    for s in sections:
        s["row_lines"] = np.asarray(s.pop("at"), dtype=np.int64)
    return sections


def _numbers(section, names, file) -> np.ndarray:
    """The section's rows as numbers, (k, len(names)); messages name the line and the column."""
    if not section["rows"]:
        return np.zeros((0, len(names)))
    return parse_block(
        section["rows"], section["row_lines"], names, range(len(names)), delimiter=None, file=file
    )


def _cells(sections, dim, n, file, notes):
    """The kept elements as 0-based (m, dim + 1) int64, or None (notes say why)."""
    elements = [s for s in sections if s["kind"] == "elements"]
    kept, corners = _KEPT[dim]
    own = _VOLUME if dim == 3 else _SURFACE
    unknown = sorted({s["label"] for s in elements if s["label"].lower() not in _KNOWN})
    if unknown:  # of which dimension? their nodes may be the map's: none is used
        notes.append(f"elements of type {', '.join(unknown)} are not used: {DELAUNAY_NOTE}")
        return None
    mine = [s for s in elements if s["label"].lower() in own]
    if not mine:
        notes.append(f"no {kept} in the export: {DELAUNAY_NOTE}")
        return None
    others = sorted({s["label"] for s in mine if s["label"].lower() != kept})
    if others:
        notes.append(f"elements of type {', '.join(others)} are not used: {DELAUNAY_NOTE}")
        return None
    blocks = []
    for s in mine:
        width = len(s["rows"][0].split()) if s["rows"] else corners
        if width != corners:
            raise CfmInputError(
                f"'% Elements ({s['label']})' rows have {width} node numbers; expected "
                f"{corners} (linear {kept})",
                file=file,
                line=int(s["row_lines"][0]),
            )
        names = [f"node {j + 1}" for j in range(corners)]
        numbers = _numbers(s, names, file)
        bad = (numbers != np.round(numbers)) | (numbers < 1) | (numbers > n)
        if bad.any():
            i, j = np.argwhere(bad)[0]
            raise CfmInputError(
                f"'{names[j]}' of an element of '% Elements ({s['label']})' is "
                f"{numbers[i, j]:g}; expected a node number, a whole number from 1 to {n} (the "
                "rows of '% Coordinates')",
                file=file,
                line=int(s["row_lines"][i]),
                column=names[j],
            )
        blocks.append(numbers.astype(np.int64) - 1)
    cells = np.concatenate(blocks)
    notes.append(f"{len(cells)} {kept} of the export used as the map's cells")
    return cells if len(cells) else None
