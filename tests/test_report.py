"""The HTML reports: open them, decode their figures, check their numbers against the JSON."""

from __future__ import annotations

import base64
import json
import re
from html.parser import HTMLParser

import numpy as np
import pytest

from cfm_fem.cli import main
from cfm_fem.io import write_field
from cfm_fem.io.bench_toml import read_reference_bench
from cfm_fem.io.recordings import write_tracker
from cfm_fem.models.field import FieldMap
from cfm_fem.report.html import HtmlReport, fmt
from cfm_fem.workflows.synthetic import synthetic_tracker

PNG = b"\x89PNG\r\n\x1a\n"


class _Parse(HTMLParser):
    """Images (alt, data-file, decoded bytes) and tables (id -> rows of cell text)."""

    def __init__(self):
        super().__init__()
        self.images, self.tables = [], {}
        self._table = self._row = self._cell = None

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        if tag == "img":
            src = a["src"]
            assert src.startswith("data:image/png;base64,")
            self.images.append((a["data-file"], base64.b64decode(src.split(",", 1)[1])))
        elif tag == "table":
            self._table = self.tables.setdefault(a.get("id", f"t{len(self.tables)}"), [])
        elif tag == "tr":
            self._row = []
        elif tag in ("td", "th"):
            self._cell = ""

    def handle_endtag(self, tag):
        if tag in ("td", "th"):
            self._row.append(self._cell)
            self._cell = None
        elif tag == "tr":
            self._table.append(self._row)
        elif tag == "table":
            self._table = None

    def handle_data(self, data):
        if self._cell is not None:
            self._cell += data


def parse(path):
    p = _Parse()
    p.feed(path.read_text(encoding="utf-8"))
    return p


def check_images(p, folder, expected):
    names = [n for n, _ in p.images]
    assert set(expected) <= set(names)
    for name, data in p.images:
        assert data.startswith(PNG) and len(data) > 5000  # a real plot, not an empty canvas
        assert (folder / name).read_bytes() == data  # the side file is the same figure


def row(table, label):
    return next(r for r in table if r[0] == label)


def test_html_report_escapes_and_formats():
    r = HtmlReport("a <b> & c")
    r.table(["x", "y"], [["<i>", 1.23456], ["n", None]], table_id="t")
    text = r.render()
    assert "&lt;i&gt;" in text and "<i>" not in text.split("<body>")[1]
    assert fmt(1.23456) == "1.23" and fmt(True) == "yes" and fmt(float("nan")) == "nan"


def test_coupled_report(tmp_path):
    out = tmp_path / "c"
    args = ["coupled", "--trials", "400", "--z", "0", "--step", "5", "--out", str(out)]
    assert main(args) == 0
    summary = json.loads((out / "summary.json").read_text())
    p = parse(out / "report.html")
    check_images(p, out, ["hist_point.png", "hist_pooled.png"])
    s = summary["table_v"]["simulated"]
    r = row(p.tables["table_v"], "this run (pooled Bx, By)")
    assert r[1:4] == [fmt(s["systematic_units"]), fmt(s["std_units"]), fmt(s["U_f_units"])]
    assert row(p.tables["table_v"], "paper, simulated")[1:4] == ["4", "5", "6.5"]
    assert summary["b_ref_T"] == pytest.approx(0.0696) and summary["r_ref_mm"] == 10.0
    assert summary["trials"] == 400 and summary["points"] == 13
    fb = summary["field_budget"]
    assert row(p.tables["field_budget"], "probe only (bench exact)")[3] == fmt(
        fb["probe_only"]["U_f_units"]
    )
    assert len(p.tables["budget"]) == 23  # header, 21 errors, vibration+delay
    html = (out / "report.html").read_text()
    assert "cfm-fem coupled --trials 400" in html and "R_ref = 10 mm" in html


def test_tracker_report(tmp_path):
    bench = read_reference_bench()
    rec = synthetic_tracker(bench, seed=4, reps=3, grid=(2, 2, 2), reversal_um=4.0)
    path = tmp_path / "t.csv"
    write_tracker(path, rec)
    out = tmp_path / "cmp"
    assert main(["compare", "--tracker", str(path), "--trials", "500", "--out", str(out)]) == 0
    doc = json.loads((out / "compare.json").read_text())
    p = parse(out / "report.html")
    check_images(p, out, ["fig12.png", "residuals.png", "fig10.png"])
    for a in "xyz":
        e, s = doc["table_iv"]["experiment"][a], doc["table_iv"]["simulation"][a]
        r = row(p.tables["table_iv"], a.upper())
        assert r[1] == fmt(e["systematic_um"]) and r[4] == fmt(s["systematic_um"])
        f = row(p.tables["fig12"], a.upper())
        ov = next(v["overlap"] for v in doc["fig12"] if v["name"] == a)
        assert f[5] == fmt(ov)
    iso = doc["iso230_2"][0]["axis_values_um"]
    assert row(p.tables["iso230"], p.tables["iso230"][1][0])[7] == fmt(iso["B"])


@pytest.mark.slow
def test_fig4_report_linear_law(tmp_path, capsys):
    """Linear quadrupole map: U_f = 1.96 U_p G / B_ref at every body node."""
    g = np.linspace(-8.0, 8.0, 9)
    z = np.linspace(-40.0, 40.0, 5)
    x, y, zz = (a.ravel() for a in np.meshgrid(g, g, z, indexing="ij"))
    G = 0.07  # T/mm
    fm = FieldMap.from_arrays(np.column_stack([x, y, zz]), np.column_stack([G * y, G * x, 0 * x]))
    path = tmp_path / "quad.csv"
    write_field(path, fm)
    out = tmp_path / "f4"
    code = main(["fig4", str(path), "--up", "0,20,50", "--trials", "400", "--out", str(out)])
    assert code == 0
    doc = json.loads((out / "fig4.json").read_text())
    b_ref = G * 8 * np.sqrt(2)
    assert doc["b_ref_T"] == pytest.approx(b_ref)
    for r in doc["table"][1:]:
        law = 1.96 * r["up_um"] * 1e-3 * G / b_ref * 1e4
        assert r["analytic"] == pytest.approx(law, rel=1e-3)
        # median over nodes of a quantile estimated from 400 trials: a few % at most
        assert r["p50"] == pytest.approx(law, rel=0.08)
    assert doc["table"][0]["p50"] == 0.0
    p = parse(out / "report.html")
    check_images(p, out, ["fig4_curve.png", "fig4_plane.png"])
    t = p.tables["fig4"]
    assert row(t, "20")[5] == "10" and row(t, "50")[5] == "25"
    assert row(t, "50")[1] == fmt(doc["table"][2]["p50"])
    assert re.search(r"linear in U_p", (out / "report.html").read_text())
    # the printed table names the nodes of each row: it said "over the <U_p = 0 count>
    # magnet-body nodes" while the rows above 0 are over fewer (surface nodes lose trials)
    printed = capsys.readouterr().out
    assert "magnet-body nodes (|z| <= 30 mm) that kept every trial" in printed
    for r in doc["table"]:
        assert re.search(rf"^\s*{r['up_um']:g}\s+{r['nodes']}\s", printed, re.M), printed
    assert doc["table"][0]["nodes"] > doc["table"][1]["nodes"]
