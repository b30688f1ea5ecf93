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
from cfm_fem.models.field import FieldMap
from cfm_fem.models.sweep import SweepConfig
from cfm_fem.workflows.sweep.in_memory import run_sweep

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


# --------------------------------------------------------------------------- cut last line


@pytest.mark.skipif(not OPERA.exists(), reason="real data folder absent")
@pytest.mark.parametrize("cut", [2, 3, 5, 9])
def test_a_file_cut_inside_its_last_number_is_refused(tmp_path, capsys, cut):
    """``head -c -2`` of the Opera table: the last Bz read -0.503 T instead of -5.03e-6 T and
    B_ref jumped from 0.0036 to 0.503 T, exit 0."""
    path = tmp_path / "c.table"
    path.write_bytes(OPERA.read_bytes()[:-cut])
    out = tmp_path / "out"
    err = _refused(["sweep", path, "--trials", 20, "--out", out], capsys, out)
    assert f"{path}:9479: column 'BZ': the last value" in err and "cut short" in err, err


@pytest.mark.skipif(not OPERA.exists(), reason="real data folder absent")
def test_a_complete_last_line_without_a_line_end_is_read(tmp_path):
    from cfm_fem.io import read_field

    path = tmp_path / "c.table"
    path.write_bytes(OPERA.read_bytes().rstrip(b"\r\n"))
    whole = read_field(OPERA)
    np.testing.assert_array_equal(read_field(path).B, whole.B)


@pytest.mark.parametrize(
    "last, what",
    [
        ("4,4,4,0.5,0.25,0.12", "shorter than every value above it"),
        ("4,4,4,0.512500,0.256250,10.12500", "fewer decimals than the 6"),
        ("4,4,4,5.125000e-01,2.562500e-01,1.250000e-0", "an exponent with fewer digits"),
    ],
)
def test_cut_csv_and_comsol_last_lines(tmp_path, last, what):
    from cfm_fem.io import read_field

    fixed = "e" in last
    rows = "".join(
        f"{x},{y},{z},{0.1 + x / 8:.6e},{0.2 + y / 16:.6e},{0.125:.6e}\n"
        if fixed
        else f"{x},{y},{z},{0.1 + x / 8:.6f},{0.2 + y / 16:.6f},{0.125 + z / 64:.6f}\n"
        for x in range(4) for y in range(4) for z in range(4)
    )  # fmt: skip
    for name, head in (
        ("m.csv", HEADER),
        ("m.txt", "% Length unit: mm\n% X Y Z Bx (T) By (T) Bz (T)\n"),
    ):
        text = head + rows + last
        if name.endswith(".txt"):
            text = text.replace(",", " ")
        path = tmp_path / name
        path.write_text(text, encoding="utf-8")
        with pytest.raises(CfmInputError, match="cut short") as exc:
            read_field(path)
        assert what in str(exc.value)
        path.write_text(text + "\n", encoding="utf-8")  # ended: a value like any other
        read_field(path)


# --------------------------------------------------------------------------- numbers


@pytest.mark.parametrize(
    "token, what", [("1_000", "digit separator '_'"), ("\u0661\u0662", "other than ASCII")]
)
@pytest.mark.parametrize("kind", ["map", "recording"])
def test_numbers_python_reads_but_files_do_not_hold(tmp_path, token, what, kind):
    from cfm_fem.io import read_field
    from cfm_fem.io.recordings import read_tracker

    path = tmp_path / "f.csv"
    if kind == "map":
        pts, B = _scattered(20)
        _csv(path, pts, B)
        text = path.read_text().replace("\n", f"\n{token},", 1)
        text = text.replace(f"\n{token},", "\n", 1).splitlines()
        text[2] = token + text[2][text[2].index(",") :]
        read = read_field
    else:
        text = ["point_id,rep,x_cmd,y_cmd,z_cmd,x_meas,y_meas,z_meas"]
        text += [f"{i},0,1,2,3,1,2,3" for i in range(5)]
        text[2] = f"1,0,{token},2,3,1,2,3"
        read = read_tracker
    path.write_text("\n".join(text) + "\n", encoding="utf-8")
    with pytest.raises(CfmInputError, match=what) as exc:
        read(path)
    assert f"{path}:3:" in str(exc.value)


