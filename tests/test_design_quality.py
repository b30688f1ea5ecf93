"""``cfm-fem design --quantity Q --max X``: the largest U_p whose U95 of a field-quality figure
(the quality Monte Carlo in mode gauss) stays within X, by bisection on U_p."""

from __future__ import annotations

import json

import numpy as np
import pytest

import cfm_fem
from cfm_fem.cli import main
from cfm_fem.io import write_field
from cfm_fem.models.field import FieldMap
from cfm_fem.models.quality import VECTOR_NAMES
from cfm_fem.workflows.design_quality import quality_up_max
from cfm_fem.workflows.quality import run_quality

R_REF = 4.0
TRIALS = 200


def _quadrupole():
    g = np.arange(-4.0, 4.01, 1.0)
    x, y, z = np.meshgrid(g, g, np.arange(-10.0, 10.01, 5.0), indexing="ij")
    pts = np.column_stack([x.ravel(), y.ravel(), z.ravel()])
    w = (pts[:, 0] + 1j * pts[:, 1]) / R_REF
    f = 0.01 + 0.3 * w + 0.003 * w**2  # F = B_y + i B_x
    return FieldMap.from_arrays(pts, np.column_stack([f.imag, f.real, np.zeros(len(pts))]))


@pytest.fixture(scope="module")
def quad():
    return _quadrupole()


def _u95(fm, up_um, name, seed):
    res = run_quality(fm, R_REF, up_um=up_um, trials=TRIALS, seed=seed, budget=False)
    return res.mc.u95[VECTOR_NAMES.index(name)]


@pytest.mark.parametrize(
    ("quantity", "column", "limit", "factor"),
    [("b3", "b3", 1.0, 1.0), ("centre_x_um", "centre_x", 0.5, 1e3)],
)
def test_answer_is_the_largest_up_within_the_limit(quad, quantity, column, limit, factor):
    d = quality_up_max(quad, R_REF, quantity, limit, trials=TRIALS, seed=3, rel_tol=0.01)
    assert d.method == "bisection" and d.up_max_um > 0
    # the same Monte Carlo at the answer is within the limit, one bracket width above it is not
    assert _u95(quad, d.up_max_um, column, 3) * factor <= limit
    assert _u95(quad, d.up_max_um * 1.011, column, 3) * factor > limit
    assert d.u95_at_answer == pytest.approx(_u95(quad, d.up_max_um, column, 3) * factor)
    assert 0 < d.u_up_max_um < 0.5 * d.up_max_um
    # U95 grows in proportion to U_p here (the field is linear over the displacements)
    start, u_start = d.evaluations[0]
    assert d.up_max_um == pytest.approx(start * limit / u_start, rel=0.02)


def test_cli_writes_design_json(quad, tmp_path, capsys):
    path = tmp_path / "quad.csv"
    write_field(path, quad)
    out = tmp_path / "out"
    argv = ["design", str(path), "--quantity", "b3", "--max", "1", "--r-ref", str(R_REF),
            "--trials", str(TRIALS), "--seed", "3", "--out", str(out)]  # fmt: skip
    assert main(argv) == 0, capsys.readouterr().err
    doc = json.loads((out / "design.json").read_text())
    ref = cfm_fem.run_design_quality(quad, R_REF, "b3", 1.0, trials=TRIALS, seed=3)
    assert doc["up_max_um"] == pytest.approx(ref.up_max_um, rel=1e-12)
    api = json.loads(json.dumps(ref.summary()))  # the API's design.json, as the CLI writes it
    assert {k: v for k, v in doc.items() if k != "provenance"} == {
        k: v for k, v in api.items() if k != "provenance"
    }
    assert doc["answer"].startswith("U_p <= ") and doc["unit"] == "units"
    assert doc["evaluations"][0]["up_um"] == 10.0


@pytest.mark.parametrize(("extra", "message"), [
    (["--quantity", "b16", "--max", "1", "--r-ref", "4"], "--quantity must be one of"),
    (["--quantity", "b3", "--r-ref", "4"], "needs --max"),
    (["--quantity", "b3", "--max", "1"], "needs --r-ref"),
    (["--quantity", "b3", "--max", "-1", "--r-ref", "4"], "--max must be a positive"),
    (["--quantity", "b3", "--max", "1", "--r-ref", "4", "--uf-max", "3"], "--uf-max"),
    (["--r-ref", "4"], "design needs --uf-max"),
])  # fmt: skip
def test_cli_refuses_bad_options(quad, tmp_path, capsys, extra, message):
    path = tmp_path / "quad.csv"
    write_field(path, quad)
    out = tmp_path / "out"
    assert main(["design", str(path), "--out", str(out), *extra]) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err
    assert not out.exists()
