"""Field-map readers on small files written here: column mapping, units, notes, format choice."""

from __future__ import annotations

import warnings

import meshio
import numpy as np
import pytest

from cfm_fem.errors import CfmInputError, CfmInputWarning
from cfm_fem.io import (
    _parse,
    detect_format,
    meshfile,
    read_comsol,
    read_field,
    read_meshfile,
    read_opera,
    read_table,
)


def _write(tmp_path, name, text):
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    return path


COMSOL_3D = """\
% Model:              test.mph
% Version:            COMSOL 6.1
% Dimension:          3
% Nodes:              3
% Expressions:        3
% Length unit:        cm
% Z   X   mfnc.BZ (kG)   y   MFNC.bx (kG)   mfnc.By (kG)
1     2   10             3   20             30
4     5   0.5            6   1              2
-7    8   -1             9   -2             -3
"""


# ---------------------------------------------------------------------------- COMSOL


def test_comsol_maps_columns_by_name_in_any_order_and_converts_cm_and_kg(tmp_path):
    path = _write(tmp_path, "map.txt", COMSOL_3D)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        fm = read_comsol(path)
    np.testing.assert_array_equal(fm.points[0], [20.0, 30.0, 10.0])  # x=2 cm, y=3 cm, z=1 cm
    np.testing.assert_allclose(fm.B[0], [2.0, 3.0, 1.0])  # kG -> T: x 0.1
    np.testing.assert_allclose(fm.B[2], [-0.2, -0.3, -0.1])
    np.testing.assert_array_equal(fm.lines, [8, 9, 10])
    assert fm.source == str(path)
    assert any("'cm'" in n and "% Length unit" in n for n in fm.notes)
    assert any("'kG'" in n for n in fm.notes)


def test_comsol_2d_export_gets_z_and_bz_zero(tmp_path):
    text = (
        "% Dimension: 2\n% Nodes: 2\n% Length unit: m\n"
        "% X Y mf.Bx (T) mf.By (T)\n0.1 0.2 1.5 -0.5\n0.3 0.4 2.5 0.25\n"
    )
    fm = read_comsol(_write(tmp_path, "planar.txt", text))
    np.testing.assert_allclose(fm.points, [[100, 200, 0], [300, 400, 0]])
    np.testing.assert_array_equal(fm.B, [[1.5, -0.5, 0.0], [2.5, 0.25, 0.0]])
    assert any("no 'z' column" in n for n in fm.notes)
    assert any("no 'Bz' column" in n for n in fm.notes)


def test_comsol_3d_export_without_z_is_an_error(tmp_path):
    text = "% Dimension: 3\n% Length unit: mm\n% X Y mf.Bx (T) mf.By (T) mf.Bz (T)\n1 2 3 4 5\n"
    with pytest.raises(CfmInputError, match=r"missing column\(s\) 'z'"):
        read_comsol(_write(tmp_path, "m.txt", text))


def test_comsol_wrong_node_count_is_a_warning_and_a_note(tmp_path):
    text = COMSOL_3D.replace("% Nodes:              3", "% Nodes:              53742")
    with pytest.warns(CfmInputWarning, match=r":4: header says '% Nodes: 53742' but 3 data rows"):
        fm = read_comsol(_write(tmp_path, "m.txt", text))
    assert fm.n_nodes == 3
    assert any("53742" in n for n in fm.notes)


ZERO_ROWS = """\
% Length unit: mm
% X Y Z mf.Bx (T) mf.By (T) mf.Bz (T)
0 0 0 0 0 0
1 0 0 0.5 0 0
2 0 0 0 0 0
3 0 0 0 0 0.25
"""


def test_zero_rows_warn_keeps_them_and_says_how_to_drop(tmp_path):
    path = _write(tmp_path, "z.txt", ZERO_ROWS)
    with pytest.warns(CfmInputWarning, match=r"2 row\(s\).*first at line 3.*zero_rows='drop'"):
        fm = read_comsol(path)
    assert fm.n_nodes == 4
    assert any("2 row(s)" in n for n in fm.notes)


