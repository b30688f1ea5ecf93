"""`cfm-fem sweep` as a user runs it: outputs, contract keys, exit codes, nothing half-written."""

import json
import xml.etree.ElementTree as ET

import meshio
import numpy as np
import pytest
import pyvista as pv

from cfm_fem.cli import main
from cfm_fem.io.vtk import read_text_field

G = np.array([[0.2, 0.0, 0.0], [0.0, -0.2, 0.0], [0.0, 0.0, 0.1]])


@pytest.fixture
def csv_map(grid_csv):
    return grid_csv(6, lambda pts: pts @ G.T + [0.0, 0.0, 1.0])


def test_sweep_writes_pvd_vtu_and_summary(csv_map, tmp_path, capsys):
    out = tmp_path / "res"
    rc = main(
        [
            "sweep",
            str(csv_map),
            "--up",
            "0:20:10",
            "--trials",
            "400",
            "--seed",
            "3",
            "--out",
            str(out),
        ]
    )
    assert rc == 0
    s = json.loads((out / "summary.json").read_text())
    for key in ("b_ref_T", "trials", "seed", "up_um", "uf_units", "outside_fraction", "seconds"):
        assert key in s
    assert s["up_um"] == [0, 10, 20] and s["trials"] == 400 and s["seed"] == 3
    assert set(s["uf_units"]) == {"p50", "p95", "p99", "max"}
    assert s["provenance"]["inputs"]["field"]["sha256"]
    # B_ref defaults to max |B|; U_f of a node ~ 1.96 U_p |grad |B|| / B_ref (|B| ~ Bz here)
    absb = np.linalg.norm(
        np.stack(np.meshgrid(*[np.arange(6.0)] * 3, indexing="ij"), -1).reshape(-1, 3) @ G.T
        + [0, 0, 1],
        axis=1,
    )
    assert s["b_ref_T"] == pytest.approx(absb.max())
    timesteps = [
        float(d.get("timestep")) for d in ET.parse(out / "sweep.pvd").getroot().iter("DataSet")
    ]
    assert timesteps == [0.0, 10.0, 20.0]
    m = pv.read(out / "uf_up20um.vtu")
    assert m.n_points == 216 and set(m.celltypes) == {pv.CellType.TETRA}
    uf = m.point_data["U_f_units"]
    complete = m.point_data["complete"] == 1
    np.testing.assert_allclose(np.nanmax(uf), s["uf_units"]["max"][2])
    # a node that lost trials has no U_f: NaN, its half-space figure kept under its own name
    assert np.isnan(uf[~complete]).all() and np.isfinite(uf[complete]).all()
    inside = m.point_data["absB_U95_inside_trials_units"]
    assert np.isfinite(inside[~complete]).all() and np.isnan(inside[complete]).all()
    assert np.isnan(m.point_data["Bx_u_units"][~complete]).all()
    assert "absB_U95_units" not in m.point_data and "Bx_Uk2_T" not in m.point_data
    assert read_text_field(m.field_data, "column") == "up20um" and m.field_data["U_p_um"][0] == 20
    assert json.loads(read_text_field(m.field_data, "provenance")) == s["provenance"]
    assert "Bz_gum_disagree" in m.point_data and "grad_B_T_per_mm" in m.point_data
    printed = capsys.readouterr().out
    assert "U_f p50" in printed and "Kuhn" in printed


def test_outside_extrapolate_gives_surface_nodes_a_figure_and_says_so(csv_map, tmp_path, capsys):
    base = ["sweep", str(csv_map), "--up", "0,30", "--trials", "1000", "--seed", "1"]
    assert main([*base, "--outside", "extrapolate", "--out", str(tmp_path / "x")]) == 0
    s = json.loads((tmp_path / "x" / "summary.json").read_text())
    assert s["outside"] == "extrapolate" and s["uf_nodes"] == [216, 216]
    assert s["outside_fraction"][1] > 0.1  # the 152 surface nodes of 216 lost trials
    m = pv.read(tmp_path / "x" / "uf_up30um.vtu")
    assert (m.point_data["complete"] == 1).all()
    # a linear map: U_f / (linear GUM figure) at the surface as inside, within the Monte Carlo
    # tolerance of the two means (both carry the upward bias of max(|low|, |high|), ~+5 %);
    # the default's half-space samples of surface nodes are ~12 % high, beyond it
    ratio = m.point_data["U_f_units"] / m.point_data["absB_gum_U95_units"]
    surface = m.point_data["outside_fraction"] > 0
    assert surface.sum() == 152  # 216 - 4 ** 3
    tol = 4 * s["uf_relative_mc_std"] * np.sqrt(1 / 152 + 1 / 64)
    assert abs(ratio[surface].mean() - ratio[~surface].mean()) < tol
    assert "Taylor expansion" in capsys.readouterr().out
    # out of core: the same figures
    assert (
        main([*base, "--outside", "extrapolate", "--slabs", "2", "--out", str(tmp_path / "s")]) == 0
    )
    sl = json.loads((tmp_path / "s" / "summary.json").read_text())
    assert sl["uf_nodes"] == [216, 216] and sl["outside"] == "extrapolate"
    np.testing.assert_allclose(sl["uf_units"]["p95"], s["uf_units"]["p95"], rtol=1e-9)


