"""The held-out guard of a prior release: a released parameter that predicts nothing new costs
held-out chi2 through its own estimation noise, and the guard must allow that cost (and only
about that cost) in K-fold cross-validation."""

from __future__ import annotations

import numpy as np

from cfm_fem.workflows.diagnose.select import _release_within_its_freedom


def _held_out_chi2(X, y, free, folds):
    """Per-row held-out chi2 of least squares on the columns ``free`` (unit noise); the other
    columns are fixed at their true value 0 (a prior at the truth, infinitely tight)."""
    out = np.empty(y.size)
    for f in np.unique(folds):
        test = folds == f
        A = X[~test][:, free]
        b, *_ = np.linalg.lstsq(A, y[~test], rcond=None)
        out[test] = (y[test] - X[test][:, free] @ b) ** 2
    return out


def test_a_release_that_predicts_nothing_passes_at_the_stated_rate():
    rng = np.random.default_rng(7)
    n, k_folds, trials = 2000, 5, 400
    folds = np.arange(n) * k_folds // n
    rejected_guard = rejected_rows = 0
    for _ in range(trials):
        X = np.column_stack([np.ones(n), rng.normal(size=n), rng.normal(size=n)])
        y = X[:, 0] * 0.3 + rng.normal(size=n)  # column 2 has no effect; its prior is right
        before = _held_out_chi2(X, y, [0, 1], folds)
        after = _held_out_chi2(X, y, [0, 1, 2], folds)
        diff = before - after
        rejected_guard += not _release_within_its_freedom(diff, 1, folds, 2.0)
        z = diff.mean() / (diff.std(ddof=1) / np.sqrt(n))
        rejected_rows += z < -2.0
    # chi2(1) beyond 1 + 2 sqrt(2): 5.0 %; the binomial scatter of 400 draws is 1.1 %
    assert 0.015 < rejected_guard / trials < 0.09
    # a paired test over rows takes the freedom's cost for a worse prediction far more often
    assert rejected_rows / trials > 2 * rejected_guard / trials


def test_a_release_that_predicts_worse_is_rejected():
    rng = np.random.default_rng(8)
    n, k_folds = 2000, 5
    folds = np.arange(n) * k_folds // n
    X = np.column_stack([np.ones(n), rng.normal(size=n)])
    y = 0.3 + rng.normal(size=n)
    before = _held_out_chi2(X, y, [0, 1], folds)
    # fitted to the folds, but with a value the other folds contradict: a drift in time
    after = before + 0.01 * (folds - 2.0) ** 2
    assert not _release_within_its_freedom(before - after, 1, folds, 2.0)
