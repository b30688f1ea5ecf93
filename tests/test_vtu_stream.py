"""Maps written array by array on a shared mesh block read back as VTK's own writer's do."""

import meshio
import numpy as np
import pytest
import pyvista as pv

from cfm_fem.io.vtk import read_text_field, write_vtu
from cfm_fem.io.vtu_stream import BLOCK, EncodedArray, MeshBlock, write_mesh_vtu


def _map(n_points, cells_per_point, rng):
    pts = rng.normal(size=(n_points, 3)) * 10.0
    cells = rng.integers(0, n_points, size=(cells_per_point * n_points, 4))
    data = {
        "B_nominal_T": rng.normal(size=(n_points, 3)),
        "U_f_units": rng.normal(size=n_points).astype(np.float32),
        "all_nan": np.full(n_points, np.nan, dtype=np.float32),
        "complete": (rng.random(n_points) < 0.5).astype(np.uint8),
        "grad": rng.normal(size=(n_points, 9)),
    }
    data["U_f_units"][::7] = np.nan
    fields = {"U_p_um": 20.0, "seed": 3, "provenance": '{"a": "\u00b5m"}'}
    return pts, cells, data, fields


@pytest.mark.parametrize("shape", ["tetra", "triangle", "points"])
def test_mesh_block_map_reads_back_as_vtks_own(tmp_path, shape):
    """meshio and pyvista read the same points, cells, point data (dtypes, NaN) and field data
    from a map written here as from `write_vtu`'s; arrays span several zlib blocks."""
    rng = np.random.default_rng(4)
    pts, cells, data, fields = _map(3000, 5, rng)
    assert data["grad"].nbytes > 4 * BLOCK
    if shape == "triangle":
        cells = cells[:, :3]
    elif shape == "points":
        cells = None
    write_vtu(tmp_path / "vtk.vtu", pts, cells, data, fields)
    write_mesh_vtu(tmp_path / "own.vtu", MeshBlock(pts, cells), data, fields)
    a, b = meshio.read(tmp_path / "vtk.vtu"), meshio.read(tmp_path / "own.vtu")
    assert np.array_equal(a.points, b.points)
    assert [c.type for c in a.cells] == [c.type for c in b.cells]
    assert all(np.array_equal(x.data, y.data) for x, y in zip(a.cells, b.cells, strict=True))
    assert list(a.point_data) == list(b.point_data) == list(data)
    for name, values in data.items():
        assert b.point_data[name].dtype == a.point_data[name].dtype == values.dtype
        assert np.array_equal(b.point_data[name], values, equal_nan=True)
    assert read_text_field(b.field_data, "provenance") == fields["provenance"]
    assert b.field_data["U_p_um"][0] == 20.0
    pa, pb = pv.read(tmp_path / "vtk.vtu"), pv.read(tmp_path / "own.vtu")
    assert np.array_equal(pa.cells, pb.cells) and np.array_equal(pa.celltypes, pb.celltypes)
    assert pb.active_scalars_name == pa.active_scalars_name == "B_nominal_T"
    for name in data:
        assert np.array_equal(pa.point_data[name], pb.point_data[name], equal_nan=True)
    assert read_text_field(pb.field_data, "provenance") == fields["provenance"]


def test_mesh_block_map_refuses_point_data_of_another_mesh_and_leaves_no_file(tmp_path):
    rng = np.random.default_rng(5)
    pts, cells, data, fields = _map(50, 2, rng)
    with pytest.raises(ValueError, match="rows"):
        write_mesh_vtu(tmp_path / "m.vtu", MeshBlock(pts[:40], cells % 40), data, fields)
    assert list(tmp_path.iterdir()) == []


def test_arrays_encoded_once_and_blocks_compressed_side_by_side_write_the_same_bytes(tmp_path):
    """A map with its shared arrays pre-encoded (`EncodedArray`) and its mesh block's zlib
    blocks compressed on threads is byte for byte the map written array by array."""
    from concurrent.futures import ThreadPoolExecutor

    rng = np.random.default_rng(7)
    pts, cells, data, fields = _map(3000, 5, rng)
    write_mesh_vtu(tmp_path / "plain.vtu", MeshBlock(pts, cells), data, fields)
    with ThreadPoolExecutor(3) as pool:
        mesh = MeshBlock(pts, cells, pool)
        shared = {k: EncodedArray(k, data[k], pool) for k in ("B_nominal_T", "grad")}
    write_mesh_vtu(tmp_path / "shared.vtu", mesh, {k: shared.get(k, v) for k, v in data.items()},
                   fields)  # fmt: skip
    assert (tmp_path / "shared.vtu").read_bytes() == (tmp_path / "plain.vtu").read_bytes()
    short = EncodedArray("grad", data["grad"][:-1])
    with pytest.raises(ValueError, match="rows"):
        write_mesh_vtu(tmp_path / "bad.vtu", mesh, {"grad": short}, fields)
    assert not (tmp_path / "bad.vtu").exists()


def test_maps_deflated_by_zlib_where_isal_is_missing_read_back_the_same(tmp_path, monkeypatch):
    """Without ISA-L the point data is deflated by zlib: other bytes, the same arrays."""
    import zlib

    from cfm_fem.io import vtu_stream

    rng = np.random.default_rng(9)
    pts, cells, data, fields = _map(3000, 5, rng)
    write_mesh_vtu(tmp_path / "fast.vtu", MeshBlock(pts, cells), data, fields)
    isal = vtu_stream.fast_zlib is not zlib
    monkeypatch.setattr(vtu_stream, "fast_zlib", zlib)
    write_mesh_vtu(tmp_path / "zlib.vtu", MeshBlock(pts, cells), data, fields)
    fast, slow = (tmp_path / "fast.vtu").read_bytes(), (tmp_path / "zlib.vtu").read_bytes()
    assert (fast != slow) == isal
    a, b = meshio.read(tmp_path / "fast.vtu"), meshio.read(tmp_path / "zlib.vtu")
    for name, values in data.items():
        assert np.array_equal(a.point_data[name], values, equal_nan=True)
        assert np.array_equal(b.point_data[name], values, equal_nan=True)
