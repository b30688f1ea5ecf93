"""The sweep's report.html: its numbers are summary.json's, its figures come from the maps
(read back piece by piece, each node once)."""

import json
import re
from html.parser import HTMLParser

import numpy as np
import pytest

from cfm_fem.cli import main
from cfm_fem.report import sweep_digest
from cfm_fem.report.html import fmt
from cfm_fem.report.sweep_digest import SweepDigest

G = np.array([[0.2, 0.0, 0.0], [0.0, -0.2, 0.0], [0.0, 0.0, 0.1]])


class _Tables(HTMLParser):
    """Tables by id: rows of cell texts."""

    def __init__(self):
        super().__init__()
        self.tables, self._id, self._row, self.images = {}, None, None, []

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        if tag == "table":
            self._id = a.get("id")
            self.tables[self._id] = []
        elif tag == "tr" and self._id is not None:
            self._row = []
            self.tables[self._id].append(self._row)
        elif tag == "img":
            self.images.append(a["data-file"])

    def handle_endtag(self, tag):
        if tag == "table":
            self._id = None

    def handle_data(self, data):
        if self._row is not None and self._id is not None:
            self._row.append(data)


@pytest.fixture(scope="module")
def grid_map(tmp_path_factory):
    ax = np.arange(-3.0, 4.0)
    pts = np.stack(np.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3)
    B = pts @ G.T + [0.0, 0.0, 1.0]
    path = tmp_path_factory.mktemp("map") / "map.csv"
    rows = "\n".join(",".join(f"{v:.17g}" for v in r) for r in np.c_[pts, B])
    path.write_text("x [mm],y [mm],z [mm],Bx [T],By [T],Bz [T]\n" + rows + "\n")
    return path


@pytest.fixture(scope="module")
def runs(grid_map, tmp_path_factory):
    base = tmp_path_factory.mktemp("runs")
    common = ["sweep", str(grid_map), "--up", "0:40:20", "--trials", "300", "--seed", "2"]
    assert main([*common, "--out", str(base / "one")]) == 0
    assert main([*common, "--pieces", "3", "--out", str(base / "pc")]) == 0
    return base


def _parse(path):
    p = _Tables()
    p.feed(path.read_text())
    return p


def test_report_tables_are_the_summary_and_figures_are_embedded(runs):
    out = runs / "one"
    s = json.loads((out / "summary.json").read_text())
    p = _parse(out / "report.html")
    rows = p.tables["uf_percentiles"][1:]
    assert len(rows) == 3
    for k, row in enumerate(rows):
        assert row[0] == f"U_p = {s['up_um'][k]:g} um"
        expect = [s["uf_units"][q][k] for q in ("p50", "p95", "p99", "max")]
        assert row[1:5] == [fmt(v) for v in expect]
        assert row[5] == str(s["uf_nodes"][k])
        assert row[6] == fmt(100 * s["outside_fraction"][k])
    flags = p.tables["gum_flags"][2]
    assert flags[1] == fmt(100 * s["gum_disagree_fraction"][1]["absB"])
    assert set(p.images) == {"uf_vs_up.png", "uf_slices.png", "uf_histograms.png"}
    for name in p.images:
        assert (out / name).read_bytes()[:4] == b"\x89PNG"
    html = (out / "report.html").read_text()
    assert s["provenance"]["inputs"]["field"]["sha256"] in html
    assert re.search(r"cfm-fem sweep \S+map.csv --up 0:40:20", html)
    assert (out / "open_in_paraview.py").is_file()


