"""`--pieces K`: a partitioned .pvtu per U_p with exactly the numbers of the one-file output."""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET

import numpy as np
import pytest
import pyvista as pv
from vtk_points import by_position, owned_points, vtk_histogram_count

from cfm_fem.cli import main
from cfm_fem.io.vtk import read_text_field


def _write_map(path, n=7):
    ax = np.arange(float(n))
    pts = np.stack(np.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3)
    B = np.c_[0.03 * pts[:, 0] ** 2, -0.02 * pts[:, 1] * pts[:, 2], 1.0 + 0.1 * pts[:, 2]]
    rows = "\n".join(",".join(f"{v:.17g}" for v in r) for r in np.c_[pts, B])
    path.write_text("x [mm],y [mm],z [mm],Bx [T],By [T],Bz [T]\n" + rows + "\n")
    return path


def test_pieces_give_the_numbers_of_the_single_file(tmp_path):
    path = _write_map(tmp_path / "map.csv")
    base = ["sweep", str(path), "--up", "0:30:15", "--trials", "200", "--chunk-nodes", "40"]
    assert main([*base, "--out", str(tmp_path / "one")]) == 0
    assert main([*base, "--pieces", "3", "--out", str(tmp_path / "pc")]) == 0
    one = json.loads((tmp_path / "one" / "summary.json").read_text())
    pc = json.loads((tmp_path / "pc" / "summary.json").read_text())
    assert pc["pieces"] == 3
    for key in set(one) - {"seconds", "provenance"}:
        assert one[key] == pc[key], key
    files = [d.get("file") for d in ET.parse(tmp_path / "pc" / "sweep.pvd").iter("DataSet")]
    assert files == ["uf_up0um.pvtu", "uf_up15um.pvtu", "uf_up30um.pvtu"]
    assert len(list((tmp_path / "pc" / "uf_up15um").glob("piece_*.vtu"))) == 3
    assert not (tmp_path / "pc" / ".cfm_fem_chunks").exists()
    for up in (0, 15, 30):
        g1, a = by_position(pv.read(tmp_path / "one" / f"uf_up{up}um.vtu"))
        g2, b = by_position(pv.read(tmp_path / "pc" / f"uf_up{up}um.pvtu"))  # VTK's reader
        assert g1.n_points == g2.n_points == 343 and g1.n_cells == g2.n_cells
        assert set(a) == set(b)
        for name in a:
            np.testing.assert_array_equal(a[name], b[name], err_msg=name)


def test_nodes_shared_by_pieces_are_counted_once_as_vtk_ghost_points(tmp_path):
    """A node used by cells of several pieces is written in each; every copy but the one in
    the piece whose node range holds it is flagged vtkGhostType = 1, so VTK counts each node
    once, with the values of the one-file output."""
    from cfm_fem.models.sweep import piece_bounds

    path = _write_map(tmp_path / "map.csv")
    base = ["sweep", str(path), "--up", "15", "--trials", "100", "--chunk-nodes", "40"]
    assert main([*base, "--out", str(tmp_path / "one")]) == 0
    assert main([*base, "--pieces", "3", "--out", str(tmp_path / "pc")]) == 0
    one = pv.read(tmp_path / "one" / "uf_up15um.vtu")
    pc = pv.read(tmp_path / "pc" / "uf_up15um.pvtu")
    assert pc.n_points > one.n_points == 343  # the shared nodes are repeated
    pts, b = owned_points(pc)
    order = np.lexsort(np.asarray(one.points).T)
    np.testing.assert_array_equal(pts, np.asarray(one.points)[order])  # each node once
    assert set(b) == set(one.point_data)
    for name in one.point_data:
        np.testing.assert_array_equal(b[name], np.asarray(one.point_data[name])[order], name)
    assert vtk_histogram_count(pc, "U_f_units") == vtk_histogram_count(one, "U_f_units") == 343
    owned = [
        int((np.asarray(pv.read(f).point_data["vtkGhostType"]) == 0).sum())
        for f in sorted((tmp_path / "pc" / "uf_up15um").glob("piece_*.vtu"))
    ]
    assert owned == np.diff(piece_bounds(343, 3)).tolist()  # the owner: the node's range


