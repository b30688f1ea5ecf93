"""The curvature-corrected interpolant of a field map (`cfm_fem.models.curvature`)."""

from __future__ import annotations

import numpy as np
import pytest

from cfm_fem.models.curvature import CurvatureCorrected
from cfm_fem.models.field import FieldMap
from cfm_fem.models.interpolation import LinearInterpolator

H = 5.0
G = np.arange(-20.0, 20.0 + H / 2, H)
NODES = np.column_stack([a.ravel() for a in np.meshgrid(G, G, G, indexing="ij")])


def _quadratic(p):
    x, y, z = p.T
    return np.column_stack(
        [0.01 * x * z + 0.002 * x * y, 0.003 * (y * y - z * z) + 0.001 * x,
         0.5 + 0.004 * x * x - 0.002 * y * z]
    )  # fmt: skip


def _fringe(decay_mm):
    def f(p):
        x, y, z = p.T
        e = np.exp(z / decay_mm)
        return np.column_stack([0.01 * x * e, 0.2 * e * (1 + 0.001 * y * y), 0.1 * e])

    return f


def _both(f):
    lin = LinearInterpolator(FieldMap(NODES, f(NODES)))
    return lin, CurvatureCorrected(lin, H)


def test_a_quadratic_field_is_reproduced_exactly_also_at_the_border():
    lin, cc = _both(_quadratic)
    q = np.random.default_rng(1).uniform(-19.9, 19.9, (300, 3))
    assert np.abs(lin.field_at(q)[0] - _quadratic(q)).max() > 1e-3
    np.testing.assert_allclose(cc.field_at(q)[0], _quadratic(q), atol=1e-13)


def test_nodes_are_kept_and_outside_is_nan():
    lin, cc = _both(_quadratic)
    np.testing.assert_allclose(cc.field_at(NODES[::7])[0], _quadratic(NODES[::7]), atol=1e-13)
    B, inside = cc.field_at([[0.0, 0.0, 25.0]])
    assert not inside[0] and np.isnan(B).all()


@pytest.mark.parametrize("decay, gain", [(30.0, 20.0), (10.0, 7.0)])
def test_a_fringe_is_read_far_better_than_linearly_and_its_error_is_stated(decay, gain):
    """Exponential fringes of decay length 6 and 2 node spacings: the corrected interpolant
    errs by at most 1/gain of the linear one (rms over the grid's interior), and the error it
    states (`error_var`) is of the size of the error it makes (mean ratio 0.5 to 2)."""
    f = _fringe(decay)
    lin, cc = _both(f)
    q = np.random.default_rng(2).uniform(-12.0, 12.0, (400, 3))
    e_lin = lin.field_at(q)[0] - f(q)
    e_cc = cc.field_at(q)[0] - f(q)
    rms_lin, rms_cc = np.sqrt((e_lin**2).mean(0)), np.sqrt((e_cc**2).mean(0))
    assert np.all(rms_cc * gain < rms_lin), (rms_cc, rms_lin)
    ratio = (e_cc**2).mean(0) / cc.error_var(q).mean(0)
    assert np.all((ratio > 0.5) & (ratio < 2.0)), ratio
