"""The model pieces of a diagnosis problem (`ProblemContext`) follow the rows they describe.

A problem restricted to some rows (`subset_rows`) keeps, for each of those rows, the reference
field, gradient, lever and position index the whole problem held for it; what is stored per
distinct position (``upts``, the caches) is shared, and the point ids are those of the points
left.
"""

from __future__ import annotations

from dataclasses import fields

import numpy as np
from diagnose_grids import BENCH, P, Q

from cfm_fem.workflows.diagnose.effects import sensor_volume_averaging
from cfm_fem.workflows.diagnose.problem import hall_problem, subset_rows, tracker_problem
from cfm_fem.workflows.diagnose.twin import hall_twin, tracker_twin

#: The pieces of a Hall map's context that hold one entry per row.
HALL_ROWS = ("B0", "B_read", "G", "rows", "uinv", "bench_disp", "lever", "H")


def _per_row(ctx) -> set[str]:
    return {f.name for f in fields(ctx) if f.metadata.get("per_row")}


def _hall():
    rec, _, tw = hall_twin(0, {}, n_reps=2, points=P)
    mp = tw["multipole"]
    return hall_problem(rec, mp.field, mp.b_ref, tw["bench"])


def test_every_per_row_piece_of_a_hall_map_has_one_entry_per_row():
    prob = _hall()
    assert not isinstance(sensor_volume_averaging(prob), str)  # fills the cache H
    assert prob.ctx.nominal is None  # a tracker's
    assert _per_row(prob.ctx) == {*HALL_ROWS, "nominal"}
    for name in HALL_ROWS:
        assert getattr(prob.ctx, name).shape[0] == prob.n, name
    # and no other piece has as many entries (the grid has fewer distinct positions than rows)
    others = [f.name for f in fields(prob.ctx) if f.name not in HALL_ROWS]
    for name in others:
        v = getattr(prob.ctx, name)
        assert not (isinstance(v, np.ndarray) and v.shape[0] == prob.n), name
    # the distinct positions and the index of each row into them give back the positions
    np.testing.assert_allclose(prob.ctx.upts[prob.ctx.uinv], prob.pos, atol=1e-9)
    assert prob.ctx.lever.shape == (prob.n, 3, 3) and prob.ctx.axis_var.shape == (3,)


def test_a_subset_of_a_hall_map_keeps_the_pieces_of_its_rows():
    prob = _hall()
    sensor_volume_averaging(prob)
    keep = (prob.pos[:, 2] > 0) & (prob.rep == prob.rep.min())
    sub = subset_rows(prob, keep)
    assert sub.n == int(keep.sum())
    for name in HALL_ROWS:
        np.testing.assert_array_equal(getattr(sub.ctx, name), getattr(prob.ctx, name)[keep])
    assert sub.ctx.upts is prob.ctx.upts and sub.ctx.pose is prob.ctx.pose
    np.testing.assert_allclose(sub.ctx.upts[sub.ctx.uinv], sub.pos, atol=1e-9)
    np.testing.assert_array_equal(sub.ctx.point_ids, prob.ctx.point_ids[prob.point[keep]][
        np.unique(sub.point, return_index=True)[1]])  # fmt: skip
    assert len(sub.ctx.point_ids) == sub.n_points
    # a cache filled on the subset stays the subset's
    sub.ctx.V = np.zeros(len(sub.ctx.upts))
    assert prob.ctx.V is None


def test_a_subset_of_a_tracker_recording_keeps_its_nominal_positions():
    rec, _ = tracker_twin(0, {}, n_reps=2, points=Q)
    prob = tracker_problem(rec, BENCH)
    assert prob.ctx.G is None and prob.ctx.smooth and prob.ctx.rebuild is None
    keep = prob.q[:, 0] < 100.0
    sub = subset_rows(prob, keep)
    np.testing.assert_array_equal(sub.ctx.nominal, prob.ctx.nominal[keep])
    assert sub.ctx.bench is prob.ctx.bench
    assert sorted(sub.ctx.point_ids) == sorted(set(rec.point_id[keep]))
