"""`cfm-fem synth` (the synthetic recordings from the installed package) and the recording unit
options of `compare` and `diagnose`."""

import json

import numpy as np
import pytest

from cfm_fem.cli import main
from cfm_fem.io.bench_toml import read_reference_bench
from cfm_fem.io.harmonics import read_qfdp4
from cfm_fem.io.recording_units import convert_recording, read_recording_in_units
from cfm_fem.io.recordings import read_hall_map, read_tracker, write_hall_map, write_tracker
from cfm_fem.workflows.synthetic import synthetic_hall_map, synthetic_tracker


def test_synth_tracker_is_the_python_generator_and_the_seed_fixes_it(tmp_path):
    a, b, c = (tmp_path / f"{n}.csv" for n in "abc")
    argv = ["synth", "tracker", "--seed", "3", "--tracker-std-um", "2", "--reversal-um", "4"]
    assert main([*argv, "--out", str(a)]) == 0
    assert main([*argv, "--out", str(b)]) == 0
    assert main(["synth", "tracker", "--seed", "4", "--out", str(c)]) == 0
    rows = [ln for ln in a.read_text().splitlines() if not ln.startswith("#")]
    assert rows == [ln for ln in b.read_text().splitlines() if not ln.startswith("#")]
    ref = synthetic_tracker(read_reference_bench(), seed=3, tracker_std_um=2.0, reversal_um=4.0)
    rec = read_tracker(a)
    np.testing.assert_array_equal(rec.cmd, ref.cmd)
    np.testing.assert_allclose(rec.meas, ref.meas, rtol=0, atol=1e-12)
    assert not np.allclose(read_tracker(c).meas, rec.meas)


def test_synth_hall_is_the_python_generator(tmp_path):
    out = tmp_path / "h.csv"
    assert main(["synth", "hall", "--seed", "2", "--reps", "3", "--out", str(out)]) == 0
    ref = synthetic_hall_map(read_qfdp4(), read_reference_bench(), seed=2, reps=3)
    rec = read_hall_map(out)
    assert len(rec) == len(ref)
    np.testing.assert_allclose(rec.B, ref.B, rtol=1e-15, atol=0)


@pytest.mark.parametrize(
    "argv, message",
    [
        (["synth", "hall", "--reversal-um", "2"], "not an option of 'synth hall'"),
        (["synth", "tracker", "--grid", "3,3"], "--grid must be 3 comma-separated finite numbers"),
        (["synth", "tracker", "--reps", "0"], "--reps must be >= 1"),
        (["synth", "wand"], "invalid choice: 'wand'"),
    ],
)
def test_synth_bad_options_exit_2_and_write_nothing(tmp_path, capsys, argv, message):
    out = tmp_path / "r.csv"
    assert main([*argv, "--out", str(out)]) == 2
    assert message in capsys.readouterr().err
    assert not out.exists()


def test_synth_out_must_be_a_file_in_an_existing_folder(tmp_path, capsys):
    assert main(["synth", "tracker", "--out", str(tmp_path)]) == 2
    assert "is a folder" in capsys.readouterr().err
    assert main(["synth", "tracker", "--out", str(tmp_path / "no" / "r.csv")]) == 2
    assert "does not exist" in capsys.readouterr().err


def _scaled_copy(rec, path, length=1.0, field=1.0):
    import dataclasses

    if rec.kind == "tracker":
        write_tracker(path, dataclasses.replace(rec, cmd=rec.cmd * length, meas=rec.meas * length))
    else:
        write_hall_map(path, dataclasses.replace(rec, cmd=rec.cmd * length, B=rec.B * field))


def test_recordings_in_metres_and_gauss_convert_to_mm_and_t(tmp_path):
    bench = read_reference_bench()
    trk = synthetic_tracker(bench, seed=1, reps=2)
    _scaled_copy(trk, tmp_path / "t_m.csv", length=1e-3)
    got = read_recording_in_units(tmp_path / "t_m.csv", "tracker", length_unit="m")
    np.testing.assert_allclose(got.cmd, trk.cmd, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(got.meas, trk.meas, rtol=1e-12)
    hall = synthetic_hall_map(read_qfdp4(), bench, seed=1, reps=2)
    _scaled_copy(hall, tmp_path / "h_g.csv", length=1 / 25.4, field=1e4)
    got = read_recording_in_units(tmp_path / "h_g.csv", "hall", length_unit="in", field_unit="G")
    np.testing.assert_allclose(got.cmd, hall.cmd, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(got.B, hall.B, rtol=1e-12)
    assert convert_recording(hall) is hall  # no unit given: as read


def test_compare_reads_a_recording_in_metres_as_the_same_one_in_mm(tmp_path):
    trk = synthetic_tracker(read_reference_bench(), seed=5, reps=3, iso_axis=None)
    write_tracker(tmp_path / "mm.csv", trk)
    _scaled_copy(trk, tmp_path / "m.csv", length=1e-3)
    common = ["compare", "--trials", "2000", "--seed", "1"]
    assert main([*common, "--tracker", str(tmp_path / "mm.csv"), "--out", str(tmp_path / "a")]) == 0
    assert main([*common, "--tracker", str(tmp_path / "m.csv"), "--recording-length-unit", "m",
                 "--out", str(tmp_path / "b")]) == 0  # fmt: skip
    a, b = (json.loads((tmp_path / d / "compare.json").read_text()) for d in "ab")
    for axis in "xyz":
        ea, eb = a["table_iv"]["experiment"][axis], b["table_iv"]["experiment"][axis]
        assert eb["std_um"] == pytest.approx(ea["std_um"], rel=1e-9, abs=1e-9)
        assert eb["systematic_um"] == pytest.approx(ea["systematic_um"], rel=1e-9, abs=1e-9)


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--recording-length-unit", "furlong"], "unknown length unit 'furlong'"),
        (["--recording-field-unit", "G"], "--recording-field-unit applies to --hall-map only"),
    ],
)
@pytest.mark.parametrize("command", ["compare", "diagnose"])
def test_bad_recording_units_exit_2(tmp_path, capsys, command, extra, message):
    write_tracker(tmp_path / "t.csv", synthetic_tracker(read_reference_bench(), reps=2))
    out = tmp_path / "o"
    assert main([command, "--tracker", str(tmp_path / "t.csv"), *extra, "--out", str(out)]) == 2
    assert message in capsys.readouterr().err
    assert not (out / "compare.json").exists() and not (out / "diagnosis.json").exists()


@pytest.mark.parametrize(
    "argv, words",
    [
        (["synth", "--help"], ["{tracker,hall}", "--seed S", "--reversal-um", "--harmonics"]),
        (["compare", "--help"], ["--recording-length-unit", "--recording-field-unit"]),
        (["diagnose", "--help"], ["--recording-length-unit", "--recording-field-unit"]),
    ],
)
def test_help_names_the_options(capsys, argv, words):
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 0
    out = capsys.readouterr().out
    assert all(w in out for w in words), out
