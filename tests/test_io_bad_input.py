"""Bad input: one CfmInputError naming the file, the line, the column and what was expected."""

from __future__ import annotations

import meshio
import numpy as np
import pytest

from cfm_fem.errors import CfmInputError
from cfm_fem.io import read_field

CSV_HEADER = "x [mm],y [mm],z [mm],Bx [T],By [T],Bz [T]\n"
GOOD_ROW = "1,2,3,0.1,0.2,0.3\n"
COMSOL_HEAD = "% Nodes: 2\n% Length unit: mm\n% X Y Z mf.Bx (T) mf.By (T) mf.Bz (T)\n"
OPERA_HEAD = " 1 1 1 2\n 1 X [M]\n 2 Y [M]\n 3 Z [M]\n 4 BX [T]\n 5 BY [T]\n 6 BZ [T]\n 0\n"

# COMSOL sectionwise export: a unit cube split into tetrahedra around node 9 at its centre
SECT_HEAD = "% Dimension: 3\n% Nodes: 5\n% Length unit: mm\n% Coordinates\n"
SECT_XYZ = "0 0 0\n1 0 0\n0 1 0\n0 0 1\n1 1 1\n"
SECT_CELLS = "% Elements (tetrahedra)\n1 2 3 4\n2 3 4 5\n"


def _sect_data(values=("0.1",) * 5, sections=("mf.Bx (T)", "mf.By (T)", "mf.Bz (T)")):
    return "".join(f"% Data ({s})\n" + "\n".join(values) + "\n" for s in sections)


