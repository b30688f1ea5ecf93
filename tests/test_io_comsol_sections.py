"""COMSOL "Sectionwise" exports: nodes, elements and one data block per expression.

Bad sectionwise files are cases of `tests/test_io_bad_input.py` (``CASES``, "sectionwise: ...").
"""

from __future__ import annotations

import numpy as np
import pytest
import scipy.spatial

from cfm_fem.interpolation import build_mesh
from cfm_fem.io import read_field, write_comsol


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
