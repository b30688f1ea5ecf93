"""Robustness of every command beyond the readers: finite options and outputs, memory
estimates, bench defaults, library errors named, unit slips of recordings, work kept.

Each class of failure is guarded in one shared place (the option parser, the writers'
finite-value contract, `cfm_fem.threads.check_memory`, `cfm_fem.io.bench_toml`,
`cfm_fem.io.meshfile.library_reason`, `cfm_fem.models.recordings.check_tracker_scale`); these
tests run each guard through the command line where that is cheap, else directly.
"""

from __future__ import annotations

import json
from importlib import resources
from pathlib import Path

import meshio
import numpy as np
import pytest

from cfm_fem.cli import build_parser, main
from cfm_fem.cli._checks import finite_float
from cfm_fem.errors import CfmInputError
from cfm_fem.io import read_field
from cfm_fem.io._atomic import write_json
from cfm_fem.io.bench_toml import DEFAULT_NOTE, parse_bench
from cfm_fem.io.recordings import read_tracker, write_tracker
from cfm_fem.models.recordings import check_tracker_scale
from cfm_fem.threads import check_memory, check_run_time, paced
from cfm_fem.workflows.design import admissible_up

ROOT = Path(__file__).resolve().parents[1]
BENCH = resources.files("cfm_fem.data").joinpath("cfm_reference_bench.toml").read_text()


def _refused(argv, capsys, out=None):
    """Run the CLI; check exit 2, one message, no traceback, no output; return the message."""
    rc = main([str(a) for a in argv])
    err = capsys.readouterr().err
    assert rc == 2, err
    assert "Traceback" not in err and err.count("cfm-fem: error:") == 1, err
    lines = err.splitlines()  # warnings may come first; the message is the last line
    assert lines[-1].startswith("cfm-fem: error:"), "the message is not one line"
    if out is not None:
        assert not Path(out).exists() or not list(Path(out).iterdir()), "output left"
    return err


# --------------------------------------------------------------------------- options


def _float_options():
    """(command, option) of every ``type=float`` option of every command."""
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(getattr(a, "choices", None), dict))
    for name, sp in sub.choices.items():
        for a in sp._actions:
            if a.type is float:
                yield name, sp, a.option_strings[-1]


@pytest.mark.parametrize("value", ["nan", "inf", "-inf", "1e999"])
def test_every_float_option_takes_finite_numbers_only(value):
    options = list(_float_options())
    assert len(options) >= 10  # the parsers declare them; the registry covers all
    for name, sp, option in options:
        assert sp._registry_get("type", float, float) is finite_float, (name, option)
        with pytest.raises(CfmInputError, match=f"argument {option}: must be a finite number"):
            sp.parse_known_args([f"{option}={value}"])


@pytest.mark.parametrize(
    "argv, option",
    [
        (["synth", "tracker", "--drift-um-per-s", "nan"], "--drift-um-per-s"),
        (["synth", "tracker", "--reversal-um", "inf"], "--reversal-um"),
        (["synth", "hall", "--magnet-offset", "nan,0"], "--magnet-offset"),
        (["synth", "tracker", "--grid", "3,inf,3"], "--grid"),
        (["coupled", "--z", "nan"], "--z"),
        (["coupled", "--z", "0,inf"], "--z"),
        (["sweep", "map.txt", "--axis-scale", "1,nan,1"], "--axis-scale"),
        (["tolerance", "--target", "nan"], "--target"),
    ],
)
def test_non_finite_lists_name_their_option(tmp_path, capsys, argv, option):
    out = tmp_path / "out"
    target = ["--out", out / "r.csv"] if argv[0] == "synth" else ["--out", out]
    if argv[0] == "synth":
        out.mkdir()
    err = _refused([*argv, *target], capsys, out)
    assert option in err and "finite" in err, err