# (file name, content, line, column, what the message must say)
CASES = {
    "empty file": ("m.csv", "", None, None, "the file is empty; expected a field map"),
    "blank file": ("m.txt", "\n  \n\t\n", None, None, "the file is empty"),
    "only comments": ("m.csv", "# nothing\n# here\n", None, None, "only comment lines"),
    "data not split like the header": (
        "m.csv",
        CSV_HEADER + "1;2;3;0.1;0.2;0.3\n",
        1,
        None,
        "a column name holds ',': the delimiter looks wrong",
    ),
    "NUL bytes": ("m.csv", CSV_HEADER + GOOD_ROW + "1,2,4\x00\x00\n", 3, None, "NUL bytes in"),
    "header only": (
        "m.csv",
        CSV_HEADER,
        1,
        None,
        "no data rows after the header (line 1); expected one row of 6 numbers per node",
    ),
    "comsol header only": ("m.txt", COMSOL_HEAD, 3, None, "no data rows after the header"),
    "truncated last line": (
        "m.csv",
        CSV_HEADER + GOOD_ROW + "4,5,6,0.4",
        3,
        "By [T]",
        "the row has 4 field(s) but the header names 6; column 'By [T]' is missing (truncated",
    ),
    "truncated blank-separated line": (
        "m.txt",
        COMSOL_HEAD + "1 2 3 0.1 0.2 0.3\n1 2 4 0.1 0.2\n",
        5,
        "mf.Bz (T)",
        "column 'mf.Bz (T)' is missing",
    ),
    "too many fields": (
        "m.csv",
        CSV_HEADER + GOOD_ROW + "1,2,4,0.1,0.2,0.3,7\n",
        3,
        None,
        "the row has 7 fields but the header names only 6",
    ),
    "text in a numeric column": (
        "m.csv",
        "x [mm],y [mm],z [mm],Bx,By [T],Bz [T]\n" + GOOD_ROW + "1,2,4,abc,0.2,0.3\n",
        3,
        "Bx",
        "column 'Bx' must be a number; found 'abc'",
    ),
    "empty field": (
        "m.csv",
        CSV_HEADER + "1,,3,0.1,0.2,0.3\n",
        2,
        "y [mm]",
        "column 'y [mm]' must be a number; found an empty field",
    ),
    "nan": (
        "m.txt",
        COMSOL_HEAD + "1 2 3 0.1 0.2 0.3\n1 2 4 0.1 nan 0.3\n",
        5,
        "mf.By (T)",
        "column 'mf.By (T)' must be a finite number; found nan",
    ),
    "inf": (
        "m.csv",
        CSV_HEADER + GOOD_ROW + "1,2,-inf,0.1,0.2,0.3\n",
        3,
        "z [mm]",
        "column 'z [mm]' must be a finite number; found -inf",
    ),
    "overflow": (
        "m.csv",
        CSV_HEADER + "1,2,3,1e999,0.2,0.3\n",
        2,
        "Bx [T]",
        "column 'Bx [T]' must be a finite number; found inf",
    ),
    "decimal comma": (  # "0,125" must not be taken for 125 (a thousands separator)
        "m.csv",
        CSV_HEADER + '"1,000","0,000","2,000","0,100","0,200","0,300"\n',
        2,
        "y [mm]",
        "column 'y [mm]' must be a number with '.' as decimal point; found '0,000', which has "
        "a decimal comma",
    ),
    "decimal comma, six decimals": (  # "-5,000000" is no thousands group: a decimal comma
        "m.csv",
        "x [mm];y [mm];z [mm];Bx [T];By [T];Bz [T]\n-5,000000;1,5;2,0;0,1;0,2;0,3\n",
        2,
        "x [mm]",
        "column 'x [mm]' must be a number with '.' as decimal point; found '-5,000000', which "
        "has a decimal comma (a thousands group has three digits)",
    ),
    "sectionwise: a data block too short": (
        "m.txt",
        SECT_HEAD
        + SECT_XYZ
        + SECT_CELLS
        + _sect_data(sections=("mf.Bx (T)", "mf.By (T)"))
        + "% Data (mf.Bz (T))\n0.1\n0.1\n0.1\n0.1\n",
        25,
        None,
        "'% Data (mf.Bz (T))' has 4 value(s); expected 5, one per node of '% Coordinates' (line 4)",
    ),
    "sectionwise: NaN in a data block": (
        "m.txt",
        SECT_HEAD
        + SECT_XYZ
        + SECT_CELLS
        + _sect_data(values=("0.1", "0.1", "nan", "0.1", "0.1"), sections=("mf.Bx (T)",))
        + _sect_data(sections=("mf.By (T)", "mf.Bz (T)")),
        16,
        "mf.Bx (T)",
        "'mf.Bx (T)' must be a finite number; found nan",
    ),
    "sectionwise: element node out of range": (
        "m.txt",
        SECT_HEAD + SECT_XYZ + "% Elements (tetrahedra)\n1 2 3 4\n2 3 4 6\n" + _sect_data(),
        12,
        "node 4",
        "'node 4' of an element of '% Elements (tetrahedra)' is 6; expected a node number, a "
        "whole number from 1 to 5",
    ),
    "sectionwise: truncated coordinate row": (
        "m.txt",
        SECT_HEAD + "0 0 0\n1 0 0\n0 1 0\n0 0 1\n1 1\n" + SECT_CELLS + _sect_data(),
        9,
        "Z",
        "the row has 2 field(s) but the header names 3; column 'Z' is missing",
    ),
    "sectionwise: unknown section": (
        "m.txt",
        SECT_HEAD + SECT_XYZ + SECT_CELLS + "% Solution 2\n" + _sect_data(),
        13,
        None,
        "unknown section '% Solution 2'; expected '% Elements (type)' or '% Data (expression)'",
    ),
    "sectionwise: two coordinate sections": (
        "m.txt",
        SECT_HEAD + SECT_XYZ + "% Coordinates\n" + SECT_XYZ + SECT_CELLS + _sect_data(),
        10,
        None,
        "a second '% Coordinates' section; expected one per file",
    ),
    "sectionwise: no By block": (
        "m.txt",
        SECT_HEAD + SECT_XYZ + SECT_CELLS + _sect_data(sections=("mf.Bx (T)", "mf.Bz (T)")),
        4,
        "By",
        "missing column(s) 'By'",
    ),
    "comsol: two solutions": (  # a parametric export: one column per component and solution
        "m.txt",
        "% Length unit: mm\n% X Y Z mf.Bx (T) @ I0=100 mf.By (T) @ I0=100 mf.Bz (T) @ I0=100 "
        "mf.Bx (T) @ I0=200 mf.By (T) @ I0=200 mf.Bz (T) @ I0=200\n0 0 0 1 2 3 2 4 6\n",
        2,
        None,
        "the export holds 2 solutions ('@ I0=100', '@ I0=200'); expected the field of one: "
        "pass one of the tags as --solution TAG (solution= from Python), e.g. --solution I0=100, "
        "or export a single parameter value or time from COMSOL",
    ),
    "comsol: two solutions, tags without blanks": (  # read as names without a role before
        "m.txt",
        "% Length unit: mm\n% X Y Z mf.Bx(T)@t=0 mf.By(T)@t=0 mf.Bz(T)@t=0 mf.Bx(T)@t=0.5 "
        "mf.By(T)@t=0.5 mf.Bz(T)@t=0.5\n0 0 0 1 2 3 2 4 6\n",
        2,
        None,
        "the export holds 2 solutions ('@ t=0', '@ t=0.5'); expected the field of one: pass "
        "one of the tags as --solution TAG",
    ),
    "sectionwise: two solutions": (
        "m.txt",
        SECT_HEAD
        + SECT_XYZ
        + SECT_CELLS
        + _sect_data(sections=("mf.Bx (T) @ t=0", "mf.By (T) @ t=0", "mf.Bz (T) @ t=0"))
        + _sect_data(sections=("mf.Bx (T) @ t=1",)),
        31,
        None,
        "the export holds 2 solutions ('@ t=0', '@ t=1'); expected the field of one: pass one "
        "of the tags as --solution TAG (solution= from Python), e.g. --solution t=0",
    ),
    "unknown length unit": (
        "m.csv",
        "x [furlong],y [furlong],z [furlong],Bx [T],By [T],Bz [T]\n" + GOOD_ROW,
        1,
        "x [furlong]",
        "column 'x [furlong]': unknown length unit 'furlong'; expected one of",
    ),
    "unknown field unit": (
        "m.txt",
        COMSOL_HEAD.replace("mf.By (T)", "mf.By (kT)") + "1 2 3 0.1 0.2 0.3\n",
        3,
        "mf.By (kT)",
        "unknown field unit 'kT'",
    ),
    "field unit on a coordinate": (
        "m.csv",
        "x [T],y [T],z [T],Bx [T],By [T],Bz [T]\n" + GOOD_ROW,
        1,
        "x [T]",
        "unknown length unit 'T'",
    ),
    "mixed length units": (
        "m.csv",
        "x [mm],y [in],z [mm],Bx [T],By [T],Bz [T]\n" + GOOD_ROW,
        1,
        "x [mm]",
        "mixed length units in columns 'x [mm]' (mm), 'y [in]' (in), 'z [mm]' (mm)",
    ),
    "mixed field units": (
        "m.csv",
        "x [mm],y [mm],z [mm],Bx [T],By [mT],Bz [T]\n" + GOOD_ROW,
        1,
        "Bx [T]",
        "mixed field units",
    ),
    "missing column": (
        "m.csv",
        "x [mm],y [mm],z [mm],Bx [T],By [T],B [T]\n" + GOOD_ROW,
        1,
        "Bz",
        "missing column(s) 'Bz': expected coordinates x, y, z and field Bx, By, Bz (any order, "
        "names like 'x [mm]' or 'Bx [T]'); found 'x [mm]', 'y [mm]', 'z [mm]', 'Bx [T]', "
        "'By [T]', 'B [T]'",
    ),
    "no header row": (
        "m.csv",
        GOOD_ROW + GOOD_ROW,
        1,
        None,
        "the first row holds numbers, not column names; expected a header row such as "
        "'x [mm],y [mm],z [mm],Bx [T],By [T],Bz [T]'",
    ),
    "comsol without column line": (
        "m.txt",
        "% Model: m\n% Length unit: mm\n1 2 3 4 5 6\n",
        3,
        None,
        "no column line such as '% X Y Z mf.Bx (T) mf.By (T) mf.Bz (T)'",
    ),
    "opera without end of header": (
        "m.table",
        OPERA_HEAD.replace(" 0\n", "") + " -0.1 0.2 0.3 1 2 3\n",
        8,
        None,
        "expected column definition '7 <NAME> [<UNIT>]' or the line '0' ending the header; "
        "found '-0.1 0.2 0.3 1 2 3'",
    ),
    "opera header never ends": (
        "m.table",
        OPERA_HEAD.replace(" 0\n", ""),
        7,
        None,
        "the header never ends: expected a line '0' after the 6 column definition(s)",
    ),
    "opera bad counts line": (
        "m.table",
        "counts: 21 11 41\n" + OPERA_HEAD.split("\n", 1)[1] + " 1 2 3 4 5 6\n",
        1,
        None,
        "line 1 of an Opera table must hold the point counts and a trailing flag",
    ),
    "opera column numbering": (
        "m.table",
        OPERA_HEAD.replace(" 3 Z [M]", " 4 Z [M]"),
        4,
        None,
        "expected column definition '3 <NAME> [<UNIT>]'",
    ),
    "opera header only": ("m.table", OPERA_HEAD, 2, None, "no data rows after the header"),
    "duplicate node with another field": (
        "m.csv",
        CSV_HEADER + GOOD_ROW + "1,2,3,0.5,0.2,0.3\n",
        3,
        None,
        "duplicate node at [1.0, 2.0, 3.0] mm (also on line 2) with a different field",
    ),
    "near-duplicate node with another field": (  # twins 1e-12 mm apart, not neighbours in sort
        "m.csv",
        CSV_HEADER + "0,1,0,0.1,0,0.5\n0,2,0,0.2,0,0.5\n1e-12,1,0,0.9,0.9,0.9\n",
        4,
        None,
        "duplicate node at [1e-12, 1.0, 0.0] mm (also on line 2) with a different field",
    ),
}


