"""Every writer, checked by one helper: write, read back, compare points, B and cells."""

from __future__ import annotations

import importlib.util
import os
import warnings

import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from cfm_fem.errors import CfmInputError
from cfm_fem.io import read_field, write_field
from cfm_fem.models.field import FieldMap

HAVE_H5PY = importlib.util.find_spec("h5py") is not None


def _canonical(fm: FieldMap):
    """Points, B and cells in an order that does not depend on the order of the nodes."""
    order = np.lexsort(fm.points.T[::-1])
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    cells = None
    if fm.cells is not None:
        cells = np.sort(rank[fm.cells], axis=1)
        cells = cells[np.lexsort(cells.T[::-1])]
    return fm.points[order], fm.B[order], cells


def assert_roundtrip(fieldmap: FieldMap, path, *, fmt=None, rtol=0.0, expect_cells=True):
    """Write ``fieldmap`` to ``path``, read it back, compare (exactly unless ``rtol``).

    Node order may change (Opera writes z fastest); cells are compared as sets of node positions.
    Returns the map read back.
    """
    write_field(path, fieldmap, fmt=fmt)
    assert not [p for p in os.listdir(path.parent) if p.startswith(".")], "temporary file left"
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a writer's output must read back without warnings
        back = read_field(path, fmt=fmt)
    points, B, cells = _canonical(fieldmap)
    points_back, B_back, cells_back = _canonical(back)
    scale = np.abs(points).max()
    np.testing.assert_allclose(points_back, points, rtol=rtol, atol=rtol * scale)
    np.testing.assert_allclose(B_back, B, rtol=rtol, atol=0)
    if expect_cells:
        assert (cells_back is None) == (cells is None)
        if cells is not None:
            np.testing.assert_array_equal(cells_back, cells)
    assert back.source == str(path)
    return back


def _grid_map(nx=3, ny=4, nz=5, seed=0):
    x = np.linspace(-20.0, 20.0, nx)
    y = np.linspace(-7.5, 7.5, ny)
    z = np.arange(nz) * 2.5 - 1.0
    points = np.stack(np.meshgrid(x, y, z, indexing="ij"), axis=-1).reshape(-1, 3)
    rng = np.random.default_rng(seed)
    return FieldMap.from_arrays(points, rng.normal(scale=0.7, size=points.shape))


def _tetra_map():
    points = np.array(
        [[0, 0, 0], [10, 0, 0], [0, 10, 0], [0, 0, 10], [10, 10, 10], [-3.25, 1e-3, 7]], float
    )
    B = np.array(
        [[0.1, 0.2, 0.3], [1.5, -0.5, 1e-7], [0, 0, 1], [2, 2, 2], [-1, 1, 0.5], [3, 0, 0]]
    )
    return FieldMap.from_arrays(points, B, cells=[[0, 1, 2, 3], [1, 2, 3, 4], [0, 2, 3, 5]])


def _planar_map():
    points = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0.0]]) * 5.0
    B = np.array([[0.1, 0.2, 0.0], [0.3, 0.4, 0.0], [0.5, 0.6, 0.0], [0.7, 0.8, 0.01]])
    return FieldMap.from_arrays(points, B, cells=[[0, 1, 2], [1, 3, 2]])


TEXT_FORMATS = [("map.csv", None), ("map.txt", None), ("map.dat", "comsol"), ("map.out", "csv")]
MESH_FORMATS = ["map.vtu", "map.vtk", "map.msh"] + (["map.xdmf"] if HAVE_H5PY else [])


@pytest.mark.parametrize(("name", "fmt"), TEXT_FORMATS)
def test_text_formats_round_trip_exactly(tmp_path, name, fmt):
    back = assert_roundtrip(_grid_map(), tmp_path / name, fmt=fmt)
    assert back.cells is None


def test_opera_round_trip_to_printed_precision(tmp_path):
    back = assert_roundtrip(_grid_map(), tmp_path / "map.table", rtol=4e-16)
    text = (tmp_path / "map.table").read_text().split("\n")
    assert text[0].split() == ["5", "4", "3", "2"]  # nz ny nx 2, z fastest like Opera
    assert text[1:8] == [
        " 1 X [METRE]",
        " 2 Y [METRE]",
        " 3 Z [METRE]",
        " 4 BX [TESLA]",
        " 5 BY [TESLA]",
        " 6 BZ [TESLA]",
        " 0",
    ]
    assert text[8].split()[:3] == ["-0.02", "-0.0075", "-0.001"]  # metres
    assert back.n_nodes == 60


