"""The command line and the Python API run the same orchestration: the same inputs and seed give
the same files, number for number (`scripts/compare_outputs.py` compares them, skipping run
times, paths and provenance).

Each command runs small (few trials, few points) so that each test takes seconds.
"""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest

import cfm_fem
from cfm_fem.cli import main
from cfm_fem.io.recordings import write_hall_map, write_tracker

ROOT = Path(__file__).resolve().parents[1]
HARMONICS = ROOT / "cfm_fem" / "data" / "qfdp4_harmonics.csv"


def _compare_outputs():
    spec = importlib.util.spec_from_file_location(
        "compare_outputs", ROOT / "scripts" / "compare_outputs.py"
    )
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


compare_outputs = _compare_outputs()


def assert_same_outputs(cli_dir: Path, api_dir: Path, at_least: int = 10) -> int:
    """Every number of every file the CLI wrote equals the API's; returns the count."""
    tally = compare_outputs.compare_dirs(cli_dir, api_dir)
    assert not tally.diffs, "\n".join(tally.diffs[:20])
    assert tally.files >= 1 and tally.values >= at_least, (tally.files, tally.values)
    return tally.values


class _NoFigures:
    """A report without figures: both front ends build their report through the same call,
    and the comparison reads numbers only, so the tests skip matplotlib's seconds."""

    images: dict = {}

    def render(self) -> str:
        return "<html></html>"


@pytest.fixture(autouse=True)
def no_figures(monkeypatch):
    import cfm_fem.report.kinematics
    import cfm_fem.report.quality
    import cfm_fem.report.runs
    import cfm_fem.report.sweep
    import cfm_fem.report.tolerance

    for mod, name in ((cfm_fem.report.runs, "coupled_report"),
                      (cfm_fem.report.runs, "fig4_report"),
                      (cfm_fem.report.tolerance, "tolerance_report"),
                      (cfm_fem.report.runs, "tracker_report"),
                      (cfm_fem.report.runs, "hall_report"),
                      (cfm_fem.report.kinematics, "kinematics_report"),
                      (cfm_fem.report.quality, "quality_report")):  # fmt: skip
        monkeypatch.setattr(mod, name, lambda *a, **k: _NoFigures())
    monkeypatch.setattr(cfm_fem.report.sweep, "write_sweep_report", lambda *a, **k: [])


def _cli(argv) -> None:
    assert main([str(a) for a in argv]) == 0


@pytest.fixture(scope="module")
def recordings(tmp_path_factory):
    """A small tracker recording, a Hall map of QFDp4 and a Hall map of a gridded field map
    (the map as a CSV table, the recording read from it with a gain error and noise)."""
    from cfm_fem.io.harmonics import read_qfdp4
    from cfm_fem.workflows.synthetic import synthetic_hall_map, synthetic_tracker

    d = tmp_path_factory.mktemp("recordings")
    bench = cfm_fem.read_bench()
    tracker = synthetic_tracker(bench, seed=3, reps=3, grid=(2, 2, 2), reversal_um=4.0,
                                iso_targets=3, iso_runs=2)  # fmt: skip
    write_tracker(d / "tracker.csv", tracker)
    pts = np.array([[x, 0.0, z] for x in (-6.0, -2.0, 2.0, 6.0) for z in (-40.0, 0.0, 40.0)])
    hall = synthetic_hall_map(read_qfdp4(), bench, seed=4, reps=3, points=pts)
    write_hall_map(d / "hall.csv", hall)
    # a field map: a quadrupole of 20 T/m with a sextupole, on a grid, written as a CSV table
    ax = np.linspace(-8.0, 8.0, 9)
    grid = np.stack(np.meshgrid(ax, ax, np.linspace(-50.0, 50.0, 11), indexing="ij"), -1)
    grid = grid.reshape(-1, 3)
    x, y = grid[:, 0], grid[:, 1]
    B = np.c_[0.02 * y + 1e-4 * x * y, 0.02 * x + 0.5e-4 * (x**2 - y**2), 0 * x + 1e-3]
    lines = ["x [mm],y [mm],z [mm],Bx [T],By [T],Bz [T]"]
    lines += [",".join(repr(float(v)) for v in row) for row in np.c_[grid, B]]
    (d / "map.csv").write_text("\n".join(lines) + "\n")
    rng = np.random.default_rng(5)
    cmd = hall.cmd
    b_map = np.c_[0.02 * cmd[:, 1], 0.02 * cmd[:, 0], 0 * cmd[:, 0] + 1e-3] * (1 + 3e-4)
    fem = type(hall)(**{**hall.__dict__, "B": b_map + rng.normal(0, 3e-6, b_map.shape)})
    write_hall_map(d / "hall_fem.csv", fem)
    return d


