"""Out-of-core sweep (`--slabs K`): streamed input, slab + halo meshes, .pvtu pieces per slab.

The numbers of the own nodes of every slab must be those of the in-memory run on the same file.
"""

from __future__ import annotations

import dataclasses
import json
import re
import xml.etree.ElementTree as ET

import numpy as np
import pytest
import pyvista as pv
from vtk_points import by_position, owned_points, vtk_histogram_count

from cfm_fem.cli import main
from cfm_fem.errors import CfmInputError
from cfm_fem.io import read_field, streaming, write_field
from cfm_fem.io.provenance import read_xml_provenance
from cfm_fem.models.sweep import SweepConfig
from cfm_fem.workflows.sweep.slab_plan import slabs_for_memory
from cfm_fem.workflows.sweep.slabs import disk_percentiles, run_slab_sweep

HEADER = "x [mm],y [mm],z [mm],Bx [T],By [T],Bz [T]"


def _field(p):
    x, y, z = p.T
    return np.c_[0.07 * y + 1e-3 * x**2, 0.07 * x - 2e-4 * x * y, 0.1 + 1e-3 * z**2 / 30]


def _write_csv(path, pts, extra=""):
    rows = "\n".join(",".join(f"{v:.17g}" for v in r) for r in np.c_[pts, _field(pts)])
    path.write_text(HEADER + "\n" + extra + rows + "\n")
    return path


def _lattice(nx=7, nz=14):
    ax = np.linspace(-10.0, 10.0, nx)
    return np.stack(np.meshgrid(ax, ax, np.linspace(-30.0, 30.0, nz), indexing="ij"), -1).reshape(
        -1, 3
    )


def _same_summary(one, sl, exact=True):
    # the in-memory run's count of flat cells lining the Delaunay hull (kept) has no slab
    # equivalent (each slab + halo has a hull of its own): the one note slabs leave out
    one = dict(one, notes=[n for n in one["notes"] if "line the Delaunay hull" not in n])
    # node volumes sum a node's cells in mesh order (rounding only, as the gradients)
    for key in ("region_volume_mm3", "uf_volume_fraction"):
        np.testing.assert_allclose(one[key], sl[key], rtol=1e-12, err_msg=key)
    for key in set(one) - {"seconds", "provenance", "region_volume_mm3", "uf_volume_fraction"}:
        if exact or key not in ("uf_units", "uf_units_per_node"):
            assert one[key] == sl[key], key
        else:
            for q in one[key]:
                np.testing.assert_allclose(one[key][q], sl[key][q], rtol=1e-12, err_msg=q)


def _in_memory_and_slabs(tmp_path, base, k):
    """Run ``base`` in memory (DIR one) and with ``--slabs k`` (DIR sl); both summaries."""
    assert main([*base, "--out", str(tmp_path / "one")]) == 0
    assert main([*base, "--slabs", str(k), "--out", str(tmp_path / "sl")]) == 0
    return tuple(json.loads((tmp_path / d / "summary.json").read_text()) for d in ("one", "sl"))


def _same_fields(a, b, gradients):
    """Every point field equal bit for bit, except those whose name holds one of
    ``gradients``: node gradients sum a node's cells in mesh order, and a slab's mesh orders
    them differently from the whole map's (rounding only)."""
    for name in a:
        if any(g in name for g in gradients):
            np.testing.assert_allclose(a[name], b[name], rtol=1e-6, atol=1e-15, err_msg=name)
        else:  # every Monte Carlo figure
            np.testing.assert_array_equal(a[name], b[name], err_msg=name)


def test_lattice_slabs_equal_the_in_memory_run_bit_for_bit(tmp_path):
    path = _write_csv(tmp_path / "g.csv", _lattice())
    base = ["sweep", str(path), "--up", "0:40:20", "--trials", "300"]
    one, sl = _in_memory_and_slabs(tmp_path, base, 3)
    assert sl["slabs"]["count"] == 3 and sl["slabs"]["axis"] == "z" and sl["pieces"] == 3
    assert sl["slabs"]["halo_outside_nodes"] == 0
    _same_summary(one, sl)
    files = [d.get("file") for d in ET.parse(tmp_path / "sl" / "sweep.pvd").iter("DataSet")]
    assert files == ["uf_up0um.pvtu", "uf_up20um.pvtu", "uf_up40um.pvtu"]
    assert read_xml_provenance(tmp_path / "sl" / "sweep.pvd") == sl["provenance"]
    assert read_xml_provenance(tmp_path / "sl" / "uf_up20um.pvtu") == sl["provenance"]
    assert not list((tmp_path / "sl").glob(".cfm_fem_slabs*"))  # work files removed
    for up in (20, 40):
        g1, a = by_position(pv.read(tmp_path / "one" / f"uf_up{up}um.vtu"))
        g2, b = by_position(pv.read(tmp_path / "sl" / f"uf_up{up}um.pvtu"))
        assert g1.n_points == g2.n_points == 686 and g1.n_cells == g2.n_cells
        assert set(a) == set(b)
        _same_fields(a, b, gradients=("grad", "gum_U95"))


