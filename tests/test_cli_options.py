"""Options shared by several commands: the field-map reader's options wherever a map is read,
trial counts written as 1e6, one "cfm-fem: error:" prefix, and sweep's option checks made before
the map is read."""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import SHARED_DATA

from cfm_fem.cli import build_parser, main

DATA = SHARED_DATA
BODY_SCAN = DATA / "emphatic" / "EMPHATIC_body_scan_5280148.csv"
MF_MAP = DATA / "emphatic" / "mfMapMeasured_5mm.txt"

HALL_HEAD = "point_id,rep,x_cmd,y_cmd,z_cmd,Bx,By,Bz\n"

#: Each command that reads a field map, with the arguments that name the map.
MAP_COMMANDS = {
    "sweep": ["sweep", "map.csv"],
    "fig4": ["fig4", "map.csv"],
    "coupled": ["coupled", "--field", "map.csv"],
    "compare": ["compare", "--hall-map", "rec.csv", "--reference", "map.csv"],
    "diagnose": ["diagnose", "--hall-map", "rec.csv", "--reference", "map.csv"],
}

READER_ARGS = ["--format", "csv", "--length-unit", "in", "--field-unit", "mT", "--zero-rows",
               "drop", "--solution", "I0=200"]  # fmt: skip


def _no_unit_map(path, lo=-3, hi=3):
    """A grid map whose header names no length unit (the reader asks for --length-unit)."""
    g = np.stack(np.meshgrid(*[np.arange(lo, hi + 1.0)] * 3, indexing="ij"), -1).reshape(-1, 3)
    rows = "".join(f"{x:g},{y:g},{z:g},{0.1 * y:g},{0.1 * x:g},1\n" for x, y, z in g)
    path.write_text("x,y,z,Bx [T],By [T],Bz [T]\n" + rows)
    return path


def reader_kwargs(args):
    keys = ("fmt", "length_unit", "field_unit", "zero_rows", "solution")
    return {k: getattr(args, k) for k in keys}


def _err(argv, capsys):
    rc = main([str(a) for a in argv])
    err = capsys.readouterr().err
    assert rc == 2 and "Traceback" not in err, err
    return err


# --------------------------------------------------------------------------- reader options


@pytest.mark.parametrize("command", list(MAP_COMMANDS))
def test_every_command_that_reads_a_map_takes_the_reader_options(command, capsys):
    """fig4, coupled, compare and diagnose had none of them, though the reader's messages say
    to pass them: 'unrecognized arguments: --length-unit in'."""
    args = build_parser().parse_args([*MAP_COMMANDS[command], *READER_ARGS, "--out", "o"])
    assert reader_kwargs(args) == {
        "fmt": "csv", "length_unit": "in", "field_unit": "mT", "zero_rows": "drop",
        "solution": "I0=200",
    }  # fmt: skip
    defaults = build_parser().parse_args([*MAP_COMMANDS[command], "--out", "o"])
    assert reader_kwargs(defaults) == {
        "fmt": None, "length_unit": None, "field_unit": None, "zero_rows": "warn",
        "solution": None,
    }  # fmt: skip
    with pytest.raises(SystemExit):
        main([command, "--help"])
    text = " ".join(capsys.readouterr().out.split())
    # what the unit options do when the file states a unit (the help said "if the file does
    # not say"; they override it, with a warning)
    assert "overrides a unit the file states (with a warning when they differ)" in text
    # what --solution is, with an example
    assert "--solution TAG COMSOL export of a parametric or time-dependent study" in text
    assert "e.g. --solution I0=200 or --solution t=0.1" in text
    if command in ("coupled", "compare", "diagnose"):
        assert "when it is a field map (not a harmonics .csv" in text


