"""Node volumes, volume-weighted percentiles and the region of interest of a sweep."""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import write_map_csv

from cfm_fem.cli import main
from cfm_fem.errors import CfmInputError
from cfm_fem.io import read_field
from cfm_fem.models.mesh import build_mesh
from cfm_fem.models.node_weights import (
    CELL_RULE,
    GRID_RULE,
    node_volumes,
    weighted_percentiles,
)
from cfm_fem.models.region import parse_region


def _grid(xs, ys, zs):
    return np.stack(np.meshgrid(xs, ys, zs, indexing="ij"), -1).reshape(-1, 3)


def _mesh(pts, method="auto"):
    from cfm_fem.models.field import FieldMap

    fm = FieldMap.from_arrays(pts, np.c_[pts[:, 0], pts[:, 1], 1.0 + pts[:, 2]], source="t")
    return build_mesh(fm, method)


def test_grid_nodes_weigh_their_half_spacings_and_sum_to_the_box():
    xs, ys, zs = np.array([0.0, 1.0, 3.0]), np.array([0.0, 2.0]), np.array([0.0, 0.5, 1.0, 4.0])
    pts = _grid(xs, ys, zs)
    vol, rule = node_volumes(_mesh(pts, "grid"))
    assert rule == GRID_RULE
    assert vol.sum() == pytest.approx(3.0 * 2.0 * 4.0)
    # the node (1, 0, 0.5): half-spacings 1.5 (x), 1 (y, a face), 0.5 (z)
    i = np.flatnonzero((pts == [1.0, 0.0, 0.5]).all(axis=1))[0]
    assert vol[i] == pytest.approx(1.5 * 1.0 * 0.5)


def test_cell_shares_sum_to_the_meshed_volume():
    rng = np.random.default_rng(3)
    pts = np.r_[_grid([0.0, 2.0], [0.0, 2.0], [0.0, 2.0]), rng.uniform(0.2, 1.8, (40, 3))]
    mesh = _mesh(pts, "delaunay")
    vol, rule = node_volumes(mesh)
    assert rule == CELL_RULE and (vol > 0).all()
    assert vol.sum() == pytest.approx(8.0, rel=1e-6)  # Delaunay moves its nodes by ~1e-7


def test_weighted_percentiles_equal_weights_and_repeated_values():
    rng = np.random.default_rng(0)
    v = rng.normal(size=257)
    qs = [0, 5, 50, 95, 99, 100]
    assert weighted_percentiles(v, np.ones_like(v), qs) == pytest.approx(
        np.percentile(v, qs, method="inverted_cdf").tolist()
    )
    w = rng.integers(0, 4, size=v.size)  # weight 3 = the value three times; 0 = left out
    assert weighted_percentiles(v, w, qs[1:]) == pytest.approx(
        np.percentile(np.repeat(v, w), qs[1:], method="inverted_cdf").tolist()
    )
    assert weighted_percentiles(v, np.zeros_like(v), [50]) == [None]


def _z_graded_map(tmp_path, dense: bool):
    """|B| = 1 + 0.02 z^2 T on x, y in [0, 4], z in [0, 12] mm: U_f grows with z. ``dense``
    puts 4 times as many z planes into z < 6 as into z > 6."""
    zs = np.r_[np.arange(0.0, 6.0, 0.25), np.arange(6.0, 12.01, 1.0)] if dense else np.arange(13.0)
    pts = _grid(np.arange(5.0), np.arange(5.0), zs)
    B = np.c_[np.zeros(len(pts)), np.zeros(len(pts)), 1.0 + 0.02 * pts[:, 2] ** 2]
    return write_map_csv(tmp_path / f"map_{dense}.csv", pts, B)


def test_grid_density_does_not_move_the_volume_weighted_percentiles(tmp_path):
    sums = {}
    for dense in (False, True):
        out = tmp_path / f"o{dense}"
        argv = ["sweep", str(_z_graded_map(tmp_path, dense)), "--up", "20", "--trials", "400",
                "--b-ref", "1", "--outside", "extrapolate", "--out", str(out)]  # fmt: skip
        assert main(argv) == 0
        sums[dense] = json.loads((out / "summary.json").read_text())
    a, b = sums[False], sums[True]
    assert a["statistics_weighting"].startswith("volume") and a["node_volume_rule"] == GRID_RULE
    assert a["region_volume_mm3"] == pytest.approx(4 * 4 * 12) == b["region_volume_mm3"]
    # U_f = 1.96 U_p |d|B|/dz| / B_ref * 1e4 = 1.96 * 0.02 mm * 0.04 z T/mm / 1 T * 1e4 units
    for q, z in (("p50", 6.0), ("p95", 11.4)):
        expect = 1.959964 * 0.020 * 0.04 * z * 1e4
        # per node the dense map's p50 sits in its crowded low-z half; by volume both agree
        assert a["uf_units"][q][0] == pytest.approx(expect, rel=0.12)
        assert b["uf_units"][q][0] == pytest.approx(expect, rel=0.12)
    assert b["uf_units_per_node"]["p50"][0] < 0.7 * a["uf_units_per_node"]["p50"][0]


