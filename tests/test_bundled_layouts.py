"""The bundled map's three layouts, read by our own readers, describe the same magnet."""

from pathlib import Path

import numpy as np

from cfm_fem.io import read_field
from cfm_fem.models.interpolation import LinearInterpolator

MESHES = Path(__file__).resolve().parents[1] / "meshes"


def test_comsol_layout_holds_the_vtu_nodes_and_field():
    vtu = read_field(MESHES / "quadrupole.vtu")
    txt = read_field(MESHES / "quadrupole_comsol.txt")
    assert vtu.cells is not None and txt.cells is None
    np.testing.assert_allclose(txt.points, vtu.points, atol=1e-9)
    np.testing.assert_allclose(txt.B, vtu.B, rtol=1e-9, atol=1e-12)


def test_opera_grid_agrees_with_the_mesh_within_its_interpolation_error():
    vtu = read_field(MESHES / "quadrupole.vtu")
    opera = read_field(MESHES / "quadrupole_opera.table")
    assert opera.n_nodes == 15 * 15 * 61
    np.testing.assert_allclose(opera.points.min(0), [-7, -7, -120], atol=1e-9)
    np.testing.assert_allclose(opera.points.max(0), [7, 7, 120], atol=1e-9)
    B, inside = LinearInterpolator(vtu).field_at(opera.points)
    assert inside.all()
    b_ref = vtu.b_max
    err_units = np.abs(B - opera.B).max(axis=1) / b_ref * 1e4
    # linear interpolation of the mesh: a few units typically, 16 units at worst near the ends
    assert np.median(err_units) < 3 and err_units.max() < 25
    # orientation: a normal quadrupole, By = G x and Bx = G y at the centre, G ~ 71 T/m
    centre = np.abs(opera.points[:, 2]) < 1e-9
    G = np.polyfit(opera.points[centre, 0], opera.B[centre, 1], 1)[0] * 1e3
    assert 70 < G < 72