def test_point_ids_above_2_53_are_read_exactly(tmp_path):
    from cfm_fem.io.recordings import read_tracker

    big = 2**53 + 1
    rows = [f"{big + i},0,1,2,3,1,2,3" for i in range(3)]
    path = tmp_path / "t.csv"
    path.write_text(
        "point_id,rep,x_cmd,y_cmd,z_cmd,x_meas,y_meas,z_meas\n" + "\n".join(rows) + "\n"
    )
    assert read_tracker(path).point_id.tolist() == [big, big + 1, big + 2]


@pytest.mark.parametrize(
    "value, what", [("1e308", "within +-1e+06 T"), ("1e300", "within +-1e+12 mm")]
)
def test_implausible_map_values_are_refused_before_anything_is_written(
    tmp_path, capsys, value, what
):
    """1e308 T overflowed after the maps were written (a JSON ValueError, exit 1, maps and
    chunk store left)."""
    pts, B = _scattered(60)
    path = _csv(tmp_path / "m.csv", pts, B)
    lines = path.read_text().splitlines()
    fields = lines[5].split(",")
    fields[5 if "T" in what else 0] = value
    lines[5] = ",".join(fields)
    path.write_text("\n".join(lines) + "\n")
    out = tmp_path / "out"
    err = _refused(["sweep", path, "--trials", 20, "--out", out], capsys, out)
    assert f"{path}:6: column" in err and what in err, err


@pytest.mark.parametrize(
    "column, value", [("z_meas", "1e308"), ("x_cmd", "1e300"), ("t_s", "1e300")]
)
def test_implausible_recording_values_are_refused(tmp_path, column, value):
    from cfm_fem.io.recordings import read_tracker

    names = ["point_id", "rep", "x_cmd", "y_cmd", "z_cmd", "x_meas", "y_meas", "z_meas", "t_s"]
    rows = [[str(i), "0", "1", "2", "3", "1", "2", "3", str(i)] for i in range(4)]
    rows[2][names.index(column)] = value
    path = tmp_path / "t.csv"
    path.write_text(",".join(names) + "\n" + "".join(",".join(r) + "\n" for r in rows))
    with pytest.raises(CfmInputError, match=f"column '{column}' must be within") as exc:
        read_tracker(path)
    assert exc.value.line == 4


@pytest.mark.filterwarnings("ignore::cfm_fem.errors.CfmInputWarning")  # Latin-1 text
def test_opera_counts_line_with_a_superscript_digit(tmp_path):
    """``int('2¹')`` raised ValueError (a traceback): '¹'.isdigit() is True."""
    from cfm_fem.io import read_opera

    path = tmp_path / "m.table"
    path.write_text("2 2 2\u00b9\n1 X [MM]\n0\n", encoding="latin-1")
    with pytest.raises(CfmInputError, match="point counts") as exc:
        read_opera(path)
    assert exc.value.line == 1


# --------------------------------------------------------------------------- what the file is


@pytest.mark.parametrize(
    "data, what",
    [
        (b"\x00" * 5000, "NUL bytes (zeros), not text"),
        (bytes(range(256)) * 20, "this is a binary file, not text"),
        (
            HEADER.encode() + b"0,0,0,1,1,1\n0,1,0,1,1\x851\n",
            ":3: the file is not UTF-8 text: byte 0x85 at column 10",
        ),
    ],
)
def test_binary_and_damaged_files_are_named(tmp_path, capsys, data, what):
    path = tmp_path / "m.csv"
    path.write_bytes(data)
    out = tmp_path / "out"
    err = _refused(["sweep", path, "--out", out], capsys, out)
    assert what in err and "UTF-16" not in err, err