def test_opera_writer_refuses_a_map_that_is_not_a_full_grid(tmp_path):
    path = tmp_path / "map.table"
    with pytest.raises(CfmInputError, match=r"full rectilinear grid.*5 nodes but 2 x 2 x 2 .*= 8"):
        write_field(path, FieldMap.from_arrays(_tetra_map().points[:5], _tetra_map().B[:5]))
    assert not path.exists()


@pytest.mark.parametrize("name", MESH_FORMATS)
@pytest.mark.parametrize(
    "make", [_tetra_map, _planar_map, _grid_map], ids=["tetra", "tri", "cloud"]
)
def test_mesh_formats_round_trip_with_cells(tmp_path, name, make):
    fm = make()
    back = assert_roundtrip(fm, tmp_path / name)
    if fm.cells is None:
        assert back.cells is None
    else:
        assert back.cells.shape == fm.cells.shape


def test_comsol_header_is_complete(tmp_path):
    path = tmp_path / "map.txt"
    write_field(path, _tetra_map())
    header = [line for line in path.read_text().split("\n") if line.startswith("%")]
    assert [h.split(":")[0] for h in header[:-1]] == [
        "% Model",
        "% Version",
        "% Dimension",
        "% Nodes",
        "% Expressions",
        "% Description",
        "% Length unit",
    ]
    assert header[3].split()[-1] == "6"
    assert header[6].split()[-1] == "mm"
    assert header[-1].split() == [
        "%",
        "X",
        "Y",
        "Z",
        "mf.Bx",
        "(T)",
        "mf.By",
        "(T)",
        "mf.Bz",
        "(T)",
    ]


def test_csv_header_is_the_documented_one(tmp_path):
    path = tmp_path / "map.csv"
    write_field(path, _tetra_map())
    lines = path.read_text().split("\n")
    assert lines[0] == "x [mm],y [mm],z [mm],Bx [T],By [T],Bz [T]"
    assert lines[1] == "0.0,0.0,0.0,0.1,0.2,0.3"


def test_write_field_rejects_an_unknown_extension(tmp_path):
    with pytest.raises(CfmInputError, match=r"cannot tell the format from the extension '.foo'"):
        write_field(tmp_path / "map.foo", _tetra_map())


@pytest.mark.skipif(HAVE_H5PY, reason="checks the message given when h5py is missing")
def test_xdmf_without_h5py_is_a_clear_error_and_leaves_nothing(tmp_path):
    with pytest.raises(CfmInputError, match=r"needs the Python package 'h5py'"):
        write_field(tmp_path / "map.xdmf", _tetra_map())
    assert os.listdir(tmp_path) == []


# the readers refuse coordinates beyond 1e12 mm and fields beyond 1e6 T (_parse.MAX_COORD_MM)
COORD = st.floats(allow_nan=False, allow_infinity=False, min_value=-1e12, max_value=1e12)
FIELD = st.floats(allow_nan=False, allow_infinity=False, min_value=-1e6, max_value=1e6)


@settings(
    max_examples=30, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(values=st.lists(st.tuples(*[COORD] * 3, *[FIELD] * 3), min_size=1, max_size=8))
@pytest.mark.parametrize("name", ["map.csv", "map.txt"])
def test_any_float_round_trips_exactly_through_text(tmp_path, name, values):
    array = np.array(values, dtype=float)
    points, B = array[:, :3], array[:, 3:]
    gaps = np.abs(points[:, None, :] - points[None, :, :]).max(axis=2)
    np.fill_diagonal(gaps, np.inf)
    assume(gaps.min() > 1e-6)  # FieldMap merges nodes closer than 1e-9 mm
    assume(not np.all(B == 0, axis=1).any())  # placeholder rows warn
    assert_roundtrip(FieldMap.from_arrays(points, B), tmp_path / name)
