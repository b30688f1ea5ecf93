"""cfm-fem diagnose end to end: files in the 4.2 contract, diagnosis.json per 4.3, exit codes."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from cfm_fem.cli import main
from cfm_fem.diagnose.twin import tracker_twin
from cfm_fem.io.recordings import write_tracker

Q = np.stack(
    np.meshgrid(
        np.linspace(0, 150, 4), np.linspace(0, 150, 3), np.linspace(0, 800, 5), indexing="ij"
    ),
    -1,
).reshape(-1, 3)


def test_cli_tracker(tmp_path):
    rec, _ = tracker_twin(3, {"reversal": {"backlash_z": 10.0}}, n_reps=6, points=Q)
    f = tmp_path / "rec.csv"
    write_tracker(f, rec)
    out = tmp_path / "diag"
    assert main(["diagnose", "--tracker", str(f), "--out", str(out)]) == 0
    d = json.loads((out / "diagnosis.json").read_text())
    assert set(d) >= {"mismatch", "located", "effects", "fit", "advice"}
    assert d["mismatch"] is True and d["effects"][0]["name"] == "reversal"
    e = d["effects"][0]
    assert {"name", "params", "param_std", "delta_bic", "cv_rms_before", "cv_rms_after"} <= set(e)
    for k in ("rms_before", "rms_after", "chi2_dof_before", "chi2_dof_after"):
        assert np.isfinite(d["fit"][k])
    for name in ("report.md", "fit.png", "residuals.png", "residual_points.vtu"):
        assert (out / name).stat().st_size > 0


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