def test_latin1_text_is_read_with_a_warning_naming_the_byte(tmp_path):
    from cfm_fem.errors import CfmInputWarning
    from cfm_fem.io import read_field

    pts, B = _scattered(30)
    path = _csv(tmp_path / "m.csv", pts, B)
    path.write_bytes(b"# magnet \xe9t\xe9\n" + path.read_bytes())
    with pytest.warns(CfmInputWarning, match=r"m.csv:1: not UTF-8 \(byte 0xe9 at column 10\)"):
        fm = read_field(path)
    assert fm.n_nodes == 30


def test_control_characters_from_files_are_escaped(tmp_path, capsys):
    path = tmp_path / "m\x1b[2J.csv"
    path.write_text("x [mm],y [mm],z [mm],Bx [T],By [T],B\x1b[31mz\x07 [T]\n0,0,0,1,1,1\n")
    out = tmp_path / "out"
    err = _refused(["sweep", path, "--out", out], capsys, out)
    assert "\x1b" not in err and "\x07" not in err
    assert "m\\x1b[2J.csv" in err and "B\\x1b[31mz\\x07 [T]" in err, err


# --------------------------------------------------------------------------- bench and diagnose


def _bench_text():
    from importlib import resources

    return resources.files("cfm_fem.data").joinpath("cfm_reference_bench.toml").read_text()


@pytest.mark.parametrize(
    "edit, what",
    [
        (
            ("mount_offset_mm = [0.0, 0.0, 0.0]", "mount_offset_mm = [1e300, 0.0, 0.0]"),
            "must be within +-100000 mm",
        ),
        (
            ("rotation_deg = [0.0, 0.0, 0.0]", "rotation_deg = [0.0, 1e300, 0.0]"),
            "within +-360 deg",
        ),
        (("version = 1", "version = " + "7" * 5000), "a value the bench cannot hold"),
        (("version = 1", "version = 1\nname = " + "[" * 3000 + "]" * 3000), "nested too deep"),
    ],
)
def test_implausible_bench_files_are_refused(tmp_path, capsys, edit, what):
    """A mount offset of 1e300 mm or a rotation of 1e300 deg was accepted; 3,000 nested
    arrays gave a RecursionError and a 5,000-digit integer a ValueError (tracebacks)."""
    text = _bench_text()
    assert edit[0] in text
    bench = tmp_path / "b.toml"
    bench.write_text(text.replace(edit[0], edit[1], 1))
    out = tmp_path / "out"
    err = _refused(["kinematics", "--bench", bench, "--trials", 20, "--out", out], capsys, out)
    assert f"{bench}" in err and what in err, err


@pytest.fixture(scope="module")
def tracker_rows():
    from cfm_fem.workflows.diagnose.twin import tracker_twin

    q = np.stack(np.meshgrid(np.linspace(0, 150, 3), np.linspace(0, 150, 3),
                             np.linspace(0, 800, 4), indexing="ij"), -1).reshape(-1, 3)  # fmt: skip
    rec, _ = tracker_twin(3, {}, n_reps=3, points=q)
    return rec


@pytest.mark.parametrize(
    "column, value, what",
    [
        ("x_cmd", 1e4, "outside the strokes"),
        ("x_cmd", 1e300, "must be within +-1e+06 mm"),
        ("z_meas", 1e308, "must be within +-1e+06 mm"),
    ],
)
def test_diagnose_refuses_what_compare_refuses(tmp_path, capsys, tracker_rows, column, value, what):
    """Commanded positions outside the strokes gave an RMS of 5.8e11 um in diagnose (compare
    refused them); z_meas = 1e308 an OverflowError, x_cmd = 1e300 'SVD did not converge'."""
    from cfm_fem.io.recordings import write_tracker

    path = tmp_path / "t.csv"
    write_tracker(path, tracker_rows)  # the writer refuses such values: edit the text
    lines = path.read_text().splitlines()
    row = lines[5].split(",")
    row[lines[0].split(",").index(column)] = repr(value)
    lines[5] = ",".join(row)
    path.write_text("\n".join(lines) + "\n")
    out = tmp_path / "out"
    err = _refused(["diagnose", "--tracker", path, "--out", out], capsys, out)
    assert f"{path}:6:" in err and what in err, err


# --------------------------------------------------------------------------- symbolic links


