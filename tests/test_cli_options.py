"""Options shared by several commands: the field-map reader's options wherever a map is read,
trial counts written as 1e6, one "cfm-fem: error:" prefix, and sweep's option checks made before
the map is read."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from cfm_fem.cli import build_parser, main

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
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
               "drop"]  # fmt: skip


def _no_unit_map(path, lo=-3, hi=3):
    """A grid map whose header names no length unit (the reader asks for --length-unit)."""
    g = np.stack(np.meshgrid(*[np.arange(lo, hi + 1.0)] * 3, indexing="ij"), -1).reshape(-1, 3)
    rows = "".join(f"{x:g},{y:g},{z:g},{0.1 * y:g},{0.1 * x:g},1\n" for x, y, z in g)
    path.write_text("x,y,z,Bx [T],By [T],Bz [T]\n" + rows)
    return path


def reader_kwargs(args):
    return {k: getattr(args, k) for k in ("fmt", "length_unit", "field_unit", "zero_rows")}


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
        "fmt": "csv", "length_unit": "in", "field_unit": "mT", "zero_rows": "drop"
    }  # fmt: skip
    defaults = build_parser().parse_args([*MAP_COMMANDS[command], "--out", "o"])
    assert reader_kwargs(defaults) == {
        "fmt": None, "length_unit": None, "field_unit": None, "zero_rows": "warn"
    }  # fmt: skip
    with pytest.raises(SystemExit):
        main([command, "--help"])
    text = " ".join(capsys.readouterr().out.split())
    # what the unit options do when the file states a unit (the help said "if the file does
    # not say"; they override it, with a warning)
    assert "overrides a unit the file states (with a warning when they differ)" in text
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
    """kinematics --help says 'default 1e6'; --trials 1e6 was 'invalid int value'."""
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
        (["--b-ref", "-1"], "B_ref must be a positive field in T; got -1.0"),
        (["--axis-scale", "0"], "axis scale must be finite, >= 0 and not all 0"),
        (["--workers", "0"], "--workers must be >= 1; got 0"),
        (["--trials", "5", "--slabs", "2"], "--trials must be at least 20"),
    ],
)
def test_sweep_checks_its_options_before_reading_the_map(tmp_path, capsys, monkeypatch, extra,
                                                         message):  # fmt: skip
    """They were checked after the map was read and meshed: minutes on a large map."""
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
    """--workers (and --adaptive with it) were checked after the bench was read: a bad bench
    was then reported instead of the bad option."""
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
