"""``cfm-fem quality`` end to end: the files and keys of docs/quality.md, the API's identical
numbers, and bad input answered with one message and exit code 2, nothing written."""

from __future__ import annotations

import json

import numpy as np
import pytest

import cfm_fem
from cfm_fem.cli import main
from cfm_fem.io import write_field
from cfm_fem.models.field import FieldMap

R_REF = 4.0


@pytest.fixture(scope="module")
def map_file(tmp_path_factory):
    g = np.arange(-4.0, 4.01, 1.0)
    x, y, z = np.meshgrid(g, g, np.arange(-10.0, 10.01, 5.0), indexing="ij")
    pts = np.column_stack([x.ravel(), y.ravel(), z.ravel()])
    w = (pts[:, 0] + 1j * pts[:, 1]) / R_REF
    f = 0.0015 + 0.3 * w + 0.003 * w**2  # F = B_y + i B_x: 50 units of dipole, 100 of sextupole
    B = np.column_stack([f.imag, f.real, np.zeros(len(pts))])
    path = tmp_path_factory.mktemp("quality_cli") / "quad.csv"
    write_field(path, FieldMap.from_arrays(pts, B))
    return path


def test_quality_writes_the_contract(map_file, tmp_path, capsys):
    tol = tmp_path / "tol.csv"
    tol.write_text("# tolerances\nquantity,tolerance\nb3,2\ncentre_x_um,20\nroll_mrad,0.3\n")
    out = tmp_path / "out"
    argv = ["quality", str(map_file), "--r-ref", str(R_REF), "--up", "10", "--trials", "100",
            "--budget-trials", "20", "--seed", "4", "--tolerances", str(tol),
            "--out", str(out)]  # fmt: skip
    assert main(argv) == 0, capsys.readouterr().err
    for name in ("quality.json", "planes.csv", "report.html"):
        assert (out / name).is_file()
    s = json.loads((out / "quality.json").read_text())
    for key in ("r_ref_mm", "main_order", "z_range_mm", "integrated", "centre_mm",
                "U95_centre_mm", "roll_mrad", "U95_roll_mrad", "magnetic_length_mm",
                "U95_magnetic_length_mm", "trajectory", "uncertainty"):  # fmt: skip
        assert key in s, key
    integ = s["integrated"]
    for key in ("n", "B_n_Tmm", "A_n_Tmm", "b_n_units", "a_n_units", "U95_b_n_units",
                "U95_a_n_units"):  # fmt: skip
        assert len(integ[key]) == 15, key
    assert s["main_order"] == 2 and s["z_range_mm"] == [-10.0, 10.0]
    assert integ["b_n_units"][0] == pytest.approx(50.0, abs=1e-6)
    assert integ["b_n_units"][2] == pytest.approx(100.0, abs=1e-6)
    assert s["magnetic_length_mm"] == pytest.approx(20.0, abs=1e-9)
    u = s["uncertainty"]
    assert (u["mode"], u["trials"], u["seed"]) == ("gauss", 100, 4)
    assert {"numerical_tolerance", "budget"} <= set(u)
    assert [t["quantity"] for t in s["tolerances"]] == ["b3", "centre_x_um", "roll_mrad"]
    csv_lines = [ln for ln in (out / "planes.csv").read_text().splitlines() if ln[0] != "#"]
    assert csv_lines[0].startswith("z_mm,B1_T") and len(csv_lines) == 1 + 5
    # the API runs the same function: the same numbers
    api = cfm_fem.run_quality(
        map_file, R_REF, up_um=10, trials=100, seed=4, tolerances=tol, budget_trials=20
    )
    assert api.summary["U95_centre_mm"] == s["U95_centre_mm"]
    assert api.summary["integrated"]["U95_b_n_units"] == integ["U95_b_n_units"]


def _bad(argv, out, capsys):
    rc = main([str(a) for a in argv])
    err = capsys.readouterr().err
    assert rc == 2, err
    assert "Traceback" not in err and err.count("cfm-fem: error:") == 1, err
    assert not out.exists()
    return err


