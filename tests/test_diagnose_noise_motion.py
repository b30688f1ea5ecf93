"""Noise model, axis velocities and change points of the diagnosis, against closed forms."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from cfm_fem.workflows.diagnose.motion import axis_velocities
from cfm_fem.workflows.diagnose.noise import estimate_noise, line_triples, reference_error_var
from cfm_fem.workflows.diagnose.step_event import change_points


def _line_scan(speed=10.0, dz=5.0, nz=9, xs=(0.0, 10.0, 20.0), overtravel_s=2.0):
    """Bidirectional on-the-fly lines along z, an x step between lines: rows in time order."""
    cmd, t, t0 = [], [], 0.0
    for k, x in enumerate(xs):
        z = np.arange(nz) * dz
        if k % 2:
            z = z[::-1]
        for j, zz in enumerate(z):
            cmd.append((x, 0.0, zz))
            t.append(t0 + j * dz / speed)
        t0 = t[-1] + overtravel_s + 3.0  # turn round and step x
    return np.array(cmd), np.array(t)


def test_velocities_inferred_only_on_the_moving_axis():
    cmd, t = _line_scan()
    v, source = axis_velocities(cmd, np.full(len(cmd), 10.0), t)
    assert source == "inferred"
    np.testing.assert_array_equal(v[:, :2], 0.0)  # x steps between lines, never at a reading
    nz = 9
    np.testing.assert_array_equal(v[:nz, 2], 10.0)  # first line upwards
    np.testing.assert_array_equal(v[nz : 2 * nz, 2], -10.0)  # second line downwards
    np.testing.assert_array_equal(v[2 * nz :, 2], 10.0)


def test_velocities_without_times_follow_the_scan_axis():
    cmd, _ = _line_scan()
    v, _ = axis_velocities(cmd, np.full(len(cmd), 5.0))
    np.testing.assert_array_equal(np.abs(v[:, 2]), 5.0)
    np.testing.assert_array_equal(v[:, :2], 0.0)


def test_velocities_stop_and_go_are_zero_and_recorded_ones_are_kept():
    cmd, t = _line_scan()
    v, _ = axis_velocities(cmd, np.zeros(len(cmd)), t)
    np.testing.assert_array_equal(v, 0.0)
    rec = np.random.default_rng(0).normal(size=cmd.shape)
    v, source = axis_velocities(cmd, None, t, vel=rec)
    assert source == "recorded" and v is not None
    np.testing.assert_array_equal(v, rec)
    assert axis_velocities(cmd, None, t) == (None, "none")


def _problem(pos, y, var_known, reps):
    m = len(pos)
    point = np.tile(np.arange(m), reps)
    return SimpleNamespace(
        y=y,
        pos=np.tile(pos, (reps, 1)),
        point=point,
        n=len(point),
        n_points=m,
        n_reps=reps,
        var_known=var_known,
    )


@pytest.mark.parametrize("reps", [1, 6])
def test_noise_floor_holds_where_the_gradient_vanishes(reps):
    # readings along z lines: vibration seen through a gradient that falls to zero beyond
    # the magnet end (z > 100 mm); white noise of 7 (floor) everywhere. The bench file states
    # twice the bench's real vibration: subtracting it would leave no floor at all
    rng = np.random.default_rng(1)
    g = np.stack(np.meshgrid([0.0, 5.0], [0.0, 5.0], np.arange(0.0, 200.0, 5.0)), -1)
    pos = g.reshape(-1, 3)
    lever2 = np.where(pos[:, 2] < 100.0, 80.0**2, 0.0)  # stated vibration seen, y units^2
    vk_pt = np.repeat(lever2[:, None], 3, 1)
    vk = np.tile(vk_pt, (reps, 1))
    y = rng.normal(size=vk.shape) * np.sqrt(49.0 + 0.25 * vk)
    prob = _problem(pos, y, vk, reps)
    nm = estimate_noise(prob, y)
    sig = nm.sigma(vk)
    quiet = np.tile(pos[:, 2] >= 100.0, reps)
    # the quiet readings keep the probe's own noise, within the estimate's scatter
    assert np.all(np.abs(sig[quiet] / 7.0 - 1.0) < (0.15 if reps > 1 else 0.35))
    assert np.all(np.abs(sig[~quiet] / np.sqrt(49.0 + 1600.0) - 1.0) < 0.2)


def test_second_differences_ignore_a_smooth_misfit():
    # one reading per point; the residual holds a smooth quadratic misfit 100x the noise
    rng = np.random.default_rng(2)
    z = np.arange(0.0, 300.0, 5.0)
    pos = np.column_stack([np.zeros_like(z), np.zeros_like(z), z])
    y = np.outer(1e-2 * (z - 150.0) ** 2, [1.0, 1.0, 1.0]) + rng.normal(size=(len(z), 3)) * 2.0
    prob = _problem(pos, y, np.zeros_like(y), 1)
    nm = estimate_noise(prob, y)
    assert "second differences" in nm.source
    np.testing.assert_allclose(np.sqrt(nm.floor), 2.0, rtol=0.3)
    assert len(line_triples(pos)) == len(z) - 2


def test_reference_error_of_linear_interpolation_matches_the_closed_form():
    # f = c x^2 / 2 along x: rms of the linear-interpolation error over a cell of h is
    # c h^2 / sqrt(120), and the second difference of a piecewise-linear f at step h is c h^2
    c, h = 3.0, 0.5

    def field(p):
        return np.column_stack([0.5 * c * p[:, 0] ** 2, np.zeros(len(p)), np.zeros(len(p))])

    pts = np.array([[0.3, 0.0, 0.0], [1.1, 2.0, 0.0]])
    var = reference_error_var(field, pts, h)
    np.testing.assert_allclose(np.sqrt(var[:, 0]), c * h**2 / np.sqrt(120.0))
    np.testing.assert_array_equal(var[:, 1:], 0.0)
    # the closed form itself: the error c t (h - t) / 2 over t in [0, h]
    t = np.linspace(0.0, h, 200001)
    rms = np.sqrt(np.mean((0.5 * c * t * (h - t)) ** 2))
    assert rms == pytest.approx(c * h**2 / np.sqrt(120.0), rel=1e-4)


def test_change_points_between_repetitions_in_time_order():
    rep = np.repeat([3, 1, 2, 0], 5)  # repetitions recorded in the order 3, 1, 2, 0
    t_h = np.arange(20) / 10.0
    prob = SimpleNamespace(rep=rep, t_h=t_h, n=20)
    cps = change_points(prob)
    assert [info["from_repetition"] for _, _, info in cps] == [1, 2, 0]
    label, after, info = cps[1]
    np.testing.assert_array_equal(after, np.isin(rep, [2, 0]))
    assert info["t_h"] == pytest.approx(1.0)


def _floors(rng, kind, n=177, reps=4):
    """Floors of a Hall map's noise model, probe noise 1 on every component: x has quiet
    points all along, y only 5 of its 177 (elsewhere vibration of 60), z no vibration."""
    pos = np.stack([np.arange(n) * 1.0, np.zeros(n), np.zeros(n)], -1)
    vk_pt = np.stack([np.linspace(0.0, 3.0, n), np.r_[np.full(5, 1.0), np.full(n - 5, 3600.0)],
                      np.zeros(n)], -1)  # fmt: skip
    vk = np.tile(vk_pt, (reps, 1))
    y = rng.normal(size=vk.shape) * np.sqrt(1.0 + vk)
    prob = _problem(pos, y, vk, reps)
    prob.kind = kind
    return np.sqrt(estimate_noise(prob, y).floor)


def test_a_hall_components_floor_barely_determined_does_not_collapse():
    # fitted alone, y's floor rests on 15 degrees of freedom beside variances 3,600 times
    # larger and falls to zero in about one map in fifteen (3 of these 40); the probe's other
    # elements determine theirs and hold it
    alone = [_floors(np.random.default_rng(s), "tracker") for s in range(40)]
    pooled = [_floors(np.random.default_rng(s), "hall") for s in range(40)]
    assert sum(f[1] < 0.2 for f in alone) >= 2
    assert all(f[1] > 0.3 for f in pooled)
    # a floor its data determine stays where they put it
    assert np.allclose([f[0] for f in pooled], [f[0] for f in alone], rtol=0.03)
    assert np.allclose([f[2] for f in pooled], [f[2] for f in alone], rtol=0.03)