def test_fig4_reads_the_emphatic_body_scan_with_its_length_unit(tmp_path, capsys):
    """The file's message says 'pass it, e.g. --length-unit mm'; fig4 refused the option."""
    if not BODY_SCAN.is_file():
        pytest.skip(f"real data file not available: {BODY_SCAN}")
    base = ["fig4", BODY_SCAN, "--up", "0,10", "--trials", "20"]
    err = _err([*base, "--out", tmp_path / "a"], capsys)
    assert "--length-unit mm (length_unit='mm' from Python)" in err
    assert main([str(a) for a in [*base, "--length-unit", "in", "--out", tmp_path / "b"]]) == 0
    doc = json.loads((tmp_path / "b" / "fig4.json").read_text())
    assert doc["table"][1]["up_um"] == 10 and doc["table"][1]["nodes"] > 0


def test_fig4_drops_the_placeholder_rows_when_asked(tmp_path, capsys):
    """mfMapMeasured_5mm.txt: 640 rows of 0 0 0; the warning suggests --zero-rows drop, which
    fig4 could not take, so they stayed in the map as 0 T."""
    if not MF_MAP.is_file():
        pytest.skip(f"real data file not available: {MF_MAP}")
    argv = ["fig4", MF_MAP, "--up", "0", "--trials", "20", "--zero-rows", "drop"]
    assert main([str(a) for a in [*argv, "--out", tmp_path / "o"]]) == 0
    assert "7200 nodes from" in capsys.readouterr().err  # 7840 rows less the 640 placeholders


@pytest.mark.slow
def test_coupled_field_map_gets_the_reader_options(tmp_path, capsys):
    ref = _no_unit_map(tmp_path / "map.csv")
    base = ["coupled", "--field", ref, "--radius", 1, "--step", 1, "--z", 0, "--trials", 20,
            "--no-budget"]  # fmt: skip
    err = _err([*base, "--out", tmp_path / "a"], capsys)
    assert "no length unit" in err and "--length-unit mm" in err, err
    assert main([str(a) for a in [*base, "--length-unit", "mm", "--out", tmp_path / "b"]]) == 0
    # no map read: refused rather than ignored
    err = _err(["coupled", "--length-unit", "mm", "--out", tmp_path / "c"], capsys)
    assert "--length-unit applies to a field map only; without --field the bundled" in err


@pytest.mark.parametrize("command", ["compare", "diagnose"])
def test_reference_map_gets_the_reader_options(tmp_path, capsys, command):
    """The option reaches the reader: without it the map has no length unit; with it the run
    gets past reading, to the recorded point outside the map (x = 9 mm)."""
    ref = _no_unit_map(tmp_path / "ref.csv", 0, 3)
    rec = tmp_path / "hall.csv"
    rows = [f"{p},{r},{x},1,1,0,0,1\n" for p, x in enumerate([1, 2, 9]) for r in range(3)]
    rec.write_text(HALL_HEAD + "".join(rows))
    base = [command, "--hall-map", rec, "--reference", ref]
    err = _err([*base, "--out", tmp_path / "a"], capsys)
    assert "no length unit" in err, err
    err = _err([*base, "--length-unit", "mm", "--out", tmp_path / "b"], capsys)
    assert "[9.0, 1.0, 1.0] mm is outside the reference field" in err, err
    assert not (tmp_path / "b").exists()


@pytest.mark.parametrize("command", ["compare", "diagnose", "coupled"])
def test_reader_options_are_refused_for_a_harmonics_reference(tmp_path, capsys, command):
    from cfm_fem.io.harmonics import qfdp4_path

    rec = tmp_path / "hall.csv"
    rec.write_text(HALL_HEAD + "".join(f"1,{r},0,0,0,0,0,1\n" for r in range(3)))
    named = ["--field", qfdp4_path()] if command == "coupled" else [
        "--hall-map", rec, "--reference", qfdp4_path()]  # fmt: skip
    err = _err([command, *named, "--field-unit", "G", "--out", tmp_path / "o"], capsys)
    assert "--field-unit" in err and "harmonics file" in err, err
    if command == "diagnose":
        argv = [command, "--hall-map", rec, "--reference", "fit:2", "--zero-rows", "drop"]
        err = _err([*argv, "--out", tmp_path / "o"], capsys)
        assert "--zero-rows applies to a field map only; --reference fit:2 is fitted" in err


