"""The bad-input catalogue, every case through the command line.

Each case must end in exit code 2, one message on stderr naming the file (and the line and
column where there is one) and what was expected, no traceback, and no output folder.

Cases already written elsewhere are referenced, not copied: the reader cases of
`tests/test_io_bad_input.py` (``CASES``), the sweep cases of `tests/test_cli_sweep.py` and the
bench cases of `tests/test_bench.py` (their ``parametrize`` lists) all run here through the CLI.

| catalogue entry                              | where the case is written                       |
|----------------------------------------------|-------------------------------------------------|
| empty file, header only, truncated last line | test_io_bad_input.CASES                         |
| text in a numeric column, NaN or inf         | test_io_bad_input.CASES                         |
| unknown unit, mixed units                    | test_io_bad_input.CASES                         |
| duplicate nodes, fields disagree             | test_io_bad_input.CASES, test_cli_sweep         |
| duplicate nodes, identical (merged, warning) | here                                            |
| collinear nodes; coplanar (a planar map)     | test_cli_sweep; here                            |
| a single node                                | here                                            |
| map smaller than U_p, enormous U_p           | here                                            |
| bench: unknown keys, negative std, bad PDF   | here (and all of test_bench's list)             |
| recordings: missing column, repeated rows    | here (``cfm-fem compare``, else the readers)    |
| Hall map outside the reference field         | here (``cfm-fem compare``, else skipped)        |
"""

from __future__ import annotations

import json
import re
from importlib import resources
from pathlib import Path

import numpy as np
import pytest
import test_bench
import test_cli_sweep
import test_io_bad_input

import cfm_fem.io.recordings as recordings_io
from cfm_fem.cli import _COMMANDS, main
from cfm_fem.errors import CfmInputError
from cfm_fem.io.lock import LOCK_NAME


def _parametrized(func):
    """The argument list of a test's ``pytest.mark.parametrize``."""
    (mark,) = [m for m in func.pytestmark if m.name == "parametrize"]
    return list(mark.args[1])


def _run(argv, out, capsys):
    """Run the CLI; return (exit code, stderr) and check the common promises of a bad input."""
    rc = main([str(a) for a in argv])
    err = capsys.readouterr().err
    assert rc == 2, err
    assert "Traceback" not in err
    assert err.count("cfm-fem: error:") == 1, err
    assert not out.exists(), "an output was written for a bad input"
    return err


GRID = np.stack(np.meshgrid(*[np.arange(6.0)] * 3, indexing="ij"), -1).reshape(-1, 3)


def _map_text(points, B=None):
    B = np.c_[0.1 * points[:, 1], 0.1 * points[:, 0], np.ones(len(points))] if B is None else B
    rows = "".join(",".join(f"{v:.17g}" for v in r) + "\n" for r in np.c_[points, B])
    return test_io_bad_input.CSV_HEADER + rows


# --------------------------------------------------------------------------- field maps


@pytest.mark.parametrize("case", list(test_io_bad_input.CASES))
def test_reader_case_through_cli(tmp_path, capsys, case):
    name, text, line, column, what = test_io_bad_input.CASES[case]
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    out = tmp_path / "out"
    err = _run(["sweep", path, "--trials", 50, "--out", out], out, capsys)
    prefix = f"{path}:{line}: " if line is not None else f"{path}: "
    assert f"cfm-fem: error: {prefix}" in err and what in err, err
    if column is not None:
        assert column in err


@pytest.mark.parametrize(
    "last, what",
    [
        ("5,5,5,nan,0,1", "must be a finite number; found nan"),
        ("5,5,5", "is missing (truncated line?)"),
        ("5,5,5,abc,0,1", "must be a number; found 'abc'"),
        ("0,1,0,0.9,0.9,0.9", "duplicate node at [0.0, 1.0, 0.0] mm"),
    ],
)
def test_slabs_bad_input_leaves_no_folder(tmp_path, capsys, last, what):
    # the streaming path made --out before it found the bad row
    lines = _map_text(GRID).splitlines()
    lines[-1] = last
    path = tmp_path / "m.csv"
    path.write_text("\n".join(lines) + "\n")
    out = tmp_path / "out"
    argv = ["sweep", path, "--up", "0:10:10", "--trials", 20, "--slabs", 2, "--out", out]
    err = _run(argv, out, capsys)
    assert what in err, err


