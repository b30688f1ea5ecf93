"""ISO 230-2:2014 bidirectional single-axis evaluation against hand-computed values."""

from __future__ import annotations

import json

import numpy as np
import pytest

from cfm_fem.errors import CfmInputError
from cfm_fem.models.iso230 import evaluate_bidirectional, evaluate_records

# Hand example: m = 3 targets, n = 3 runs per direction, deviations in um.
TARGETS = [0.0, 100.0, 200.0]  # mm
UP = [
    [1.0, 2.0, 3.0],  # mean 2, residuals -1 0 1 -> s = sqrt(2/2) = 1
    [4.0, 4.0, 4.0],  # mean 4, s = 0
    [-1.0, 1.0, 3.0],  # mean 1, residuals -2 0 2 -> s = sqrt(8/2) = 2
]
DOWN = [
    [-1.0, -1.0, -1.0],  # mean -1, s = 0
    [0.0, 2.0, 4.0],  # mean 2, s = 2
    [-4.0, -3.0, -2.0],  # mean -3, s = 1
]


def test_hand_computed_example():
    r = evaluate_bidirectional(TARGETS, UP, DOWN)
    np.testing.assert_array_equal(r.n_up, [3, 3, 3])
    np.testing.assert_allclose(r.mean_up, [2, 4, 1])
    np.testing.assert_allclose(r.mean_down, [-1, 2, -3])
    np.testing.assert_allclose(r.s_up, [1, 0, 2])
    np.testing.assert_allclose(r.s_down, [0, 2, 1])
    # x_i = (up + down)/2 = [0.5, 3, -1]
    np.testing.assert_allclose(r.mean_bidirectional, [0.5, 3, -1])
    # B_i = up - down = [2-(-1), 4-2, 1-(-3)] = [3, 2, 4]
    np.testing.assert_allclose(r.reversal, [3, 2, 4])
    # R_i up = 4 s_up = [4, 0, 8]; R_i down = 4 s_down = [0, 8, 4]
    np.testing.assert_allclose(r.repeatability_up, [4, 0, 8])
    np.testing.assert_allclose(r.repeatability_down, [0, 8, 4])
    # R_i = max(2 s_up + 2 s_down + |B_i|, R_i up, R_i down):
    #   i=1: max(2+0+3, 4, 0) = 5;  i=2: max(0+4+2, 0, 8) = 8;  i=3: max(4+2+4, 8, 4) = 10
    np.testing.assert_allclose(r.repeatability, [5, 8, 10])
    axis = r.axis_values()
    expected = {
        "B": 4.0,  # max |B_i| = max(3, 2, 4)
        "B_mean": 3.0,  # (3 + 2 + 4)/3
        "R": 10.0,  # max R_i
        "R_up": 8.0,  # max(4, 0, 8)
        "R_down": 8.0,  # max(0, 8, 4)
        "E_up": 3.0,  # max(2, 4, 1) - min(2, 4, 1) = 4 - 1
        "E_down": 5.0,  # max(-1, 2, -3) - min(...) = 2 - (-3)
        "E": 7.0,  # max over both (4) - min over both (-3)
        "M": 4.0,  # max(0.5, 3, -1) - min(...) = 3 - (-1)
        # up: mean + 2s = [4, 4, 5], mean - 2s = [0, 4, -3] -> 5 - (-3)
        "A_up": 8.0,
        # down: mean + 2s = [-1, 6, -1], mean - 2s = [-1, -2, -5] -> 6 - (-5)
        "A_down": 11.0,
        # both: max(5, 6) - min(-3, -5) = 6 - (-5)
        "A": 11.0,
    }
    assert axis == pytest.approx(expected, abs=1e-12)
    json.dumps(r.as_dict())  # JSON-ready


def test_all_zero_deviations_give_zero_everywhere():
    z = np.zeros((4, 5))
    r = evaluate_bidirectional(np.arange(4.0), z, z)
    assert all(v == 0 for v in r.axis_values().values())
    np.testing.assert_array_equal(r.repeatability, 0)


def test_identical_directions_have_no_reversal():
    rng = np.random.default_rng(0)
    x = rng.normal(0, 1, (6, 5))
    r = evaluate_bidirectional(np.linspace(0, 150, 6), x, x)
    assert r.B == 0 and r.B_mean == 0
    np.testing.assert_array_equal(r.reversal, 0)
    # 2 s + 2 s + 0 = 4 s = R_i up: bidirectional values fall back to the unidirectional ones
    np.testing.assert_allclose(r.repeatability, r.repeatability_up)
    assert pytest.approx(r.R_up) == r.R
    assert pytest.approx(r.E_up) == r.E and pytest.approx(r.E_up) == r.M
    assert pytest.approx(r.A_up) == r.A and r.A_up == pytest.approx(r.A_down)


