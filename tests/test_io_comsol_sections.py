"""COMSOL "Sectionwise" exports: nodes, elements and one data block per expression.

Bad sectionwise files are cases of `tests/test_io_bad_input.py` (``CASES``, "sectionwise: ...").
"""

from __future__ import annotations

import numpy as np
import pytest
import scipy.spatial

from cfm_fem.errors import CfmInputError
from cfm_fem.io import read_field, write_comsol
from cfm_fem.io._parse import header_names
from cfm_fem.models.mesh import build_mesh


def _sectionwise(path, xyz, elements, data, *, dimension=3, length_unit="mm"):
    """Write a sectionwise export: ``elements`` is a list of (type, 0-based rows), ``data`` a list
    of (expression, values); numbers in shortest round-trip text."""
    lines = [
        "% Model:              magnet.mph",
        "% Version:            COMSOL 6.2.0.290",
        f"% Dimension:          {dimension}",
        f"% Nodes:              {len(xyz)}",
        f"% Elements:           {sum(len(rows) for _, rows in elements)}",
        f"% Expressions:        {len(data)}",
        f"% Length unit:        {length_unit}",
        "% Coordinates",
    ]
    lines += [" ".join(repr(float(v)) for v in row) for row in xyz]
    for kind, rows in elements:
        lines.append(f"% Elements ({kind})")
        lines += ["\t".join(str(int(v) + 1) for v in row) for row in rows]
    for name, values in data:
        lines.append(f"% Data ({name})")
        lines += [repr(float(v)) for v in values]
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


@pytest.fixture
def cloud():
    rng = np.random.default_rng(3)
    xyz = rng.uniform(-0.01, 0.01, (40, 3))  # metres
    tets = scipy.spatial.Delaunay(xyz).simplices
    B = np.c_[2.0 * xyz[:, 1], 2.0 * xyz[:, 0], 0.5 + xyz[:, 2]]  # kG
    return xyz, tets, B


def test_sectionwise_reads_nodes_field_and_tetrahedra(tmp_path, cloud):
    xyz, tets, B = cloud
    data = [("mfnc.By (kG)", B[:, 1]), ("mfnc.Bz (kG)", B[:, 2]), ("mfnc.Bx (kG)", B[:, 0])]
    path = _sectionwise(tmp_path / "s.txt", xyz, [("tetrahedra", tets)], data, length_unit="m")
    fm = read_field(path)
    np.testing.assert_allclose(fm.points, 1000.0 * xyz, rtol=1e-15)
    np.testing.assert_allclose(fm.B, 0.1 * B, rtol=1e-15)
    np.testing.assert_array_equal(fm.cells, tets)
    assert "40 tetrahedra" not in " ".join(fm.notes)  # the count is of cells, not of nodes
    assert f"{len(tets)} tetrahedra of the export used as the map's cells" in fm.notes
    np.testing.assert_array_equal(fm.lines, np.arange(9, 9 + len(xyz)))  # coordinate rows
    mesh = build_mesh(fm)
    assert mesh.kind == "native"
    assert len(mesh.simplices) == len(tets)
    # the same map as a spreadsheet export: the same nodes and field
    write_comsol(tmp_path / "plain.txt", fm)
    plain = read_field(tmp_path / "plain.txt")
    np.testing.assert_array_equal(plain.points, fm.points)
    np.testing.assert_array_equal(plain.B, fm.B)
    assert plain.cells is None


def test_sectionwise_2d_export_keeps_its_triangles(tmp_path):
    xy = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [1.0, 1.0]])
    tri = np.array([[0, 1, 2], [1, 3, 2]])
    data = [("mf.Bx (T)", [0.1, 0.2, 0.3, 0.4]), ("mf.By (T)", [1.0, 1.0, 1.0, 1.5])]
    fm = read_field(_sectionwise(tmp_path / "s.txt", xy, [("triangles", tri)], data, dimension=2))
    np.testing.assert_array_equal(fm.points, np.c_[xy, np.zeros(4)])
    np.testing.assert_array_equal(fm.B[:, 2], 0.0)
    np.testing.assert_array_equal(fm.cells, tri)
    assert "2-D export ('% Dimension: 2'): z = 0" in fm.notes


