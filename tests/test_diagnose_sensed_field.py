"""The probe's effects act on the field the probe senses, where the bench's errors move it.

A Hall map's problem against a 3-D reference, expanded at bench errors that move the probe by
tens of um, reads the reference there (``ctx.B_read``); the columns of the planar Hall term,
the element mixing and the magnet's temperature are built from that field, not from the field
at the nominal point.
"""

from __future__ import annotations

import numpy as np
from diagnose_grids import P

from cfm_fem.models.bench import ERROR_NAMES
from cfm_fem.workflows.diagnose.effects import (
    magnet_temperature,
    planar_hall,
    probe_misalignment,
)
from cfm_fem.workflows.diagnose.problem import bench_move, hall_problem
from cfm_fem.workflows.diagnose.twin import hall_twin


class _Field3D:
    """A twin's multipole whose amplitude varies slowly along z (a 3-D reference)."""

    def __init__(self, mp):
        self.mp = mp

    def field(self, p):
        p = np.asarray(p, dtype=float)
        return self.mp.field(p) * (1.0 + 0.1 * p[:, 2:3] / 300.0)


def _moved():
    """A Hall twin's problem against a 3-D reference, expanded at angular errors of 100 urad
    (moves of tens of um)."""
    rec, _, tw = hall_twin(3, {}, n_reps=1, points=P, dt_s=30.0)
    mp, bench = _Field3D(tw["multipole"]), tw["bench"]
    at = np.zeros(len(ERROR_NAMES))
    at[[k for k, n in enumerate(ERROR_NAMES) if n.startswith("eps")]] = 100.0
    prob = hall_problem(rec, mp.field, tw["multipole"].b_ref, bench, bench_at=at)
    return prob, mp, bench, at


def test_the_sensed_field_is_the_reference_where_the_bench_moves_the_probe():
    prob, mp, bench, at = _moved()
    from cfm_fem.workflows.diagnose.problem import _axis_positions

    q, bench2 = _axis_positions(bench, prob.pos, [])
    d = bench_move(bench2, q, at)
    assert np.sqrt((d**2).sum(1)).max() > 0.02  # tens of um at least somewhere
    exact = mp.field(prob.pos + d)
    moved = np.abs(prob.ctx.B_read - prob.ctx.B0).max()
    # the move changes the field well beyond the second-order expansion's own error
    assert np.abs(prob.ctx.B_read - exact).max() < 0.05 * moved
    assert np.abs(prob.ctx.B0 - exact).max() > 0.5 * moved


def test_the_probe_effects_are_built_on_the_sensed_field():
    prob, *_ = _moved()
    B = prob.ctx.B_read
    assert not np.allclose(B, prob.ctx.B0)
    ph = planar_hall(prob)
    np.testing.assert_allclose(ph.J[:, 2, 2], B[:, 0] * B[:, 1])
    np.testing.assert_allclose(ph.J[:, 0, 0], B[:, 1] * B[:, 2])
    pm = probe_misalignment(prob)
    np.testing.assert_allclose(pm.J[:, 2, pm.names.index("m_zx")], B[:, 0] * 1e-3)
    mt = magnet_temperature(prob)
    ratio = mt.J[:, :, 0] / np.where(B == 0, np.nan, B)
    spread = np.nanstd(ratio, axis=1)  # one temperature per reading scales all components
    assert np.all(spread[np.isfinite(spread)] <= 1e-9 * np.nanmax(np.abs(ratio)))


def test_the_calibrated_gains_scale_the_sensed_field():
    """A Hall element's gain scales the field it senses: on a multipole that field departs
    from the one at the nominal point by G d, so gain columns built on the nominal field leave
    gain x G d in the residual (a 0.1 % gain on a move of tens of um: above the noise)."""
    prob, *_ = _moved()
    gains = next(b for b in prob.baseline if b.names[0] == "gain_x")
    B = prob.ctx.B_read
    for i in range(3):
        np.testing.assert_allclose(gains.J[:, i, i], B[:, i] * 1e-2)
    assert np.abs(B - prob.ctx.B0).max() > 1e-3 * np.abs(B).max()


def test_a_2d_reference_is_sensed_at_the_pose_where_the_bench_moves_the_probe():
    """Against 2-D harmonics the problem reads the field exactly where the magnet's pose and
    the bench's errors put the probe; the probe's effects must act on that field, not on the
    field of the magnet unmoved at the nominal point (on a multipole's symmetry plane a
    component vanishes there, and with it a planar Hall term's whole signature)."""
    from cfm_fem.workflows.diagnose.problem import _axis_positions, posed_field

    rec, _, tw = hall_twin(3, {}, n_reps=1, points=P, dt_s=30.0)
    mp, bench = tw["multipole"], tw["bench"]
    at = np.zeros(len(ERROR_NAMES))
    at[[k for k, n in enumerate(ERROR_NAMES) if n.startswith("eps")]] = 100.0
    pose = np.array([30.0, -20.0, 5.0, 40.0, -60.0, 50.0])  # um, urad
    prob = hall_problem(rec, mp.field, mp.b_ref, bench, bench_at=at, pose=pose)
    q, bench2 = _axis_positions(bench, prob.pos, [])
    exact = posed_field(mp.field, pose)(prob.pos + bench_move(bench2, q, at))
    assert np.abs(exact - mp.field(prob.pos)).max() > 1e-3 * np.abs(exact).max()
    np.testing.assert_allclose(prob.ctx.B_read, exact, rtol=0, atol=1e-12)
    np.testing.assert_allclose(planar_hall(prob).J[:, 2, 2], exact[:, 0] * exact[:, 1], atol=1e-15)