@pytest.mark.parametrize("command", ["compare", "diagnose"])
def test_reader_options_are_refused_with_a_tracker_recording(tmp_path, capsys, command):
    argv = [command, "--tracker", "t.csv", "--length-unit", "m", "--out", tmp_path / "o"]
    assert "--length-unit applies to a field map only; --tracker" in _err(argv, capsys)


# --------------------------------------------------------------------------- --solution


def _current_sweep(path, lo=-3, hi=3):
    """A COMSOL text export of a current sweep (I0=100, I0=200; the field doubles), grid nodes."""
    g = np.stack(np.meshgrid(*[np.arange(lo, hi + 1.0)] * 3, indexing="ij"), -1).reshape(-1, 3)
    B = np.c_[0.1 * g[:, 1], 0.1 * g[:, 0], np.ones(len(g))]
    names = ["X", "Y", "Z"] + [f"mf.B{a} (T) @ I0={i}" for i in (100, 200) for a in "xyz"]
    rows = "".join(" ".join(f"{v:g}" for v in r) + "\n" for r in np.c_[g, B, 2.0 * B])
    path.write_text("% Model: magnet.mph\n% Length unit: mm\n% " + "  ".join(names) + "\n" + rows)
    return path


def test_sweep_of_one_solution_of_a_current_sweep(tmp_path, capsys):
    path = _current_sweep(tmp_path / "two_solutions.txt")
    base = ["sweep", path, "--up", "0:10:10", "--trials", "200"]
    err = _err([*base, "--out", tmp_path / "none"], capsys)
    assert "the export holds 2 solutions ('@ I0=100', '@ I0=200')" in err, err
    assert "--solution TAG" in err and not (tmp_path / "none").exists()
    err = _err([*base, "--solution", "I0=300", "--out", tmp_path / "bad"], capsys)
    assert f"{path}:3: --solution I0=300" in err and "'@ I0=100', '@ I0=200'" in err, err
    assert not (tmp_path / "bad").exists()
    out = {}
    for solution in ("I0=100", "I0=200"):
        out[solution] = tmp_path / solution
        assert main([str(a) for a in [*base, "--solution", solution, "--out", out[solution]]]) == 0
        said = capsys.readouterr().out
        assert f"note: COMSOL solution '@ {solution}' (of 2: '@ I0=100', '@ I0=200')" in said
    summary = {k: json.loads((o / "summary.json").read_text()) for k, o in out.items()}
    s = summary["I0=200"]
    assert "COMSOL solution '@ I0=200' (of 2: '@ I0=100', '@ I0=200')" in s["notes"]
    assert "--solution I0=200" in s["provenance"]["command_line"]
    # the field of I0=200 is twice that of I0=100: B_ref doubles, the relative U_f stays
    assert s["b_ref_T"] == pytest.approx(2.0 * summary["I0=100"]["b_ref_T"])
    assert s["provenance"]["run_key"] != summary["I0=100"]["provenance"]["run_key"]
    # --slabs streams only tables: a COMSOL export is read whole, by read_field, solution and all
    slabs = tmp_path / "slabs"
    argv = [*base, "--solution", "I0=200", "--slabs", "2", "--out", slabs]
    assert main([str(a) for a in argv]) == 0
    assert "is not a plain or Opera table: it is read whole" in capsys.readouterr().err
    doc = json.loads((slabs / "summary.json").read_text())
    assert "COMSOL solution '@ I0=200' (of 2: '@ I0=100', '@ I0=200')" in doc["notes"]
    assert doc["b_ref_T"] == s["b_ref_T"]


@pytest.mark.parametrize("extra", [[], ["--slabs", "2"]])
@pytest.mark.parametrize("kind", ["csv", "opera"])
def test_sweep_refuses_solution_for_a_map_that_is_not_comsol(tmp_path, capsys, extra, kind):
    """--slabs streams tables and Opera tables past read_field: refused there too."""
    if kind == "csv":
        path = _no_unit_map(tmp_path / "map.csv")
    else:
        g = np.stack(np.meshgrid(*[np.arange(3.0)] * 3, indexing="ij"), -1).reshape(-1, 3)
        head = " 3 3 3 2\n 1 X [MM]\n 2 Y [MM]\n 3 Z [MM]\n 4 BX [T]\n 5 BY [T]\n 6 BZ [T]\n 0\n"
        path = tmp_path / "map.table"
        path.write_text(head + "".join(f" {x:g} {y:g} {z:g} 0.1 0.2 1\n" for x, y, z in g))
    out = tmp_path / "DIR"
    argv = ["sweep", path, "--solution", "x", "--up", "0:10:10", "--trials", "20", *extra]
    err = _err([*argv, "--out", out], capsys)
    assert (f"cfm-fem: error: {path}: --solution x (solution='x' from Python) applies to COMSOL "
            "exports only") in err, err  # fmt: skip
    assert err.count("error:") == 1 and not out.exists()