# --------------------------------------------------------------------------- diagnose


def test_diagnose_tracker_cli_equals_api(recordings, tmp_path):
    rec = recordings / "tracker.csv"
    _cli(["diagnose", "--tracker", rec, "--no-report", "--out", tmp_path / "cli"])
    run = cfm_fem.run_diagnose(rec)
    run.write(tmp_path / "api", report=False)
    assert_same_outputs(tmp_path / "cli", tmp_path / "api")
    assert (
        run.summary["fit"] == json.loads((tmp_path / "cli" / "diagnosis.json").read_text())["fit"]
    )


def test_diagnose_hall_on_harmonics_cli_equals_api(recordings, tmp_path):
    rec = recordings / "hall.csv"
    _cli(["diagnose", "--hall-map", rec, "--reference", HARMONICS, "--no-report",
          "--out", tmp_path / "cli"])  # fmt: skip
    run = cfm_fem.run_diagnose(rec)  # reference None: the same QFDp4 harmonics
    run.write(tmp_path / "api", report=False)
    assert_same_outputs(tmp_path / "cli", tmp_path / "api")


def test_diagnose_hall_on_field_map_cli_equals_api(recordings, tmp_path):
    """Against a field map the API adds the map's interpolation error to the noise, as the
    command line does, and refuses points outside the map with the same message."""
    rec, ref = recordings / "hall_fem.csv", recordings / "map.csv"
    _cli(["diagnose", "--hall-map", rec, "--reference", ref, "--no-report",
          "--out", tmp_path / "cli"])  # fmt: skip
    run = cfm_fem.run_diagnose(rec, ref)
    run.write(tmp_path / "api", report=False)
    assert_same_outputs(tmp_path / "cli", tmp_path / "api")
    assert any("nodes 2 mm apart" in n for n in run.summary["notes"]), run.summary["notes"]
    # a recording beyond the map: the same refusal from both
    far = recordings / "hall.csv"  # x up to 6 mm, z up to 40 mm: inside; move it out
    text = far.read_text().replace(",40.0,", ",90.0,")
    out_of_map = tmp_path / "far.csv"
    out_of_map.write_text(text)
    with pytest.raises(cfm_fem.CfmInputError, match="outside the reference field map"):
        cfm_fem.run_diagnose(out_of_map, ref)
    assert main(["diagnose", "--hall-map", str(out_of_map), "--reference", str(ref),
                 "--out", str(tmp_path / "no")]) == 2  # fmt: skip


def test_diagnose_api_checks_the_strokes_and_the_point_count(recordings, tmp_path):
    lines = (recordings / "tracker.csv").read_text().splitlines(keepends=True)
    header = [ln for ln in lines if ln.startswith(("#", "point_id"))]
    rows = [ln for ln in lines if ln not in header]
    few = tmp_path / "few.csv"
    few.write_text("".join(header + rows[:1]))
    with pytest.raises(cfm_fem.CfmInputError, match="the noise estimate needs repetitions"):
        cfm_fem.run_diagnose(few)
    cols = header[-1].strip().split(",")
    k = cols.index("x_cmd")
    beyond = rows[0].split(",")
    beyond[k] = "900.0"
    beyond[0] = "999"  # a point of its own
    far = tmp_path / "far.csv"
    far.write_text("".join(header + [",".join(beyond)] + rows[1:]))
    with pytest.raises(cfm_fem.CfmInputError, match="outside the strokes"):
        cfm_fem.run_diagnose(far)