def test_sectionwise_other_volume_elements_fall_back_to_delaunay(tmp_path, cloud):
    xyz, tets, B = cloud
    hexa = np.arange(8)[None, :]
    data = [(f"mf.B{a} (T)", B[:, k]) for k, a in enumerate("xyz")]
    elements = [("tetrahedra", tets), ("hexahedra", hexa)]
    fm = read_field(_sectionwise(tmp_path / "s.txt", xyz, elements, data))
    assert fm.cells is None
    assert any(n.startswith("elements of type hexahedra are not used: interpolation will use a "
                            "Delaunay") for n in fm.notes), fm.notes  # fmt: skip
    assert build_mesh(fm).kind == "delaunay"


def test_sectionwise_boundary_elements_are_ignored(tmp_path, cloud):
    xyz, tets, B = cloud
    hull = scipy.spatial.ConvexHull(xyz).simplices
    data = [(f"mf.B{a} (T)", B[:, k]) for k, a in enumerate("xyz")]
    elements = [("triangles", hull), ("tetrahedra", tets), ("edges", hull[:, :2])]
    fm = read_field(_sectionwise(tmp_path / "s.txt", xyz, elements, data))
    np.testing.assert_array_equal(fm.cells, tets)


def test_sectionwise_through_the_cli_uses_the_export_cells(tmp_path, cloud, capsys):
    from cfm_fem.cli import main

    xyz, tets, B = cloud
    data = [(f"mf.B{a} (T)", B[:, k]) for k, a in enumerate("xyz")]
    path = _sectionwise(tmp_path / "s.txt", xyz * 1000.0, [("tetrahedra", tets)], data)
    out = tmp_path / "out"
    assert main(["sweep", str(path), "--up", "0:20:10", "--trials", "50", "--out", str(out)]) == 0
    said = capsys.readouterr().out
    assert "linear interpolation in the export's own cells" in said, said
    assert (out / "sweep.pvd").exists()


def test_one_comsol_solution_is_read_and_named(tmp_path, cloud):
    """A single-solution export tags its expressions ("mf.Bx (T) @ I0=100, p=2"), in both
    layouts; the tag is said in a note (two solutions: `tests/test_io_bad_input.py` CASES)."""
    xyz, tets, B = cloud
    tag = " @ I0=100, p=2"
    data = [(f"mf.B{a} (T){tag}", B[:, k]) for k, a in enumerate("xyz")]
    sect = read_field(_sectionwise(tmp_path / "s.txt", xyz, [("tetrahedra", tets)], data))
    header = "% Length unit: mm\n% X Y Z " + " ".join(name for name, _ in data) + "\n"
    rows = "".join(" ".join(repr(float(v)) for v in r) + "\n" for r in np.c_[xyz, B])
    (tmp_path / "p.txt").write_text(header + rows, encoding="utf-8")
    plain = read_field(tmp_path / "p.txt")
    for fm in (sect, plain):
        np.testing.assert_array_equal(fm.B, B)
        assert "COMSOL solution '@ I0=100, p=2'" in fm.notes


# --------------------------------------------------------------------------- several solutions

CURRENTS = ("100", "200")


def _two_fields(cloud):
    """The cloud's field at I0=100 and a different one at I0=200 (T)."""
    xyz, _, B = cloud
    return {"100": B, "200": np.c_[-B[:, 2], 3.0 * B[:, 0], 0.25 + B[:, 1]]}


def _spreadsheet(path, xyz, fields, *, tag="@ I0={}", delimiter=" "):
    """A COMSOL text export holding one column per component and solution ("mf.Bx (T) @ I0=100");
    ``fields`` maps the tag's value to B (n, 3); line 3 is the column line."""
    names = ["X", "Y", "Z"] + [f"mf.B{a} (T) {tag.format(v)}" for v in fields for a in "xyz"]
    values = np.hstack([xyz, *fields.values()])
    rows = "".join(delimiter.join(repr(float(v)) for v in r) + "\n" for r in values)
    header = "% Model:              magnet.mph\n% Length unit:        mm\n"
    path.write_text(header + "% " + delimiter.join(names) + "\n" + rows, encoding="utf-8")
    return path


def _sectionwise_solutions(path, cloud, fields):
    xyz, tets, _ = cloud
    data = [(f"mf.B{a} (T) @ I0={v}", B[:, k]) for v, B in fields.items() for k, a in
            enumerate("xyz")]  # fmt: skip
    return _sectionwise(path, xyz, [("tetrahedra", tets)], data)


def _first_data_line(path):
    """1-based line of the first '% Data' block of a sectionwise export."""
    lines = path.read_text().splitlines()
    return next(i + 1 for i, s in enumerate(lines) if s.startswith("% Data"))