def test_halo_nodes_are_vtk_ghost_points_each_node_counted_once(tmp_path):
    """A slab's piece holds the halo nodes its cells use, which other slabs own: they are
    flagged vtkGhostType = 1, so VTK counts each node once, with the in-memory run's values."""
    path = _write_csv(tmp_path / "g.csv", _lattice())
    base = ["sweep", str(path), "--up", "20", "--trials", "100"]
    _in_memory_and_slabs(tmp_path, base, 3)
    one = pv.read(tmp_path / "one" / "uf_up20um.vtu")
    sl = pv.read(tmp_path / "sl" / "uf_up20um.pvtu")
    assert sl.n_points > one.n_points == 686
    pts, b = owned_points(sl)
    order = np.lexsort(np.asarray(one.points).T)
    np.testing.assert_array_equal(pts, np.asarray(one.points)[order])  # each node once
    a = {k: np.asarray(v)[order] for k, v in one.point_data.items()}
    assert set(a) == set(b)
    _same_fields(a, b, gradients=("grad", "gum_U95"))
    assert vtk_histogram_count(sl, "U_f_units") == vtk_histogram_count(one, "U_f_units") == 686
    grids = [pv.read(f) for f in sorted((tmp_path / "sl" / "uf_up20um").glob("piece_*.vtu"))]
    z = [np.asarray(g.points)[np.asarray(g.point_data["vtkGhostType"]) == 0, 2] for g in grids]
    assert sum(map(len, z)) == 686
    assert z[0].max() <= z[1].min() and z[1].max() <= z[2].min()  # owner: the node's slab


def _same_scattered_maps(tmp_path, column):
    """The in-memory (DIR one) and slab (DIR sl) maps of a Delaunay run: same cells, same
    complete nodes and outside fractions, U_f to rounding (Qhull's vertex order)."""
    g1, a = by_position(pv.read(tmp_path / "one" / f"uf_{column}.vtu"))
    g2, b = by_position(pv.read(tmp_path / "sl" / f"uf_{column}.pvtu"))
    assert g1.n_cells == g2.n_cells
    np.testing.assert_array_equal(a["complete"], b["complete"])
    np.testing.assert_array_equal(a["outside_fraction"], b["outside_fraction"])
    np.testing.assert_allclose(a["U_f_units"], b["U_f_units"], rtol=1e-6)


def test_scattered_map_slabs_agree_with_the_in_memory_run(tmp_path):
    rng = np.random.default_rng(3)
    pts = rng.uniform([-10, -10, -30], [10, 10, 30], (900, 3))
    path = _write_csv(tmp_path / "s.csv", pts)
    base = ["sweep", str(path), "--up", "0,30", "--trials", "200"]
    one, sl = _in_memory_and_slabs(tmp_path, base, 2)
    assert "Delaunay" in sl["interpolation"]
    # Qhull's vertex order inside a simplex differs between slab and whole map: rounding only
    _same_summary(one, sl, exact=False)
    _same_scattered_maps(tmp_path, "up30um")


def _cylinder_nodes(n=3000, seed=5):
    """Nodes of a scattered FEM-like export of a cylinder (r 3 mm, 30 mm long): a third on
    its mantle, so its Delaunay hull is lined with flat cells (local ones: they span
    neighbouring mantle nodes)."""
    rng = np.random.default_rng(seed)
    m = n // 3
    r, t = 3 * np.sqrt(rng.uniform(0, 1, n - m)), rng.uniform(0, 2 * np.pi, n - m)
    inner = np.c_[r * np.cos(t), r * np.sin(t), rng.uniform(0, 30, n - m)]
    t = rng.uniform(0, 2 * np.pi, m)
    return np.r_[inner, np.c_[3 * np.cos(t), 3 * np.sin(t), rng.uniform(0, 30, m)]]


@pytest.mark.parametrize("outside", ["exclude", "extrapolate"])
@pytest.mark.slow
def test_hull_slivers_removed_by_slabs_as_by_the_whole_map(tmp_path, outside):
    """--hull-slivers remove with --slabs: every slab removes, from the cells around its own
    nodes, the cells the whole map removes (given the whole map's hull, the test is local), and
    the border faces that removal leaves are the map's border, not a halo border."""
    path = _write_csv(tmp_path / "c.csv", _cylinder_nodes())
    base = ["sweep", str(path), "--up", "0,40", "--trials", "200", "--hull-slivers", "remove",
            "--outside", outside]  # fmt: skip
    one, sl = _in_memory_and_slabs(tmp_path, base, 3)
    assert "flat cell(s) on the Delaunay hull removed" in " ".join(one["notes"])
    _same_summary(one, sl, exact=False)
    assert sl["slabs"]["halo_outside_nodes"] == 0
    _same_scattered_maps(tmp_path, "up40um")


