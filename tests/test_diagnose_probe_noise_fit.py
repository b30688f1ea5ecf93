"""Without the bench's vibration, a clean family map fits down to the Hall probe's own noise.

The family's readings of a permanent-magnet sextupole through both ends on lines (seed 115013,
size small: 0.8 uT of noise on fields near 1 T) are rewritten without the axes' vibration and
reading error (`scripts/fit_without_vibration.py`): what is left is the field where the drawn
bench errors, the surveyed pose and the drawn gains put it, plus the probe's white noise. The
diagnosis's deterministic model (bench errors expanded to third order, the registration, the
gains) must then reproduce the readings to about 1e-6 of the field: chi2/dof near 1 and
nothing claimed. A gain applied to the field at the nominal point instead of where the bench
moves the probe leaves gain x G d in the residual, chi2/dof near 20 and an element offset
claimed.
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SEED = 115013


def _script():
    path = ROOT / "scripts" / "fit_without_vibration.py"
    spec = importlib.util.spec_from_file_location("fit_without_vibration", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_a_map_without_vibration_fits_to_the_probe_noise(tmp_path):
    r = _script().without_vibration(SEED, "small", tmp_path)
    assert r["rc"] == 0
    assert r["strata"]["magnet"] == "sextupole" and r["strata"]["noise"] == "low"
    assert 0.8 < r["chi2_dof"] < 1.25, r["chi2_dof"]
    assert r["claimed"] == [] and r["located"] == 0 and r["mismatch"] is False, r