@pytest.mark.parametrize("case", list(CASES))
def test_bad_file_gives_one_clear_error(tmp_path, case):
    name, text, line, column, what = CASES[case]
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    with pytest.raises(CfmInputError) as info:
        read_field(path)
    error = info.value
    prefix = f"{path}:{line}: " if line is not None else f"{path}: "
    assert str(error).startswith(prefix), str(error)
    assert what in str(error), str(error)
    assert error.file == str(path)
    assert error.line == line
    if column is not None:
        assert error.column == column


def test_missing_file(tmp_path):
    with pytest.raises(CfmInputError, match=r"cannot read the file"):
        read_field(tmp_path / "absent.csv")
    with pytest.raises(CfmInputError, match=r"cannot read the file: it does not exist"):
        read_field(tmp_path / "absent.vtu")


def test_corrupt_mesh_file(tmp_path):
    path = tmp_path / "broken.vtu"
    path.write_text("<VTKFile><UnstructuredGrid>", encoding="utf-8")
    with pytest.raises(CfmInputError, match=r"broken.vtu: cannot read as a 'vtu' mesh file"):
        read_field(path)


def test_empty_or_cut_mesh_file_says_why(tmp_path):
    # meshio's ReadError() has no text: the message ended at "mesh file: "
    good = tmp_path / "good.vtu"
    meshio.write(
        good, meshio.Mesh(np.eye(4, 3), [("tetra", [[0, 1, 2, 3]])], {"B": np.ones((4, 3))})
    )
    cut = tmp_path / "cut.vtu"
    cut.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    empty = tmp_path / "empty.vtu"
    empty.write_bytes(b"")
    with pytest.raises(
        CfmInputError,
        match=r"empty.vtu: cannot read as a 'vtu' mesh file: the file is empty; expected a "
        r"complete vtu file with nodes, cells and point data B$",
    ):
        read_field(empty)
    with pytest.raises(CfmInputError, match=r"cut.vtu: cannot read as a 'vtu' mesh file: \S"):
        read_field(cut)


