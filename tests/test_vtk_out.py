"""Write-read round trip of the VTK writers (VTU via VTK's writer, read back with meshio)."""

import os
import xml.etree.ElementTree as ET

import meshio
import numpy as np

from cfm_fem.io.vtk import write_pvd, write_vtu


def test_vtu_round_trip_keeps_points_cells_arrays_and_dtypes(tmp_path):
    rng = np.random.default_rng(0)
    pts = rng.uniform(size=(20, 3))
    cells = np.array([[0, 1, 2, 3], [1, 2, 3, 4], [5, 6, 7, 8]])
    data = {
        "scalar64": rng.normal(size=20),
        "vector": rng.normal(size=(20, 3)),
        "f32": rng.normal(size=20).astype(np.float32),
        "flag": (rng.uniform(size=20) > 0.5).astype(np.uint8),
    }
    path = tmp_path / "a.vtu"
    write_vtu(path, pts, cells, data, {"U_p_um": 20.0, "seed": 3})
    m = meshio.read(path)
    np.testing.assert_array_equal(m.points, pts)
    assert m.cells[0].type == "tetra"
    np.testing.assert_array_equal(m.cells[0].data, cells)
    for k, v in data.items():
        np.testing.assert_array_equal(m.point_data[k], v)
        assert m.point_data[k].dtype == v.dtype
    assert float(np.ravel(m.field_data["U_p_um"])[0]) == 20.0
    assert not [f for f in os.listdir(tmp_path) if f.startswith(".")]  # no temporary left behind


def test_connectivity_and_offsets_are_int32_and_read_back_by_meshio_and_pyvista(tmp_path):
    import pyvista as pv

    rng = np.random.default_rng(1)
    pts = rng.uniform(size=(30, 3))
    cells = rng.integers(0, 30, size=(12, 4))
    path = tmp_path / "i.vtu"
    write_vtu(path, pts, cells, {"a": np.arange(30.0)})
    arrays = {a.get("Name"): a.get("type") for a in ET.parse(path).iter("DataArray")}
    assert arrays["connectivity"] == "Int32" and arrays["offsets"] == "Int32"
    np.testing.assert_array_equal(meshio.read(path).cells[0].data, cells)
    grid = pv.read(path)
    np.testing.assert_array_equal(grid.cells_dict[pv.CellType.TETRA], cells)
    np.testing.assert_array_equal(grid.point_data["a"], np.arange(30.0))


def test_point_cloud_and_triangles(tmp_path):
    pts = np.eye(3)
    write_vtu(tmp_path / "p.vtu", pts, None, {"a": np.arange(3.0)})
    assert meshio.read(tmp_path / "p.vtu").cells[0].type == "vertex"
    write_vtu(tmp_path / "t.vtu", pts, np.array([[0, 1, 2]]))
    assert meshio.read(tmp_path / "t.vtu").cells[0].type == "triangle"


def test_pvd_lists_timesteps_and_relative_files(tmp_path):
    files = [tmp_path / f"m{k}.vtu" for k in range(3)]
    write_pvd(tmp_path / "s.pvd", [(10.0 * k, f) for k, f in enumerate(files)])
    ds = list(ET.parse(tmp_path / "s.pvd").getroot().iter("DataSet"))
    assert [float(d.get("timestep")) for d in ds] == [0.0, 10.0, 20.0]
    assert [d.get("file") for d in ds] == ["m0.vtu", "m1.vtu", "m2.vtu"]


def test_importing_the_writers_leaves_pyvista_unloaded():
    """The sweep writes its maps with `cfm_fem.io.vtu_stream`: importing the VTK writers must
    not load pyvista and VTK (some 0.8 s of CPU time and 60 MB on every sweep)."""
    import subprocess
    import sys

    code = (
        "import sys, cfm_fem.io.vtk, cfm_fem.io.vtu_stream, cfm_fem.io.sweep_out; "
        "print(sorted(m for m in sys.modules if m.split('.')[0] in ('pyvista', 'vtkmodules')))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"