def test_trials_that_reach_the_halo_border_count_as_outside(tmp_path):
    # halo of 6 sigma = 6 mm and no cell (halo_cells=0), grid steps of 8.6 mm along z: the
    # nodes next to a slab edge lose cells of their star;
    # their trials that walk into the missing cells must be counted outside, never given a value
    path = _write_csv(tmp_path / "g.csv", _lattice(5, 8))
    cfg = SweepConfig(up_um=[0.0, 1000.0], trials=200, field_model="linear")
    fm = read_field(path)
    from cfm_fem.workflows.sweep.in_memory import run_sweep

    ref = run_sweep(fm, cfg)
    s = run_slab_sweep(path, cfg, tmp_path / "sl", n_slabs=2, halo_cells=0.0)
    assert s["slabs"]["halo_outside_nodes"] > 0
    assert any("halo border" in n for n in s["notes"])
    g, b = by_position(pv.read(tmp_path / "sl" / "uf_up1000um.pvtu"))
    order = np.lexsort(fm.points.T)
    uf_ref = np.where(ref.complete(), ref.uf_units(), np.nan)[order, 1]  # no U_f: NaN
    out_ref = ref.n_outside[order, 1]
    out_sl = np.round(b["outside_fraction"].astype(np.float64) * 200).astype(int)
    changed = out_sl != out_ref
    assert changed.any() and (out_sl >= out_ref).all()  # only ever more trials outside
    same = ~changed
    np.testing.assert_array_equal(b["U_f_units"][same], uf_ref[same].astype(np.float32))
    assert (b["complete"][changed] == 0).all()  # such nodes leave the percentiles
    assert s["outside_fraction"][1] > ref.n_outside[:, 1].sum() / (ref.fieldmap.n_nodes * 200)


def test_extrapolating_slabs_agree_with_the_in_memory_run(tmp_path):
    """``--outside extrapolate`` out of core: the same figures as in memory (the Taylor
    gradient sums a node's cells in another order: rounding only), every node complete."""
    path = _write_csv(tmp_path / "g.csv", _lattice())
    base = ["sweep", str(path), "--up", "0:40:20", "--trials", "300", "--outside", "extrapolate"]
    one, sl = _in_memory_and_slabs(tmp_path, base, 3)
    assert sl["slabs"]["halo_outside_nodes"] == 0 and sl["outside"] == "extrapolate"
    assert sl["uf_nodes"] == one["uf_nodes"] == [686] * 3
    _same_summary(one, sl, exact=False)
    for up in (20, 40):
        _, a = by_position(pv.read(tmp_path / "one" / f"uf_up{up}um.vtu"))
        _, b = by_position(pv.read(tmp_path / "sl" / f"uf_up{up}um.pvtu"))
        assert (a["outside_fraction"] > 0).sum() > 200  # the surface nodes
        for name in a:
            np.testing.assert_allclose(a[name], b[name], rtol=1e-6, atol=1e-15, err_msg=name)


def test_nodes_that_reach_the_halo_are_not_extrapolated(tmp_path):
    """As `test_trials_that_reach_the_halo_border_count_as_outside`, extrapolating: a node whose
    walks reached a slab's halo border has its leaving trials left out, and no figure."""
    path = _write_csv(tmp_path / "g.csv", _lattice(5, 8))
    cfg = SweepConfig(up_um=[0.0, 1000.0], trials=200, outside="extrapolate")
    s = run_slab_sweep(path, cfg, tmp_path / "sl", n_slabs=2, halo_cells=0.0)
    halo = s["slabs"]["halo_outside_nodes"]
    assert halo > 0 and any("not extrapolated" in n for n in s["notes"])
    _, b = by_position(pv.read(tmp_path / "sl" / "uf_up1000um.pvtu"))
    assert (b["complete"] == 0).sum() == halo == 200 - s["uf_nodes"][1]
    assert (b["outside_fraction"][b["complete"] == 0] > 0).all()
    # those nodes: the statistics of the default run (their leaving trials left out)
    ref = SweepConfig(up_um=[0.0, 1000.0], trials=200)
    run_slab_sweep(path, ref, tmp_path / "ex", n_slabs=2, halo_cells=0.0)
    _, a = by_position(pv.read(tmp_path / "ex" / "uf_up1000um.pvtu"))
    cut = b["complete"] == 0
    name = "absB_U95_inside_trials_units"  # no U_f: the figure of the trials that stayed in
    np.testing.assert_array_equal(a[name][cut], b[name][cut])
    assert np.isfinite(b[name][cut]).all()