def test_zero_rows_drop_removes_them_with_their_lines(tmp_path):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        fm = read_comsol(_write(tmp_path, "z.txt", ZERO_ROWS), zero_rows="drop")
    np.testing.assert_array_equal(fm.points[:, 0], [1.0, 3.0])
    np.testing.assert_array_equal(fm.lines, [4, 6])
    assert any("dropped" in n and "2 row(s)" in n for n in fm.notes)


def test_zero_rows_keep_is_silent_but_noted(tmp_path):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        fm = read_comsol(_write(tmp_path, "z.txt", ZERO_ROWS), zero_rows="keep")
    assert fm.n_nodes == 4
    assert any(
        "kept, as asked by --zero-rows keep (zero_rows='keep' from Python)" in n for n in fm.notes
    )


def test_comsol_spreadsheet_csv_is_read(tmp_path):
    text = "% Model,m.mph\n% X,Y,Z,mf.Bx (T),mf.By (T),mf.Bz (T)\n1,2,3,0.1,0.2,0.3\n"
    fm = read_comsol(_write(tmp_path, "m.csv", text), length_unit="mm")
    np.testing.assert_array_equal(fm.B, [[0.1, 0.2, 0.3]])


def test_comsol_length_unit_option_overrides_header_with_warning(tmp_path):
    path = _write(tmp_path, "m.txt", COMSOL_3D)
    with pytest.warns(
        CfmInputWarning,
        match=r"--length-unit m \(length_unit='m' from Python\) overrides the file's 'cm'",
    ):
        fm = read_comsol(path, length_unit="m")
    np.testing.assert_array_equal(fm.points[0], [2000.0, 3000.0, 1000.0])


def test_comsol_without_length_unit_asks_for_it(tmp_path):
    text = "% X Y Z mf.Bx (T) mf.By (T) mf.Bz (T)\n1 2 3 0.1 0.2 0.3\n"
    path = _write(tmp_path, "m.txt", text)
    with pytest.raises(
        CfmInputError, match=r"no length unit for columns 'X', 'Y', 'Z'.*length_unit"
    ):
        read_comsol(path)
    assert read_comsol(path, length_unit="in").points[0, 0] == pytest.approx(25.4)


# ---------------------------------------------------------------------------- Opera

OPERA = """\
 2 3 2 2
 1 X [MM]
 2 Y [mm]
 3 Z [Mm]
 4 BX [GAUSS]
 5 BY [gauss]
 6 BZ [Gauss]
 7 B [GAUSS]
 0
"""


def _opera_rows(xs, ys, zs):
    rows = []
    for x in xs:
        for y in ys:
            for z in zs:
                rows.append(f" {x} {y} {z} {x + y} {10 * z} -3.5E+02 999\n")
    return "".join(rows)


def test_opera_reads_units_in_any_case_and_ignores_extra_columns(tmp_path):
    path = _write(tmp_path, "f.table", OPERA + _opera_rows([0, 5], [0, 5, 10], [-1, 1]))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # counts 2 3 2 match 2 x, 3 y, 2 z values
        fm = read_opera(path)
    assert fm.n_nodes == 12
    np.testing.assert_array_equal(fm.points[1], [0.0, 0.0, 1.0])
    np.testing.assert_allclose(fm.B[-1], [15e-4, 10e-4, -350e-4])  # gauss -> T
    np.testing.assert_array_equal(fm.lines[:2], [10, 11])


def test_opera_count_mismatch_is_a_warning(tmp_path):
    """More rows than the counts make: a warning (the rows are valid nodes)."""
    text = OPERA.replace(" 2 3 2 2", " 1 3 2 2") + _opera_rows([0, 5], [0, 5, 10], [-1, 1])
    with pytest.warns(CfmInputWarning, match=r"point counts \[1, 3, 2\] do not match"):
        fm = read_opera(_write(tmp_path, "f.table", text))
    assert any("point counts" in n for n in fm.notes)


def test_opera_fewer_rows_than_its_counts_is_refused(tmp_path):
    text = OPERA.replace(" 2 3 2 2", " 4 3 2 2") + _opera_rows([0, 5], [0, 5, 10], [-1, 1])
    what = r"f.table:1: the point counts \[4, 3, 2\] make 24 rows but only 12 data rows follow"
    with pytest.raises(CfmInputError, match=what):
        read_opera(_write(tmp_path, "f.table", text))


