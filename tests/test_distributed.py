"""Dask backend on a real LocalCluster (loopback, 2 worker processes): same seed, same numbers."""

from __future__ import annotations

import json
import sys

import numpy as np
import pytest
from conftest import curved_field, grid_nodes

from cfm_fem.cli import main
from cfm_fem.models.field import FieldMap
from cfm_fem.models.sweep import SweepConfig
from cfm_fem.workflows.sweep.in_memory import run_sweep

distributed = pytest.importorskip("distributed")


@pytest.fixture(scope="module")
def cluster():
    with (
        distributed.LocalCluster(
            n_workers=2,
            threads_per_worker=1,
            processes=True,
            host="127.0.0.1",
            dashboard_address=None,
        ) as c,
        distributed.Client(c) as client,
    ):
        yield c, client


def _map(n=7):
    pts = grid_nodes(n)
    return pts, curved_field(pts)


@pytest.fixture(scope="module")
def csv_map(grid_csv):
    return grid_csv(6, curved_field)


@pytest.mark.parametrize("model", ["linear", "harmonic", "adaptive"])
def test_dask_chunks_are_bit_identical_to_one_process(cluster, model):
    """Also the adaptive estimator ("adaptive": the harmonic model, trial counts per node)."""
    from cfm_fem.workflows.sweep.distributed import dask_chunk_map

    _, client = cluster
    estimator = "adaptive" if model == "adaptive" else "plain"
    model = "harmonic" if model == "adaptive" else model
    pts, B = _map()
    if model == "harmonic":  # a field the harmonic fits hold at every node
        from test_sweep_harmonic import exact_field

        B = exact_field(pts * 3.0)
    fm = FieldMap.from_arrays(pts, B)
    ref = run_sweep(
        fm,
        SweepConfig(
            up_um=[0.0, 25.0, 60.0],
            trials=300,
            seed=11,
            chunk_nodes=10**6,
            field_model=model,
            estimator=estimator,
        ),
    )
    for chunk in (37, 128):  # odd sizes, many chunks, completion order differs from node order
        cfg = SweepConfig(
            up_um=[0.0, 25.0, 60.0],
            trials=300,
            seed=11,
            chunk_nodes=chunk,
            field_model=model,
            estimator=estimator,
        )
        res = run_sweep(fm, cfg, map_chunks=dask_chunk_map(client))
        np.testing.assert_array_equal(res.stats, ref.stats)  # NaN == NaN, bit for bit
        np.testing.assert_array_equal(res.n_outside, ref.n_outside)
        np.testing.assert_array_equal(res.n_walk_failed, ref.n_walk_failed)
        np.testing.assert_array_equal(res.linear_in_up, ref.linear_in_up)
    if model == "harmonic":
        assert (ref.field_fit["degree"] > 0).mean() > 0.9
    other = run_sweep(fm, SweepConfig(up_um=[25.0], trials=300, seed=12, chunk_nodes=64))
    assert not np.array_equal(other.stats[:, 0], ref.stats[:, 1])  # the seed matters


def test_cli_scheduler_gives_the_single_process_outputs(cluster, csv_map, tmp_path):
    import pyvista as pv

    c, _ = cluster
    common = ["sweep", str(csv_map), "--up", "0:20:10", "--trials", "200", "--seed", "5"]
    assert main([*common, "--out", str(tmp_path / "one")]) == 0
    rc = main(
        [
            *common,
            "--chunk-nodes",
            "50",
            "--scheduler",
            c.scheduler_address,
            "--out",
            str(tmp_path / "dask"),
        ]
    )
    assert rc == 0
    one = json.loads((tmp_path / "one" / "summary.json").read_text())
    dsk = json.loads((tmp_path / "dask" / "summary.json").read_text())
    for key in ("uf_units", "outside_fraction", "uf_nodes", "gum_disagree_fraction"):
        assert one[key] == dsk[key]
    assert dsk["provenance"]["backend"].startswith("dask scheduler tcp://127.0.0.1")
    a = pv.read(tmp_path / "one" / "uf_up20um.vtu").point_data
    b = pv.read(tmp_path / "dask" / "uf_up20um.vtu").point_data
    for name in a:
        np.testing.assert_array_equal(a[name], b[name], err_msg=name)
    assert not (tmp_path / "dask" / ".cfm_fem_chunks").exists()


@pytest.mark.slow
def test_cli_workers_starts_a_local_cluster(csv_map, tmp_path, capsys):
    common = ["sweep", str(csv_map), "--up", "10", "--trials", "100", "--seed", "2"]
    assert main([*common, "--out", str(tmp_path / "one")]) == 0
    assert (
        main([*common, "--chunk-nodes", "40", "--workers", "2", "--out", str(tmp_path / "w")]) == 0
    )
    one = json.loads((tmp_path / "one" / "summary.json").read_text())
    w = json.loads((tmp_path / "w" / "summary.json").read_text())
    assert one["uf_units"] == w["uf_units"]
    assert "LocalCluster, 2 worker" in w["provenance"]["backend"]