def test_constant_offset_and_scale_error():
    p = np.linspace(0.0, 800.0, 9)
    offset = np.full((9, 5), 7.0)
    r = evaluate_bidirectional(p, offset, offset)
    # a constant deviation moves every mean equally: no range, no scatter
    assert r.E == 0 and r.M == 0 and r.A == 0 and r.R == 0
    k = 1e-5  # scale error: x = k P in both directions
    ramp = np.repeat((k * p)[:, None], 5, axis=1)
    r = evaluate_bidirectional(p, ramp, ramp)
    assert pytest.approx(k * 800) == r.E and pytest.approx(k * 800) == r.M
    assert pytest.approx(k * 800) == r.A


def test_pure_backlash_shows_only_in_reversal_and_bidirectional_values():
    p = np.linspace(0, 100, 5)
    up = np.full((5, 5), +1.5)
    down = np.full((5, 5), -1.5)
    r = evaluate_bidirectional(p, up, down)
    assert r.B == 3.0 and r.B_mean == 3.0
    assert r.E_up == 0 and r.E_down == 0 and r.M == 0
    assert r.E == 3.0 and r.A == 3.0 and r.R == 3.0  # R_i = 0 + 0 + |B_i|


def test_swapping_directions_flips_reversal_sign_only():
    rng = np.random.default_rng(3)
    up, down = rng.normal(1, 1, (5, 5)), rng.normal(-1, 1, (5, 5))
    p = np.arange(5.0)
    a, b = evaluate_bidirectional(p, up, down), evaluate_bidirectional(p, down, up)
    np.testing.assert_allclose(a.reversal, -b.reversal)
    assert a.B_mean == pytest.approx(-b.B_mean)
    for k in ("A", "E", "M", "R", "B"):
        assert getattr(a, k) == pytest.approx(getattr(b, k))
    assert a.A_up == pytest.approx(b.A_down) and a.R_up == pytest.approx(b.R_down)


def test_records_equal_table_form_in_any_order():
    recs = []
    for i, p in enumerate(TARGETS):
        for j in range(3):
            recs.append((p, UP[i][j], "up"))
            recs.append((p, DOWN[i][j], -1))
    order = np.random.default_rng(9).permutation(len(recs))
    pos = np.array([recs[k][0] for k in order])
    dev = np.array([recs[k][1] for k in order])
    dirs = np.array([str(recs[k][2]) for k in order])
    r = evaluate_records(pos, dev, dirs)
    ref = evaluate_bidirectional(TARGETS, UP, DOWN)
    np.testing.assert_array_equal(r.targets, TARGETS)
    assert r.axis_values() == pytest.approx(ref.axis_values(), abs=1e-12)
    np.testing.assert_allclose(r.repeatability, ref.repeatability)
    # numeric directions and nearly-equal targets
    num = np.where(dirs == "up", 1, -1)
    r2 = evaluate_records(pos + 1e-12, dev, num)
    assert r2.axis_values() == pytest.approx(ref.axis_values(), abs=1e-12)


def test_missing_run_is_left_out():
    up = np.array(UP)
    up_nan = np.column_stack([up, np.full(3, np.nan)])
    r = evaluate_bidirectional(TARGETS, up_nan, DOWN)
    assert r.axis_values() == pytest.approx(evaluate_bidirectional(TARGETS, UP, DOWN).axis_values())
    np.testing.assert_array_equal(r.n_up, [3, 3, 3])


def test_bad_input():
    with pytest.raises(CfmInputError, match="at least 2"):
        evaluate_bidirectional([0.0, 1.0], [[1.0, 2.0], [1.0, np.nan]], [[0.0, 0.0], [0.0, 0.0]])
    with pytest.raises(CfmInputError, match="shape"):
        evaluate_bidirectional([0.0, 1.0], np.zeros((3, 5)), np.zeros((2, 5)))
    with pytest.raises(CfmInputError, match="record 2: direction"):
        evaluate_records([0, 0, 0], [1, 2, 3], [1, 0, -1])
    with pytest.raises(CfmInputError, match="same length"):
        evaluate_records([0, 0], [1, 2, 3], [1, 1, -1])
    with pytest.raises(CfmInputError, match="down run"):
        evaluate_records([0, 0, 0], [1, 2, 3], [1, 1, -1])
