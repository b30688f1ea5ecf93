"""Physically implausible fits are reported as such, never as found; bounds live with
every effect of the catalogue."""

from __future__ import annotations

import numpy as np
from diagnose_grids import BENCH, P, Q

from cfm_fem.workflows.diagnose import effects as fx
from cfm_fem.workflows.diagnose.problem import hall_problem, tracker_problem
from cfm_fem.workflows.diagnose.select import implausible_reason
from cfm_fem.workflows.diagnose.twin import hall_twin, tracker_twin
from cfm_fem.workflows.diagnose.workflow import diagnose


def _problems():
    rec, _ = tracker_twin(0, {}, n_reps=2, points=Q, speeds=[10.0, 20.0])
    hrec, _, ctx = hall_twin(0, {}, n_reps=2, points=P)
    mp = ctx["multipole"]
    return tracker_problem(rec, BENCH), hall_problem(hrec, mp.field, mp.b_ref, ctx["bench"])


def test_every_catalogued_parameter_has_bounds_and_a_reason():
    for prob in _problems():
        blocks, untestable = fx.build(prob)
        assert not untestable  # the twins log time, temperature, directions and speeds
        for name, blk in blocks.items():
            names = list(blk.names) + list(blk.release)
            bounds, why = fx.bounds_for(name, names)
            assert np.all(np.isfinite(bounds)), (name, names)
            assert np.all(bounds[:, 0] < bounds[:, 1])
            assert all(why), (name, names)


def test_implausible_reason_uses_the_reported_uncertainty():
    b = np.array([[-50.0, 50.0]])
    # 80 +- 5: the whole 3u interval is outside; 80 +- 15: 35..125 reaches the bound
    assert "drift_x" in implausible_reason(["drift_x"], [80.0], [5.0], b, ["why"], ["um/h"])
    assert implausible_reason(["drift_x"], [80.0], [15.0], b, ["why"], ["um/h"]) == ""
    assert implausible_reason(["drift_x"], [-40.0], [1.0], b, ["why"], ["um/h"]) == ""


def test_tracker_knock_is_a_step_event_not_a_thermal_drift():
    # the tracker was knocked 0.5 mm in x half-way through a 1 h run: a step at the
    # repetition where it happened, its size within 3 reported std, and no drift claimed
    rec, _ = tracker_twin(0, {}, n_reps=6, points=Q, dt_s=4.0)
    after = rec.t_s > rec.t_s.max() / 2
    rec.meas[after, 0] += 0.5
    s = diagnose(tracker_problem(rec, BENCH)).summary
    assert s["mismatch"] is True
    assert all(e["name"] != "thermal_drift" for e in s["effects"])
    e = s["effects"][0]
    assert e["name"] == "step_event", s["candidates"]
    assert abs(e["params"]["step_x"] - 500.0) < 3 * e["param_std"]["step_x"]
    assert e["where"]["step_x"]["from_repetition"] == rec.rep[after].min()


def test_hall_gain_of_fifty_percent_is_not_a_hall_gain_error():
    # every reading 1.5 times the field (wrong calibration constant): a 50 % 'gain' is not a
    # Hall gain error of the probe; the tool must say so instead of reporting it found.
    rec, _, ctx = hall_twin(0, {}, n_reps=6, points=P)
    rec.B = rec.B * 1.5
    mp = ctx["multipole"]
    s = diagnose(hall_problem(rec, mp.field, mp.b_ref, ctx["bench"])).summary
    assert s["mismatch"] is True
    assert all(e["name"] != "hall_offset_gain" for e in s["effects"])
    imp = {c["name"]: c["reason"] for c in s["implausible"]}
    assert "gain_x" in imp["hall_offset_gain"] and "%" in imp["hall_offset_gain"]