def test_htm_slabs_equal_the_in_memory_run(tmp_path):
    """``--mode htm --slabs``: nodes keep their whole-map index as noise stream, so the three
    maps (total, geometric, vibration and delay) are those of the in-memory run; the columns'
    U_p (RMS of the probe error over the map) too."""
    pts = _lattice() + [70.0, 0.0, 0.0]  # x = 60..80 mm: the nodes beyond 75 mm are out of
    # the reference bench's X stroke (magnet axis at mid-stroke, 150 mm)
    path = _write_csv(tmp_path / "g.csv", pts)
    base = ["sweep", str(path), "--mode", "htm", "--trials", "200"]
    one, sl = _in_memory_and_slabs(tmp_path, base, 3)
    assert sl["slabs"]["count"] == 3 and sl["slabs"]["halo_outside_nodes"] == 0
    assert any("outside the strokes" in n for n in sl["notes"])
    assert 0 < sl["processed_nodes"] < 686
    assert sl["columns"] == one["columns"] == ["htm_total", "htm_geometric", "htm_vibration_delay"]
    np.testing.assert_allclose(sl["up_um"], one["up_um"], rtol=1e-12)
    _same_summary({k: v for k, v in one.items() if k != "up_um"},
                  {k: v for k, v in sl.items() if k != "up_um"})  # fmt: skip
    for label in one["columns"]:
        _, a = by_position(pv.read(tmp_path / "one" / f"uf_{label}.vtu"))
        _, b = by_position(pv.read(tmp_path / "sl" / f"uf_{label}.pvtu"))
        assert set(a) == set(b) and "positioning_std_um" in a
        _same_fields(a, b, gradients=("grad", "gum"))


def test_an_interrupted_slab_run_resumes_to_the_same_numbers(tmp_path):
    """Killed after two of four slabs, the run keeps them in DIR/.cfm_fem_slabs; ``--resume``
    computes the other two and writes the outputs of an uninterrupted run (bit for bit); a
    resume with other options is refused, naming them."""
    from cfm_fem.workflows.sweep.resume import describe_sweep

    path = _write_csv(tmp_path / "g.csv", _lattice())
    cfg = SweepConfig(up_um=[0.0, 30.0], trials=200, seed=4)
    desc = describe_sweep(cfg, "sha", {}, None)
    run_slab_sweep(path, cfg, tmp_path / "ref", n_slabs=4)
    seen = []

    def kill_after_two(n):
        seen.append(n)
        if len(seen) == 2:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        run_slab_sweep(path, cfg, tmp_path / "cut", n_slabs=4, description=desc,
                       progress=kill_after_two)  # fmt: skip
    store = tmp_path / "cut" / ".cfm_fem_slabs"
    assert len(list(store.glob("results/slab*/done.json"))) == 2
    other = describe_sweep(SweepConfig(up_um=[0.0, 30.0], trials=200, seed=5), "sha", {}, None)
    with pytest.raises(CfmInputError, match="seed: 4 in the store, 5 now"):
        run_slab_sweep(path, cfg, tmp_path / "cut", n_slabs=4, description=other, resume=True)
    s = run_slab_sweep(path, cfg, tmp_path / "cut", n_slabs=4, description=desc, resume=True)
    assert any("resumed: 2 of 4 slabs" in n for n in s["notes"]) and not store.exists()
    ref = json.loads((tmp_path / "ref" / "summary.json").read_text())
    got = json.loads((tmp_path / "cut" / "summary.json").read_text())
    got["notes"] = [n for n in got["notes"] if not n.startswith("resumed")]
    _same_summary(ref, got)
    _, a = by_position(pv.read(tmp_path / "ref" / "uf_up30um.pvtu"))
    _, b = by_position(pv.read(tmp_path / "cut" / "uf_up30um.pvtu"))
    for name in a:
        np.testing.assert_array_equal(a[name], b[name], err_msg=name)