def test_opera_metre_and_tesla_with_five_columns(tmp_path):
    text = (
        " 1 1 2 2\n 1 x [METRE]\n 2 Y [M]\n 3 Z [metre]\n 4 Bx [TESLA]\n 5 BY [T]\n 6 BZ [T]\n 0\n"
    )
    text += " 0.1 0.2 3 1 2 3\n 0.1 0.2 4 1 2 3\n"
    fm = read_opera(_write(tmp_path, "f.table", text))
    np.testing.assert_allclose(fm.points, [[100, 200, 3000], [100, 200, 4000]])
    bad = text.replace("[metre]", "[CM]")
    with pytest.raises(CfmInputError, match=r"mixed length units .*'Z' \(CM\)"):
        read_opera(_write(tmp_path, "g.table", bad))


def test_opera_column_without_unit_needs_the_option(tmp_path):
    rows = _opera_rows([0, 5], [0, 5, 10], [-1, 1])
    text = OPERA.replace(" 1 X [MM]", " 1 X")  # Y and Z still say MM: applied to X
    fm = read_opera(_write(tmp_path, "f.table", text + rows))
    assert any("applied also to 'X'" in n for n in fm.notes)
    text = text.replace(" 2 Y [mm]", " 2 Y").replace(" 3 Z [Mm]", " 3 Z")
    path = _write(tmp_path, "g.table", text + rows)
    with pytest.raises(CfmInputError, match=r"no length unit for columns 'X', 'Y', 'Z'") as info:
        read_opera(path)
    assert str(info.value).startswith(f"{path}:2: ")
    assert info.value.column == "X"
    assert read_opera(path, length_unit="cm").points[1, 2] == pytest.approx(10.0)


# ---------------------------------------------------------------------------- plain tables


@pytest.mark.parametrize(
    ("header", "sep", "mm", "tesla"),
    [
        ("x [mm],y [mm],z [mm],Bx [T],By [T],Bz [T]", ",", 1.0, 1.0),
        ("x (in) y (in) z (in) Bx_mT By_mT Bz_mT", " ", 25.4, 1e-3),
        ("X [inch]\tY [inch]\tZ [inch]\tBX [G]\tBY [G]\tBZ [G]", "\t", 25.4, 1e-4),
        ("x_m;y_m;z_m;Bx (kG);By (kG);Bz (kG)", ";", 1000.0, 0.1),
        ("x[cm] y[cm] z[cm] b_x[T] b_y[T] b_z[T]", " ", 10.0, 1.0),
    ],
)
def test_table_units_in_column_names(tmp_path, header, sep, mm, tesla):
    rows = [[1.0, 2.0, 3.0, 4.0, 5.0, 6.0], [-1.5, 0.0, 2.25, -4.0, 0.5, 1e-3]]
    text = header + "\n" + "\n".join(sep.join(map(str, r)) for r in rows) + "\n"
    fm = read_table(_write(tmp_path, "t.csv", text))
    expected = np.array(rows)
    np.testing.assert_allclose(fm.points, expected[:, :3] * mm, rtol=1e-15)
    np.testing.assert_allclose(fm.B, expected[:, 3:] * tesla, rtol=1e-15)


def test_table_columns_by_name_with_extra_text_column(tmp_path):
    text = (
        "# probe run 7\n"
        "Bz [T],label,y [mm],By [T],x [mm],Bx [T],z [mm]\n"
        "3,first,20,2,10,1,30\n"
        "# a comment between rows\n"
        "\n"
        "6,second,21,5,11,4,31\n"
    )
    fm = read_table(_write(tmp_path, "t.csv", text))
    np.testing.assert_array_equal(fm.points, [[10, 20, 30], [11, 21, 31]])
    np.testing.assert_array_equal(fm.B, [[1, 2, 3], [4, 5, 6]])
    np.testing.assert_array_equal(fm.lines, [3, 6])


