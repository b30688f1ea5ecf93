"""A reference map's error at a point is one value, read again by every repetition.

The rows of a Hall map carry it as noise of variance c r (c readings of the point, r the
error's variance), so that the mean over the repetitions, which the located residuals test,
has the variance v / c + r it has: its z is of unit size on a clean map, however many
repetitions, instead of growing as the square root of their number.
"""

from types import SimpleNamespace

import numpy as np
import pytest

from cfm_fem.workflows.diagnose.locate import standardised
from cfm_fem.workflows.diagnose.reference_rows import shared_by


@pytest.mark.parametrize("reps", [1, 3, 10])
def test_point_means_of_a_shared_reference_error_are_standard(reps):
    rng = np.random.default_rng(reps)
    m, v, r = 4000, 1.0, 4.0  # points; noise and reference-error variances
    point = np.repeat(np.arange(m), reps)
    resid = rng.normal(0.0, np.sqrt(r), (m, 3))[point] + rng.normal(0.0, np.sqrt(v), (m * reps, 3))
    var_ref = np.full((m * reps, 3), r) * shared_by(point)[:, None]
    prob = SimpleNamespace(point=point, n_points=m)
    _, zp = standardised(prob, resid, np.sqrt(v + var_ref))
    assert abs(np.std(zp) - 1.0) < 0.03
    # counted once per repetition, the same error makes every point mean too large
    _, z_naive = standardised(prob, resid, np.sqrt(v + r))
    expected = np.sqrt((v + reps * r) / (v + r))
    assert abs(np.std(z_naive) - expected) < 0.05 * expected


def test_readings_of_one_point_share_it():
    assert np.array_equal(shared_by(np.array([0, 1, 0, 2, 0, 1])), [3, 2, 3, 1, 3, 2])