@pytest.mark.parametrize("fmt", ["csv", "table"])
def test_stream_reads_what_the_in_memory_reader_reads(tmp_path, monkeypatch, fmt):
    monkeypatch.setattr(streaming, "READ_BYTES", 97)  # blocks cut inside lines, CRLF pairs
    fm0 = read_field(_write_csv(tmp_path / "a.csv", _lattice(4, 5)))
    path = tmp_path / f"m.{fmt}"
    write_field(path, fm0)
    if fmt == "csv":  # comment lines, CRLF ends, a trailing blank line
        text = path.read_text().splitlines()
        text.insert(3, "# a comment")
        path.write_bytes(("\r\n".join(text) + "\r\n\r\n").encode())
    fm = read_field(path)
    st = streaming.open_stream(path, "table" if fmt == "csv" else "opera")
    blocks = list(st.blocks(rows_per_block=7))
    v = np.concatenate([b[0] for b in blocks])
    lines = np.concatenate([b[1] for b in blocks])
    np.testing.assert_array_equal(v[:, :3], fm.points)
    np.testing.assert_array_equal(v[:, 3:], fm.B)
    np.testing.assert_array_equal(lines, fm.lines)
    assert st.notes == fm.notes[: len(st.notes)]


@pytest.mark.parametrize(
    "tail, where",
    [("1,2,abc,4,5,6\n", ":82: column 'z [mm]'"), ("1,2,3,4,5\n", ":82: the row has 5")],
)
def test_bad_rows_give_the_same_message_and_exit_2_with_nothing_written(
    tmp_path, capsys, tail, where
):
    path = _write_csv(tmp_path / "b.csv", _lattice(4, 5))
    path.write_text(path.read_text() + tail)
    with pytest.raises(CfmInputError) as mem:
        read_field(path)
    with pytest.raises(CfmInputError) as stream:
        list(streaming.open_stream(path, "table").blocks(16))
    assert str(mem.value) == str(stream.value) and where in str(stream.value)
    out = tmp_path / "o"
    assert main(["sweep", str(path), "--slabs", "2", "--trials", "50", "--out", str(out)]) == 2
    assert where in capsys.readouterr().err
    assert not out.exists() or not [p for p in out.rglob("*") if p.is_file()]


def test_disk_percentiles_are_numpys_bit_for_bit():
    rng = np.random.default_rng(0)
    vals = np.concatenate([rng.lognormal(size=5001), np.full(300, 1.5), rng.normal(size=77)])
    chunks = np.array_split(vals, 13)
    qs = [0, 50, 95, 99, 99.9, 100]
    got = disk_percentiles(lambda: iter(chunks), qs, in_memory_limit=0)
    assert got == [float(np.percentile(vals, q)) for q in qs]
    assert disk_percentiles(lambda: iter([np.empty(0)]), [50]) == [None]


def test_memory_budget_chooses_the_slabs_and_bad_sizes_exit_2(tmp_path, capsys):
    assert slabs_for_memory(10_000_000, 4e9, 6) > slabs_for_memory(10_000_000, 16e9, 6) >= 1
    path = _write_csv(tmp_path / "g.csv", _lattice(4, 6))
    out = tmp_path / "o"
    args = ["sweep", str(path), "--up", "10", "--trials", "50", "--out", str(out)]
    assert main([*args, "--max-memory", "lots"]) == 2
    assert "--max-memory must be a size" in capsys.readouterr().err
    assert main([*args, "--slabs", "2", "--pieces", "2"]) == 2
    assert main([*args, "--max-memory", "1G"]) == 0
    assert json.loads((out / "summary.json").read_text())["slabs"]["count"] >= 1


def test_mesh_formats_are_read_whole_and_say_so(tmp_path, capsys):
    fm = read_field(_write_csv(tmp_path / "g.csv", _lattice(4, 6)))
    write_field(tmp_path / "g.vtu", fm)
    out = tmp_path / "o"
    args = ["sweep", str(tmp_path / "g.vtu"), "--up", "10", "--trials", "50", "--slabs", "2"]
    assert main([*args, "--out", str(out)]) == 0
    assert "read whole" in capsys.readouterr().err
    assert json.loads((out / "summary.json").read_text())["pieces"] == 2