def test_table_quoted_thousands_separators(tmp_path):
    text = 'X [inch],Y [inch],Z [inch],Bx [T],By [T],Bz [T]\n"1,066.67",-2,"-1,000",0.1,0.2,0.3\n'
    with pytest.warns(CfmInputWarning, match="-1,000 read with ','"):  # 1000 or -1.0?
        fm = read_table(_write(tmp_path, "t.csv", text))
    np.testing.assert_allclose(fm.points[0], [1066.67 * 25.4, -50.8, -25400.0])


def test_thousands_separators_only_where_they_cannot_be_decimal_commas(tmp_path):
    text = "x [mm] y [mm] z [mm] Bx [T] By [T] Bz [T]\n1,066.5 2 3 0.1 0.2 0.3\n"
    fm = read_table(_write(tmp_path, "a.txt", text))
    assert fm.points[0, 0] == 1066.5
    text = text.replace("1,066.5", "1,066")  # 1066 or 1.066? refuse to guess
    with pytest.raises(
        CfmInputError,
        match=r":2: column 'x \[mm\]' must be a number; found '1,066', which is 1066 with a "
        r"thousands separator or 1\.066 with a decimal comma",
    ):
        read_table(_write(tmp_path, "b.txt", text))
    with pytest.raises(CfmInputError, match=r"found '0,125', which has a decimal comma"):
        read_table(_write(tmp_path, "c.txt", text.replace("1,066", '"0,125"')))


def test_table_without_units_needs_options(tmp_path):
    path = _write(tmp_path, "t.csv", "x,y,z,Bx,By,Bz\n1,2,3,4,5,6\n")
    with pytest.raises(CfmInputError, match=r"no length unit.*length_unit='mm'"):
        read_table(path)
    with pytest.raises(CfmInputError, match=r"no field unit for columns 'Bx', 'By', 'Bz'"):
        read_table(path, length_unit="mm")
    fm = read_table(path, length_unit="mm", field_unit="mT")
    np.testing.assert_allclose(fm.B, [[4e-3, 5e-3, 6e-3]])


def test_table_unit_on_one_coordinate_applies_to_all_with_a_note(tmp_path):
    fm = read_table(_write(tmp_path, "t.csv", "x [cm],y,z,Bx [T],By [T],Bz [T]\n1,2,3,4,5,6\n"))
    np.testing.assert_array_equal(fm.points, [[10, 20, 30]])
    assert any("applied also to 'y', 'z'" in n for n in fm.notes)


def test_table_prefers_the_magnet_frame_coordinate(tmp_path):
    text = "x [mm],y [mm],Z(stage),Zmagnet,Bx [T],By [T],Bz [T]\n1,2,100,40,0.1,0.2,0.3\n"
    fm = read_table(_write(tmp_path, "t.csv", text), length_unit="mm")
    assert fm.points[0, 2] == 40.0
    assert any("'Zmagnet'" in n and "'Z(stage)'" in n for n in fm.notes)


def test_table_two_plain_candidates_are_ambiguous(tmp_path):
    path = _write(tmp_path, "t.csv", "x,y,z,Z,Bx,By,Bz\n1,2,3,4,5,6,7\n")
    with pytest.raises(CfmInputError, match=r"several columns could be 'z': 'z', 'Z'"):
        read_table(path, length_unit="mm", field_unit="T")


def test_clean_numeric_file_takes_the_fast_path(tmp_path, monkeypatch):
    rows = "\n".join(f"{i},{i + 1},{i + 2},0.{i + 1},0.2,0.3" for i in range(200))
    path = _write(tmp_path, "t.csv", "x [mm],y [mm],z [mm],Bx [T],By [T],Bz [T]\n" + rows + "\n")

    def no_scan(*args, **kwargs):
        raise AssertionError("slow scan used on a clean file")

    monkeypatch.setattr(_parse, "_scan_rows", no_scan)
    fm = read_table(path)
    assert fm.n_nodes == 200
    assert fm.lines[-1] == 201


# ---------------------------------------------------------------------------- meshio formats

TETRA_POINTS = np.array(
    [[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1], [2, 0, 0], [0, 2, 0], [0, 0, 2]],
    dtype=float,
)
TETRA_FIELD = np.arange(24, dtype=float).reshape(8, 3) / 10 + 0.05