def test_conflicting_duplicate_in_a_mesh_names_both_nodes(tmp_path):
    # a mesh file has no line numbers: the message said "also on line None"
    pts = np.r_[np.eye(4, 3), [[0.0, 0.0, 0.0]]]
    B = np.r_[np.ones((4, 3)), [[9.0, 9.0, 9.0]]]
    path = tmp_path / "m.vtu"
    meshio.write(path, meshio.Mesh(pts, [("tetra", [[0, 1, 2, 3]])], {"B": B}))
    with pytest.raises(CfmInputError) as info:
        read_field(path)
    assert "(nodes 3 and 4, 0-based) with a different field" in str(info.value), str(info.value)
    assert "None" not in str(info.value)


def test_unknown_extension(tmp_path):
    path = tmp_path / "map.xyz123"
    path.write_text(CSV_HEADER + GOOD_ROW, encoding="utf-8")
    with pytest.raises(CfmInputError, match=r"unknown mesh file extension '.xyz123'.*fmt="):
        read_field(path)


def test_unknown_unit_option(tmp_path):
    path = tmp_path / "m.csv"
    path.write_text("x,y,z,Bx [T],By [T],Bz [T]\n" + GOOD_ROW, encoding="utf-8")
    with pytest.raises(CfmInputError, match=r"unknown length unit 'parsec'"):
        read_field(path, length_unit="parsec")