def test_help_exits_zero(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["sweep", "--help"])
    assert exc.value.code == 0
    assert "--up" in capsys.readouterr().out


def _bad(tmp_path, name, text):
    p = tmp_path / name
    p.write_text(text)
    return p


HEADER = "x [mm],y [mm],z [mm],Bx [T],By [T],Bz [T]\n"
GOOD_ROWS = "".join(f"{i % 2},{i // 2 % 2},{i // 4},0,0,1\n" for i in range(8))


@pytest.mark.parametrize(
    "name, text, message",
    [
        ("empty.csv", "", "empty"),
        ("header_only.csv", HEADER, "no data"),
        ("missing.csv", "x [mm],y [mm],z [mm],Bx [T],By [T]\n0,0,0,1,1\n", "Bz"),
        ("text.csv", HEADER + GOOD_ROWS + "1,1,2,abc,0,1\n", "abc"),
        ("nan.csv", HEADER + GOOD_ROWS + "1,1,2,nan,0,1\n", "finite"),
        ("unit.csv", "x [furlong],y [mm],z [mm],Bx [T],By [T],Bz [T]\n" + GOOD_ROWS, "furlong"),
        ("truncated.csv", HEADER + GOOD_ROWS + "1,1,2,0\n", "truncated.csv:10:"),
        ("dup.csv", HEADER + GOOD_ROWS + "0,0,0,0,0,2\n", "duplicate"),
        ("coplanar.csv", HEADER + "".join(f"{i},{2 * i},0,0,0,1\n" for i in range(6)), "collinear"),
    ],
)
def test_bad_input_exit_2_and_nothing_written(tmp_path, capsys, name, text, message):
    out = tmp_path / "out"
    rc = main(["sweep", str(_bad(tmp_path, name, text)), "--trials", "50", "--out", str(out)])
    err = capsys.readouterr().err
    assert rc == 2
    assert message in err and name in err
    assert "Traceback" not in err
    assert not out.exists()


def test_bad_arguments_exit_2(csv_map, tmp_path, capsys):
    for args in (
        ["--up", "0:10"],
        ["--trials", "3"],
        ["--up", "0:900000:300000"],
        ["--axis-scale", "1,2"],
    ):
        out = tmp_path / "o"
        assert main(["sweep", str(csv_map), "--out", str(out), *args]) == 2
        assert not out.exists()
    assert main(["sweep", str(tmp_path / "nope.vtu"), "--out", str(tmp_path / "o")]) == 2
    assert main(["nonsense"]) == 2
    assert "error" in capsys.readouterr().err


@pytest.mark.parametrize(
    "argv, message",
    [
        (
            ["tolerance", "--target", "5,5"],
            "--target: must be 1 or 3 comma-separated finite numbers in um",
        ),
        (
            ["sweep", "map.csv", "--axis-scale", "1,2", "--out", "o"],
            "--axis-scale: must be 1 or 3 comma-separated",
        ),
        # C9: a bench in mode gauss was ignored without a word
        (["sweep", "map.csv", "--bench", "b.toml", "--out", "o"], "--bench is used by --mode htm"),
    ],
)
def test_option_errors_give_their_own_message(capsys, argv, message):
    # argparse replaces a ValueError from type= by "invalid _target value"
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert message in err and "invalid" not in err, err