def test_bad_scale_out_options_exit_2(csv_map, tmp_path, capsys, monkeypatch):
    out = tmp_path / "o"
    base = ["sweep", str(csv_map), "--trials", "50", "--out", str(out)]
    assert main([*base, "--workers", "0"]) == 2
    assert main([*base, "--workers", "2", "--scheduler", "tcp://127.0.0.1:1"]) == 2
    monkeypatch.setattr("cfm_fem.workflows.sweep.distributed.CONNECT_TIMEOUT_S", 1)
    assert main([*base, "--scheduler", "tcp://127.0.0.1:9"]) == 2  # nothing listens there
    err = capsys.readouterr().err
    assert "--workers must be >= 1" in err and "cannot reach the Dask scheduler" in err
    assert "Traceback" not in err
    monkeypatch.setitem(sys.modules, "distributed", None)  # as if Dask were not installed
    assert main([*base, "--workers", "2"]) == 2
    assert "pip install 'cfm_fem[dask]'" in capsys.readouterr().err
    assert not out.exists()


def test_kinematics_on_dask_matches_one_process(cluster):
    from cfm_fem.io.bench_toml import read_reference_bench
    from cfm_fem.models.kinematics.monte_carlo import run_kinematics
    from cfm_fem.workflows.sweep.distributed import run_kinematics_dask

    _, client = cluster
    bench = read_reference_bench()
    ref = run_kinematics(bench, trials=3000, seed=4)
    res = run_kinematics_dask(client, bench, 3000, 4, block_points=100)
    for name in ("mean", "std", "low", "high", "q_cmd", "nominal"):
        np.testing.assert_array_equal(getattr(res, name), getattr(ref, name), err_msg=name)
    assert res.pooled == ref.pooled


def test_cli_kinematics_on_dask(cluster, tmp_path):
    c, _ = cluster
    base = ["kinematics", "--trials", "2000", "--seed", "3"]
    rc = main([*base, "--scheduler", c.scheduler_address, "--out", str(tmp_path / "dask")])
    assert rc == 0
    assert main([*base, "--out", str(tmp_path / "one")]) == 0
    one = json.loads((tmp_path / "one" / "summary.json").read_text())
    dsk = json.loads((tmp_path / "dask" / "summary.json").read_text())
    assert one["axes"] == dsk["axes"] and one["norm"] == dsk["norm"]
    rows = [(tmp_path / d / "points.csv").read_text().splitlines() for d in ("one", "dask")]
    assert [r for r in rows[0] if not r.startswith("#")] == [
        r for r in rows[1] if not r.startswith("#")
    ]
    assert main([*base, "--adaptive", "2", "--workers", "2", "--out", str(tmp_path / "x")]) == 2


def test_workers_with_other_code_are_refused(cluster, monkeypatch):
    from cfm_fem.workflows.sweep.distributed import check_workers

    _, client = cluster
    check_workers(client)  # same code: fine
    monkeypatch.setattr(
        "cfm_fem.workflows.sweep.resume.code_fingerprint", lambda: "not-the-workers-code"
    )
    with pytest.raises(Exception, match="run other cfm_fem code than this process"):
        check_workers(client)


def test_slabs_on_workers_equal_the_serial_slabs(cluster, tmp_path):
    """``--slabs`` with the slabs run on the cluster's workers (they map the staged rows in the
    output folder): every output field and the summary bit for bit as one process."""
    import pyvista as pv

    from cfm_fem.io.provenance import file_sha256
    from cfm_fem.workflows.sweep.distributed import dask_chunk_map
    from cfm_fem.workflows.sweep.resume import describe_sweep
    from cfm_fem.workflows.sweep.slabs import run_slab_sweep

    pts, B = _map(9)
    path = tmp_path / "m.csv"
    rows = "\n".join(",".join(f"{v:.17g}" for v in r) for r in np.c_[pts, B])
    path.write_text("x [mm],y [mm],z [mm],Bx [T],By [T],Bz [T]\n" + rows + "\n")
    cfg = SweepConfig(up_um=[0.0, 40.0], trials=150, seed=8)
    desc = describe_sweep(cfg, file_sha256(path), {}, None)
    one = run_slab_sweep(path, cfg, tmp_path / "one", n_slabs=3)
    _, client = cluster
    dist = run_slab_sweep(path, cfg, tmp_path / "w", n_slabs=3, description=desc,
                          map_chunks=dask_chunk_map(client))  # fmt: skip
    for key in set(one) - {"seconds", "provenance"}:
        assert one[key] == dist[key], key
    a, b = pv.read(tmp_path / "one" / "uf_up40um.pvtu"), pv.read(tmp_path / "w" / "uf_up40um.pvtu")
    assert a.n_points == b.n_points > 0
    for name in a.point_data:
        np.testing.assert_array_equal(a.point_data[name], b.point_data[name], err_msg=name)
    assert not (tmp_path / "w" / ".cfm_fem_slabs").exists()