def test_report_of_pieces_counts_each_node_once(runs):
    """The histograms count every node with a U_f once, also over pieces with ghost copies."""
    from cfm_fem.io.sweep_maps import iter_map_nodes

    for d in ("one", "pc"):
        s = json.loads((runs / d / "summary.json").read_text())
        digest = SweepDigest(s["uf_units"]["max"])
        n = [0, 0, 0]
        for k, pts, arr in iter_map_nodes(runs / d):
            digest.add(k, pts, arr["U_f_units"], arr["complete"] == 1)
            n[k] += len(pts)
        assert n == [343] * 3
        assert [int(digest.histogram(k)[1].sum()) for k in range(3)] == s["uf_nodes"]
        # the grid's level y = 0: 49 nodes, the 25 inner ones with a U_f at U_p > 0
        plane = digest.plane(2)
        assert plane.y_mm == 0 and len(plane.points) == 49
        assert np.isfinite(plane.uf).sum() == 25
    a = _parse(runs / "one" / "report.html").tables["uf_percentiles"]
    b = _parse(runs / "pc" / "report.html").tables["uf_percentiles"]
    assert a == b


def test_report_drawn_from_memory_is_the_one_drawn_from_the_maps(grid_map, tmp_path):
    """The command line draws the figures from the result in memory: the same digest, and
    the same figures, as from the maps read back; for maps written whole and as pieces."""
    from cfm_fem.io import read_field
    from cfm_fem.io.sweep_maps import iter_map_nodes
    from cfm_fem.io.sweep_out import write_sweep, write_sweep_pieces
    from cfm_fem.models.sweep import SweepConfig
    from cfm_fem.report.sweep import write_sweep_report
    from cfm_fem.workflows.sweep.in_memory import run_sweep
    from cfm_fem.workflows.sweep.pieces import run_sweep_pieces
    from cfm_fem.workflows.sweep.resume import ResumableRun

    fm = read_field(grid_map)
    cfg = SweepConfig(up_um=[0.0, 20.0, 40.0], trials=300, seed=2)
    res = run_sweep(fm, cfg)
    runner = ResumableRun(tmp_path / "pc", {"test": 1})
    compact = run_sweep_pieces(fm, cfg, runner.mapper())
    gather = lambda nodes: runner.gather(nodes, [(0, fm.n_nodes)])  # noqa: E731
    for out, result in ((tmp_path / "one", res), (tmp_path / "pc", compact)):
        if result is res:
            s = write_sweep(out, result)
        else:
            s = write_sweep_pieces(out, result, 3, gather)
        memory = SweepDigest.of_result(result, s["uf_units"]["max"])
        maps = SweepDigest(s["uf_units"]["max"])
        for k, pts, arr in iter_map_nodes(out):
            maps.add(k, pts, arr["U_f_units"], arr["complete"] == 1)
        for k in range(3):
            np.testing.assert_array_equal(memory.histogram(k)[1], maps.histogram(k)[1])
            a, b = memory.plane(k), maps.plane(k)
            assert a.y_mm == b.y_mm
            order_a, order_b = np.lexsort(a.points.T), np.lexsort(b.points.T)
            np.testing.assert_array_equal(a.points[order_a], b.points[order_b])
            np.testing.assert_array_equal(a.uf[order_a], b.uf[order_b])
        write_sweep_report(out)
        read_back = {n: (out / n).read_bytes() for n in ("uf_slices.png", "uf_histograms.png")}
        write_sweep_report(out, result=result)
        for name, png in read_back.items():
            assert (out / name).read_bytes() == png


def test_digest_keeps_the_nodes_nearest_the_plane_in_bounded_memory(monkeypatch):
    monkeypatch.setattr(sweep_digest, "MAX_PLANE_NODES", 50)
    rng = np.random.default_rng(1)
    d = SweepDigest([1.0])
    pts = rng.uniform(-10, 10, (1000, 3))
    for part in np.array_split(np.arange(1000), 7):
        d.add(0, pts[part], np.full(len(part), 0.5), np.ones(len(part), bool))
    kept = d.columns[0].points[:, 1]
    near = np.sort(np.abs(pts[:, 1]))
    assert 50 <= len(kept) <= 100
    np.testing.assert_array_equal(np.sort(np.abs(kept)), near[: len(kept)])  # the nearest
    plane = d.plane(0)  # scattered: every kept node within 0.5 mm of the nearest level
    assert np.abs(plane.y_mm) == near[0]
    assert len(plane.points) == np.sum(np.abs(kept - plane.y_mm) <= 0.5) >= 50
    assert d.histogram(0)[1].sum() == 1000  # the histogram counts every node