# --------------------------------------------------------------------------- coupled, compare


def test_coupled_cli_equals_api(tmp_path):
    _cli(["coupled", "--trials", 200, "--step", 5, "--z", "-20,20", "--seed", 1,
          "--out", tmp_path / "cli"])  # fmt: skip
    run = cfm_fem.run_coupled(step_mm=5.0, z_mm=[-20.0, 20.0], trials=200, seed=1)
    run.write(tmp_path / "api")
    assert_same_outputs(tmp_path / "cli", tmp_path / "api", at_least=200)
    assert run.summary["field_budget"]["trials"] == 200  # the split, as the command line's


def test_coupled_on_a_field_map_cli_equals_api(recordings, tmp_path):
    ref = recordings / "map.csv"
    _cli(["coupled", "--field", ref, "--trials", 100, "--step", 3, "--z", 0, "--no-budget",
          "--centre-magnet", "--seed", 2, "--out", tmp_path / "cli"])  # fmt: skip
    run = cfm_fem.run_coupled(None, ref, step_mm=3.0, z_mm=[0.0], trials=100, seed=2,
                              budget=False, centre_magnet=True)  # fmt: skip
    run.write(tmp_path / "api")
    assert_same_outputs(tmp_path / "cli", tmp_path / "api", at_least=100)


def test_compare_tracker_cli_equals_api(recordings, tmp_path):
    rec = recordings / "tracker.csv"
    _cli(["compare", "--tracker", rec, "--trials", 300, "--tracker-u-um", 2, "--seed", 3,
          "--out", tmp_path / "cli"])  # fmt: skip
    run = cfm_fem.run_compare(rec, trials=300, seed=3, tracker_u_um=2.0)
    run.write(tmp_path / "api")
    assert_same_outputs(tmp_path / "cli", tmp_path / "api", at_least=100)
    assert run.pooled_exp["x"] == run.comparison.pooled_exp["x"]


def test_compare_hall_cli_equals_api(recordings, tmp_path):
    rec = recordings / "hall.csv"
    _cli(["compare", "--hall-map", rec, "--reference", HARMONICS, "--trials", 200, "--seed", 4,
          "--out", tmp_path / "cli"])  # fmt: skip
    run = cfm_fem.run_compare(rec, HARMONICS, trials=200, seed=4)
    run.write(tmp_path / "api")
    assert_same_outputs(tmp_path / "cli", tmp_path / "api", at_least=100)


# --------------------------------------------------------------------------- kinematics


def test_kinematics_cli_equals_api(tmp_path):
    _cli(["kinematics", "--trials", 300, "--seed", 7, "--out", tmp_path / "cli"])
    run = cfm_fem.run_kinematics(trials=300, seed=7)
    run.write(tmp_path / "api")
    n = assert_same_outputs(tmp_path / "cli", tmp_path / "api", at_least=1000)
    assert n > 936 * 3  # every point's statistics
    written = json.loads((tmp_path / "cli" / "summary.json").read_text())
    assert written["axes"]["x"]["U_p_um"] == run.axis("x")["U_p_um"]


def test_tolerance_cli_equals_api(tmp_path):
    _cli(["tolerance", "--target", "9,9,12", "--check", 200, "--seed", 4, "--out",
          tmp_path / "cli"])  # fmt: skip
    run = cfm_fem.run_tolerance([9, 9, 12], check_trials=200, seed=4)
    run.write(tmp_path / "api")
    assert_same_outputs(tmp_path / "cli", tmp_path / "api", at_least=21 * 3)
    assert cfm_fem.run_tolerance(10.0).design["target_um"] == [10.0, 10.0, 10.0]


# --------------------------------------------------------------------------- sweep, design


