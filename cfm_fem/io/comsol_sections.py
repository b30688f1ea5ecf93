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
from ..field import FieldMap
from ._parse import DELAUNAY_NOTE, build_fieldmap, describe_column, parse_block, table_layout

__all__ = ["is_coordinates_line", "read_sections", "solution_columns"]

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
        file, notes,
    )  # fmt: skip
    blocks = [xyz]
    for section in data:
        label = section["label"]
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


def solution_columns(names, lines, file, notes) -> list:
    """Columns whose names may carry COMSOL's solution tag (``mf.Bx (T) @ t=0.1``).

    One solution: the tag is dropped for the column's role and said in a note. Several (a
    parametric or time-dependent export holds one column per component and solution): an error,
    since which one is the map is the user's choice.

    Parameters
    ----------
    names : list of str
        Column names (or ``% Data`` expressions) in file order.
    lines : list of int
        1-based line where each is written.
    """
    columns, tags = [], {}
    for k, (name, line) in enumerate(zip(names, lines, strict=True)):
        base, _, tag = name.partition(" @ ")
        column = dataclasses.replace(describe_column(base, k, line), name=name)
        columns.append(column)
        if tag and column.role is not None:
            tags.setdefault(tag.strip(), []).append(column)
    if len(tags) > 1:
        listed = ", ".join(f"'@ {t}'" for t in tags)
        raise CfmInputError(
            f"the export holds {len(tags)} solutions ({listed}); expected the field of one: "
            "export a single parameter value or time from COMSOL",
            file=file,
            line=list(tags.values())[1][0].line,
        )
    if tags:
        notes.append(f"COMSOL solution '@ {next(iter(tags))}'")
    return columns


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