@pytest.mark.parametrize(
    "name, text, message", _parametrized(test_cli_sweep.test_bad_input_exit_2_and_nothing_written)
)
def test_sweep_case_through_cli(tmp_path, capsys, name, text, message):
    path = tmp_path / name
    path.write_text(text)
    out = tmp_path / "out"
    err = _run(["sweep", path, "--trials", 50, "--out", out], out, capsys)
    assert f"error: {path}" in err and message in err


SWEEP_CASES = {
    "a single node": (
        _map_text(GRID[:1]),
        [],
        "the map has 1 node(s); expected at least 4 non-coplanar nodes",
    ),
    "two nodes": (_map_text(GRID[:2]), [], "the map has 2 node(s)"),
    "collinear nodes": (
        _map_text(np.c_[np.arange(5.0), np.zeros(5), np.zeros(5)]),
        [],
        "collinear",
    ),
    "map smaller than U_p": (
        _map_text(GRID),
        ["--up", "0:3000:1000"],
        "U_p of 3000 um is too large for this map: 5 U_p exceeds its smallest extent of 5 mm",
    ),
    "enormous U_p": (_map_text(GRID), ["--up", "1e300"], "U_p of 1e+300 um is too large"),
}


@pytest.mark.parametrize("case", list(SWEEP_CASES))
def test_map_case(tmp_path, capsys, case):
    text, extra, what = SWEEP_CASES[case]
    path = tmp_path / "map.csv"
    path.write_text(text)
    out = tmp_path / "out"
    err = _run(["sweep", path, "--trials", 50, *extra, "--out", out], out, capsys)
    assert f"error: {path}: " in err and what in err, err


@pytest.mark.parametrize(
    "up, what",
    [
        ("1e999", "--up values must be finite and >= 0 um"),
        ("0:1e12:1", "asks for 1e+12 U_p values; expected at most 1000"),
        ("-5", "--up values must be finite and >= 0 um"),
        ("0:50", "--up must be START:STOP:STEP"),
    ],
)
def test_impossible_up(tmp_path, capsys, up, what):
    path = tmp_path / "map.csv"
    path.write_text(_map_text(GRID))
    out = tmp_path / "out"
    err = _run(["sweep", path, "--up", up, "--out", out], out, capsys)
    assert what in err


def test_identical_duplicate_nodes_are_merged_with_a_warning(tmp_path, capsys):
    path = tmp_path / "map.csv"
    path.write_text(_map_text(np.r_[GRID, GRID[7:9]]))
    out = tmp_path / "out"
    assert main(["sweep", str(path), "--up", "10", "--trials", "50", "--out", str(out)]) == 0
    err = capsys.readouterr().err
    assert f"warning: {path}: merged 2 duplicate node(s) with identical position and field" in err


def test_coplanar_nodes_make_a_planar_map(tmp_path, capsys):
    """Coplanar nodes are a mid-plane export, not an error: triangulated in their plane, and the
    outputs say that the out-of-plane part of U_p is not covered."""
    pts = GRID[GRID[:, 2] == 0.0]
    path = tmp_path / "map.csv"
    path.write_text(_map_text(pts))
    out = tmp_path / "out"
    assert main(["sweep", str(path), "--up", "10", "--trials", "50", "--out", str(out)]) == 0
    assert "out-of-plane component of U_p is not covered" in capsys.readouterr().out


# --------------------------------------------------------------------------- bench files


def _ref_bench_text():
    return resources.files("cfm_fem.data").joinpath("cfm_reference_bench.toml").read_text()


