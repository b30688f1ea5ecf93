"""What an approximate model accepted against a 2-D reference leaves to further claims.

The soft ends on a 2-D reference describe the magnet's 3-D departure only approximately: where
they misfit, the misfit is stated as a model error (so that no further effect is claimed from
it), plane by plane along z; and a linear baseline pulled by the ends' fall-off does not move
the bench expansion to where no bench put the probe.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from diagnose_grids import P

from cfm_fem.models.bench import ERROR_NAMES
from cfm_fem.workflows.diagnose.calibrate import fit_map, stack
from cfm_fem.workflows.diagnose.problem import hall_problem, noise_sigma
from cfm_fem.workflows.diagnose.register import STEERED_STD, _bench_steered
from cfm_fem.workflows.diagnose.select import approximation_error
from cfm_fem.workflows.diagnose.twin import hall_twin


def _problem(n_reps=4):
    rec, _, tw = hall_twin(5, {}, n_reps=n_reps, points=P, dt_s=30.0)
    mp = tw["multipole"]
    return hall_problem(rec, mp.field, mp.b_ref, tw["bench"])


def test_a_plane_that_misfits_gets_its_misfit_as_model_error_and_the_others_none():
    prob = _problem()
    base = stack(prob.baseline)
    fit0 = fit_map(prob.y, np.ones_like(prob.y), base)
    sigma = noise_sigma(prob, fit0.resid, fit0.edf)[0]
    planes = np.unique(np.round(prob.pos[:, 2], 3))
    bad = np.round(prob.pos[:, 2], 3) == planes[-2]
    rng = np.random.default_rng(1)
    bump = np.zeros_like(prob.y)
    # a misfit the same on every repetition, 8 sigma in B_x, of either sign across the plane
    signs = rng.choice([-1.0, 1.0], size=len(P))
    point = np.unique(prob.ctx.uinv, return_inverse=True)[1]
    bump[bad, 0] = 8.0 * sigma[bad, 0] * signs[point[bad] % len(P)]
    y = prob.y + bump
    probe = dataclasses.replace(prob, y=y)
    rows, var = approximation_error(probe, sigma, base, np.zeros(prob.n, dtype=bool))
    assert np.array_equal(rows, bad)  # that plane only
    s2 = var[:, 0] / sigma[bad, 0] ** 2
    assert np.all((s2 > 0.5 * 64) & (s2 < 1.5 * 64)), s2  # its size, from the data
    assert np.all(var[:, 1:] == 0.0)  # the components within the noise keep none
    # without the misfit no plane is flagged at the family-wise level
    rows0, _ = approximation_error(prob, sigma, base, np.zeros(prob.n, dtype=bool))
    assert not rows0.any()


def test_bench_errors_far_beyond_their_priors_are_steered_against_a_2d_reference():
    prob = _problem(n_reps=1)
    base = stack(prob.baseline)
    idx = [base.names.index(n) for n in ERROR_NAMES]
    at = base.prior_mean[idx].copy()
    assert not _bench_steered(prob, base, at)
    k = int(np.argmax(np.isfinite(base.prior_std[idx])))
    at[k] += 0.9 * STEERED_STD * base.prior_std[idx][k]
    assert not _bench_steered(prob, base, at)
    at[k] += 0.2 * STEERED_STD * base.prior_std[idx][k]
    assert _bench_steered(prob, base, at)
    # against a reference that is not 2-D the data alone decide
    flat = dataclasses.replace(prob.ctx, rebuild=None)
    assert not _bench_steered(dataclasses.replace(prob, ctx=flat), base, at)
