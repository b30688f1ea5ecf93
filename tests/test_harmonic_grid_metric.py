"""Harmonic fits of a grid whose steps differ along its axes, read between its planes.

An FEM export is often fine across the bore and coarse along the magnet: the nearest nodes of a
node then all lie in its plane. The reference reading of the diagnosis measures neighbourhoods
in steps on such a grid (`cfm_fem.models.harmonic.grid_metric`); its error between the planes,
against the exact field of a simulated quadrupole (magpylib, written apart from the model), must
stay near the error of the same grid read at its own planes' spacing, and within its stated
error.
"""

import numpy as np

from cfm_fem.models.field import FieldMap
from cfm_fem.models.harmonic import ANISOTROPY_MAX, fit_harmonic, grid_metric
from cfm_fem.models.interpolation import LinearInterpolator
from cfm_fem.simulation import magnets
from cfm_fem.workflows.diagnose.reference import reference_model

QUAD = {"source": "pm", "order": 2, "bore_mm": 14.0, "length_mm": 200.0, "scale_T": 0.5}


def _grid(step_xy, step_z, half_xy=6.0, z=(-60.0, 60.0)):
    gxy = np.arange(-half_xy, half_xy + 1e-9, step_xy)
    gz = np.arange(z[0], z[1] + 1e-9, step_z)
    return np.stack(np.meshgrid(gxy, gxy, gz, indexing="ij"), -1).reshape(-1, 3)


def test_grid_metric_measures_a_coarse_axis_in_steps():
    assert np.allclose(grid_metric(_grid(1.5, 10.0)), [1.0, 1.0, 0.15])
    # below the ratio at which the nearest nodes collapse into a plane: millimetres
    assert np.array_equal(grid_metric(_grid(1.5, 1.5 * ANISOTROPY_MAX)), np.ones(3))
    # not a full grid (a node missing, or scattered nodes): millimetres
    assert np.array_equal(grid_metric(_grid(1.5, 10.0)[1:]), np.ones(3))
    rng = np.random.default_rng(1)
    assert np.array_equal(grid_metric(rng.uniform(-5, 5, (500, 3)) * [1, 1, 10]), np.ones(3))


def test_a_fit_in_millimetres_is_unchanged_by_the_default():
    pts = _grid(1.5, 10.0, half_xy=3.0, z=(-20.0, 20.0))
    b = magnets.field(QUAD, pts)
    a = fit_harmonic(pts, b)
    c = fit_harmonic(pts, b, metric=np.ones(3))
    assert np.array_equal(a.coef, c.coef) and np.array_equal(a.reach_mm, c.reach_mm)
    assert np.array_equal(a.metric, np.ones(3))


def test_across_an_end_between_coarse_planes_the_reading_is_accurate_and_stated():
    """Readings across the quadrupole's end (at z = 100 mm) between the planes of a grid 1.5 mm
    apart across the bore and 10 mm along it: far below the linear interpolant's error (in
    millimetres the fits of such a grid reach none of these points and the reading errs by
    0.44 of the linear one), and within the error it states."""
    rng = np.random.default_rng(3)
    pts = rng.uniform([-4.0, -4.0, 60.0], [4.0, 4.0, 140.0], (300, 3))
    exact = magnets.field(QUAD, pts)
    nodes = _grid(1.5, 10.0, z=(40.0, 160.0))
    fm = FieldMap(points=nodes, B=magnets.field(QUAD, nodes), source="coarse along z")
    model, kind, _ = reference_model(fm, "auto")
    assert kind == "harmonic"
    _, ok = model.fit.field_at(pts)
    assert ok.all(), "every point between the planes is within a fit's reach"
    err = model(pts) - exact
    lin = LinearInterpolator(fm).field_at(pts)[0] - exact
    ratio = np.sqrt(np.mean(err**2) / np.mean(lin**2))
    assert ratio < 0.15, f"harmonic over linear rms error {ratio:.2f}"
    z = err / np.sqrt(model.error_var(pts) + (1e-6 * 0.5) ** 2)
    assert np.std(z) <= 1.5 and np.abs(z).max() <= 6.0, (np.std(z), np.abs(z).max())
