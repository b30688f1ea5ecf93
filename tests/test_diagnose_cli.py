"""cfm-fem diagnose end to end: files in the 4.2 contract, diagnosis.json per 4.3, exit codes."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest

from cfm_fem.cli import main
from cfm_fem.io.lock import LOCK_NAME
from cfm_fem.io.recordings import write_hall_map, write_tracker
from cfm_fem.workflows.diagnose.twin import hall_twin, tracker_twin

Q = np.stack(
    np.meshgrid(
        np.linspace(0, 150, 4), np.linspace(0, 150, 3), np.linspace(0, 800, 5), indexing="ij"
    ),
    -1,
).reshape(-1, 3)


@pytest.mark.slow
def test_cli_tracker(tmp_path, capsys):
    rec, _ = tracker_twin(3, {"reversal": {"backlash_z": 10.0}}, n_reps=6, points=Q)
    f = tmp_path / "rec.csv"
    write_tracker(f, rec)
    out = tmp_path / "diag"
    assert main(["diagnose", "--tracker", str(f), "--out", str(out)]) == 0
    # the closing line names every file written, no more, no fewer
    wrote = [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("wrote ")]
    assert len(wrote) == 1
    named = sorted(Path(p).name for p in wrote[0].removeprefix("wrote ").split(", "))
    assert named == sorted(p.name for p in out.iterdir() if p.name != LOCK_NAME)  # not output
    assert {"residual_rows.vtu", "fit.png", "residuals.png", "diagnosis.json"} <= set(named)
    d = json.loads((out / "diagnosis.json").read_text())
    assert set(d) >= {"mismatch", "located", "effects", "fit", "advice"}
    assert d["mismatch"] is True and d["effects"][0]["name"] == "reversal"
    e = d["effects"][0]
    assert {"name", "params", "param_std", "delta_bic", "cv_rms_before", "cv_rms_after"} <= set(e)
    for k in ("rms_before", "rms_after", "chi2_dof_before", "chi2_dof_after"):
        assert np.isfinite(d["fit"][k])
    for name in ("report.html", "fit.png", "residuals.png", "residual_points.vtu"):
        assert (out / name).stat().st_size > 0
    html = (out / "report.html").read_text()
    assert "<h3>reversal" in html and 'data-file="fit.png"' in html
    assert d["provenance"]["inputs"]["tracker"]["sha256"] in html
    # what produced it, as every other command records it: the recording and the packaged bench
    inputs = d["provenance"]["inputs"]
    assert inputs["tracker"]["sha256"] == hashlib.sha256(f.read_bytes()).hexdigest()
    assert inputs["bench"]["packaged_default"] is True and len(inputs["bench"]["sha256"]) == 64
    assert d["provenance"]["command_line"].startswith("cfm-fem diagnose --tracker")


def test_cli_no_report_writes_the_diagnosis_and_maps_only(tmp_path):
    rec, _ = tracker_twin(4, {}, n_reps=4, points=Q)
    f = tmp_path / "rec.csv"
    write_tracker(f, rec)
    out = tmp_path / "diag"
    assert main(["diagnose", "--tracker", str(f), "--no-report", "--out", str(out)]) == 0
    names = {p.name for p in out.iterdir()} - {LOCK_NAME}
    assert names == {"diagnosis.json", "residual_points.vtu", "residual_rows.vtu"}


@pytest.mark.parametrize(
    "args",
    [
        ["--hall-map", "x.csv", "--out", "o"],  # no reference
        ["--tracker", "missing.csv", "--out", "o"],
    ],
)
def test_cli_bad_input(tmp_path, args, capsys):
    out = tmp_path / "o"
    args = [a if a != "o" else str(out) for a in args]
    assert main(["diagnose", *args]) == 2
    assert not out.exists() or not any(Path(out).iterdir())


def test_cli_bad_column(tmp_path):
    f = tmp_path / "bad.csv"
    f.write_text("point_id,rep,x_cmd,y_cmd,z_cmd,x_meas,y_meas\n0,0,1,2,3,4,5\n")
    assert main(["diagnose", "--tracker", str(f), "--out", str(tmp_path / "o")]) == 2
    assert not (tmp_path / "o" / "diagnosis.json").exists()


HALL_HEAD = "point_id,rep,x_cmd,y_cmd,z_cmd,Bx,By,Bz\n"


def _hall(tmp_path, rows):
    f = tmp_path / "hall.csv"
    f.write_text(HALL_HEAD + "".join(rows))
    return f


def _err(argv, out, capsys):
    assert main([str(a) for a in argv]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and not out.exists(), err
    return err


def test_broken_harmonics_reference_reports_its_own_error(tmp_path, capsys):
    from importlib import resources

    text = (resources.files("cfm_fem") / "data" / "qfdp4_harmonics.csv").read_text()
    lines = text.splitlines(keepends=True)
    i = next(k for k, s in enumerate(lines) if s.startswith("3,"))
    lines[i] = "3,abc,0\n"
    ref = tmp_path / "h.csv"
    ref.write_text("".join(lines))
    rec = _hall(tmp_path, ["1,0,0,0,0,0,0,0\n", "1,1,0,0,0,0,0,0\n"])
    out = tmp_path / "o"
    err = _err(["diagnose", "--hall-map", rec, "--reference", ref, "--out", out], out, capsys)
    assert f"{ref}:{i + 1}: column 'Bn' must be a number; found 'abc'" in err, err


def test_hall_map_outside_reference_names_line_and_point(tmp_path, capsys):
    grid = np.stack(np.meshgrid(*[np.arange(4.0)] * 3, indexing="ij"), -1).reshape(-1, 3)
    ref = tmp_path / "ref.csv"
    ref.write_text(
        "x [mm],y [mm],z [mm],Bx [T],By [T],Bz [T]\n"
        + "".join(f"{x},{y},{z},0,0,1\n" for x, y, z in grid)
    )
    rows = [f"{p},{r},{x},1,1,0,0,1\n" for p, x in enumerate([1, 2, 9]) for r in range(3)]
    rec = _hall(tmp_path, rows)
    out = tmp_path / "o"
    err = _err(["diagnose", "--hall-map", rec, "--reference", ref, "--out", out], out, capsys)
    assert f"{rec}:8: commanded point [9.0, 1.0, 1.0] mm is outside" in err, err
    assert "(1 of 3 points outside, 3 of 9 rows)" in err, err


@pytest.mark.parametrize("n", [1, 2])
def test_too_few_tracker_rows_are_refused(tmp_path, capsys, n):
    f = tmp_path / "rec.csv"
    rows = "".join(f"{i},1,0,0,{i},0,-60,{500 + i}\n" for i in range(n))
    f.write_text("point_id,rep,x_cmd,y_cmd,z_cmd,x_meas,y_meas,z_meas\n" + rows)
    out = tmp_path / "o"
    err = _err(["diagnose", "--tracker", f, "--out", out], out, capsys)
    assert f"error: {f}: no point has two or more repetitions" in err, err
    assert "warning" not in err


def test_b_ref_with_tracker_is_refused(tmp_path, capsys):
    out = tmp_path / "o"
    err = _err(["diagnose", "--tracker", "x.csv", "--b-ref", "1", "--out", out], out, capsys)
    assert "--b-ref is for --hall-map only" in err, err


@pytest.mark.slow
def test_r_ref_for_a_harmonics_reference_that_does_not_state_it(tmp_path, capsys):
    """The harmonics reader asks for --r-ref when the file gives no R_ref; diagnose had none."""
    from importlib import resources

    text = (resources.files("cfm_fem") / "data" / "qfdp4_harmonics.csv").read_text()
    ref = tmp_path / "h.csv"
    ref.write_text("".join(s for s in text.splitlines(True) if not s.startswith("# r_ref_mm")))
    rec, _, _ = hall_twin(3, {}, n_reps=3)
    f = tmp_path / "rec.csv"
    write_hall_map(f, rec)
    base = ["diagnose", "--hall-map", f, "--reference", ref]
    err = _err([*base, "--out", tmp_path / "o"], tmp_path / "o", capsys)
    assert "--r-ref" in err, err
    assert main([str(a) for a in [*base, "--r-ref", 10, "--out", tmp_path / "ok"]]) == 0
    d = json.loads((tmp_path / "ok" / "diagnosis.json").read_text())
    assert d["provenance"]["inputs"]["reference"]["path"] == str(ref)
    err = _err(["diagnose", "--tracker", f, "--r-ref", 10, "--out", tmp_path / "t"],
               tmp_path / "t", capsys)  # fmt: skip
    assert "--r-ref is for --hall-map" in err
