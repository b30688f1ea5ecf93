"""A reference's error coherent across the map is not credited to volume averaging.

Unit checks of :func:`~cfm_fem.workflows.diagnose.select.reference_explains` on a synthetic
fit: an error of the stated size, aligned with the averaging column at every point, is fully
explained; an averaging term well beyond it keeps the evidence of its excess; a block without a
stated reference error is untouched. The family cases (clean maps read against coarse grids,
and a concealed averaging) are in ``tests/test_diagnose_reference_share.py``.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from cfm_fem.workflows.diagnose.calibrate import Columns, fit_map, stack
from cfm_fem.workflows.diagnose.select import reference_explains

M, REPS = 60, 3  # distinct points, readings of each
NOISE = 1.0


def _design(seed=0):
    rng = np.random.default_rng(seed)
    z = np.linspace(-1.0, 1.0, M)
    shape = np.zeros((M, 3))
    shape[:, 0] = np.exp(-(((np.abs(z) - 0.8) / 0.1) ** 2))  # curvature at both ends
    shape[:, 2] = 0.5 * np.sign(z) * shape[:, 0]
    key = np.repeat(np.arange(M), REPS)
    base = Columns(np.tile(np.eye(3), (M * REPS, 1, 1)), ["b_x", "b_y", "b_z"], ["T"] * 3,
                   np.zeros(3), np.full(3, 1e3), "offsets")  # fmt: skip
    blk = Columns(shape[key][..., None], ["dw"], ["1e-3 mm^2"], np.zeros(1), np.full(1, 1e6),
                  "sensor_volume_averaging")  # fmt: skip
    noise = rng.normal(0.0, NOISE, size=(M * REPS, 3))
    return shape, key, base, blk, noise


def _beyond_offsets(shape):
    """The averaging column less what the offsets reproduce (per component): what the
    estimate sees."""
    return shape - shape.mean(0)


def _gain(y, base, blk, std=None, key=None):
    sigma = np.full_like(y, NOISE)
    if std is not None:
        blk.ref_error = (std, key)
    trial = stack([base, blk])
    f0, f = fit_map(y, sigma, base), fit_map(y, sigma, trial)
    d = f0.objective - f.objective
    return d, reference_explains(SimpleNamespace(y=y), sigma, trial, f, blk), f.theta[-1]


def test_an_error_of_the_stated_size_aligned_with_averaging_is_explained():
    shape, key, base, blk, noise = _design()
    std = np.full((M, 3), 1.0)
    err = std * np.sign(_beyond_offsets(shape))  # one sign across each end, the stated size
    y = err[key] + 0.05 * noise
    d, ref, theta = _gain(y, base, blk, std, key)
    assert d > 100.0  # taken as independent per reading, it would be claimed
    assert ref >= 0.99 * d


def test_averaging_beyond_the_reference_error_keeps_the_evidence_of_its_excess():
    shape, key, base, blk, noise = _design(1)
    std = np.full((M, 3), 0.05)
    r = _beyond_offsets(shape)
    y = 3.0 * shape[key] + (std * np.sign(r))[key] + noise
    d, ref, theta = _gain(y, base, blk, std, key)
    sd = 1.0 / np.sqrt(REPS * np.sum(r**2))
    bound = np.sum(np.abs(r) * std) / np.sum(r**2)  # |influence| x std, summed over points
    left = ((abs(theta) - bound) / sd) ** 2
    np.testing.assert_allclose(d - ref, left, rtol=1e-4)
    assert d - ref > 0.5 * d > 100.0


def test_no_stated_error_leaves_the_evidence_alone():
    shape, key, base, blk, noise = _design(2)
    y = 0.5 * shape[key] + noise
    d, ref, _ = _gain(y, base, blk)
    assert ref == 0.0 and d > 0
    d2, ref2, _ = _gain(y, base, blk, np.zeros((M, 3)), key)
    assert ref2 == 0.0