@pytest.mark.parametrize("delimiter", [" ", ","])
def test_spreadsheet_export_of_a_current_sweep_reads_the_chosen_solution(tmp_path, cloud,
                                                                         delimiter):  # fmt: skip
    fields = _two_fields(cloud)
    path = _spreadsheet(tmp_path / "sweep.txt", cloud[0], fields, delimiter=delimiter)
    of_two = "(of 2: '@ I0=100', '@ I0=200')"
    for solution, current in [("I0=100", "100"), ("@ I0 = 200", "200"), ("@I0=200", "200")]:
        fm = read_field(path, solution=solution)
        np.testing.assert_array_equal(fm.B, fields[current])
        np.testing.assert_array_equal(fm.points, cloud[0])
        assert f"COMSOL solution '@ I0={current}' {of_two}" in fm.notes, fm.notes
    # the two solutions differ, so each call really took its own columns
    assert not np.allclose(fields["100"], fields["200"])


@pytest.mark.parametrize("layout", ["spreadsheet", "sectionwise"])
def test_several_solutions_without_a_choice_ask_for_solution(tmp_path, cloud, layout):
    fields = _two_fields(cloud)
    path = tmp_path / "sweep.txt"
    if layout == "spreadsheet":
        _spreadsheet(path, cloud[0], fields)
        line = 3
    else:
        _sectionwise_solutions(path, cloud, fields)
        line = _first_data_line(path) + 3 * (len(cloud[0]) + 1)  # the first '@ I0=200' block
    with pytest.raises(CfmInputError) as info:
        read_field(path)
    msg = str(info.value)
    assert msg.startswith(f"{path}:{line}: the export holds 2 solutions ('@ I0=100', "
                          "'@ I0=200'); expected the field of one"), msg  # fmt: skip
    assert "pass one of the tags as --solution TAG (solution= from Python)" in msg
    assert "e.g. --solution I0=100" in msg
    assert "or export a single parameter value or time from COMSOL" in msg
    assert info.value.line == line


@pytest.mark.parametrize("layout", ["spreadsheet", "sectionwise"])
@pytest.mark.parametrize("solution", ["I0=300", "I0=1e2", "t=0"])
def test_an_unknown_solution_lists_the_export_s_tags(tmp_path, cloud, layout, solution):
    """Compared as text: 1e2 is not 100."""
    path = tmp_path / "sweep.txt"
    if layout == "spreadsheet":
        _spreadsheet(path, cloud[0], _two_fields(cloud))
        line = 3
    else:
        _sectionwise_solutions(path, cloud, _two_fields(cloud))
        line = _first_data_line(path)
    with pytest.raises(CfmInputError) as info:
        read_field(path, solution=solution)
    assert str(info.value) == (
        f"{path}:{line}: --solution {solution} (solution='{solution}' from Python) is none of "
        "the export's 2 solutions ('@ I0=100', '@ I0=200'); --solution expects one of them, "
        "e.g. --solution I0=100"
    )
    assert info.value.file == str(path) and info.value.line == line


def test_sectionwise_export_of_a_current_sweep_reads_the_chosen_solution(tmp_path, cloud):
    xyz, tets, _ = cloud
    fields = _two_fields(cloud)
    path = _sectionwise_solutions(tmp_path / "s.txt", cloud, fields)
    for solution, current in [("I0=100", "100"), ("@ I0 = 200", "200")]:
        fm = read_field(path, solution=solution)
        np.testing.assert_array_equal(fm.B, fields[current])
        np.testing.assert_array_equal(fm.points, xyz)
        np.testing.assert_array_equal(fm.cells, tets)
        assert (f"COMSOL solution '@ I0={current}' (of 2: '@ I0=100', '@ I0=200')"
                in fm.notes), fm.notes  # fmt: skip


def test_sectionwise_blocks_of_the_other_solutions_are_not_read(tmp_path, cloud):
    """They have no role, as if absent: a NaN or a short block there does not matter."""
    xyz, tets, B = cloud
    data = [(f"mf.B{a} (T) @ t=0", B[:, k]) for k, a in enumerate("xyz")]
    data += [("mf.Bx (T) @ t=1", [float("nan")] * len(xyz)), ("mf.By (T) @ t=1", [1.0])]
    path = _sectionwise(tmp_path / "s.txt", xyz, [("tetrahedra", tets)], data)
    np.testing.assert_array_equal(read_field(path, solution="t=0").B, B)
    with pytest.raises(CfmInputError, match="must be a finite number; found nan"):
        read_field(path, solution="t=1")