def test_sweep_cli_equals_api(recordings, tmp_path):
    ref = recordings / "map.csv"
    _cli(["sweep", ref, "--up", "0:20:10", "--trials", 100, "--seed", 3, "--region",
          "cylinder:6,-30:30", "--out", tmp_path / "cli"])  # fmt: skip
    maps = cfm_fem.run_sweep(ref, [0, 10, 20], trials=100, seed=3, region="cylinder:6,-30:30")
    maps.write(tmp_path / "api")
    assert_same_outputs(tmp_path / "cli", tmp_path / "api", at_least=891 * 3)


def test_sweep_by_pieces_with_a_table_cli_equals_api(recordings, tmp_path):
    ref = recordings / "map.csv"
    _cli(["sweep", ref, "--up", "5,15", "--trials", 60, "--seed", 4, "--pieces", 2,
          "--table", "csv", "--chunk-nodes", 300, "--out", tmp_path / "cli"])  # fmt: skip
    run = cfm_fem.run_sweep(ref, [5, 15], trials=60, seed=4, pieces=2, table="csv",
                            chunk_nodes=300, out_dir=tmp_path / "api")  # fmt: skip
    assert run.written == [] and (tmp_path / "api" / "nodes.csv").is_file()
    assert_same_outputs(tmp_path / "cli", tmp_path / "api", at_least=891 * 2)


def test_sweep_htm_cli_equals_api(recordings, tmp_path):
    ref = recordings / "map.csv"
    _cli(["sweep", ref, "--mode", "htm", "--trials", 40, "--seed", 5, "--out", tmp_path / "cli"])
    cfm_fem.run_sweep(ref, mode="htm", trials=40, seed=5).write(tmp_path / "api")
    assert_same_outputs(tmp_path / "cli", tmp_path / "api", at_least=891)


def test_fig4_cli_equals_api(recordings, tmp_path):
    ref = recordings / "map.csv"
    _cli(["fig4", ref, "--up", "0:20:10", "--trials", 60, "--seed", 2, "--field-model",
          "harmonic", "--out", tmp_path / "cli"])  # fmt: skip
    run = cfm_fem.run_fig4(ref, [0, 10, 20], trials=60, seed=2, field_model="harmonic")
    run.write(tmp_path / "api")
    assert_same_outputs(tmp_path / "cli", tmp_path / "api", at_least=3 * 4)


def test_design_cli_equals_api(recordings, tmp_path):
    ref = recordings / "map.csv"
    _cli(["design", ref, "--uf-max", 20, "--up", "0:20:10", "--trials", 80, "--seed", 6,
          "--region", "-4:4,-4:4,:", "--out", tmp_path / "cli"])  # fmt: skip
    run = cfm_fem.run_design(ref, 20.0, up_um=[0, 10, 20], trials=80, seed=6,
                             region="-4:4,-4:4,:")  # fmt: skip
    run.write(tmp_path / "api")
    assert_same_outputs(tmp_path / "cli", tmp_path / "api", at_least=891 * 3)
    written = json.loads((tmp_path / "cli" / "design.json").read_text())
    assert written["up_max_um"] == run.up_max_um
    again = cfm_fem.run_design(run.maps, 20.0, region="-4:4,-4:4,:", seed=6)
    assert again.up_max_um == run.up_max_um  # the question asked of the sweep alone


# --------------------------------------------------------------------------- quality


def test_quality_cli_equals_api(recordings, tmp_path):
    ref = recordings / "map.csv"
    _cli(["quality", ref, "--r-ref", 5, "--up", 10, "--trials", 20, "--no-budget", "--seed", 8,
          "--out", tmp_path / "cli"])  # fmt: skip
    run = cfm_fem.run_quality(ref, 5.0, up_um=10.0, trials=20, seed=8, budget=False)
    run.write(tmp_path / "api")
    assert_same_outputs(tmp_path / "cli", tmp_path / "api", at_least=100)