@pytest.mark.parametrize(
    ("extra", "expect"),
    [
        (["--up", "10"], "--r-ref"),
        (["--r-ref", "-1", "--up", "10"], "--r-ref must be a positive radius"),
        (["--r-ref", "4", "--up", "-5"], "--up must be a length >= 0"),
        (["--r-ref", "4", "--mode", "gauss"], "--mode gauss needs --up"),
        (["--r-ref", "4", "--up", "10", "--mode", "htm"], "not allowed with argument"),
        (["--r-ref", "4", "--up", "10", "--bench", "b.toml"], "apply to mode htm"),
        (["--r-ref", "4", "--up", "10", "--trials", "5"], "--trials must be >= 20"),
        (["--r-ref", "4", "--up", "10", "--main-order", "16"], "--main-order must be 1 .. 15"),
        (["--r-ref", "4", "--up", "10", "--sampling", "circles", "--radius", "30"], "--radius 30"),
        (["--r-ref", "4", "--up", "10", "--sampling", "circles", "--dz", "1e9"], "--dz 1e+09"),
        (["--r-ref", "4", "--up", "10", "--energy", "-1"], "positive kinetic energy in GeV"),
        (["--r-ref", "4", "--up", "10", "--rigidity", "1e-300"], "--rigidity 1e-300 T m"),
        (["--r-ref", "4", "--up", "10", "--rigidity", "1", "--energy", "2"], "not allowed"),
        (["--r-ref", "4", "--mode", "htm", "--bench", "none.toml"], "none.toml"),
    ],
)
def test_bad_options(map_file, tmp_path, capsys, extra, expect):
    out = tmp_path / "out"
    err = _bad(["quality", map_file, *extra, "--out", out], out, capsys)
    assert expect in err


def test_bad_tolerance_table_names_file_and_line(map_file, tmp_path, capsys):
    tol = tmp_path / "tol.csv"
    tol.write_text("quantity,tolerance\nb3,2\nb99,1\n")
    out = tmp_path / "out"
    err = _bad(["quality", map_file, "--r-ref", "4", "--up", "10", "--tolerances", tol, "--out",
                out], out, capsys)  # fmt: skip
    assert "tol.csv:3" in err and "b99" in err
    tol.write_text("quantity,tolerance\nroll_mrad,abc\n")
    err = _bad(["quality", map_file, "--r-ref", "4", "--up", "10", "--tolerances", tol, "--out",
                out], out, capsys)  # fmt: skip
    assert "tol.csv:2" in err and "positive number" in err


def test_missing_map(tmp_path, capsys):
    out = tmp_path / "out"
    err = _bad(["quality", tmp_path / "none.csv", "--r-ref", "4", "--up", "10", "--out", out],
               out, capsys)  # fmt: skip
    assert "none.csv" in err


def test_a_dipole_main_order_writes_its_report_without_a_centre(map_file, tmp_path):
    """--main-order 1 has no magnetic centre: quality.json says null, the report leaves out the
    centre figure and still shows the budget (no failing figure)."""
    out = tmp_path / "q"
    argv = ["quality", str(map_file), "--r-ref", "2", "--up", "10", "--trials", "40",
            "--budget-trials", "40", "--main-order", "1", "--out", str(out)]  # fmt: skip
    assert main(argv) == 0
    doc = json.loads((out / "quality.json").read_text())
    assert doc["main_order"] == 1 and None in (doc["centre_mm"] or [None])
    assert (out / "budget.png").exists() and not (out / "centre.png").exists()


def test_summary_says_when_the_adaptive_rule_reached_its_digits(map_file, capsys):
    from cfm_fem.cli.quality import _print_summary
    from cfm_fem.workflows.quality import run_quality

    done = run_quality(map_file, R_REF, up_um=10.0, seed=1, budget=False, batch_trials=200,
                       max_trials=20_000)  # fmt: skip
    capped = run_quality(map_file, R_REF, up_um=10.0, seed=1, budget=False, batch_trials=100,
                         max_trials=300, digits=2)  # fmt: skip
    fixed = run_quality(map_file, R_REF, up_um=10.0, seed=1, budget=False, trials=100)
    assert done.mc.converged and not capped.mc.converged
    for res, said in ((done, True), (capped, False), (fixed, False)):
        _print_summary(res.summary)
        err = capsys.readouterr().err
        assert ("the adaptive rule reached 1 digit(s)" in err) is said, err