def test_one_solution_and_a_solution_given(tmp_path, cloud):
    """Accepted when it is the export's tag (noted as without it), refused otherwise; refused
    for an export whose columns carry no tag."""
    xyz, _, B = cloud
    path = _spreadsheet(tmp_path / "one.txt", xyz, {"100, p=2": B})
    for solution in ("I0=100, p=2", "I0=100,p=2", "@ I0 = 100 , p = 2"):
        fm = read_field(path, solution=solution)
        np.testing.assert_array_equal(fm.B, B)
        assert "COMSOL solution '@ I0=100, p=2'" in fm.notes, fm.notes
    with pytest.raises(CfmInputError) as info:
        read_field(path, solution="I0=100")
    assert str(info.value) == (
        f"{path}:3: --solution I0=100 (solution='I0=100' from Python) is not the export's "
        "solution ('@ I0=100, p=2'); --solution expects its tag, --solution I0=100,p=2, or may "
        "be left out"
    )
    plain = _spreadsheet(tmp_path / "plain.txt", xyz, {"": B}, tag="")
    assert "COMSOL solution" not in " ".join(read_field(plain).notes)
    with pytest.raises(CfmInputError) as info:
        read_field(plain, solution="I0=100")
    assert str(info.value).startswith(f"{plain}:3: --solution I0=100 (solution='I0=100' from "
                                      "Python) names a solution, but no column name carries "
                                      "a COMSOL solution tag")  # fmt: skip


@pytest.mark.parametrize("tag", ["@t=0", "@ t=0", " @t=0", "@t=0, p=2"])
def test_a_tag_without_blanks_around_its_at_is_a_tag(tmp_path, cloud, tag):
    """'mf.Bx(T)@t=0' is the column Bx of solution t=0, also without blanks around the @."""
    xyz, tets, B = cloud
    names = [f"mf.B{a}(T){tag}" for a in "xyz"]
    header = "% Length unit: mm\n% X Y Z " + " ".join(names) + "\n"
    rows = "".join(" ".join(repr(float(v)) for v in r) + "\n" for r in np.c_[xyz, B])
    (tmp_path / "p.txt").write_text(header + rows, encoding="utf-8")
    data = [(name, B[:, k]) for k, name in enumerate(names)]
    sect = _sectionwise(tmp_path / "s.txt", xyz, [("tetrahedra", tets)], data)
    spelled = tag.strip().removeprefix("@").strip()
    for path in (tmp_path / "p.txt", sect):
        for solution in (None, "t=0" + spelled[3:]):
            fm = read_field(path, solution=solution)
            np.testing.assert_array_equal(fm.B, B)
            assert f"COMSOL solution '@ {spelled}'" in fm.notes, fm.notes


def test_glued_tags_of_several_solutions(tmp_path, cloud):
    fields = _two_fields(cloud)
    path = _spreadsheet(tmp_path / "g.txt", cloud[0], fields, tag="@I0={}")
    path.write_text(path.read_text().replace(" (T) @", "(T)@"))
    assert "mf.Bx(T)@I0=100 mf.By(T)@I0=100" in path.read_text()
    np.testing.assert_array_equal(read_field(path, solution="I0=200").B, fields["200"])
    with pytest.raises(CfmInputError, match=r"2 solutions \('@ I0=100', '@ I0=200'\)"):
        read_field(path)


@pytest.mark.parametrize(
    "header, names",
    [
        ("X Y Z mf.Bx(T)@t=0 mf.By (T)@t=0", ["X", "Y", "Z", "mf.Bx(T)@t=0", "mf.By (T)@t=0"]),
        ("X mf.Bx (T)@ t=0 mf.By (T) @t=0", ["X", "mf.Bx (T)@ t=0", "mf.By (T) @t=0"]),
        ("X mf.Bx(T)@t=0, p=2 By", ["X", "mf.Bx(T)@t=0, p=2", "By"]),
        ("X mf.Bx (T) @ I0=100, p=2 By", ["X", "mf.Bx (T) @ I0=100, p=2", "By"]),
        # an '@' that starts no tag (no 'name=' after it) is left as it was
        ("x y z Bx By Bz user@host", ["x", "y", "z", "Bx", "By", "Bz", "user@host"]),
        ("x y z B@1 Bx By Bz", ["x", "y", "z", "B@1", "Bx", "By", "Bz"]),
    ],
)
def test_header_names_keep_a_glued_tag_with_its_name(header, names):
    assert header_names(header, None) == names
