"""The diagnosis reads a coarse map by its harmonic fits wherever Laplace's curl test holds.

A coil dipole's coarse map (one case of the randomized family: 11 mm bore radius, nodes 1.47
mm apart across the bore and 2.76 mm along it) leaves 2,062 of its 6,561 nodes' harmonic fits
past the misfit bound of the fallback rule, none failing the curl test. Read there by the
curvature-corrected interpolant, the map errs by hundreds of uT next to a scan point; read by
the fits, by tens. Checked against the magnet's exact field (magpylib), which the map samples.
"""

from __future__ import annotations

import numpy as np
import pytest

from cfm_fem.models.harmonic import fit_harmonic
from cfm_fem.simulation import family, magnets
from cfm_fem.workflows.diagnose.reference import reference_model
from cfm_fem.workflows.inputs import field_map

SEED = 80997  # a clean Hall map of a coil dipole against a coarse map, full size
POINT = np.array([3.867996, 2.578664, 27.375417])  # a scan point of the case, mm


@pytest.fixture(scope="module")
def coil_dipole(tmp_path_factory):
    folder = tmp_path_factory.mktemp("misfit")
    files = family.write_family_case(SEED, folder, "full", "null")
    cfg = family.draw_config(SEED, "full", "null")
    fm = field_map(str(files["reference"]), None)
    return cfg, fm


def _line(point, half_mm=0.3, n=13):
    """Points along x, y and z through ``point`` (3 n, 3), mm."""
    t = np.linspace(-half_mm, half_mm, n)
    out = np.repeat(point[None], 3 * n, axis=0)
    for a in range(3):
        out[a * n : (a + 1) * n, a] += t
    return out


def test_the_map_fails_the_misfit_bound_alone(coil_dipole):
    _, fm = coil_dipole
    default = fit_harmonic(fm.points, fm.B, metric="grid")
    curl_only = fit_harmonic(fm.points, fm.B, metric="grid", misfit_rel=np.inf)
    assert (~default.use).sum() > 0.2 * len(fm.points)
    assert curl_only.use.all()


def test_its_reading_follows_the_exact_field_next_to_a_scan_point(coil_dipole):
    cfg, fm = coil_dipole
    reader, kind, _ = reference_model(fm, "auto")
    assert kind == "harmonic"
    pts = _line(POINT)
    exact = magnets.field(cfg["magnet"], pts)
    err_fit = np.abs(reader.field_at(pts)[0] - exact).max()
    err_curved = np.abs(reader.curved(pts) - exact).max()
    assert reader.n_fallback == 0
    assert err_fit < 60e-6, err_fit
    assert err_curved > 5 * err_fit, (err_curved, err_fit)