BENCH_CASES = [
    ("unknown key", "stroke_mm = 150.0\nmount", "stroke_mm = 150.0\nstrok_mm = 3\nmount",
     ["'axes.x.strok_mm'", "not a known key"]),
    ("negative std", "mean = 5.5\nstd = 7.8", "mean = 5.5\nstd = -7.8",
     ["errors.z.delta_x", "std >= 0"]),
    ("unknown pdf", 'pdf = "uniform"\nlow = -18.5', 'pdf = "cauchy"\nlow = -18.5',
     ["errors.x.eps_x.pdf", "one of"]),
    # a table named only inside a longer header had no line: "bench.toml: 'errors.w' is ..."
    ("unknown error group", "[errors.z.delta_y]", "[errors.w.delta_y]",
     ["'errors.w' is not a known key; expected one of squareness, x, y, z"]),
    # integers too large for a float (TypeError in numpy's isfinite before)
    ("400-digit stroke", "stroke_mm = 800.0", "stroke_mm = " + "9" * 400,
     ["axes.z.stroke_mm", "must be a finite number", "(400 characters)"]),
    ("400-digit tool offset", "tool_offset_mm = [0.0, -60.0, 500.0]",
     "tool_offset_mm = [0.0, -60.0, " + "9" * 400 + "]",
     ["frame.tool_offset_mm", "must be a list of 3 finite numbers"]),
    # sizes without a limit (MemoryError or an endless run before)
    ("huge grid num", "stop = 800.0, num = 13", "stop = 800.0, num = 100000000",
     ["grid.z_mm.num", "must be >= 1 and <= 100,000"]),
    ("huge grid", "stop = 800.0, num = 13", "stop = 800.0, num = 90000",
     ["'grid' has 6,480,000 points; expected at most 100,000"]),
    ("huge std", "mean = 51.4\nstd = 11.0", "mean = 51.4\nstd = 1e300",
     ["describes errors up to", "expected at most 1 "]),
    ("huge vibration", "std_um = 2.5", "std_um = 1e300",
     ["vibration.std_um", "must be <= 1e+06 um"]),
] + [
    (f"test_bench: {new.splitlines()[0][:30]}", old, new, fragments)
    for old, new, fragments in _parametrized(test_bench.test_impossible_values_name_the_key)
]  # fmt: skip


@pytest.mark.parametrize("case, old, new, fragments", BENCH_CASES, ids=[c[0] for c in BENCH_CASES])
def test_bench_case_through_cli(tmp_path, capsys, case, old, new, fragments):
    text = _ref_bench_text()
    assert old in text, f"the case edits {old!r}, which the reference bench must contain"
    path = tmp_path / "bench.toml"
    path.write_text(text.replace(old, new, 1))
    out = tmp_path / "out"
    err = _run(["kinematics", "--bench", path, "--trials", 100, "--out", out], out, capsys)
    assert re.search(rf"error: {re.escape(str(path))}:\d+: ", err), err
    for f in fragments:
        assert f in err


# --------------------------------------------------------------------------- recordings

TRACKER_HEAD = "point_id,rep,x_cmd,y_cmd,z_cmd,x_meas,y_meas,z_meas\n"
RECORDING_CASES = {
    "missing required column": (
        "tracker",
        "point_id,rep,x_cmd,y_cmd,z_cmd,x_meas,y_meas\n1,0,0,0,0,0,0\n",
        1,
        "column 'z_meas' is missing; a laser-tracker recording needs the columns",
    ),
    "repeated (point_id, rep)": (
        "tracker",
        "# comment\n" + TRACKER_HEAD + "1,0,0,0,0,0,0,0\n2,0,1,0,0,1,0,0\n1,0,0,0,0,0,0,0\n",
        5,
        "(point_id, rep) = (1, 0) appears twice (lines 3 and 5); expected one row per point",
    ),
    "hall map missing Bz": (
        "hall",
        "point_id,rep,x_cmd,y_cmd,z_cmd,Bx,By\n1,0,0,0,0,0,0\n",
        1,
        "column 'Bz' is missing",
    ),
}


@pytest.mark.parametrize("case", list(RECORDING_CASES))
def test_recording_case(tmp_path, capsys, case):
    kind, text, line, what = RECORDING_CASES[case]
    path = tmp_path / "rec.csv"
    path.write_text(text)
    out = tmp_path / "out"
    if kind == "tracker":
        err = _run(["compare", "--tracker", path, "--out", out], out, capsys)
        assert f"error: {path}:{line}: " in err and what in err, err
        return
    reader = recordings_io.read_tracker if kind == "tracker" else recordings_io.read_hall_map
    with pytest.raises(CfmInputError) as info:
        reader(path)
    assert str(info.value).startswith(f"{path}:{line}: ") and what in str(info.value)