def _mesh_file(tmp_path, name, cells, point_data, points=TETRA_POINTS):
    path = tmp_path / name
    fmt = "gmsh22" if name.endswith(".msh") else None  # meshio would pick ANSYS for .msh
    meshio.write(path, meshio.Mesh(points, cells, point_data=point_data), file_format=fmt)
    return path


def test_vtu_with_b_vector_keeps_tetrahedra_and_assumes_mm_and_t(tmp_path):
    cells = [("tetra", np.array([[0, 1, 2, 3], [1, 2, 3, 4]]))]
    fm = read_field(_mesh_file(tmp_path, "m.vtu", cells, {"B": TETRA_FIELD}))
    np.testing.assert_array_equal(fm.points, TETRA_POINTS)
    np.testing.assert_array_equal(fm.B, TETRA_FIELD)
    np.testing.assert_array_equal(fm.cells, [[0, 1, 2, 3], [1, 2, 3, 4]])
    assert fm.cells.dtype == np.int64
    assert fm.lines is None
    assert any("assumed" in n and "'mm'" in n for n in fm.notes)
    assert any("assumed" in n and "'T'" in n for n in fm.notes)


def test_mesh_components_and_units_from_options(tmp_path):
    data = {"Bx": TETRA_FIELD[:, 0], "By": TETRA_FIELD[:, 1], "Bz": TETRA_FIELD[:, 2]}
    path = _mesh_file(tmp_path, "m.vtk", [("tetra", np.array([[0, 1, 2, 3]]))], data)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # an option replacing an assumption is not a conflict
        fm = read_field(path, length_unit="m", field_unit="mT")
    np.testing.assert_array_equal(fm.points, TETRA_POINTS * 1000)
    np.testing.assert_allclose(fm.B, TETRA_FIELD * 1e-3)


def test_mesh_field_unit_from_point_data_name(tmp_path):
    path = _mesh_file(
        tmp_path, "m.vtu", [("vertex", np.arange(8)[:, None])], {"mf.B (G)": TETRA_FIELD}
    )
    fm = read_field(path)
    np.testing.assert_allclose(fm.B, TETRA_FIELD * 1e-4)
    assert fm.cells is None


def test_gmsh_tetra10_uses_corner_nodes_and_ignores_boundary_triangles(tmp_path):
    points = np.vstack([TETRA_POINTS, TETRA_POINTS[:2] + 5.0])  # 10 nodes
    field = np.vstack([TETRA_FIELD, TETRA_FIELD[:2] + 1.0])
    cells = [("triangle", np.array([[0, 1, 2]])), ("tetra10", np.arange(10)[None, :])]
    path = _mesh_file(tmp_path, "m.msh", cells, {"magnetic_flux_density": field}, points)
    fm = read_field(path)
    np.testing.assert_array_equal(fm.cells, [[0, 1, 2, 3]])
    assert any("tetra10" in n and "4 corner nodes" in n for n in fm.notes)


def test_hexahedra_are_dropped_with_a_delaunay_note(tmp_path):
    path = _mesh_file(
        tmp_path, "m.vtu", [("hexahedron", np.arange(8)[None, :])], {"B": TETRA_FIELD}
    )
    fm = read_field(path)
    assert fm.cells is None
    assert any("hexahedron" in n and "Delaunay" in n for n in fm.notes)


def test_planar_triangles_from_2d_points(tmp_path, monkeypatch):
    points2 = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [1.0, 1.0]])
    mesh = meshio.Mesh(
        points2, [("triangle", np.array([[0, 1, 2], [1, 3, 2]]))], point_data={"B": TETRA_FIELD[:4]}
    )
    path = tmp_path / "planar.vtu"
    path.write_bytes(b"placeholder")  # the reading is replaced: 2-D points survive no writer
    monkeypatch.setattr(meshfile, "_meshio_read", lambda *a, **k: mesh)
    fm = read_meshfile(path)
    np.testing.assert_array_equal(fm.points[:, 2], 0.0)
    np.testing.assert_array_equal(fm.cells, [[0, 1, 2], [1, 3, 2]])
    assert any("2-D node coordinates" in n for n in fm.notes)
    assert any("planar map in the plane z = 0.0 mm" in n for n in fm.notes)


