"""Without the bench's vibration, a clean family map fits down to the Hall probe's own noise.

The family's readings of a permanent-magnet sextupole through both ends on lines (seed 115013,
size small: 0.8 uT of noise on fields near 1 T) are rewritten without the axes' vibration and
reading error: what is left is the field where the drawn bench errors, the surveyed pose and
the drawn gains put it, plus the probe's white noise. The diagnosis's deterministic model
(bench errors expanded to third order, the registration, the gains) must then reproduce the
readings to about 1e-6 of the field: chi2/dof near 1 and nothing claimed. A gain applied to
the field at the nominal point instead of where the bench moves the probe leaves gain x G d
in the residual, chi2/dof near 20 and an element offset claimed.
"""

from __future__ import annotations

import contextlib
import io
import json
from pathlib import Path

import numpy as np

from cfm_fem.cli import main
from cfm_fem.simulation import family as F
from cfm_fem.simulation import family_hall as FH

SEED = 115013


def _without_vibration(recording: Path, values: np.ndarray) -> None:
    """Rewrite the Bx, By, Bz columns of a family recording with ``values`` (T, (n, 3))."""
    lines = recording.read_text().splitlines()
    head = next(i for i, line in enumerate(lines) if line.startswith("point_id"))
    cols = lines[head].split(",")
    where = [cols.index(c) for c in ("Bx", "By", "Bz")]
    for k in range(len(values)):
        fields = lines[head + 1 + k].split(",")
        for j, c in enumerate(where):
            fields[c] = f"{values[k, j]:.12f}"
        lines[head + 1 + k] = ",".join(fields)
    recording.write_text("\n".join(lines) + "\n")


def test_a_map_without_vibration_fits_to_the_probe_noise(tmp_path):
    files = F.write_family_case(SEED, tmp_path / "case", "small", role="null", kind="hall")
    case = F._drawn_case(SEED, "small", "null", "hall", 0)
    cfg, ctx = case["cfg"], case["ctx"]
    assert cfg["strata"]["magnet"] == "sextupole" and cfg["noise_uT"] < 1.0
    readings = FH.forward(cfg, ctx, {}, noisy=False) + ctx["noise"]
    _without_vibration(Path(files["recording"]), readings)
    out = tmp_path / "out"
    with contextlib.redirect_stdout(io.StringIO()):
        assert main(["diagnose", *files["args"], "--no-report", "--out", str(out)]) == 0
    d = json.loads((out / "diagnosis.json").read_text())
    assert 0.8 < d["fit"]["chi2_dof_before"] < 1.25, d["fit"]["chi2_dof_before"]
    assert d["effects"] == [], [e["name"] for e in d["effects"]]
    assert d["mismatch"] is False