@pytest.mark.parametrize("encoding", ["utf-16", "utf-16-le", "utf-32"])
@pytest.mark.parametrize("name", ["m.csv", "m.table", "h.csv", "stream.csv"])
def test_utf16_file_is_refused_in_words(tmp_path, encoding, name):
    # read as UTF-8 the message quoted column names full of NUL bytes
    from cfm_fem.io.harmonics import read_harmonics
    from cfm_fem.io.streaming import open_stream

    text = {"m.table": OPERA_HEAD + "0.001 0.002 0.003 0.1 0.2 0.3\n", "h.csv": "n,Bn,An\n2,1,0\n"}
    path = tmp_path / name
    path.write_text(text.get(name, CSV_HEADER + GOOD_ROW), encoding=encoding)
    reader = {"h.csv": read_harmonics, "stream.csv": lambda p: open_stream(p, "table")}
    with pytest.raises(CfmInputError) as info:
        reader.get(name, read_field)(path)
    kind = "UTF-32" if encoding == "utf-32" else "UTF-16"
    assert str(info.value).startswith(f"{path}: the file is {kind}"), str(info.value)
    assert "save it as UTF-8" in str(info.value) and "\x00" not in str(info.value)


def test_comsol_length_unit_contradicting_the_columns_warns(tmp_path):
    from cfm_fem.errors import CfmInputWarning

    path = tmp_path / "c.txt"
    rows = "".join(f"{i} {j} {k} 0 0 1\n" for i in (0, 1) for j in (0, 1) for k in (0, 1))
    path.write_text(
        "% Length unit: m\n% X (mm) Y (mm) Z (mm) mf.Bx (T) mf.By (T) mf.Bz (T)\n" + rows
    )
    with pytest.warns(CfmInputWarning, match=r"column names say 'mm' but the file states 'm'"):
        fm = read_field(path)
    assert fm.points.max() == 1.0  # the column unit is used


def test_error_deep_in_a_large_file_names_its_line(tmp_path):
    rows = [f"{i} 0 0 0.1 0.2 0.3" for i in range(20000)]
    rows[17321] = "17321 0 0 0.1 0.2 O.3"  # letter O for zero
    path = tmp_path / "big.txt"
    path.write_text("x [mm] y [mm] z [mm] Bx [T] By [T] Bz [T]\n" + "\n".join(rows), "utf-8")
    with pytest.raises(CfmInputError) as info:
        read_field(path)
    assert str(info.value) == f"{path}:17323: column 'Bz [T]' must be a number; found 'O.3'"


def test_nan_in_mesh_point_data_names_the_node(tmp_path):
    field = np.ones((4, 3))
    field[3, 1] = np.nan
    path = tmp_path / "m.vtu"
    meshio.write(path, meshio.Mesh(np.eye(4, 3), [("tetra", [[0, 1, 2, 3]])], {"B": field}))
    with pytest.raises(CfmInputError) as info:
        read_field(path)
    assert str(info.value) == (
        f"{path}: column 'B[1]' must be a finite number; found nan at node 3 (0-based)"
    )