def test_triangles_of_a_curved_surface_are_not_used(tmp_path):
    path = _mesh_file(
        tmp_path, "m.vtu", [("triangle", np.array([[0, 1, 2], [1, 3, 4]]))], {"B": TETRA_FIELD}
    )
    fm = read_field(path)
    assert fm.cells is None
    assert any("non-planar" in n for n in fm.notes)


def test_two_vector_candidates_are_ambiguous(tmp_path):
    data = {"B": TETRA_FIELD, "mf.B": TETRA_FIELD}
    path = _mesh_file(tmp_path, "m.vtu", [("tetra", np.array([[0, 1, 2, 3]]))], data)
    with pytest.raises(CfmInputError, match=r"several point data could be the flux density"):
        read_field(path)


def test_mesh_without_field_lists_the_point_data(tmp_path):
    data = {"H": TETRA_FIELD, "T": TETRA_FIELD[:, 0]}
    path = _mesh_file(tmp_path, "m.vtu", [("tetra", np.array([[0, 1, 2, 3]]))], data)
    with pytest.raises(CfmInputError, match=r"expected 'B' .*found 'H', 'T'"):
        read_field(path)


def test_mesh_zero_rows_drop_removes_their_cells(tmp_path):
    field = TETRA_FIELD.copy()
    field[4] = 0.0
    cells = [("tetra", np.array([[0, 1, 2, 3], [1, 2, 3, 4], [5, 6, 7, 0]]))]
    fm = read_field(_mesh_file(tmp_path, "m.vtu", cells, {"B": field}), zero_rows="drop")
    assert fm.n_nodes == 7
    np.testing.assert_array_equal(fm.cells, [[0, 1, 2, 3], [4, 5, 6, 0]])


# ---------------------------------------------------------------------------- format choice


@pytest.mark.parametrize(
    ("name", "text", "expected"),
    [
        ("a.txt", COMSOL_3D, "comsol"),
        ("a.dat", OPERA + " 0 0 0 1 1 1 1\n", "opera"),
        ("a.txt", "x [mm] y [mm] z [mm] Bx [T] By [T] Bz [T]\n1 2 3 4 5 6\n", "table"),
        ("a.csv", "% X,Y,Z,Field X (T),Field Y (T),Field Z (T)\n1,2,3,4,5,6\n", "comsol"),
        ("a.csv", "x [mm],y [mm],z [mm],Bx [T],By [T],Bz [T]\n1,2,3,4,5,6\n", "table"),
        ("a.table", "anything", "opera"),
        ("a.vtu", "", "vtu"),
        ("a.msh", "", "gmsh"),
    ],
)
def test_detect_format(tmp_path, name, text, expected):
    assert detect_format(_write(tmp_path, name, text)) == expected


def test_read_field_dispatches_on_content(tmp_path):
    fm = read_field(_write(tmp_path, "m.txt", COMSOL_3D))
    np.testing.assert_array_equal(fm.points[0], [20.0, 30.0, 10.0])
    fm = read_field(_write(tmp_path, "o.dat", OPERA + _opera_rows([0, 5], [0, 5, 10], [-1, 1])))
    assert fm.n_nodes == 12


def test_read_field_fmt_overrides_the_extension(tmp_path):
    path = _write(tmp_path, "data.bin", "x [mm] y [mm] z [mm] Bx [T] By [T] Bz [T]\n1 2 3 4 5 6\n")
    assert read_field(path, fmt="csv").n_nodes == 1
    with pytest.raises(
        CfmInputError, match=r"unknown format --format excel \(fmt='excel' from Python\)"
    ):
        read_field(path, fmt="excel")