@pytest.mark.slow
def test_solution_reaches_the_reader_of_coupled_and_compare(tmp_path, capsys):
    ref = _current_sweep(tmp_path / "map.txt")
    base = ["coupled", "--field", ref, "--radius", 1, "--step", 1, "--z", 0, "--trials", 20,
            "--no-budget"]  # fmt: skip
    err = _err([*base, "--out", tmp_path / "a"], capsys)
    assert "the export holds 2 solutions" in err and "--solution TAG" in err, err
    assert main([str(a) for a in [*base, "--solution", "I0=200", "--out", tmp_path / "b"]]) == 0
    rec = tmp_path / "hall.csv"
    rows = [f"{p},{r},{x},1,1,0,0,1\n" for p, x in enumerate([1, 2, 9]) for r in range(3)]
    rec.write_text(HALL_HEAD + "".join(rows))
    argv = ["compare", "--hall-map", rec, "--reference", ref, "--solution", "I0=100"]
    err = _err([*argv, "--out", tmp_path / "c"], capsys)  # read: on to the point outside it
    assert "[9.0, 1.0, 1.0] mm is outside the reference field" in err, err


@pytest.mark.parametrize(
    "argv, message",
    [
        (["coupled"], "--solution applies to a field map only; without --field the bundled"),
        (["compare", "--tracker", "t.csv"], "--solution applies to a field map only; --tracker"),
        (["diagnose", "--hall-map", "h.csv", "--reference", "fit:2"],
         "--solution applies to a field map only; --reference fit:2 is fitted"),
        (["coupled", "--field", "QFDP4"], "--solution t=0 (solution='t=0' from Python) applies "
         "to field maps; this is a harmonics file"),
    ],
)  # fmt: skip
def test_solution_is_refused_where_no_field_map_is_read(tmp_path, capsys, argv, message):
    from cfm_fem.io.harmonics import qfdp4_path

    hall = tmp_path / "h.csv"
    hall.write_text(HALL_HEAD + "".join(f"1,{r},0,0,0,0,0,1\n" for r in range(3)))
    argv = [qfdp4_path() if a == "QFDP4" else hall if a == "h.csv" else a for a in argv]
    err = _err([*argv, "--solution", "t=0", "--out", tmp_path / "o"], capsys)
    assert message in err, err
    assert not (tmp_path / "o").exists()


# --------------------------------------------------------------------------- trial counts

TRIAL_OPTIONS = {
    "sweep": ["sweep", "map.csv", "--out", "o", "--trials"],
    "fig4": ["fig4", "map.csv", "--out", "o", "--trials"],
    "coupled": ["coupled", "--out", "o", "--trials"],
    "compare": ["compare", "--tracker", "t.csv", "--out", "o", "--trials"],
    "kinematics": ["kinematics", "--out", "o", "--trials"],
    "tolerance": ["tolerance", "--target", "5", "--check"],
}


@pytest.mark.parametrize("command", list(TRIAL_OPTIONS))
@pytest.mark.parametrize("text, value", [("1e6", 10**6), ("2.5e5", 250_000), ("3000", 3000),
                                         ("1E3", 1000), ("20.0", 20)])  # fmt: skip
def test_trial_counts_written_with_an_exponent(command, text, value):
    """Trial counts may be written as kinematics --help writes its default: 1e6."""
    args = build_parser().parse_args([*TRIAL_OPTIONS[command], text])
    got = args.check if command == "tolerance" else args.trials
    assert got == value and type(got) is int