def test_l_shaped_map_slabs_equal_the_in_memory_run_bit_for_bit(tmp_path):
    """A grid map with a notch (x > 0, y > 0 removed) cut into slabs across it: trials that
    cross the notch are found in the other arm (the exact search of each slab's own mesh, its
    face excess taken over the slab's own nodes) exactly as by the whole map's."""
    ax = np.linspace(-10.0, 10.0, 7)
    pts = np.stack(np.meshgrid(np.linspace(-30.0, 30.0, 14), ax, ax, indexing="ij"), -1)
    pts = pts.reshape(-1, 3)
    pts = pts[~((pts[:, 0] > 0) & (pts[:, 1] > 0))]
    path = _write_csv(tmp_path / "l.csv", pts)
    base = ["sweep", str(path), "--up", "0,1000,2000", "--trials", "300"]
    one, sl = _in_memory_and_slabs(tmp_path, base, 3)
    assert sl["slabs"]["count"] == 3 and sl["slabs"]["axis"] == "x"
    assert sl["slabs"]["halo_outside_nodes"] == 0
    assert one["outside_fraction"][2] > 0  # trials do leave across the notch
    _same_summary(one, sl)
    for up in (1000, 2000):
        _, a = by_position(pv.read(tmp_path / "one" / f"uf_up{up}um.vtu"))
        _, b = by_position(pv.read(tmp_path / "sl" / f"uf_up{up}um.pvtu"))
        _same_fields(a, b, gradients=("grad", "gum_U95"))
    from cfm_fem.models.mesh import exact_search
    from cfm_fem.models.sweep import SweepConfig as _Cfg
    from cfm_fem.workflows.sweep.problem import prepare_sweep

    mesh, problem, _ = prepare_sweep(read_field(path), _Cfg(up_um=[2000.0], trials=300))
    assert len(exact_search(mesh)[0]) > 0  # the exact search did run
    # the nodes beside the notch's face x = 0, y > 0: their trials that cross it end in the
    # other arm, behind the border
    edge = np.flatnonzero(
        np.isclose(mesh.coords[:, 0], -30 / 13) & np.isclose(mesh.coords[:, 1], 10 / 3)
    )
    _, n_out, _, _, _ = problem.run_nodes(edge)
    plain = dataclasses.replace(problem, search=None).run_nodes(edge)[1]
    assert (n_out <= plain).all() and n_out.sum() < plain.sum()  # trials found across the notch


@pytest.mark.parametrize("k", [3, 4])
@pytest.mark.slow
def test_kept_hull_slivers_slabs_agree_with_the_in_memory_run(tmp_path, k):
    """--hull-slivers keep with --slabs on random nodes: a suspect border face that holds an
    own node led that node's star into the halo sentinel cell (tables written past their end)
    and NaN samples into the kernel's counting sort (heap corruption, exit 139). Now the star
    stops there, and the maps are the in-memory run's (to Qhull's rounding)."""
    rng = np.random.default_rng(2)  # main crashed on this map with --slabs 4
    pts = rng.uniform([-3, -3, -10], [3, 3, 10], (3000, 3))
    path = _write_csv(tmp_path / "r.csv", pts)
    base = ["sweep", str(path), "--up", "0,20,50", "--trials", "400", "--hull-slivers", "keep"]
    one, sl = _in_memory_and_slabs(tmp_path, base, k)
    assert "kept" in " ".join(one["notes"])
    assert one["outside_fraction"] == sl["outside_fraction"] and one["outside"] == "exclude"
    # hull faces the box test cannot prove (slanted ones) send a few nodes' trials to the
    # halo-border pass, which counts them outside: as the whole map does here. The count of
    # simplices differs too: each slab + halo keeps the slivers of its own hull
    assert sl["slabs"]["halo_outside_nodes"] < 60
    _same_summary(dict(one, notes=[], interpolation=""), dict(sl, notes=[], interpolation=""),
                  exact=False)  # fmt: skip
    for up in (20, 50):  # the cells written differ by the slivers of the slab hulls
        _, a = by_position(pv.read(tmp_path / "one" / f"uf_up{up}um.vtu"))
        _, b = by_position(pv.read(tmp_path / "sl" / f"uf_up{up}um.pvtu"))
        np.testing.assert_array_equal(a["complete"], b["complete"])
        np.testing.assert_array_equal(a["outside_fraction"], b["outside_fraction"])
        np.testing.assert_allclose(a["U_f_units"], b["U_f_units"], rtol=1e-6)


@pytest.mark.slow
def test_jittered_maps_slabs_equal_the_in_memory_run(tmp_path):
    """Scattered nodes beside a block of lattice nodes (co-spherical sets: their cells are flat
    unless the nodes are jittered). The jitter is keyed by each node's coordinates and scaled
    by the whole map's size, so every slab triangulates its nodes as the whole map does
    (with a random stream in slab order and the slab's own size, U_f of 568 of 3,160 complete
    nodes differed, by up to 1.75 units, on the audit's 4,519-node map). Here the slabs grow to
    1,267-1,520 of the 1,520 nodes (`SMALL_SLAB_ROWS`); the next test keeps them small."""
    rng = np.random.default_rng(8)
    scattered = rng.uniform([-5, -5, -30], [5, 5, 8], (1200, 3))
    ax = np.linspace(-5, 5, 6)
    lattice = np.stack(np.meshgrid(ax, ax, np.linspace(12, 30, 10), indexing="ij"), -1)
    lattice = lattice.reshape(-1, 3)
    lattice = lattice[rng.uniform(size=len(lattice)) > 0.15]  # with holes: not a grid
    path = _write_csv(tmp_path / "m.csv", np.r_[scattered, lattice])
    base = ["sweep", str(path), "--up", "0,300", "--trials", "200"]
    one, sl = _in_memory_and_slabs(tmp_path, base, 4)
    assert any("jittered" in n for n in one["notes"])
    _same_summary(one, sl, exact=False)
    _, a = by_position(pv.read(tmp_path / "one" / "uf_up300um.vtu"))
    _, b = by_position(pv.read(tmp_path / "sl" / "uf_up300um.pvtu"))
    np.testing.assert_array_equal(a["complete"], b["complete"])
    np.testing.assert_allclose(a["U_f_units"], b["U_f_units"], rtol=1e-9)