def test_solution_applies_to_comsol_exports_only(tmp_path):
    """A COMSOL file read as another format (--format table) refuses it too."""
    opera = _write(tmp_path, "f.table", OPERA + _opera_rows([0, 5], [0, 5, 10], [-1, 1]))
    table = _write(tmp_path, "m.csv", "x [mm],y [mm],z [mm],Bx [T],By [T],Bz [T]\n1,2,3,4,5,6\n")
    vtu = _mesh_file(tmp_path, "m.vtu", [("tetra", [[0, 1, 2, 3]])], {"B": TETRA_FIELD})
    comsol = _write(tmp_path, "m.txt", COMSOL_3D)
    cases = [(opera, None, "an Opera table"), (table, None, "a table (CSV or blank-separated)"),
             (vtu, None, "a mesh file (vtu)"), (comsol, "table", "a table")]  # fmt: skip
    for path, fmt, what in cases:
        with pytest.raises(CfmInputError) as info:
            read_field(path, fmt=fmt, solution="I0=200")
        assert str(info.value) == (
            f"{path}: --solution I0=200 (solution='I0=200' from Python) applies to COMSOL "
            "exports only (the solutions of a parametric or time-dependent study); this file is "
            f"read as {what}" + (" (CSV or blank-separated)" if fmt else "")
        )
        assert info.value.file == str(path) and info.value.line is None
        if fmt is None:
            assert read_field(path).n_nodes > 0  # the file itself is fine


def test_read_field_rejects_bad_zero_rows_value(tmp_path):
    path = _write(tmp_path, "m.txt", COMSOL_3D)
    with pytest.raises(CfmInputError, match=r"zero_rows must be one of warn, drop, keep"):
        read_field(path, zero_rows="remove")


def test_thousands_separator_without_decimal_point_warns(tmp_path):
    """ "1,250" is 1250 or 1.25 depending on the writer's locale: read as 1250, with a warning."""
    text = 'x [mm],y [mm],z [mm],Bx [T],By [T],Bz [T]\n"1,250",2,3,0.1,0.2,0.3\n'
    with pytest.warns(CfmInputWarning, match=r":2: column 'x \[mm\]': 1,250 read with ','"):
        fm = read_table(_write(tmp_path, "t.csv", text))
    assert fm.points[0, 0] == 1250.0


def test_thousands_separator_warning_once_per_file_when_streamed_in_blocks(tmp_path):
    """The streaming reader (--slabs) parses a file block by block: the ambiguity warning came
    once per block holding a "1,250"; it is said once per file, naming the first."""
    from cfm_fem.io.streaming import open_stream

    rows = "".join(f'"1,25{i}",{i},3,0.1,0.2,0.3\n' for i in range(10))
    path = _write(tmp_path, "t.csv", "x [mm],y [mm],z [mm],Bx [T],By [T],Bz [T]\n" + rows)
    stream = open_stream(path, "table")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")  # as the CLI does: every warning shown
        blocks = list(stream.blocks(rows_per_block=3))
    assert len(blocks) == 4
    said = [str(w.message) for w in caught if "thousands separator" in str(w.message)]
    assert len(said) == 1 and ":2: column 'x [mm]': 1,250 read with ','" in said[0]
    assert np.concatenate([v[:, 0] for v, _ in blocks]).tolist() == [1250.0 + i for i in range(10)]


def test_opera_cut_short_in_its_last_plane_is_refused(tmp_path):
    """A file cut inside its last x plane still holds every distinct x, y, z value: only the row
    count shows the cut (in the in-memory and the streaming reader), and it is refused."""
    text = OPERA + _opera_rows([0, 5], [0, 5, 10], [-1, 1])
    text = text[: text.rindex(" 5 10 -1")]  # the last two rows cut off
    path = _write(tmp_path, "f.table", text)
    what = r"point counts \[2, 3, 2\] make 12 rows but only 10 data rows follow \(2 missing\)"
    with pytest.raises(CfmInputError, match=what):
        read_opera(path)

    from cfm_fem.io.streaming import check_opera_counts, open_stream

    stream = open_stream(path, "opera")
    blocks = list(stream.blocks(rows_per_block=4))
    distinct = [len(np.unique(np.concatenate([v[:, k] for v, _ in blocks]))) for k in range(3)]
    with pytest.raises(CfmInputError, match=what):
        check_opera_counts(stream, distinct)