@pytest.mark.slow
def test_hall_map_outside_the_reference_field(tmp_path, capsys):
    ref = tmp_path / "ref.csv"
    ref.write_text(_map_text(GRID))
    rec = tmp_path / "hall.csv"
    rec.write_text(
        "point_id,rep,x_cmd,y_cmd,z_cmd,Bx,By,Bz\n"
        "1,0,1,1,1,0.1,0.1,1\n2,0,2,2,2,0.2,0.2,1\n3,0,90,2,2,0.2,0.2,1\n"
    )
    out = tmp_path / "out"
    argv = ["compare", "--hall-map", rec, "--reference", ref, "--trials", 100, "--out", out]
    err = _run(argv, out, capsys)
    assert f"error: {rec}:4: " in err and "outside the reference field" in err, err


def _hall_text(factor):
    """A Hall map of GRID points 1..3 (two readings each) recording `_map_text`'s field x factor."""
    rows = ["point_id,rep,x_cmd,y_cmd,z_cmd,Bx,By,Bz"]
    for pid, p in enumerate(GRID[[43, 86, 129]]):
        B = factor * np.array([0.1 * p[1], 0.1 * p[0], 1.0])
        rows += [f"{pid},{rep}," + ",".join(f"{v:g}" for v in (*p, *B)) for rep in (0, 1)]
    return "\n".join(rows) + "\n"


@pytest.mark.parametrize("command", ["compare", "diagnose"])
def test_hall_map_in_gauss_is_refused(tmp_path, capsys, command):
    """A Hall map in gauss (values ~1e4 times the reference in T) is refused, not compared."""
    ref = tmp_path / "ref.csv"
    ref.write_text(_map_text(GRID))
    rec = tmp_path / "hall.csv"
    rec.write_text(_hall_text(1e4))
    out = tmp_path / "out"
    argv = [command, "--hall-map", rec, "--reference", ref, "--out", out]
    err = _run(argv + (["--trials", 100] if command == "compare" else []), out, capsys)
    assert f"error: {rec}: the recorded |B| is 1e+04 times the reference |B|" in err, err
    assert "look like G (gauss), not T" in err


def test_hall_scale_check():
    from cfm_fem.models.recordings import check_hall_scale

    ref = np.array([[0.0, 0.0, 1.0], [0.5, 0.0, 0.0], [0.0, 1e-6, 0.0]])
    assert check_hall_scale(ref * 1.01, ref, source="h.csv") == []
    for factor, what in [(1e3, "look like mT"), (10, "look like kG"), (1e-4, "1e4 times too")]:
        with pytest.raises(CfmInputError, match=what):
            check_hall_scale(ref * factor, ref, source="h.csv")
    with pytest.warns(match=r"h.csv: the recorded \|B\| is 3 times"):
        (note,) = check_hall_scale(ref * 3, ref, source="h.csv")
    assert "check the units" in note


# --------------------------------------------------------------------------- options

OUT_FILE_COMMANDS = {
    "sweep": ["sweep", "{map}", "--trials", 20],
    "kinematics": ["kinematics", "--trials", 20],
    "tolerance": ["tolerance", "--target", 5],
    "fig4": ["fig4", "{map}", "--trials", 20, "--up", "0:1:1"],
    "diagnose": ["diagnose", "--tracker", "{map}"],
    "compare": ["compare", "--tracker", "{map}", "--trials", 20],
    "coupled": ["coupled", "--trials", 20, "--no-budget"],
}


@pytest.mark.parametrize("command", list(OUT_FILE_COMMANDS))
def test_out_is_an_existing_file(tmp_path, capsys, command):
    """--out naming a file is refused before any computation, without a traceback."""
    path = tmp_path / "map.csv"
    path.write_text(_map_text(GRID))
    out = tmp_path / "afile"
    out.write_text("keep me")
    argv = [str(a).replace("{map}", str(path)) for a in OUT_FILE_COMMANDS[command]]
    rc = main([*argv, "--out", str(out)])
    err = capsys.readouterr().err
    assert rc == 2 and "Traceback" not in err, err
    assert f"error: --out '{out}' is an existing file; expected a folder" in err
    assert out.read_text() == "keep me"