@pytest.mark.parametrize("command", list(TRIAL_OPTIONS))
@pytest.mark.parametrize("text", ["1.5", "2.5e0", "1e6x", "nan", "inf", "1e400", ""])
def test_trial_counts_that_are_not_whole_numbers_are_refused(command, text, capsys):
    err = _err([*TRIAL_OPTIONS[command], text], capsys)
    option = "--check" if command == "tolerance" else "--trials"
    assert f"error: {command}: argument {option}: must " in err, err
    assert err.count("cfm-fem") == 1 and "invalid" not in err, err


# --------------------------------------------------------------------------- messages


@pytest.mark.parametrize(
    "argv", [["-x"], ["kinematics", "--out", "o", "-x"], ["sweep", "m.csv", "--out", "o", "-x"]]
)
def test_unknown_option_names_cfm_fem_once(argv, capsys):
    err = _err(argv, capsys)
    assert err.strip() == "cfm-fem: error: unrecognized arguments: -x", err


def test_a_subcommand_option_error_names_the_subcommand_once(capsys):
    err = _err(["sweep", "--out", "o"], capsys)
    assert err.strip() == "cfm-fem: error: sweep: the following arguments are required: FIELD"


# --------------------------------------------------------------------------- sweep, early checks


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--trials", "0"], "--trials must be at least 20 for a 95 % interval; got 0"),
        (["--b-ref", "-1"], "--b-ref (B_ref) must be a positive field in T; got -1.0"),
        (["--axis-scale", "0"], "--axis-scale (axis_scale) must be finite, >= 0 and not all 0"),
        (["--workers", "0"], "--workers must be >= 1; got 0"),
        (["--trials", "5", "--slabs", "2"], "--trials must be at least 20"),
    ],
)
def test_sweep_checks_its_options_before_reading_the_map(tmp_path, capsys, monkeypatch, extra,
                                                         message):  # fmt: skip
    """Bad options stop the sweep before the map is read and meshed (minutes on a large map)."""
    import cfm_fem.io
    import cfm_fem.io.streaming

    def no_reading(*args, **kwargs):
        raise AssertionError("the map was read before the options were checked")

    monkeypatch.setattr(cfm_fem.io, "read_field", no_reading)
    monkeypatch.setattr(cfm_fem.io.streaming, "is_streamable", no_reading)
    path = _no_unit_map(tmp_path / "map.csv")
    err = _err(["sweep", path, "--length-unit", "mm", *extra, "--out", tmp_path / "o"], capsys)
    assert message in err, err
    assert not (tmp_path / "o").exists()


# ------------------------------------------------------------------ kinematics, early checks


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--workers", "0"], "--workers must be >= 1; got 0"),
        (["--workers", "-3"], "--workers must be >= 1; got -3"),
        (["--trials", "1"], "--trials must be >= 2; got 1"),
        (["--adaptive", "9"], "--adaptive must be 1..4 significant digits; got 9"),
        (["--seed", "-1"], "--seed must be in [0, 2**63); got -1"),
        (["--adaptive", "2", "--workers", "2"], "--adaptive stops on the pooled result"),
    ],
)
def test_kinematics_checks_its_options_before_reading_the_bench(tmp_path, capsys, monkeypatch,
                                                                extra, message):  # fmt: skip
    """--workers (and --adaptive with it) are checked before the bench is read, so a bad
    option is reported as such."""
    import cfm_fem.io.bench_toml

    def no_reading(*args, **kwargs):
        raise AssertionError("the bench was read before the options were checked")

    monkeypatch.setattr(cfm_fem.io.bench_toml, "read_bench", no_reading)
    monkeypatch.setattr(cfm_fem.io.bench_toml, "read_reference_bench", no_reading)
    bad = tmp_path / "bad.toml"
    bad.write_text("this is [ not toml\n")
    for bench in ([], ["--bench", bad]):
        err = _err(["kinematics", *bench, *extra, "--out", tmp_path / "o"], capsys)
        assert message in err and err.count("error:") == 1 and "toml" not in err, err
        assert not (tmp_path / "o").exists()