def test_a_symlinked_lock_is_not_followed(tmp_path, capsys):
    """With ``DIR/.cfm_fem.lock`` a link to a file the user owns, a run truncated that file."""
    from cfm_fem.io.lock import LOCK_NAME

    victim = tmp_path / "victim.txt"
    victim.write_text("precious\n")
    out = tmp_path / "out"
    out.mkdir()
    (out / LOCK_NAME).symlink_to(victim)
    err = _refused(["kinematics", "--trials", 20, "--out", out], capsys)
    assert "is a symbolic link; not followed" in err, err
    assert victim.read_text() == "precious\n"
    assert sorted(p.name for p in out.iterdir()) == [LOCK_NAME]


def test_a_symlinked_chunk_store_is_refused(tmp_path):
    from cfm_fem.io.chunk_store import STORE_NAME, ChunkStore

    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (tmp_path / STORE_NAME).symlink_to(elsewhere)
    with pytest.raises(CfmInputError, match="is a symbolic link"):
        ChunkStore(tmp_path)


# --------------------------------------------------------------------------- numba's cache


def test_numba_cache_falls_back_to_a_private_temporary_folder(tmp_path, monkeypatch):
    """A user who can write neither the package folder nor HOME: every run died with "cannot
    cache function 'mix64': no locator available"."""
    from cfm_fem import _numba_cache

    monkeypatch.setattr(_numba_cache, "NOTE", None)
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    env = {"HOME": str(blocker / "home")}  # nothing can be made under a file
    note = _numba_cache.configure(package_dir=blocker / "pkg", env=env, temp_dir=tmp_path)
    folder = tmp_path / f"cfm_fem-numba-{os.getuid()}"
    assert env["NUMBA_CACHE_DIR"] == str(folder) and folder.is_dir()
    assert str(folder) in note and (folder.stat().st_mode & 0o077) == 0
    # a folder of that name that is not this user's own (here: a link) is not used
    env = {"HOME": str(blocker / "home")}
    folder.rmdir()
    folder.symlink_to(tmp_path)
    monkeypatch.setattr(_numba_cache, "CACHE", True)
    note = _numba_cache.configure(package_dir=blocker / "pkg", env=env, temp_dir=tmp_path)
    assert "NUMBA_CACHE_DIR" not in env and "compiled on each run" in note
    assert _numba_cache.CACHE is False


def test_numba_cache_is_left_alone_where_numba_can_write(tmp_path):
    from cfm_fem import _numba_cache

    env = {"HOME": str(tmp_path)}
    assert _numba_cache.configure(package_dir=tmp_path / "pkg", env=env) is None
    assert "NUMBA_CACHE_DIR" not in env


# --------------------------------------------------------------------------- a full disk


def _no_space(*args, **kwargs):
    raise OSError(28, "No space left on device", "/somewhere/chunk.npz")


@pytest.mark.parametrize("where", ["chunk", "vtu"])
def test_a_full_disk_removes_the_run_and_says_so(tmp_path, capsys, monkeypatch, where):
    """A full disk while saving a chunk gave a chained OSError traceback; VTK's writer
    aborted the process (exit 134) or crashed (139)."""
    import shutil

    from cfm_fem.io import _atomic
    from cfm_fem.io.chunk_store import ChunkStore

    pts, B = _scattered(80)
    field = _csv(tmp_path / "m.csv", pts, B)
    if where == "chunk":
        monkeypatch.setattr(ChunkStore, "save", _no_space)
        what = "the disk is full (No space left on device)"
    else:  # the .vtu does not fit: refused before VTK or Python writes a byte of it
        usage = shutil.disk_usage(tmp_path)
        monkeypatch.setattr(_atomic.shutil, "disk_usage", lambda p: usage._replace(free=4096))
        what = "uf_up10um.vtu needs"
    out = tmp_path / "out"
    err = _refused(["sweep", field, "--trials", 20, "--up", 10, "--out", out], capsys, out)
    assert what in err and "were removed" in err and "now free" in err, err