def test_region_restricts_the_figures_and_sets_b_ref(tmp_path):
    path = _z_graded_map(tmp_path, False)
    out = tmp_path / "r"
    argv = ["sweep", str(path), "--up", "20", "--trials", "300", "--region", "cylinder:2.5,2:4",
            "--outside", "extrapolate", "--table", "csv", "--out", str(out)]  # fmt: skip
    assert main(argv) == 0
    s = json.loads((out / "summary.json").read_text())
    inside = parse_region("cylinder:2.5,2:4").mask(read_field(path).points)
    assert s["region_nodes"] == int(inside.sum()) == 8 * 3
    assert s["region"] == {"cylinder_radius_mm": 2.5, "z_mm": [2.0, 4.0]}
    assert s["b_ref_T"] == pytest.approx(1.0 + 0.02 * 16)
    assert "region of interest" in s["b_ref_rule"] and s["uf_nodes"] == [24]
    table = np.genfromtxt(out / "nodes.csv", delimiter=",", names=True)
    assert table["in_region"].sum() == 24 and len(table) == 5 * 5 * 13
    sel = table["in_region"] == 1
    assert np.nanmax(table["U_f_units_up20um"][sel]) == pytest.approx(s["uf_units"]["max"][0])


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--region", "cylinder:-1,:"], "argument --region: must be"),
        (["--region", "50:60,:,:"], "--region (box x 50:60"),
        (["--region", "0:1,0:1,0:1", "--slabs", "2"], "--region cannot be combined"),
    ],
)
def test_bad_region_is_one_clear_error(tmp_path, capsys, extra, message):
    path = _z_graded_map(tmp_path, False)
    argv = ["sweep", str(path), "--up", "20", "--trials", "100", "--out", str(tmp_path / "o")]
    assert main([*argv, *extra]) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err
    assert not (tmp_path / "o" / "summary.json").exists()


def test_parquet_table_needs_pyarrow(tmp_path, capsys):
    try:
        import pyarrow  # noqa: F401
    except ImportError:
        path = _z_graded_map(tmp_path, False)
        argv = ["sweep", str(path), "--up", "20", "--trials", "100", "--table", "parquet",
                "--out", str(tmp_path / "o")]  # fmt: skip
        assert main(argv) == 2
        assert "--table parquet needs pyarrow" in capsys.readouterr().err
        assert not (tmp_path / "o").exists() or not any((tmp_path / "o").iterdir())
        with pytest.raises(CfmInputError, match="needs pyarrow"):
            from cfm_fem.io.sweep_table import check_table_format

            check_table_format("parquet")
        return
    import pyarrow.parquet as pq

    path = _z_graded_map(tmp_path, False)
    out = tmp_path / "p"
    assert main(["sweep", str(path), "--up", "20", "--trials", "100", "--table", "parquet",
                 "--out", str(out)]) == 0  # fmt: skip
    t = pq.read_table(out / "nodes.parquet")
    assert t.num_rows == 5 * 5 * 13 and "U_f_units_up20um" in t.column_names


def test_out_of_core_weighted_percentiles_equal_the_in_memory_ones():
    from cfm_fem.workflows.sweep.slabs import disk_weighted_percentiles

    rng = np.random.default_rng(7)
    v = np.r_[rng.lognormal(size=5000), np.full(300, 2.0)]  # ties too
    w = rng.uniform(0.0, 3.0, size=v.size) * (rng.random(v.size) > 0.1)
    qs = [1, 50, 95, 99]
    expect = weighted_percentiles(v, w, qs)

    def chunks():
        for a in range(0, v.size, 700):
            yield v[a : a + 700], w[a : a + 700]

    assert disk_weighted_percentiles(chunks, qs) == expect  # gathered in memory
    # histogram refinement (a tiny memory limit), down to a few values per window
    assert disk_weighted_percentiles(chunks, qs, in_memory_limit=50, bins=8) == expect


def test_python_sweep_takes_the_region_as_text_and_its_percentile_is_the_summarys(tmp_path):
    import cfm_fem

    path = _z_graded_map(tmp_path, True)
    maps = cfm_fem.run_sweep(str(path), up_um=[20], trials=200, region="cylinder:2.5,2:10")
    s = maps.summary
    assert s["region"] == {"cylinder_radius_mm": 2.5, "z_mm": [2.0, 10.0]}
    assert maps.percentile(50, up_um=20) == s["uf_units"]["p50"][0]
    assert maps.percentile(95, up_um=20, per_node=True) == s["uf_units_per_node"]["p95"][0]


def test_node_table_and_volumes_are_the_same_in_memory_in_pieces_and_in_slabs(tmp_path):
    path = _z_graded_map(tmp_path, True)
    tables = []
    for name, extra in (("one", []), ("pc", ["--pieces", "3"]), ("sl", ["--slabs", "2"])):
        out = tmp_path / name
        argv = ["sweep", str(path), "--up", "0,20", "--trials", "100", "--table", "csv",
                "--out", str(out), *extra]  # fmt: skip
        assert main(argv) == 0
        t = np.genfromtxt(out / "nodes.csv", delimiter=",", names=True)
        tables.append(t[np.lexsort((t["z_mm"], t["y_mm"], t["x_mm"]))])
    a = tables[0]
    assert len(a) == 5 * 5 * 31 and a["node_volume_mm3"].sum() == pytest.approx(4 * 4 * 12)
    for b in tables[1:]:
        for name in a.dtype.names:
            np.testing.assert_array_equal(a[name], b[name], err_msg=name)