@pytest.mark.parametrize("command", ["sweep", "fig4"])
@pytest.mark.parametrize("seed", [2**63, -1])
def test_seed_out_of_range(tmp_path, capsys, command, seed):
    """A seed >= 2**63 ended in numba's TypingError and left sweep's chunk manifest behind."""
    path = tmp_path / "map.csv"
    path.write_text(_map_text(GRID))
    out = tmp_path / "out"
    argv = [command, path, "--up", "0:10:10", "--trials", 20, "--seed", seed, "--out", out]
    err = _run(argv, out, capsys)
    assert f"error: --seed must be in [0, 2**63); got {seed}" in err


def _zero_bench_text():
    """The reference bench with every error N(0, 0) and no vibration or reading delay."""
    lines = []
    for line in _ref_bench_text().splitlines():
        key = line.split("=")[0].strip()
        if key == "pdf":
            lines += ['pdf = "normal"', "mean = 0.0", "std = 0.0"]
        elif key in ("low", "high", "mean", "std", "mode", "beta", "value"):
            continue
        else:
            lines.append("std_um = 0.0" if key == "std_um" else line)
    return "\n".join(lines) + "\n"


@pytest.mark.slow
def test_bench_without_errors(tmp_path, capsys):
    """A bench with every error zero runs: kinematics says U_p = 0 in a note instead of budget
    shares of 0/0 and writes every output; tolerance gives the common factor 'inf'."""
    bench = tmp_path / "zero.toml"
    bench.write_text(_zero_bench_text())
    out = tmp_path / "k"
    assert main(["kinematics", "--bench", str(bench), "--trials", "20", "--out", str(out)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["axes"]["x"]["U_p_um"] == 0.0
    assert "U_p = 0 on axis x" in summary["budget"]["notes"][0]
    assert sorted(p.name for p in out.iterdir()) == [
        LOCK_NAME,
        "fig10.png",
        "points.csv",
        "points.vtu",
        "report.html",
        "summary.json",
    ]
    out = tmp_path / "t"
    assert main(["tolerance", "--target", "5", "--bench", str(bench), "--out", str(out)]) == 0
    assert json.loads((out / "tolerance.json").read_text())["common_factor"] == "inf"
    capsys.readouterr()


def test_kinematics_outputs_all_or_none(tmp_path, monkeypatch):
    """A failing summary.json leaves no points.csv / points.vtu behind."""
    from cfm_fem.io import kinematics_out

    def fail(*args, **kwargs):
        raise RuntimeError("disk full")

    monkeypatch.setattr(kinematics_out, "write_points_vtu", fail)
    out = tmp_path / "k"
    with pytest.raises(RuntimeError, match="disk full"):
        main(["kinematics", "--trials", "20", "--out", str(out)])
    assert not out.exists() or not list(out.iterdir())


@pytest.mark.parametrize("target", ["1e300", "5,5,2e6"])
def test_tolerance_target_too_large(tmp_path, capsys, target):
    out = tmp_path / "out"
    err = _run(["tolerance", "--target", target, "--out", out], out, capsys)
    assert "--target must be at most 1e+06 um (1 m) per axis" in err


@pytest.mark.parametrize("target", ["inf", "5,nan,5", "1e999"])
def test_tolerance_target_not_finite(tmp_path, capsys, target):
    out = tmp_path / "out"
    err = _run(["tolerance", "--target", target, "--out", out], out, capsys)
    assert "argument --target: must be 1 or 3 comma-separated finite numbers in um" in err


def test_fig4_on_a_uniform_field(tmp_path, capsys):
    """G = 0: r_eff = B_ref / G ended fig4 in a ZeroDivisionError after the whole sweep."""
    path = tmp_path / "map.csv"
    path.write_text(_map_text(GRID, np.tile([0.1, 0.2, 0.3], (len(GRID), 1))))
    out = tmp_path / "out"
    argv = ["fig4", path, "--trials", 20, "--up", "0:10:10", "--out", out]
    assert main([str(a) for a in argv]) == 0, capsys.readouterr().err
    doc = json.loads((out / "fig4.json").read_text())
    assert doc["r_eff_mm"] is None and doc["g_med_T_per_mm"] == 0.0
    assert "r_eff is undefined" in doc["explanation"]


@pytest.mark.filterwarnings("ignore::RuntimeWarning")  # numpy's overflow on the way there
def test_kinematics_refuses_non_finite_positions():
    """std = 1e300 um (past the reader's limits here) kept `while np.any(slot < 0)` going for ever
    on NaN positions; now a clear error after the first pass."""
    import dataclasses

    from cfm_fem.io.bench_toml import read_reference_bench
    from cfm_fem.models.kinematics.monte_carlo import run_kinematics
    from cfm_fem.models.mc import Pdf

    bench = read_reference_bench()
    errors = list(bench.errors)
    errors[0] = dataclasses.replace(errors[0], pdf=Pdf.from_params("normal", mean=0.0, std=1e300))
    bench = dataclasses.replace(bench, errors=tuple(errors))
    with pytest.raises(CfmInputError, match="infinite or NaN probe positions"):
        run_kinematics(bench, trials=50, seed=0)


def test_coupled_step_in_metres(tmp_path, capsys):
    """--step 0.002 (metres typed as mm) asked for 78.5 million points: MemoryError."""
    out = tmp_path / "out"
    err = _run(
        ["coupled", "--step", 0.002, "--trials", 20, "--no-budget", "--out", out], out, capsys
    )
    assert "asks for about 3.93e+08 scan points; expected at most 100,000" in err


def test_harmonic_order_too_high(tmp_path, capsys):
    """A harmonic order above the readable maximum is refused when the file is read."""
    rows = "".join(f"{n},{1.0 if n == 2 else 1e-3},0\n" for n in range(1, 5))
    path = tmp_path / "h.csv"
    path.write_text(f"# r_ref_mm: 10\n# convention: tesla\nn,Bn,An\n{rows}100000000,1e-3,0\n")
    out = tmp_path / "out"
    err = _run(
        ["coupled", "--field", path, "--trials", 20, "--no-budget", "--out", out], out, capsys
    )
    assert f"error: {path}:8: column 'n' must be an order <= 1000; found '100000000'" in err


@pytest.mark.parametrize(
    "argv, dest, value",
    [
        (["coupled", "--z", "-100,0,100", "--out", "o"], "z", "-100,0,100"),  # the help's form
        (["sweep", "m.csv", "--up", "-10:50:10", "--out", "o"], "up", "-10:50:10"),
        (["sweep", "m.csv", "--axis-scale", "-1,1,1", "--out", "o"], "axis_scale", (-1, 1, 1)),
    ],
)
def test_values_that_start_with_a_minus_sign_are_values(argv, dest, value):
    """A value such as '-100,0,100' after an option is its value, not another option."""
    from cfm_fem.cli import build_parser

    assert tuple(np.atleast_1d(getattr(build_parser().parse_args(argv), dest))) == (
        value if isinstance(value, tuple) else (value,)
    )


def test_negative_target_says_why(capsys):
    assert main(["tolerance", "--target", "-5,5,5"]) == 2
    err = capsys.readouterr().err
    assert "--target: must be one or three positive numbers in um; got '-5,5,5'" in err, err


def test_negative_up_range_says_why(tmp_path, capsys):
    path = tmp_path / "map.csv"
    path.write_text(_map_text(GRID))
    out = tmp_path / "out"
    err = _run(["sweep", path, "--up", "-10:50:10", "--out", out], out, capsys)
    assert "--up values must be finite and >= 0 um; got '-10:50:10'" in err, err


@pytest.mark.parametrize("name", ["maps", "map.table", "map.csv", "map.vtu"])
@pytest.mark.parametrize("extra", [[], ["--slabs", 2]])
def test_field_is_a_folder(tmp_path, capsys, name, extra):
    """A folder given as the field map is named as a folder, with or without --slabs."""
    folder = tmp_path / name
    folder.mkdir()
    out = tmp_path / "out"
    err = _run(["sweep", folder, "--trials", 20, *extra, "--out", out], out, capsys)
    assert f"error: {folder}: " in err, err
    assert "this is a folder; expected a field-map file" in err or "Is a directory" in err, err


def test_missing_field_without_extension(tmp_path, capsys):
    """A missing file without an extension is reported as missing."""
    path = tmp_path / "quadrupole"
    out = tmp_path / "out"
    err = _run(["sweep", path, "--trials", 20, "--out", out], out, capsys)
    assert f"error: {path}: cannot read the file: it does not exist" in err, err


def test_hashing_an_unreadable_input_is_a_bad_input(tmp_path):
    """The out-of-core sweep hashes its input before reading it: a PermissionError traceback
    (exit 1) for a file without read permission."""
    from cfm_fem.io.provenance import file_sha256

    with pytest.raises(CfmInputError, match=r"this is a folder"):
        file_sha256(tmp_path)


@pytest.mark.parametrize("command", ["sweep", "fig4"])
@pytest.mark.parametrize("up", ["0,10,10", "10,10.0000001"])
def test_up_values_that_name_the_same_map(tmp_path, capsys, command, up):
    """U_p values that would name the same map (--up 0,10,10) are refused."""
    path = tmp_path / "map.csv"
    path.write_text(_map_text(GRID))
    out = tmp_path / "out"
    err = _run([command, path, "--up", up, "--trials", 20, "--out", out], out, capsys)
    assert "--up: U_p = 10 um appears twice" in err and "uf_up10um.vtu" in err, err


def test_up_values_that_name_the_same_map_from_python():
    from cfm_fem.models.field import FieldMap
    from cfm_fem.models.sweep import SweepConfig
    from cfm_fem.workflows.sweep.in_memory import run_sweep

    fm = FieldMap(GRID, np.c_[0.1 * GRID[:, 1], 0.1 * GRID[:, 0], np.ones(len(GRID))])
    with pytest.raises(CfmInputError, match=r"up_um: U_p = 10 um appears twice"):
        run_sweep(fm, SweepConfig(up_um=[10.0, 10.0], trials=20))


@pytest.mark.parametrize("command", _COMMANDS)
def test_help_cites_no_file_outside_the_project(capsys, command):
    """compare's and diagnose's --help sent the user to DESIGN.md, which is not shipped."""
    with pytest.raises(SystemExit):
        main([command, "--help"])
    text = capsys.readouterr().out
    assert "DESIGN.md" not in text
    if command == "compare":  # the columns a recording needs, as diagnose --help gives them
        assert "point_id,rep,x_cmd,y_cmd,z_cmd,x_meas,y_meas,z_meas" in text.replace("\n", "")


def test_the_repository_cites_no_design_notes_outside_it():
    """scripts/make_default_mesh.py, scripts/reproduce_paper.py and tests/test_recordings_io.py
    cited DESIGN.md, a file a clone of the repository does not have: the facts they pointed to
    are stated in place. (This file names it only to guard against it.)"""
    root = Path(__file__).resolve().parents[1]
    files = [
        *root.glob("cfm_fem/**/*.py"),
        *root.glob("cfm_fem/data/*"),
        *root.glob("scripts/*.py"),
        *root.glob("tests/*.py"),
        *root.glob("docs/*.md"),
        *root.glob("*.md"),
        *root.glob("meshes/*.md"),
        root / "pyproject.toml",
    ]
    citing = [
        f.relative_to(root).as_posix()
        for f in files
        if f.is_file()
        and f.name != Path(__file__).name
        and "DESIGN.md" in f.read_text(encoding="utf-8", errors="replace")
    ]
    assert len(files) > 100 and citing == []


@pytest.mark.parametrize(
    "extra, what",
    [
        (["--up", "0:10:10"], "--up is used by --mode gauss only"),
        (["--axis-scale", "1,1,2"], "--axis-scale is used by --mode gauss only"),
        (["--up", "5", "--axis-scale", "2"], "--up and --axis-scale are used by --mode gauss only"),
    ],
)
def test_gauss_options_in_mode_htm(tmp_path, capsys, extra, what):
    """Options of mode gauss (--up, --axis-scale) are refused in mode htm, as --bench is in
    mode gauss (C9)."""
    path = tmp_path / "map.csv"
    path.write_text(_map_text(GRID))
    out = tmp_path / "out"
    err = _run(["sweep", path, "--mode", "htm", "--trials", 20, *extra, "--out", out], out, capsys)
    assert what in err, err


def test_format_help_names_the_formats(capsys):
    """sweep --help said only 'input format if the extension is ambiguous': no value named."""
    from cfm_fem.io import _TEXT_READERS

    with pytest.raises(SystemExit):
        main(["sweep", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    help_fmt = text[text.index("--format FMT input format") :][:200]
    for name in [*_TEXT_READERS, "vtu", "gmsh"]:
        assert name in help_fmt, help_fmt