def _tmpfs(path, size):
    import subprocess

    path.mkdir()
    if os.geteuid() != 0:
        pytest.skip("mounting a tmpfs needs root")
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(path)],
                          capture_output=True)  # fmt: skip
    if done.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {done.stderr.decode().strip()}")


def test_a_full_tmpfs(tmp_path):
    """The sweep on a 2 MB file system: exit 2 with the message, the output folder removed."""
    import subprocess
    import sys

    small = tmp_path / "small"
    _tmpfs(small, "2m")
    try:
        out = small / "out"
        env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[1]))
        run = subprocess.run(
            [sys.executable, "-m", "cfm_fem", "sweep", str(Path(__file__).resolve().parents[1] /
             "meshes" / "quadrupole.vtu"), "--trials", "20", "--up", "10", "--out", str(out)],
            capture_output=True, text=True, env=env, timeout=600,
        )  # fmt: skip
        assert run.returncode == 2, run.stderr
        assert "the disk is full" in run.stderr and "Traceback" not in run.stderr, run.stderr
        assert not out.exists() and os.listdir(small) == []
    finally:
        subprocess.run(["umount", str(small)], check=False)


def test_a_native_mesh_with_an_outlier_node_is_searched_quickly(tmp_path):
    """One node of a native tetrahedral mesh moved to x = 1e9 mm: the bucket grid of the exact
    search spanned 1e9 mm and held every other cell in one bucket (minutes of searching).
    The grid now covers the cells' centres; the far cells sit in its border buckets, and the
    search finds every point the cells hold, beyond the grid too."""
    from cfm_fem import _kernels
    from cfm_fem.models.mesh import barycentric_transforms, cell_buckets, kuhn_simplices

    g = np.stack(np.meshgrid(*[np.arange(12.0)] * 3, indexing="ij"), -1).reshape(-1, 3)
    simplices = kuhn_simplices((12, 12, 12), np.arange(len(g)))
    coords = g.copy()
    coords[0] = [1e9, 0.0, 0.0]  # cells of node 0 now reach to 1e9 mm
    boxes = _kernels.cell_boxes(coords, simplices)
    box, dims, bstart, bcells = cell_buckets(coords, simplices, boxes=boxes)
    assert box[0, 0] + dims[0] / box[1, 0] < 100.0  # the grid ends near the other cells
    assert np.diff(bstart).max() < 2000  # of 7,986 cells: not all in one bucket
    T, _ = barycentric_transforms(coords, simplices)
    rng = np.random.default_rng(3)
    far = simplices[(simplices == 0).any(axis=1)][:5]
    points = [coords[c].mean(axis=0) for c in far] + list(rng.uniform(1, 10, (50, 3)))
    bary = np.empty(4)
    for p in points:
        c = _kernels.find_cell(np.asarray(p), T, box, dims, bstart, bcells, bary)
        assert c >= 0 and (bary > -1e-9).all(), p


BODY = DATA / "emphatic" / "EMPHATIC_body_scan_5280148.csv"


@pytest.mark.skipif(not BODY.exists(), reason="real data folder absent")
def test_a_far_node_of_a_small_scan_does_not_hang(tmp_path, capsys):
    """Found by scripts/fuzz_inputs.py: x of one row of 299 read as -5,905,512 in (the
    decimal point lost): the bucket grid could not get coarser (m / per_bucket < 1) and
    `cell_buckets` looped for ever. It now falls back to one bucket."""
    import signal

    lines = BODY.read_bytes().splitlines(keepends=True)[:300]
    lines[102] = lines[102].replace(b"-0.5905512,", b"-005905512,", 1)
    path = tmp_path / "scan.csv"
    path.write_bytes(b"".join(lines))
    out = tmp_path / "out"
    signal.signal(signal.SIGALRM, lambda *a: pytest.fail("no answer in 120 s"))
    signal.alarm(120)
    try:
        argv = ["sweep", str(path), "--length-unit", "in", "--trials", "20", "--up", "10"]
        rc = main([*argv, "--out", str(out)])
    finally:
        signal.alarm(0)
    assert rc == 0, capsys.readouterr().err