def test_more_pieces_than_nodes_and_bad_count(tmp_path, capsys):
    path = _write_map(tmp_path / "map.csv", n=3)
    out = tmp_path / "o"
    base = ["sweep", str(path), "--up", "1", "--trials", "50"]
    assert main([*base, "--pieces", "100", "--out", str(out)]) == 0
    assert len(list((out / "uf_up1um").glob("piece_*.vtu"))) == 27
    assert pv.read(out / "uf_up1um.pvtu").n_cells == pv.read(
        out / "uf_up1um" / "piece_0000.vtu"
    ).n_cells + sum(pv.read(p).n_cells for p in sorted((out / "uf_up1um").glob("piece_*.vtu"))[1:])
    assert main([*base, "--pieces", "0", "--out", str(tmp_path / "x")]) == 2
    assert "--pieces must be >= 1" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()


def test_pieces_in_mode_htm_give_the_numbers_of_the_single_file(tmp_path):
    from cfm_fem.io.provenance import read_xml_provenance

    path = _write_map(tmp_path / "map.csv", n=5)
    base = ["sweep", str(path), "--mode", "htm", "--trials", "40", "--chunk-nodes", "30"]
    assert main([*base, "--out", str(tmp_path / "one")]) == 0
    assert main([*base, "--pieces", "2", "--out", str(tmp_path / "pc")]) == 0
    one = json.loads((tmp_path / "one" / "summary.json").read_text())
    pc = json.loads((tmp_path / "pc" / "summary.json").read_text())
    for key in set(one) - {"seconds", "provenance"}:
        assert one[key] == pc[key], key  # up_um too: the RMS probe error of each column
    files = [d.get("file") for d in ET.parse(tmp_path / "pc" / "sweep.pvd").iter("DataSet")]
    assert files == ["uf_htm_total.pvtu", "uf_htm_geometric.pvtu", "uf_htm_vibration_delay.pvtu"]
    assert read_xml_provenance(tmp_path / "pc" / "sweep.pvd") == pc["provenance"]
    assert read_xml_provenance(tmp_path / "one" / "sweep.pvd") == one["provenance"]
    g1, a = by_position(pv.read(tmp_path / "one" / "uf_htm_geometric.vtu"))
    g2, b = by_position(pv.read(tmp_path / "pc" / "uf_htm_geometric.pvtu"))
    assert g1.n_points == g2.n_points == 125 and g1.n_cells == g2.n_cells
    assert "positioning_std_um" in b
    # the time axis of mode htm (0, 1, 2) is named by each map's field data
    for k, col in enumerate(("htm_total", "htm_geometric", "htm_vibration_delay")):
        m = pv.read(tmp_path / "one" / f"uf_{col}.vtu")
        assert read_text_field(m.field_data, "column") == col
        assert m.field_data["U_p_um"][0] == pytest.approx(one["up_um"][k])
        piece = pv.read(tmp_path / "pc" / f"uf_{col}" / "piece_0001.vtu")
        assert read_text_field(piece.field_data, "column") == col
        assert piece.field_data["piece"][0] == 1
    for name in a:
        np.testing.assert_array_equal(a[name], b[name], err_msg=name)


def test_provenance_comment_is_lossless_and_valid_xml(tmp_path):
    from cfm_fem.io.provenance import read_xml_provenance
    from cfm_fem.io.vtk import write_pvd

    record = {"command_line": "cfm-fem sweep --up 0:50:10 ---x --", "é": "-->"}
    write_pvd(tmp_path / "s.pvd", [(0.0, tmp_path / "a.vtu")], provenance=record)
    ET.parse(tmp_path / "s.pvd")  # well-formed: no '--' inside the comment
    assert read_xml_provenance(tmp_path / "s.pvd") == record
