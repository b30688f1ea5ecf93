"""Calibration of a coarse reference map's own error between its nodes, against the exact field.

The family's simulated magnets (``cfm_fem.simulation.magnets``) give the exact field; a coarse
FEM-like grid of it (steps along z a few times those across, as the family's coarse references)
is read between its nodes by :func:`cfm_fem.workflows.diagnose.reference.reference_model`, and
the reading's error over its estimated standard deviation must be of unit size: no wider than
1.5 in standard deviation and without heavy tails, in a magnet's body and across its end.
"""

import numpy as np
import pytest

from cfm_fem.models.field import FieldMap
from cfm_fem.simulation import magnets
from cfm_fem.workflows.diagnose.reference import reference_model

#: Errors below this fraction of the map's largest field are below any Hall probe's noise
#: (1e-6: a hundredth of a field unit); the estimate is not judged there.
FLOOR = 1e-6

MAGNETS = {
    "dipole": {"source": "pm", "order": 1},
    "quadrupole": {"source": "pm", "order": 2},
    "sextupole": {"source": "coil", "order": 3},
    "octupole": {"source": "pm", "order": 4},
    "solenoid": {"source": "solenoid", "order": 0},
}


def _case(name: str, where: str, seed: int = 7):
    spec = MAGNETS[name] | {"bore_mm": 14.0, "length_mm": 120.0, "scale_T": 0.5}
    half_xy = 0.45 * spec["bore_mm"]
    gxy = np.linspace(-half_xy, half_xy, 9)
    step = float(np.clip(spec["bore_mm"] / 4.0, 2.0, 5.0))
    z0 = 0.0 if where == "body" else 0.5 * spec["length_mm"]
    gz = np.arange(z0 - 8.0 * step, z0 + 8.5 * step, step)
    nodes = np.stack(np.meshgrid(gxy, gxy, gz, indexing="ij"), -1).reshape(-1, 3)
    fm = FieldMap(points=nodes, B=magnets.field(spec, nodes), source=f"{name} {where}")
    model, _, _ = reference_model(fm, "auto")
    rng = np.random.default_rng(seed)
    lo, hi = nodes.min(0), nodes.max(0)
    pts = lo + (hi - lo) * rng.uniform(0.05, 0.95, size=(300, 3))
    err = model(pts) - magnets.field(spec, pts)
    var = model.error_var(pts)
    floor = FLOOR * float(np.abs(fm.B).max())
    return err, var, floor


@pytest.mark.parametrize("where", ["body", "end"])
@pytest.mark.parametrize("name", sorted(MAGNETS))
def test_coarse_reference_error_is_calibrated(name, where):
    err, var, floor = _case(name, where)
    z = (err / np.sqrt(var + floor**2)).ravel()
    assert np.all(np.isfinite(z))
    assert np.std(z) <= 1.5, f"std {np.std(z):.2f}"
    assert np.abs(z).max() <= 6.0, f"max |z| {np.abs(z).max():.1f}"
    # honest, not merely safe: the stated error is not far above the true one where it matters
    big = np.sqrt(var) > 10 * floor
    if big.sum() >= 30:
        ratio = np.sqrt(np.mean(var[big])) / np.sqrt(np.mean(err[big] ** 2))
        assert ratio < 10.0, f"stated error {ratio:.1f} times the true one"