def test_an_empty_out_is_refused(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    err = _refused(["kinematics", "--trials", "20", "--out", ""], capsys)
    assert "--out is empty; expected the name of an output folder" in err
    assert not list(tmp_path.iterdir()), "written into the current folder"


# --------------------------------------------------------------------------- outputs


def test_synth_refuses_an_implausible_field_and_writes_nothing(tmp_path, capsys):
    out = tmp_path / "hall.csv"
    err = _refused(["synth", "hall", "--magnet-offset", "1e9,0", "--out", out], capsys)
    assert "not written: 'Bx' would hold" in err and "within +-1e+06 T" in err, err
    assert "hall.csv" in err and not out.exists()


def test_recording_writer_refuses_nan(tmp_path):
    rec = read_tracker(_tracker_file(tmp_path))
    rec.meas[3, 1] = np.nan
    with pytest.raises(CfmInputError, match=r"t2.csv: not written: 'y_meas' would hold nan mm"):
        write_tracker(tmp_path / "t2.csv", rec)
    assert not (tmp_path / "t2.csv").exists()


def test_json_writer_names_the_non_finite_key(tmp_path):
    data = {"uf_units": {"p95": [1.0, float("inf")]}, "b_ref_T": 1.0}
    with pytest.raises(CfmInputError, match=r"s.json: not written: 'uf_units.p95\[1\]' would"):
        write_json(tmp_path / "s.json", data)
    assert not (tmp_path / "s.json").exists()


def test_design_on_a_field_that_does_not_vary_answers_without_nan():
    zeros = np.zeros((30, 3))
    ans = admissible_up([10.0, 20.0, 30.0], zeros, zeros, np.ones((30, 3), bool), 5.0,
                        rel_mc_std=0.03)  # fmt: skip
    assert ans.method == "unbounded" and ans.up_max_um is None and ans.u_up_max_um is None
    assert "no largest U_p" in ans.sentence() and "nan" not in ans.sentence()
    json.dumps(ans.to_dict(), allow_nan=False)


# --------------------------------------------------------------------------- memory


def test_check_memory_says_what_fits():
    with pytest.raises(CfmInputError) as info:
        check_memory("--trials", 1e14, 400.0, "trials", available=10**10)
    msg = str(info.value)
    assert msg.startswith("--trials: 100,000,000,000,000 trials need about 40,000,000 GB")
    assert "at most about 20,000,000 trials fit" in msg
    check_memory("--trials", 1e6, 400.0, "trials", available=10**10)  # 0.4 GB: fits


@pytest.mark.parametrize(
    "argv",
    [
        ["sweep", "{map}", "--trials", "1e14"],
        ["design", "{map}", "--uf-max", "10", "--trials", "1e14"],
        ["fig4", "{map}", "--trials", "1e14"],
        ["sweep", "{map}", "--mode", "htm", "--trials", "1e14"],
    ],
)
def test_absurd_trial_counts_are_refused_before_any_work(tmp_path, capsys, argv):
    out = tmp_path / "out"
    path = _small_map(tmp_path)
    err = _refused([a.replace("{map}", str(path)) for a in argv] + ["--out", out], capsys, out)
    assert "--trials: 100,000,000,000,000 trials need about" in err and "trials fit" in err
    assert not out.exists(), "a chunk manifest or lock was left"


def test_check_run_time_refuses_work_no_machine_ends_within_a_week():
    with pytest.raises(CfmInputError) as info:
        check_run_time("tolerance --check", 1e14, 936, "trials", cores=2)
    msg = str(info.value)
    assert msg.startswith("tolerance --check: 100,000,000,000,000 trials of 936 point")
    assert "1.48 years on 2 core(s)" in msg and "trials end within a week" in msg
    check_run_time("tolerance --check", 1e9, 936, "trials", cores=2)  # 468 s at the floor


def test_paced_refuses_once_the_pace_shows_the_run_cannot_end_within_a_week(monkeypatch):
    import cfm_fem.threads as threads

    clock = [0.0]
    monkeypatch.setattr("time.monotonic", lambda: clock[0])
    seen = []
    update = paced("--budget-trials", 1e9, "trials", seen.append, after=2.0)
    update(100)  # before the check: counted and passed on
    clock[0] = 4.0  # 200 trials in 4 s: 1e9 trials take 231 days
    with pytest.raises(CfmInputError) as info:
        update(100)
    assert "--budget-trials: 1,000,000,000 trials would take about 2.3e+02 days" in str(info.value)
    assert "at most about 30,240,000 trials end within a week" in str(info.value)
    assert seen == [100]
    fine = paced("--trials", 1e5, "trials", after=2.0)  # 1e5 trials: 33 min at that pace
    fine(100)
    clock[0] = 8.0
    fine(100)
    assert threads.MAX_RUN_SECONDS == 7 * 86400.0


def test_tolerance_check_beyond_any_run_time_is_refused(tmp_path, capsys):
    out = tmp_path / "out"
    err = _refused(["tolerance", "--target", "30", "--check", "1e14", "--out", out], capsys, out)
    assert "tolerance --check: 100,000,000,000,000 trials" in err and "within a week" in err


@pytest.mark.parametrize("option", ["--tracker", "--hall-map"])
def test_an_empty_recording_name_is_named_as_such(tmp_path, capsys, option):
    argv = ["diagnose", option, ""] + (["--reference", "fit:3"] if option == "--hall-map" else [])
    err = _refused(argv + ["--out", tmp_path / "d"], capsys)
    assert "'': an empty file name; expected a recording" in err


def test_an_empty_field_map_name_is_named_as_such(tmp_path, capsys):
    err = _refused(["sweep", "", "--out", tmp_path / "s"], capsys)
    assert "'': an empty file name; expected a field-map file" in err


def test_synth_grid_too_large_for_memory(tmp_path, capsys):
    out = tmp_path / "t.csv"
    err = _refused(["synth", "tracker", "--grid", "3000,3000,3000", "--out", out], capsys)
    assert "synth tracker --grid and --reps: 135,000,000,000 rows need about" in err
    assert "rows fit" in err and not out.exists()


# --------------------------------------------------------------------------- bench defaults


def _without(text: str, table: str) -> str:
    out, skip = [], False
    for line in text.splitlines():
        if line.startswith("["):
            skip = line.strip() == f"[{table}]"
        if not skip:
            out.append(line)
    return "\n".join(out) + "\n"


@pytest.mark.parametrize("table", ["vibration", "reading_delay"])
def test_an_uncertainty_table_left_out_is_an_error(table):
    with pytest.raises(CfmInputError, match=rf"b.toml: \[{table}\] is missing; expected .*0\.0"):
        parse_bench(_without(BENCH, table), source="b.toml")


def test_an_error_without_unit_is_an_error():
    text = BENCH.replace('unit = "urad"\n', "", 1)
    with pytest.raises(CfmInputError, match=r"b.toml:\d+: 'errors.x.eps_x.unit' is missing"):
        parse_bench(text, source="b.toml")


def test_defaults_taken_are_stated_in_the_assumptions():
    bench = parse_bench(_without(_without(BENCH, "grid"), "magnet"), source="b.toml")
    stated = [a for a in bench.assumptions if a.startswith(DEFAULT_NOTE)]
    assert len(stated) == 5, stated  # three grid axes, magnet rotation and translation
    assert any("z_mm = { start = 0, stop = 800, num = 13 }" in a for a in stated)
    assert bench.grid.x == (0.0, 150.0, 9) and np.all(bench.magnet.translation_mm == 0)
    assert not [a for a in parse_bench(BENCH).assumptions if a.startswith(DEFAULT_NOTE)]


def test_a_grid_left_out_follows_the_strokes():
    text = _without(BENCH, "grid").replace("stroke_mm = 150.0", "stroke_mm = 100.0", 1)
    bench = parse_bench(text, source="b.toml")
    assert bench.grid.x == (0.0, 100.0, 9)  # the x stroke, not the reference 150 mm
    assert not bench.outside_stroke(bench.grid.points()).any()


@pytest.mark.parametrize("tau", ['pdf = "uniform", low = -1.0, high = -0.5',
                                 'pdf = "normal", mean = 0.0, std = 1e-4'])  # fmt: skip
def test_a_negative_reading_delay_is_refused(tau):
    delay = f'model = "speed_tau"\nspeed_mm_s = [0.0, 0.0, 10.0]\ntau = {{ {tau} }}'
    text = BENCH.replace('model = "normal"\nstd_um = 1.0', delay)
    with pytest.raises(CfmInputError, match=r"'reading_delay.tau' reaches -.* expected a delay"):
        parse_bench(text, source="b.toml")


# --------------------------------------------------------------------------- readers


def _mesh(path, points, cells, data, **kw):
    meshio.write(path, meshio.Mesh(points, cells, point_data=data), **kw)
    return path


def test_library_errors_are_translated(tmp_path):
    pts = np.random.default_rng(0).random((10, 3))
    cells = [("tetra", np.array([[0, 1, 2, 3]]))]
    _mesh(tmp_path / "zero.vtu", np.zeros((0, 3)), [], {})
    with pytest.raises(CfmInputError, match=r"zero.vtu: .*the file holds no nodes"):
        read_field(tmp_path / "zero.vtu")
    good = _mesh(tmp_path / "g.vtu", pts, cells, {"B": pts}, binary=False)
    text = good.read_text().replace('NumberOfPoints="10"', 'NumberOfPoints="9"')
    (tmp_path / "n.vtu").write_text(text)
    with pytest.raises(CfmInputError, match=r"n.vtu: .*holds 30 values where the file's counts "
                       r"ask for 9 x 3 .*; expected a complete vtu file"):  # fmt: skip
        read_field(tmp_path / "n.vtu")
    nodes = "\n".join(f"{i + 1} {p[0]} {p[1]} {p[2]}" for i, p in enumerate(pts))
    msh = (f"$MeshFormat\n2.2 0 8\n$EndMeshFormat\n$Nodes\n10\n{nodes}\n$EndNodes\n$Elements\n"
           "1\n1 4 2 0 0 1 2 3 40\n$EndElements\n")  # fmt: skip
    (tmp_path / "o.msh").write_text(msh)
    with pytest.raises(CfmInputError, match=r"o.msh: .*a node or element number outside"):
        read_field(tmp_path / "o.msh")


def test_vector_and_components_must_agree(tmp_path):
    pts = np.random.default_rng(1).random((6, 3))
    cells = [("tetra", np.array([[0, 1, 2, 3]]))]
    same = {"B": pts, "Bx": pts[:, 0], "By": pts[:, 1], "Bz": pts[:, 2]}
    fm = read_field(_mesh(tmp_path / "s.vtu", pts, cells, same), length_unit="mm",
                    field_unit="T")  # fmt: skip
    assert any("'B' used; Bx, By, Bz agree with it" in n for n in fm.notes)
    other = dict(same, Bx=pts[:, 0] + 1.0)
    with pytest.raises(CfmInputError, match=r"d.vtu: point data 'B' and 'Bx', 'By', 'Bz' "
                       "disagree"):  # fmt: skip
        read_field(_mesh(tmp_path / "d.vtu", pts, cells, other))


def test_a_line_feed_in_a_file_name_stays_on_one_line(tmp_path, capsys):
    path = tmp_path / "a\nb.vtu"
    path.write_text("x")
    err = _refused(["sweep", path, "--out", tmp_path / "out"], capsys)
    assert "a\\nb.vtu" in err


# --------------------------------------------------------------------------- recordings


def _tracker_file(tmp_path, scale=1.0):
    from cfm_fem.io.bench_toml import read_reference_bench

    bench = read_reference_bench()
    cmd = np.array([[x, y, z] for x in (0, 75, 150) for y in (0, 150) for z in (0, 400)], float)
    meas = bench.nominal_probe_mm(cmd) + 1e-3
    rows = [f"{i},{r},{c[0] * scale},{c[1] * scale},{c[2] * scale},{m[0] * scale},"
            f"{m[1] * scale},{m[2] * scale}" for i, (c, m) in enumerate(zip(cmd, meas, strict=True))
            for r in (1, 2)]  # fmt: skip
    path = tmp_path / ("t.csv" if scale == 1 else "t_scaled.csv")
    path.write_text("point_id,rep,x_cmd,y_cmd,z_cmd,x_meas,y_meas,z_meas\n" + "\n".join(rows))
    return path


@pytest.mark.parametrize("unit, scale", [("m", 1e-3), ("in", 1 / 25.4)])
def test_a_tracker_recording_in_another_unit_is_refused(tmp_path, unit, scale):
    from cfm_fem.io.bench_toml import read_reference_bench

    nominal = read_reference_bench().nominal_probe_mm
    rec = read_tracker(_tracker_file(tmp_path, scale))
    with pytest.raises(CfmInputError, match=rf"look like {unit}, not mm.*"
                       rf"--recording-length-unit {unit}"):  # fmt: skip
        check_tracker_scale(rec.cmd, rec.meas, nominal, source=rec.source)
    good = read_tracker(_tracker_file(tmp_path))
    assert check_tracker_scale(good.cmd, good.meas, nominal, source=good.source) == []


# --------------------------------------------------------------------------- sweep


def _small_map(tmp_path) -> Path:
    path = tmp_path / "map.txt"
    lines = (ROOT / "meshes" / "quadrupole_comsol.txt").read_text().splitlines()[:400]
    path.write_text("\n".join(lines) + "\n")
    return path


def test_the_chunk_store_outlives_a_stop_before_the_report(tmp_path, capsys, monkeypatch):
    """A run stopped while its report is written resumes from its chunks, all of them."""
    import cfm_fem.report.sweep

    path, out = _small_map(tmp_path), tmp_path / "out"
    argv = ["sweep", str(path), "--up", "10", "--trials", "20", "--chunk-nodes", "64",
            "--out", str(out)]  # fmt: skip

    def stop(out, result=None, drawn=None):
        raise KeyboardInterrupt

    monkeypatch.setattr(cfm_fem.report.sweep, "write_sweep_report", stop)
    assert main(argv) == 1
    assert list((out / ".cfm_fem_chunks").glob("*")), "the chunk store was deleted"
    monkeypatch.undo()
    capsys.readouterr()
    assert main([*argv, "--resume"]) == 0
    err = capsys.readouterr().err
    assert "resumed:" in err and ", 0 computed" in err, err
    assert not (out / ".cfm_fem_chunks").exists()


def test_summary_of_a_map_whose_nodes_all_fall_back_to_linear(capsys):
    from cfm_fem.cli.sweep import _print_summary

    s = {"harmonic": {"nodes_by_degree": {}, "neighbours": 20, "linear_fallback_nodes": 40,
                      "residual_units": {"p95": None}, "fallback_rule": "misfit"},
         "interpolation": "delaunay", "b_ref_T": 1.0, "b_ref_rule": "max |B|", "trials": 20,
         "uf_relative_mc_std": 0.3, "up_um": [10.0], "uf_units": {q: [None] for q in
         ("p50", "p95", "p99", "max")}, "outside_fraction": [0.0], "uf_nodes": [0],
         "mode": "gauss", "outside": "exclude", "processed_nodes": 40,
         "walk_failed_fraction": [0.0], "notes": [], "seconds": 1.0}  # fmt: skip
    _print_summary(s, "out")
    printed = capsys.readouterr().out
    assert "linear interpolant at every node (delaunay): no node's harmonic fit holds" in printed


@pytest.mark.parametrize("argv", [["kinematics", "--trials", "20"], ["synth", "tracker"]])
def test_an_out_name_too_long_is_refused(tmp_path, capsys, argv):
    out = tmp_path / ("x" * 300)
    err = _refused([*argv, "--out", out], capsys)
    assert "--out" in err and "File name too long" in err and "expected a" in err, err


@pytest.mark.parametrize("value", ["1_000", "\u0661\u0662", "2,5_0"])
def test_options_refuse_digit_separators_and_other_digits(value):
    from cfm_fem.cli._checks import number_list

    with pytest.raises(Exception, match="must be a number|finite numbers"):
        finite_float(value)
    with pytest.raises(CfmInputError, match=r"--z must be comma-separated finite numbers"):
        number_list(value, "--z")


def test_int_options_take_ascii_digits_and_workers_are_bounded(tmp_path, capsys):
    from cfm_fem.workflows.sweep.distributed import MAX_WORKERS_PER_CPU

    err = _refused(["sweep", "m.txt", "--workers", "1_000", "--out", tmp_path / "o"], capsys)
    assert "argument --workers: must be a whole number; got '1_000'" in err
    err = _refused(["kinematics", "--workers", "100000", "--out", tmp_path / "o"], capsys)
    assert (
        f"--workers must be at most {MAX_WORKERS_PER_CPU * (__import__('os').cpu_count() or 1)}"
        in err
    )


def test_an_absurdly_small_b_ref_is_refused_before_the_run(tmp_path, capsys):
    """B_ref = 1e-300 T made every U_f infinite and the design summary a TypeError."""
    out = tmp_path / "out"
    argv = ["design", _small_map(tmp_path), "--uf-max", "10", "--up", "10,20", "--trials", "20",
            "--b-ref", "1e-300", "--out", out]  # fmt: skip
    err = _refused(argv, capsys, out)
    assert "--b-ref 1e-300 T is below 1e-09 of the map's largest |B|" in err


def test_a_perturbation_too_large_for_the_map_names_the_axis_scale(tmp_path, capsys):
    ax = np.linspace(0.0, 4.0, 5)
    pts = np.stack(np.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3)
    rows = "\n".join(",".join(f"{v:.17g}" for v in r) for r in np.c_[pts, 0.1 * pts + 1.0])
    path = tmp_path / "map.csv"
    path.write_text("x [mm],y [mm],z [mm],Bx [T],By [T],Bz [T]\n" + rows + "\n")
    argv = ["sweep", str(path), "--up", "10", "--axis-scale", "1e14", "--out", str(tmp_path / "o")]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "--axis-scale" in err and "map.csv" in err and "Traceback" not in err


def test_quality_names_the_perturbation_that_moves_every_point_off_the_map(tmp_path, capsys):
    argv = ["quality", ROOT / "meshes" / "quadrupole_opera.table", "--r-ref", "3", "--up", "1e6",
            "--trials", "40", "--no-budget", "--out", tmp_path / "q"]  # fmt: skip
    err = _refused(argv, capsys, tmp_path / "q")
    assert "displaced by --up 1e+06 um left the field model" in err