def test_top_level_help_lists_every_command(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["--help"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    assert "sweep" in out and "U_f maps (95 %)" in out


def test_help_does_not_import_the_numerics():
    """``--help`` and option errors build the parser only: numba, scipy and pyvista are imported
    by the command that runs (fresh interpreter: this one has imported them already)."""
    import subprocess
    import sys

    code = (
        "import sys; from cfm_fem.cli import build_parser; build_parser(); "
        "print(' '.join(m for m in ('numba', 'scipy', 'pyvista', 'meshio', 'dask') "
        "if m in sys.modules))"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert done.stdout.strip() == ""


def test_ctrl_c_inside_numba_is_a_clean_interrupt_for_every_command(monkeypatch, capsys):
    import cfm_fem.cli.kinematics as kin

    def wrapped_ctrl_c(args):
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt as exc:  # numba re-raises a Ctrl-C as a SystemError
            raise SystemError("<numba> returned a result with an exception set") from exc

    monkeypatch.setattr(kin, "run", wrapped_ctrl_c)
    assert main(["kinematics", "--out", "unused"]) == 1
    assert "interrupted" in capsys.readouterr().err

    def real_system_error(args):
        raise SystemError("not an interrupt")

    monkeypatch.setattr(kin, "run", real_system_error)
    with pytest.raises(SystemError, match="not an interrupt"):
        main(["kinematics", "--out", "unused"])


@pytest.mark.slow
def test_hull_slivers_option(tmp_path):
    """The hull's flat cells are removed by default and the summary's notes say so (with
    --slabs: tests/test_slabs.py); --hull-slivers keep keeps them and counts them in a note."""
    pts = np.random.default_rng(4).uniform(0, 6, (400, 3))
    path = tmp_path / "s.csv"
    rows = "\n".join(",".join(f"{v:.17g}" for v in r) for r in np.c_[pts, pts @ G.T + [0, 0, 1]])
    path.write_text("x [mm],y [mm],z [mm],Bx [T],By [T],Bz [T]\n" + rows + "\n")
    base = ["sweep", str(path), "--up", "0,20", "--trials", "100"]
    assert main([*base, "--out", str(tmp_path / "a")]) == 0
    notes = json.loads((tmp_path / "a" / "summary.json").read_text())["notes"]
    assert any("flat cell(s) on the Delaunay hull removed" in n for n in notes)
    assert not any("flat cell(s) line the Delaunay hull" in n for n in notes)
    assert main([*base, "--out", str(tmp_path / "b"), "--hull-slivers", "keep"]) == 0
    notes = json.loads((tmp_path / "b" / "summary.json").read_text())["notes"]
    assert not any("Delaunay hull removed" in n for n in notes)
    assert any("flat cell(s) line the Delaunay hull" in n for n in notes)


def test_slabs_say_the_thousands_separator_ambiguity_once(tmp_path, capsys, monkeypatch):
    """--slabs streams the file in blocks; the "1,250 read with ',' as thousands separator"
    warning was printed once per block. Once per file now."""
    import cfm_fem.io.slab_files

    monkeypatch.setattr(cfm_fem.io.slab_files, "BLOCK", 50)  # 216 rows: 5 blocks
    ax = np.arange(6.0)
    pts = np.stack(np.meshgrid(ax + 1000.0, ax, ax, indexing="ij"), -1).reshape(-1, 3)
    B = (pts - [1000.0, 0.0, 0.0]) @ G.T + [0.0, 0.0, 1.0]
    rows = "".join(
        f'"1,{p[0] - 1000:03.0f}",{p[1]:g},{p[2]:g},' + ",".join(f"{v:.17g}" for v in b) + "\n"
        for p, b in zip(pts, B, strict=True)
    )
    path = tmp_path / "thousands.csv"
    path.write_text("x [mm],y [mm],z [mm],Bx [T],By [T],Bz [T]\n" + rows)
    argv = ["sweep", str(path), "--up", "10", "--trials", "50", "--slabs", "2"]
    assert main([*argv, "--out", str(tmp_path / "o")]) == 0
    err = capsys.readouterr().err
    assert err.count("read with ',' as thousands separator") == 1, err
    s = json.loads((tmp_path / "o" / "summary.json").read_text())
    assert s["nodes"] == 216


def test_slabs_read_a_planar_map_once(tmp_path, capsys, monkeypatch):
    """--slabs on a planar map (left to the in-memory run) staged the file, then read it again
    whole: every warning of the file (thousands separators, placeholder rows) was printed
    twice. The in-memory run now takes the staged rows; its numbers are those of --pieces."""
    import cfm_fem.io

    ax = np.arange(7.0)
    pts = np.stack(np.meshgrid(ax + 1000.0, ax, [0.0], indexing="ij"), -1).reshape(-1, 3)
    B = (pts - [1000.0, 0.0, 0.0]) @ G.T + [0.0, 0.0, 1.0]
    B[5] = 0.0  # a placeholder row, kept with a warning
    rows = "".join(
        f'"1,{p[0] - 1000:03.0f}",{p[1]:g},{p[2]:g},' + ",".join(f"{v:.17g}" for v in b) + "\n"
        for p, b in zip(pts, B, strict=True)
    )
    path = tmp_path / "planar.csv"
    path.write_text("x [mm],y [mm],z [mm],Bx [T],By [T],Bz [T]\n" + rows)
    argv = ["sweep", str(path), "--up", "0,10", "--trials", "60"]
    assert main([*argv, "--pieces", "2", "--out", str(tmp_path / "mem")]) == 0
    err = capsys.readouterr().err
    assert err.count("read with ',' as thousands separator") == 1, err
    assert err.count("exactly 0 0 0") == 1, err
    reads = []
    read_field = cfm_fem.io.read_field
    monkeypatch.setattr(
        cfm_fem.io, "read_field", lambda *a, **k: reads.append(a) or read_field(*a, **k)
    )
    assert main([*argv, "--slabs", "2", "--out", str(tmp_path / "sl")]) == 0
    err = capsys.readouterr().err
    assert "the map is not 3-D: run in memory" in err
    assert err.count("read with ',' as thousands separator") == 1, err
    assert err.count("exactly 0 0 0") == 1, err
    assert reads == []
    mem, sl = (json.loads((tmp_path / d / "summary.json").read_text()) for d in ("mem", "sl"))
    assert sl["nodes"] == 49 and "slabs" not in sl
    for key in set(mem) - {"seconds", "provenance"}:
        assert mem[key] == sl[key], key


@pytest.mark.parametrize("extra", [[], ["--slabs", "2"]], ids=["in_memory", "slabs"])
def test_rerun_removes_the_temporaries_a_killed_run_left(csv_map, tmp_path, capsys, extra):
    """A run killed while writing leaves hidden temporaries (`cfm_fem.io._atomic.atomic_path`)
    in --out; the next run removes those of its outputs, says how many in one line, and
    leaves every other file, and those modified within the hour (another run's, in flight)."""
    import os
    import time

    out = tmp_path / "res"
    argv = ["sweep", str(csv_map), "--up", "0,10", "--trials", "60", *extra, "--out", str(out)]
    assert main(argv) == 0
    pieces = "uf_up10um/" if extra else ""
    ours = [".uf_up10um.vtu.k3x_9abq.vtu", ".summary.json.0a1b2c3d.json", ".sweep.pvd.zz_zz_zz.pvd",
            ".uf_up50um.pvtu.abcdefgh.pvtu"]  # fmt: skip
    if extra:
        ours.append(f"{pieces}.piece_0001.vtu.q1w2e3r4.vtu")
    others = [
        "uf_up10um.vtu.k3x_9abq.vtu",  # not hidden
        ".uf_up10um.vtu.k3x9abq.vtu",  # 7 random characters
        ".uf_up10um.vtu.k3x_9abq.pvd",  # suffix of another file
        ".map.csv.k3x_9abq.csv",  # not a sweep output
        ".points.csv.k3x_9abq.csv",
        ".uf_up10um.vtu.k3x_9abq.vtu.bak",
    ]
    if extra:
        others.append(f"{pieces}.notes.txt.k3x_9abq.txt")
    for name in ours + others:
        (out / name).write_bytes(b"<VTKFile")
    hours_ago = time.time() - 7200.0
    for name in ours:  # a killed run's: written two hours ago
        os.utime(out / name, (hours_ago, hours_ago))
    # named like ours but modified a minute ago: another run may be writing it right now
    others.append(".uf_up10um.vtu.in_fl1gt.vtu")
    (out / others[-1]).write_bytes(b"<VTKFile")
    os.utime(out / others[-1], (time.time() - 60.0,) * 2)
    (out / ".uf_up20um.vtu.linkto12.vtu").symlink_to(out / "summary.json")
    (out / ".uf_up30um.vtu.folder12.vtu").mkdir()
    capsys.readouterr()
    assert main(argv) == 0
    err = capsys.readouterr().err
    told = [line for line in err.splitlines() if "leftover temporary" in line]
    assert len(told) == 1, err
    assert f"removed {len(ours)} leftover temporary file(s)" in told[0]
    assert not [n for n in ours if os.path.lexists(out / n)]
    for name in others + [".uf_up20um.vtu.linkto12.vtu", ".uf_up30um.vtu.folder12.vtu"]:
        assert os.path.lexists(out / name), name
    assert (out / "summary.json").is_file()
    assert main(argv) == 0  # nothing left to remove: nothing said
    assert "leftover temporary" not in capsys.readouterr().err


class _Bars:
    """Stands in for `cfm_fem.cli._progress.progress_bar`: records each bar's total and updates."""

    def __init__(self):
        self.bars = []

    def __call__(self, total, unit):
        import contextlib

        bar = {"total": total, "unit": unit, "done": 0, "updates": []}
        self.bars.append(bar)

        class _Bar:
            def update(self, n=1):
                bar["done"] += n
                bar["updates"].append(n)

            @property
            def total(self):
                return bar["total"]

            @total.setter
            def total(self, n):  # as tqdm: a total set once it is known
                bar["total"] = n

            def refresh(self):
                pass

            def write(self, text, file=None):
                print(text, file=file)

        return contextlib.nullcontext(_Bar())


@pytest.mark.parametrize("option", [["--slabs", "2"], ["--max-memory", "1G"]])
def test_slab_runs_show_progress_over_the_nodes(csv_map, tmp_path, monkeypatch, option):
    """--slabs/--max-memory show progress: the bar counts the nodes as the slabs finish,
    against the total the slab run sets once the file is staged."""
    import cfm_fem.cli.sweep

    bars = _Bars()
    monkeypatch.setattr(cfm_fem.cli.sweep, "progress_bar", bars)
    argv = ["sweep", str(csv_map), "--up", "10", "--trials", "50", *option]
    assert main([*argv, "--out", str(tmp_path / "o")]) == 0
    assert [b["unit"] for b in bars.bars] == ["nodes"]
    assert bars.bars[0]["done"] == bars.bars[0]["total"] == 216


def test_slab_progress_advances_within_a_slab_and_changes_no_number(csv_map, tmp_path,
                                                                    monkeypatch):  # fmt: skip
    """The bar of a --slabs run advanced once per finished slab; it now advances by blocks of
    --chunk-nodes nodes within a slab. The maps are those of one call per slab, bit for bit."""
    import cfm_fem.cli.sweep

    bars = _Bars()
    monkeypatch.setattr(cfm_fem.cli.sweep, "progress_bar", bars)
    argv = ["sweep", str(csv_map), "--up", "0,10,30", "--trials", "80", "--slabs", "2"]
    assert main([*argv, "--out", str(tmp_path / "one")]) == 0
    assert main([*argv, "--chunk-nodes", "25", "--out", str(tmp_path / "blocks")]) == 0
    one, blocks = (b for b in bars.bars)
    assert one["done"] == blocks["done"] == blocks["total"] == 216
    assert len(one["updates"]) == 2  # one per slab: each slab is a single block
    assert len(blocks["updates"]) >= 8 and max(blocks["updates"]) == 25
    a, b = (json.loads((tmp_path / d / "summary.json").read_text()) for d in ("one", "blocks"))
    assert a["uf_units"] == b["uf_units"] and a["outside_fraction"] == b["outside_fraction"]
    pieces = sorted(p.relative_to(tmp_path / "one") for p in (tmp_path / "one").glob("*/*.vtu"))
    assert len(pieces) == 6
    for rel in pieces:
        ma, mb = pv.read(tmp_path / "one" / rel), pv.read(tmp_path / "blocks" / rel)
        np.testing.assert_array_equal(ma.points, mb.points)
        assert set(ma.point_data) == set(mb.point_data)
        for name in ma.point_data:
            np.testing.assert_array_equal(ma.point_data[name], mb.point_data[name], err_msg=name)


def _maps_named(out):
    """The files sweep.pvd names, with the pieces of its .pvtu indices (relative, posix)."""
    names = set()
    for ds in ET.parse(out / "sweep.pvd").getroot().iter("DataSet"):
        names.add(ds.get("file"))
        if ds.get("file").endswith(".pvtu"):
            for piece in ET.parse(out / ds.get("file")).getroot().iter("Piece"):
                names.add(piece.get("Source"))
    return names


def _maps_present(out):
    return {
        p.relative_to(out).as_posix()
        for p in out.rglob("*")
        if p.is_file() and p.suffix in (".vtu", ".pvtu") and p.name.startswith(("uf_", "piece_"))
    }


def test_rerun_into_the_same_out_removes_the_earlier_runs_stale_maps_only(
    csv_map, tmp_path, capsys
):
    """A re-run with fewer U_p values (or with pieces instead of one file, or fewer pieces)
    into the same --out left the earlier maps beside the new sweep.pvd: ParaView users opened
    stale figures. Once the new outputs are written, the maps a sweep wrote that the new
    sweep.pvd does not name are removed (and named on stderr); other files are left."""
    out = tmp_path / "res"
    base = ["sweep", str(csv_map), "--trials", "50", "--out", str(out)]
    assert main([*base, "--up", "0:20:10"]) == 0
    assert _maps_present(out) == {"uf_up0um.vtu", "uf_up10um.vtu", "uf_up20um.vtu"}
    # the user's own files, some named like maps, are never deleted
    (out / "notes.txt").write_text("mine\n")
    (out / "uf_custom.vtu").write_text("<VTKFile>my own map</VTKFile>\n")
    (out / "uf_mine").mkdir()
    (out / "uf_mine" / "piece_0000.vtu").write_text("not a sweep's\n")
    capsys.readouterr()

    assert main([*base, "--up", "10"]) == 0  # fewer U_p values
    err = capsys.readouterr().err
    assert "removed 2 map file(s) of an earlier run" in err
    assert "uf_up0um.vtu" in err and "uf_up20um.vtu" in err
    assert "left in" in err and "uf_custom.vtu" in err
    assert _maps_present(out) - {"uf_custom.vtu", "uf_mine/piece_0000.vtu"} == {"uf_up10um.vtu"}
    assert (out / "notes.txt").exists() and (out / "uf_custom.vtu").exists()
    assert (out / "uf_mine" / "piece_0000.vtu").exists()

    assert main([*base, "--up", "10", "--pieces", "3"]) == 0  # pieces instead of one file
    assert "uf_up10um.vtu" in capsys.readouterr().err
    assert not (out / "uf_up10um.vtu").exists()
    assert main([*base, "--up", "10", "--slabs", "2"]) == 0  # fewer pieces (out of core)
    assert "uf_up10um/ (1 piece(s))" in capsys.readouterr().err
    mine = {"uf_custom.vtu", "uf_mine/piece_0000.vtu"}
    assert (
        _maps_present(out) - mine
        == _maps_named(out)
        == {
            "uf_up10um.pvtu",
            "uf_up10um/piece_0000.vtu",
            "uf_up10um/piece_0001.vtu",
        }
    )
    assert main([*base, "--up", "10,20"]) == 0  # back to one file per U_p value
    assert "uf_up10um/ (2 piece(s), folder removed)" in capsys.readouterr().err
    assert _maps_present(out) - mine == _maps_named(out) == {"uf_up10um.vtu", "uf_up20um.vtu"}
    assert not (out / "uf_up10um").exists() and (out / "notes.txt").exists()
    s = json.loads((out / "summary.json").read_text())
    assert s["up_um"] == [10, 20]
    # a run that fails writes nothing and removes nothing
    assert main([*base, "--up", "5e5"]) == 2
    assert _maps_present(out) - mine == {"uf_up10um.vtu", "uf_up20um.vtu"}


def test_python_writers_remove_the_earlier_runs_stale_maps_once_complete(
    csv_map, tmp_path, monkeypatch
):
    """`write_sweep`, `write_sweep_pieces` and `run_slab_sweep` into a folder holding an earlier
    sweep left its maps that the new sweep.pvd does not name (only the CLI removed them). They
    now remove them as the CLI does, after the new outputs are complete, never before; the
    user's files stay, and ``remove_stale=False`` leaves everything."""
    import cfm_fem.io.sweep_out as so
    from cfm_fem.io import read_field
    from cfm_fem.models.sweep import SweepConfig
    from cfm_fem.workflows.sweep.in_memory import run_sweep
    from cfm_fem.workflows.sweep.pieces import run_sweep_pieces
    from cfm_fem.workflows.sweep.problem import serial_map
    from cfm_fem.workflows.sweep.slabs import run_slab_sweep

    fm = read_field(csv_map)
    out = tmp_path / "res"
    so.write_sweep(out, run_sweep(fm, SweepConfig(up_um=(0.0, 10.0, 20.0), trials=40)))
    (out / "uf_custom.vtu").write_text("<VTKFile>my own map</VTKFile>\n")
    mine = {"uf_custom.vtu"}
    res = run_sweep(fm, SweepConfig(up_um=(10.0,), trials=40))
    so.write_sweep(out, res)  # fewer U_p values
    assert _maps_present(out) - mine == _maps_named(out) == {"uf_up10um.vtu"}

    kept = {}

    def mapper(problem, chunks):
        for ab, r in serial_map(problem, chunks):
            kept[ab] = r
            yield ab, r

    compact = run_sweep_pieces(fm, SweepConfig(up_um=(10.0,), trials=40), mapper)
    full = [np.concatenate([kept[ab][i] for ab in sorted(kept)]) for i in range(5)]
    so.write_sweep_pieces(out, compact, 3, lambda nodes: tuple(x[nodes] for x in full))
    want = {"uf_up10um.pvtu", *(f"uf_up10um/piece_000{p}.vtu" for p in range(3))}
    assert _maps_present(out) - mine == _maps_named(out) == want  # the one-file map is gone

    run_slab_sweep(csv_map, SweepConfig(up_um=(10.0,), trials=40), out, n_slabs=2)
    assert _maps_present(out) - mine == _maps_named(out) == want - {"uf_up10um/piece_0002.vtu"}

    so.write_sweep(out, res, remove_stale=False)  # left to the caller (the CLI names them)
    assert _maps_present(out) - mine == {"uf_up10um.vtu", *want} - {"uf_up10um/piece_0002.vtu"}
    so.write_sweep(out, run_sweep(fm, SweepConfig(up_um=(0.0, 10.0, 20.0), trials=40)))
    before = _maps_present(out)
    assert before - mine == {"uf_up0um.vtu", "uf_up10um.vtu", "uf_up20um.vtu"}

    def fail(*args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr(so, "write_json", fail)  # no summary: the run is not complete
    with pytest.raises(OSError, match="disk full"):
        so.write_sweep(out, res)
    assert _maps_present(out) == before  # nothing removed before the outputs were complete
    assert (out / "uf_custom.vtu").read_text() == "<VTKFile>my own map</VTKFile>\n"


def test_leftover_temporaries_modified_within_the_hour_are_left(tmp_path):
    """A temporary of a sweep output named as a killed run leaves it may be another run's that
    is still writing into the same folder: only those modified an hour ago or more are
    removed (a later run removes the others)."""
    import os
    import time

    from cfm_fem.io.sweep_out import remove_leftover_temporaries

    hour = 3600.0  # `cfm_fem.io.sweep_out.TEMPORARY_AGE_S`
    (tmp_path / "uf_up10um").mkdir()
    ages = {  # seconds since the last modification
        ".uf_up20um.vtu.old_0001.vtu": 2 * hour,
        ".summary.json.old_0002.json": hour + 1.0,
        "uf_up10um/.piece_0001.vtu.old_0003.vtu": 3 * hour,
        ".uf_up30um.vtu.young001.vtu": hour - 60.0,
        ".sweep.pvd.young002.pvd": 0.0,
        "uf_up10um/.piece_0000.vtu.young003.vtu": 5.0,
        ".uf_up40um.vtu.future01.vtu": -600.0,  # a clock ahead of ours: young
    }
    now = time.time()
    for name, age in ages.items():
        (tmp_path / name).write_bytes(b"<VTKFile")
        os.utime(tmp_path / name, (now - age, now - age))
    old = sorted(n for n in ages if ".old_" in n)
    assert sorted(remove_leftover_temporaries(tmp_path)) == old
    left = sorted(p.relative_to(tmp_path).as_posix() for p in tmp_path.rglob(".*"))
    assert left == sorted(set(ages) - set(old))
    assert sorted(remove_leftover_temporaries(tmp_path, min_age_s=0.0)) == sorted(
        n for n in left if "future" not in n
    )


@pytest.mark.parametrize("layout", [[], ["--pieces", "2"], ["--slabs", "2"]])
def test_interrupted_rerun_leaves_no_earlier_summary_beside_new_maps(
    csv_map, tmp_path, monkeypatch, layout
):
    """A re-run stopped (Ctrl-C) after its first new map leaves no summary.json or sweep.pvd
    of the earlier run beside it: they are removed before any new map is written, so a
    folder without a summary says the run did not complete."""
    import cfm_fem.io.slab_files
    import cfm_fem.io.sweep_out

    out = tmp_path / "res"
    base = ["sweep", str(csv_map), "--up", "0,10,20", "--trials", "50", "--out", str(out)]
    assert main([*base, *layout, "--seed", "1"]) == 0
    assert (out / "summary.json").exists() and (out / "sweep.pvd").exists()
    calls = []

    def stop_after_one(real):
        def write(*args, **kwargs):
            if calls:
                raise KeyboardInterrupt
            calls.append(args[0])
            return real(*args, **kwargs)

        return write

    for module, name in ((cfm_fem.io.sweep_out, "write_vtu"),
                         (cfm_fem.io.sweep_out, "write_mesh_vtu"),
                         (cfm_fem.io.slab_files, "write_vtu")):  # fmt: skip
        monkeypatch.setattr(module, name, stop_after_one(getattr(module, name)))
    assert main([*base, *layout, "--seed", "0"]) == 1  # interrupted
    assert len(calls) == 1  # one new map (or piece) was written
    assert not (out / "summary.json").exists() and not (out / "sweep.pvd").exists()


def test_reader_hints_name_the_command_line_option_and_the_python_argument(
    csv_map, tmp_path, capsys
):
    """What a message tells the user to pass is spelt as the option of this command, with the
    Python argument beside it, never as the Python argument alone."""
    no_units = tmp_path / "no_units.csv"
    no_units.write_text("x,y,z,Bx [T],By [T],Bz [T]\n0,0,0,0,0,1\n1,0,0,0,0,1\n")
    assert main(["sweep", str(no_units), "--out", str(tmp_path / "a")]) == 2
    err = capsys.readouterr().err
    assert "no length unit" in err and "--length-unit mm (length_unit='mm' from Python)" in err

    zeros = tmp_path / "zeros.csv"
    text = csv_map.read_text().splitlines()
    text[1] = "0,0,0,0,0,0"  # one placeholder row
    zeros.write_text("\n".join(text) + "\n")
    base = ["sweep", str(zeros), "--up", "10", "--trials", "20"]
    assert main([*base, "--out", str(tmp_path / "b")]) == 0
    err = capsys.readouterr().err
    assert "drop them with --zero-rows drop (zero_rows='drop' from Python)" in err
    for run in (["--out", str(tmp_path / "c")], ["--slabs", "2", "--out", str(tmp_path / "s")]):
        assert main([*base, "--zero-rows", "drop", *run]) == 0
        notes = json.loads((tmp_path / run[-1] / "summary.json").read_text())["notes"]
        hint = "as asked by --zero-rows drop (zero_rows='drop' from Python)"
        assert any(hint in n for n in notes), notes

    vtu = tmp_path / "map.vtu"  # a mesh file: no length unit in it, mm assumed and noted
    ax = np.arange(4.0)
    pts = np.stack(np.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3)
    meshio.write(vtu, meshio.Mesh(pts, [("vertex", np.arange(len(pts))[:, None])],
                                  point_data={"B": pts @ G.T + [0.0, 0.0, 1.0]}))  # fmt: skip
    capsys.readouterr()
    assert (
        main(["sweep", str(vtu), "--up", "10", "--trials", "20", "--out", str(tmp_path / "d")]) == 0
    )
    out = capsys.readouterr().out
    assert "if not mm, pass --length-unit UNIT (length_unit= from Python)" in out
    assert "if not T, pass --field-unit UNIT (field_unit= from Python)" in out

    assert main(["sweep", str(csv_map), "--format", "excel", "--out", str(tmp_path / "e")]) == 2
    assert "unknown format --format excel (fmt='excel' from Python)" in capsys.readouterr().err