def test_quality_htm_cli_equals_api(recordings, tmp_path):
    ref = recordings / "map.csv"
    _cli(["quality", ref, "--r-ref", 5, "--trials", 20, "--no-budget", "--seed", 9,
          "--out", tmp_path / "cli"])  # fmt: skip
    run = cfm_fem.run_quality(ref, 5.0, mode="htm", trials=20, budget=False, seed=9)
    run.write(tmp_path / "api")
    assert_same_outputs(tmp_path / "cli", tmp_path / "api", at_least=100)


# --------------------------------------------------------------------------- the API's checks


@pytest.mark.parametrize(
    "call, message",
    [
        (lambda m, r: cfm_fem.run_sweep(m, [float("nan")], trials=20), "must be finite"),
        (lambda m, r: cfm_fem.run_sweep(m, [10, 10], trials=20), "10"),
        (lambda m, r: cfm_fem.run_sweep(m, bench=cfm_fem.read_bench(), trials=20), "--bench"),
        (lambda m, r: cfm_fem.run_coupled(z_mm=[float("inf")], trials=20), "--z must be"),
        (lambda m, r: cfm_fem.run_coupled(step_mm=1e-4, trials=20), "scan points"),
        (lambda m, r: cfm_fem.run_compare(r, trials=20, tracker_u_um=-1.0), "--tracker-u-um"),
        (lambda m, r: cfm_fem.run_compare(r, m, trials=20), "--reference applies"),
        (lambda m, r: cfm_fem.run_diagnose(r, b_ref_T=1.0), "--b-ref is for --hall-map"),
        (lambda m, r: cfm_fem.run_kinematics(trials=1), "--trials must be >= 2"),
        (lambda m, r: cfm_fem.run_design(m, 0.0, trials=20), "--uf-max must be > 0"),
        (lambda m, r: cfm_fem.run_tolerance(-1.0), "--target must be"),
        (lambda m, r: cfm_fem.run_tolerance(5.0, check_trials=1), "--check must be"),
        (lambda m, r: cfm_fem.run_fig4(m, [float("nan")], trials=20), "must be finite"),
    ],
)
def test_the_api_refuses_what_the_command_line_refuses(recordings, call, message):
    with pytest.raises(cfm_fem.CfmInputError, match=message):
        call(recordings / "map.csv", recordings / "tracker.csv")


# --------------------------------------------------------------------------- the comparison


def test_compare_outputs_finds_a_changed_number_and_skips_run_times(tmp_path):
    import meshio

    a, b = tmp_path / "a", tmp_path / "b"
    for d, value, seconds in ((a, 1.5, 3.0), (b, 1.5, 9.0)):
        d.mkdir()
        doc = {"x": [value, float("nan")], "seconds": seconds, "provenance": {"t": seconds}}
        (d / "s.json").write_text(json.dumps(doc).replace("NaN", "null"))
        (d / "p.csv").write_text("# comment\nname,u\nn1,0.25\nn2,\n")
        pts = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
        cells = [("tetra", np.array([[0, 1, 2, 3]]))]
        meshio.write(d / "m.vtu", meshio.Mesh(pts, cells, point_data={"U": np.arange(4.0)}))
    tally = compare_outputs.compare_dirs(a, b)
    assert not tally.diffs and tally.files == 3 and tally.values >= 4 + 2 + 2
    (b / "s.json").write_text(json.dumps({"x": [1.5000000000000002, None], "seconds": 1}))
    (b / "p.csv").write_text("name,u\nn1,0.25\nn2,7\n")
    mesh = meshio.read(b / "m.vtu")
    mesh.point_data["U"][2] += 1e-15
    meshio.write(b / "m.vtu", mesh)
    (b / "extra.json").write_text("{}")
    diffs = "\n".join(compare_outputs.compare_dirs(a, b).diffs)
    assert "s.json.x[0]: 1.5 vs 1.5000000000000002" in diffs
    assert "p.csv column 'u' row 2" in diffs
    assert "m.vtu: point data 'U' differs" in diffs
    assert "extra.json: only in the new run" in diffs
    assert "seconds" not in diffs and "provenance" not in diffs
