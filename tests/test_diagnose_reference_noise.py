"""The diagnosis' reading of a reference map between its nodes, and its noise floor.

* `NodeExactHarmonic` reproduces a map at its nodes, reads a harmonic field between the nodes of
  a coarse grid far better than the linear interpolant, and states its own error there within
  a small factor of the true one (zero at the nodes).
* The noise floor is fitted by likelihood: where the bench's vibration dominates most points, the
  floor still comes from the points without it, instead of collapsing to zero.
"""

from __future__ import annotations

import numpy as np
import pytest

from cfm_fem.models.field import FieldMap
from cfm_fem.models.interpolation import LinearInterpolator
from cfm_fem.workflows.diagnose.noise import _fit_floor_scale
from cfm_fem.workflows.diagnose.reference import NodeExactHarmonic, reference_model

#: Point dipoles (position mm, moment) outside the box: a harmonic field inside it.
_SOURCES = [((40.0, 5.0, 0.0), (0.0, 3e3, 0.0)), ((-35.0, -10.0, 20.0), (2e3, 0.0, 1e3)),
            ((5.0, 45.0, -30.0), (0.0, 0.0, 2e3))]  # fmt: skip


def _field(p):
    """Field (T) of the dipoles of `_SOURCES` at points p (k, 3) mm (units arbitrary)."""
    p = np.asarray(p, dtype=float)
    out = np.zeros_like(p)
    for r0, m in _SOURCES:
        r = p - np.asarray(r0)
        d = np.linalg.norm(r, axis=1)[:, None]
        m = np.asarray(m)
        out += (3 * r * (r @ m)[:, None] / d**2 - m) / d**3
    return out


@pytest.fixture(scope="module")
def coarse():
    ax = np.arange(-10.0, 10.01, 2.5)
    az = np.arange(-15.0, 15.01, 3.0)
    nodes = np.stack(np.meshgrid(ax, ax, az, indexing="ij"), -1).reshape(-1, 3)
    fm = FieldMap.from_arrays(nodes, _field(nodes), source="dipoles")
    return fm, NodeExactHarmonic(fm, LinearInterpolator(fm))


def test_the_model_is_exact_at_the_nodes(coarse):
    fm, model = coarse
    b, inside = model.field_at(fm.points)
    assert inside.all()
    np.testing.assert_allclose(b, fm.B, rtol=0, atol=1e-9 * np.abs(fm.B).max())
    assert np.all(model.error_var(fm.points[:50]) == 0.0)


def test_between_nodes_the_model_beats_linear_and_states_its_error(coarse):
    fm, model = coarse
    rng = np.random.default_rng(3)
    p = rng.uniform([-7, -7, -10], [7, 7, 10], (400, 3))
    exact = _field(p)
    err_h = model(p) - exact
    err_l = LinearInterpolator(fm).field_at(p)[0] - exact
    rms_h, rms_l = np.sqrt(np.mean(err_h**2)), np.sqrt(np.mean(err_l**2))
    assert rms_h < 0.01 * rms_l, (rms_h, rms_l)
    stated = np.sqrt(np.mean(model.error_var(p)))
    assert 0.3 * rms_h < stated < 10 * rms_h, (stated, rms_h)


def test_a_planar_map_is_read_linearly():
    ax = np.arange(-10.0, 10.01, 2.0)
    nodes = np.stack(np.meshgrid(ax, ax, [0.0], indexing="ij"), -1).reshape(-1, 3)
    fm = FieldMap.from_arrays(nodes, _field(nodes), source="plane")
    model, kind, why = reference_model(fm, "auto")
    assert kind == "linear" and "plane" in why
    assert isinstance(model, LinearInterpolator)


@pytest.mark.parametrize("seed", range(6))
def test_the_floor_does_not_collapse_where_vibration_dominates(seed):
    """Variances in T^2 (a floor of 0.1 uT squared), the vibration term spread over seven decades
    of the floor (gradients from zero to large): floor and scale come out within their
    sampling error, neither pulled to zero nor to the largest variances."""
    rng = np.random.default_rng(seed)
    k, n, floor, scale = 4, 200, 1e-14, 1.0  # five repetitions per point
    v = floor * 10 ** rng.uniform(-4, 3, n)
    s2 = (floor + scale * v) * rng.chisquare(k, n) / k
    a, b = _fit_floor_scale(s2, v, np.full(n, float(k)))
    assert 0.75 < a / floor < 1.3, a / floor
    assert abs(b - scale) < 0.15, b