def test_slabs_of_co_spherical_nodes_triangulate_them_as_the_whole_map(tmp_path, monkeypatch):
    """The map of `test_jittered_maps_slabs_equal_the_in_memory_run`, in slabs that stay parts
    of it (no growth to 20,000 rows). Nodes were jittered (1e-5 of the map size) only when
    Qhull left flat cells: all of them in the whole map (its lattice block), none in the three
    slabs of scattered nodes alone, whose 450 complete nodes' U_f then differed by up to 1.2
    units (and 21 nodes' outside fractions). Now Delaunay always triangulates the nodes moved
    by 1e-6 of the map size (one triangulation, the same in every slab), and the nodes of the
    cells flat without the move keep it, the same in every slab too."""
    import cfm_fem.workflows.sweep.slabs

    monkeypatch.setattr(cfm_fem.workflows.sweep.slabs, "SMALL_SLAB_ROWS", 0)
    rng = np.random.default_rng(8)
    scattered = rng.uniform([-5, -5, -30], [5, 5, 8], (1200, 3))
    ax = np.linspace(-5, 5, 6)
    lattice = np.stack(np.meshgrid(ax, ax, np.linspace(12, 30, 10), indexing="ij"), -1)
    lattice = lattice.reshape(-1, 3)
    lattice = lattice[rng.uniform(size=len(lattice)) > 0.15]
    path = _write_csv(tmp_path / "m.csv", np.r_[scattered, lattice])
    base = ["sweep", str(path), "--up", "0,300", "--trials", "200"]
    one, sl = _in_memory_and_slabs(tmp_path, base, 4)
    assert sl["slabs"]["count"] == 4 and max(sl["slabs"]["edges_mm"][1:4]) < 8  # 3 scattered
    _, a = by_position(pv.read(tmp_path / "one" / "uf_up300um.vtu"))
    _, b = owned_points(pv.read(tmp_path / "sl" / "uf_up300um.pvtu"))
    np.testing.assert_array_equal(a["complete"], b["complete"])
    assert a["complete"].sum() > 800
    np.testing.assert_allclose(a["U_f_units"], b["U_f_units"], rtol=1e-6)
    np.testing.assert_array_equal(a["outside_fraction"], b["outside_fraction"])
    assert one["outside_fraction"] == sl["outside_fraction"]
    ties = [n for n in one["notes"] if "co-spherical" in n]  # the lattice's nodes, counted
    assert len(ties) == 1 and ties == [n for n in sl["notes"] if "co-spherical" in n]


@pytest.mark.parametrize("seed", [-1, 2**63, True], ids=["negative", "too_large", "bool"])
def test_run_slab_sweep_refuses_a_bad_seed_before_reading_or_writing(tmp_path, monkeypatch, seed):
    """A bad seed is refused with the CLI's message before the file is staged or anything is
    made in out_dir."""
    import cfm_fem.io.slab_files
    import cfm_fem.workflows.sweep.slabs
    from cfm_fem.errors import check_seed

    path = _write_csv(tmp_path / "g.csv", _lattice(4, 6))

    def no_read(*args, **kwargs):
        raise AssertionError("the file was read")

    monkeypatch.setattr(cfm_fem.workflows.sweep.slabs, "stage", no_read)
    monkeypatch.setattr(cfm_fem.io.slab_files, "open_stream", no_read)
    with pytest.raises(CfmInputError) as cli:
        check_seed(seed)
    out = tmp_path / "o"
    cfg = SweepConfig(up_um=[10.0], trials=50, seed=seed)
    for desc in (None, {"run": "resumable"}):
        with pytest.raises(CfmInputError) as api:
            run_slab_sweep(path, cfg, out, n_slabs=2, description=desc)
        assert str(api.value) == str(cli.value)
        assert not out.exists()


