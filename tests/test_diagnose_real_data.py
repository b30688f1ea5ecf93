"""Hall-map diagnosis of the measured EMPHATIC map against a smooth curl/div-free fit of itself."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest

from cfm_fem.models.recordings import Recording
from cfm_fem.workflows.diagnose.harmonic_fit import fit_harmonic_field, fit_piecewise_harmonic
from cfm_fem.workflows.diagnose.problem import hall_problem
from cfm_fem.workflows.diagnose.workflow import diagnose

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "emphatic"
MAP = DATA / "mfMapMeasured_5mm.txt"


def test_harmonic_fit_is_exact_on_a_harmonic_field():
    rng = np.random.default_rng(0)
    p = rng.uniform(-10, 10, (300, 3))
    # B = grad(x y z + x^2 - y^2): div = 0 and curl = 0
    B = np.stack(
        [p[:, 1] * p[:, 2] + 2 * p[:, 0], p[:, 0] * p[:, 2] - 2 * p[:, 1], p[:, 0] * p[:, 1]], 1
    )
    hf = fit_harmonic_field(p, B, 3)
    assert hf.rms_T < 1e-9 * np.abs(B).max()


@pytest.mark.skipif(not MAP.exists(), reason="shared data folder absent")
def test_emphatic_map_diagnosis():
    from cfm_fem.io import read_field

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        fm = read_field(MAP, zero_rows="drop")
    keep = np.abs(fm.points[:, 2] - 30.0) <= 60.0  # the strongest-field slab keeps the test short
    fm_points, fm_B = fm.points[keep], fm.B[keep]
    n = len(fm_points)
    rec = Recording(
        kind="hall", point_id=np.arange(n), rep=np.zeros(n), cmd=fm_points, B=fm_B, source=str(MAP)
    )
    ref = fit_piecewise_harmonic(fm_points, fm_B, degree=5)
    b_ref = float(np.abs(fm_B).max())
    prob = hall_problem(rec, ref, b_ref, bench=None)
    s = diagnose(prob).summary
    assert set(s) >= {"mismatch", "located", "effects", "fit", "advice"}
    assert np.isfinite(s["fit"]["rms_before"])
    # whatever it finds must predict data it was not fitted to: a new signature lowers the
    # held-out RMS; a prior release (the data outweigh the prior, the predictions barely
    # change) has its conflict replicated in every held-out fold on its own
    for e in s["effects"]:
        if e["evidence"] == "new signature":
            assert e["cv_rms_after"] <= e["cv_rms_before"]
        else:
            assert e["cv_z"] > 2.0
