"""Inputs found by fuzzing and fault injection: each ends in a right answer or a clean refusal
(exit 2, one message naming the file, nothing written), never a silent wrong answer, a hang, a
crash or a traceback."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest

from cfm_fem.cli import main
from cfm_fem.errors import CfmInputError
from cfm_fem.field import FieldMap
from cfm_fem.sweep import SweepConfig, run_sweep

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data"
OPERA = DATA / "cctpy" / "test_opera_field_table.table"
HEADER = "x [mm],y [mm],z [mm],Bx [T],By [T],Bz [T]\n"


def _refused(argv, capsys, out=None):
    """Run the CLI; check exit 2, one message, no traceback, no output; return the message."""
    rc = main([str(a) for a in argv])
    err = capsys.readouterr().err
    assert rc == 2, err
    assert "Traceback" not in err and err.count("cfm-fem: error:") == 1, err
    if out is not None:
        assert not Path(out).exists(), "an output was written for a bad input"
    return err


def _scattered(n=400, seed=4):
    rng = np.random.default_rng(seed)
    pts = rng.uniform(-5, 5, (n, 3))
    B = np.c_[0.06 * pts[:, 1], 0.06 * pts[:, 0], 0.01 * pts[:, 2] ** 2 + 0.1]
    return pts, B


def _csv(path, pts, B):
    rows = "".join(",".join(repr(float(v)) for v in r) + "\n" for r in np.c_[pts, B])
    Path(path).write_text(HEADER + rows, encoding="utf-8")
    return path


# --------------------------------------------------------------------------- far from the origin


@pytest.mark.parametrize("offset", [1e6, 1e9])
def test_a_map_far_from_the_origin_gives_the_same_uf(offset):
    """x shifted by 1e9 mm: Qhull left most nodes out of the triangulation (exit 0, U_f of
    the rest only); triangulated in a frame centred on the nodes, every node keeps its cells
    and U_f is that of the map at the origin."""
    pts, B = _scattered()
    cfg = SweepConfig(up_um=[30.0], trials=300, seed=2)
    near = run_sweep(FieldMap.from_arrays(pts, B), cfg)
    moved = pts + [offset, 0.0, 0.0]
    far = run_sweep(FieldMap.from_arrays(moved, B), cfg)
    assert not any("left out" in n for n in far.mesh.notes)
    # the nodes are rounded to 1e-7 mm at 1e9 mm, so a hull sliver may differ: same figures
    assert abs(len(far.mesh.simplices) - len(near.mesh.simplices)) <= 2
    assert abs(int(far.complete().sum()) - int(near.complete().sum())) <= 2
    # the linear (GUM) figure depends on the cells and gradients only: the same map
    gum = [np.nanpercentile(r.gum_u[:, 0, 3], [50, 95]) for r in (near, far)]
    np.testing.assert_allclose(gum[0], gum[1], rtol=1e-6)
    # the Monte Carlo figure draws other numbers (a node's stream is keyed by its coordinates):
    # the same within its standard error (+-4 % per node at 300 trials, far less on percentiles)
    uf = [np.nanpercentile(r.uf_units()[:, 0], [50, 95]) for r in (near, far)]
    np.testing.assert_allclose(uf[0], uf[1], rtol=0.03)


def test_an_outlier_node_is_refused_quickly(tmp_path, capsys):
    """One node at x = 1e9 mm among nodes a few mm apart: the rest of the map is closer than
    the triangulation's round-off at that size. Refused, in seconds (it took minutes)."""
    pts, B = _scattered()
    pts[0, 0] = 1e9
    path = _csv(tmp_path / "outlier.csv", pts, B)
    out = tmp_path / "out"
    err = _refused(["sweep", path, "--trials", 20, "--up", 10, "--out", out], capsys, out)
    assert f"{path}: " in err and "merge with others" in err, err


def test_shuffled_rows_give_the_same_numbers(tmp_path, capsys):
    """The same map with its rows in another order: every node keeps its numbers (its random
    stream is keyed by its coordinates), so the summary is the same."""
    pts, B = _scattered(300)
    perm = np.random.default_rng(1).permutation(len(pts))
    summaries = []
    for name, order in (("a", np.arange(len(pts))), ("b", perm)):
        path = _csv(tmp_path / f"{name}.csv", pts[order], B[order])
        out = tmp_path / f"out_{name}"
        assert main(["sweep", str(path), "--trials", "200", "--up", "20", "--out", str(out)]) == 0
        summaries.append(json.loads((out / "summary.json").read_text())["uf_units"])
    capsys.readouterr()
    assert summaries[0] == summaries[1]


# --------------------------------------------------------------------------- not a regular file


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no FIFOs here")
@pytest.mark.parametrize("role", ["field", "bench"])
def test_a_fifo_is_refused_without_blocking(tmp_path, capsys, role):
    """A FIFO as the field map or the bench blocked forever (nothing writes to it)."""
    fifo = tmp_path / "pipe.csv"
    os.mkfifo(fifo)
    out = tmp_path / "out"
    if role == "field":
        argv = ["sweep", fifo, "--out", out]
    else:
        pts, B = _scattered(50)
        field = _csv(tmp_path / "m.csv", pts, B)
        argv = ["sweep", field, "--mode", "htm", "--bench", fifo, "--out", out]
    err = _refused(argv, capsys, out)
    assert f"{fifo}: this is a FIFO (named pipe)" in err, err


def test_a_device_is_refused(capsys, tmp_path):
    out = tmp_path / "out"
    err = _refused(["sweep", "/dev/zero", "--format", "table", "--out", out], capsys, out)
    assert "/dev/zero: this is a character device" in err, err


def test_hashing_a_fifo_is_a_bad_input(tmp_path):
    from cfm_fem.io.provenance import file_sha256

    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    with pytest.raises(CfmInputError, match="FIFO"):
        file_sha256(fifo)