@pytest.mark.parametrize("ext", ["csv", "table"])
@pytest.mark.parametrize("zero_rows", ["warn", "drop"])
def test_staged_planar_map_is_the_map_read_field_gives(tmp_path, ext, zero_rows):
    """A map that is not 3-D goes to the in-memory run as staged (`staged_fieldmap`, not read
    again): the same points, field, lines, notes and source as `read_field`."""
    import warnings

    from cfm_fem.io.slab_files import stage, staged_fieldmap
    from cfm_fem.models.field import FieldMap

    ax = np.linspace(-10.0, 10.0, 6)
    pts = np.stack(np.meshgrid(ax, [2.5], ax, indexing="ij"), -1).reshape(-1, 3)
    B = _field(pts)
    B[[4, 17]] = 0.0
    path = tmp_path / f"plane.{ext}"
    write_field(path, FieldMap.from_arrays(pts, B))
    with warnings.catch_warnings(record=True):
        warnings.simplefilter("always")
        ref = read_field(path, zero_rows=zero_rows)
        fmt = streaming.is_streamable(path)
        (tmp_path / "w").mkdir()
        st = stage(path, fmt, tmp_path / "w", zero_rows=zero_rows)
        assert st.dim == 2
        fm = staged_fieldmap(st, path)
    np.testing.assert_array_equal(fm.points, ref.points)
    np.testing.assert_array_equal(fm.B, ref.B)
    np.testing.assert_array_equal(fm.lines, ref.lines)
    assert fm.cells is None and ref.cells is None
    assert fm.notes == ref.notes and fm.source == ref.source


def test_cylinder_mantle_slivers_do_not_widen_the_halo_to_the_whole_map(
    tmp_path, capsys, monkeypatch
):
    """Nodes in rings on a cylinder's mantle (co-planar along its generator lines, as FEM
    exports of an aperture have them): which hull slivers Delaunay makes there depends on nodes
    anywhere along the map, so no halo short of the whole map certified them, and each slab
    grew to the whole map (the bundled map as CSV: 3 slabs, 5 doublings each, 150 s against 8 s
    in memory). Now slab + halo grows for them to twice a slab's share of the rows at most
    (`GONE_ROWS_FACTOR`; small maps, here all, may grow further: `SMALL_SLAB_ROWS`, set to 0),
    the faces the uncertified slivers leave become halo borders, and the complete nodes'
    numbers are the in-memory ones."""
    import cfm_fem.workflows.sweep.slabs
    from cfm_fem.workflows.sweep.slabs import GONE_ROWS_FACTOR

    monkeypatch.setattr(cfm_fem.workflows.sweep.slabs, "SMALL_SLAB_ROWS", 0)
    rng = np.random.default_rng(3)
    t, z = np.meshgrid(np.linspace(0, 2 * np.pi, 24, endpoint=False), np.linspace(-30, 30, 31))
    mantle = np.c_[5 * np.cos(t.ravel()), 5 * np.sin(t.ravel()), z.ravel()]
    r, a = 4 * np.sqrt(rng.uniform(size=1500)), rng.uniform(0, 2 * np.pi, 1500)
    inner = np.c_[r * np.cos(a), r * np.sin(a), rng.uniform(-30, 30, 1500)]
    nodes = np.r_[mantle, inner]
    path = _write_csv(tmp_path / "cyl.csv", nodes)
    base = ["sweep", str(path), "--up", "0,20", "--trials", "200"]
    assert main([*base, "--out", str(tmp_path / "one")]) == 0
    capsys.readouterr()
    assert main([*base, "--slabs", "3", "--out", str(tmp_path / "sl")]) == 0
    err = capsys.readouterr().err
    assert "could not be certified" in err
    one, sl = (json.loads((tmp_path / d / "summary.json").read_text()) for d in ("one", "sl"))
    edges = sl["slabs"]["edges_mm"]
    for k in range(3):
        widened = re.findall(rf"slab {k}: halo widened to ([0-9.e+-]+) mm", err)
        h = float(widened[-1]) if widened else sl["slabs"]["halo_mm"]
        rows = ((nodes[:, 2] >= edges[k] - h) & (nodes[:, 2] <= edges[k + 1] + h)).sum()
        assert rows <= GONE_ROWS_FACTOR * len(nodes) / 3 < len(nodes)
    assert sl["slabs"]["halo_outside_nodes"] > 0  # the mantle nodes' trials met such faces
    assert one["outside_fraction"] == sl["outside_fraction"]
    for q in one["uf_units"]:  # percentiles over the nodes: taken in another order on disk
        np.testing.assert_allclose(one["uf_units"][q], sl["uf_units"][q], rtol=1e-12)
    _, a = by_position(pv.read(tmp_path / "one" / "uf_up20um.vtu"))
    _, b = owned_points(pv.read(tmp_path / "sl" / "uf_up20um.pvtu"))
    np.testing.assert_array_equal(a["complete"], b["complete"])
    done = a["complete"] == 1
    np.testing.assert_array_equal(a["U_f_units"][done], b["U_f_units"][done])
