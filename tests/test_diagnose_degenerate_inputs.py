"""Inputs that leave a field component without scatter, or without a unit: the diagnosis runs
to the end with finite figures, or refuses the input by name (exit 2, nothing written)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from cfm_fem.cli import main
from cfm_fem.workflows.diagnose.noise import _fit_floor_scale


@pytest.fixture(scope="module")
def synth_hall(tmp_path_factory):
    path = tmp_path_factory.mktemp("hall") / "h.csv"
    assert main(["synth", "hall", "--out", str(path)]) == 0
    return path


def test_a_component_without_scatter_gets_no_floor_and_no_nan():
    a, b = _fit_floor_scale(np.zeros(12), np.linspace(0.0, 1.0, 12), np.ones(12))
    assert (a, b) == (0.0, 0.0)
    a, b = _fit_floor_scale(np.full(12, 4.0), np.zeros(12), np.ones(12))
    assert a == pytest.approx(4.0) and b == 0.0


@pytest.mark.parametrize("reference", ["fit:3", "fitz:4"])
def test_a_polynomial_that_reproduces_a_component_exactly_runs(synth_hall, tmp_path, reference):
    """synth hall's Bz is zero wherever the polynomial fits it: zero residual, no scatter."""
    out = tmp_path / "d"
    argv = ["diagnose", "--hall-map", str(synth_hall), "--reference", reference, "--no-report"]
    assert main([*argv, "--out", str(out)]) == 0
    fit = json.loads((out / "diagnosis.json").read_text())["fit"]
    assert np.isfinite(fit["rms_before"]) and np.isfinite(fit["chi2_dof_before"])


def test_a_reference_whose_field_is_zero_is_refused_by_name(synth_hall, tmp_path, capsys):
    ax, az = np.linspace(-10, 10, 6), np.linspace(-50, 50, 11)
    pts = np.stack(np.meshgrid(ax, ax, az, indexing="ij"), -1).reshape(-1, 3)
    rows = "\n".join(",".join(f"{v:.17g}" for v in r) for r in np.c_[pts, np.zeros_like(pts)])
    ref = tmp_path / "zero.csv"
    ref.write_text("x [mm],y [mm],z [mm],Bx [T],By [T],Bz [T]\n" + rows + "\n")
    out = tmp_path / "d"
    argv = ["diagnose", "--hall-map", str(synth_hall), "--reference", str(ref), "--out", str(out)]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "zero everywhere" in err and "zero.csv" in err and "Traceback" not in err
    assert not out.exists()
