"""On an octupole's axis a Hall map's model is the reference where the bench puts the probe.

There the field, its gradient and its Hessian vanish: a move d of a hundred um by the bench's
errors reaches the readings only through the third derivatives, k d^3, and a difference
quotient of step h reads a gradient k h^2 where there is none. `hall_problem` expanded at the
errors ``at`` with the magnet at ``pose`` must give the exact reading B(p - t + d) and its
derivatives in the errors and the registration, well within a low-noise probe's floor.
"""

from __future__ import annotations

import numpy as np
from hall_exact import exact_problem, exact_reading

from cfm_fem.models.bench import ERROR_NAMES
from cfm_fem.workflows.diagnose.problem import (
    REG_NAMES,
    _axis_positions,
    bench_move,
    field_third,
)
from cfm_fem.workflows.inputs import choose_bench

K_OCT = 0.01  # T/mm^3: 0.64 T at a bore radius of 4 mm


def _octupole(p):
    """B_y + i B_x = k(z) (x + i y)^3, k growing slowly along z (a 3-D field), T (p in mm)."""
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    k = K_OCT * (1.0 + z / 3000.0)
    c = k * (x + 1j * y) ** 3
    bz = K_OCT / 3000.0 * (x**3 * y - x * y**3)
    return np.stack([c.imag, c.real, bz], -1)


def _setup():
    bench = choose_bench(None)[0]
    z = np.linspace(-40.0, 40.0, 5)
    pts = np.array([[x, y, zz] for x, y in ((0.0, 0.0), (2.0, 0.0), (0.0, -1.5)) for zz in z])
    q = bench.axis_positions_for(pts)
    assert not np.any(bench.outside_stroke(q))
    at = np.zeros(len(ERROR_NAMES))
    for k, name in enumerate(ERROR_NAMES):  # moves of about a hundred um
        at[k] = (60.0 if name.startswith(("eps", "alpha")) else 10.0) * (-1.0) ** k
    pose = np.array([30.0, -25.0, 10.0, 40.0, -30.0, 60.0])  # um, urad
    return bench, pts, q, at, pose


def _reading(bench, pts, q, theta, pose):
    return exact_reading(_octupole, bench, pts, q, theta, pose)


def _problem(bench, pts, q, at, pose, reference=_octupole):
    return exact_problem(_octupole, reference, 0.64, bench, pts, q, at, pose)


def test_third_derivatives_of_a_cubic_field_are_exact():
    p = np.array([[0.0, 0.0, 0.0], [1.0, -2.0, 30.0]])
    T = field_third(_octupole, p, 0.5)
    k = K_OCT * (1.0 + p[:, 2] / 3000.0)
    np.testing.assert_allclose(T[:, 1, 0, 0, 0], 6.0 * k, rtol=1e-9)  # d^3 B_y / dx^3
    np.testing.assert_allclose(T[:, 0, 0, 0, 1], 6.0 * k, rtol=1e-9)  # d^3 B_x / dx^2 dy
    assert np.allclose(T, np.swapaxes(T, 2, 4)) and np.allclose(T, np.swapaxes(T, 3, 4))


def test_the_model_on_the_axis_is_the_exact_reading():
    bench, pts, q, at, pose = _setup()
    prob = _problem(bench, pts, q, at, pose)
    _, bench2 = _axis_positions(bench, pts, [])
    d = bench_move(bench2, q, at)
    axis = (pts[:, 0] == 0.0) & (pts[:, 1] == 0.0)
    assert np.sqrt((d[axis] ** 2).sum(1)).min() > 0.05  # moves of 50 um at least
    exact = _reading(bench, pts, q, at, pose)
    move = np.abs(exact - prob.ctx.B0)[axis].max()
    assert move > 1e-6  # the move changes the axis readings by more than a uT
    err = np.abs(prob.ctx.B_read - exact)[axis].max()
    assert err < 1e-3 * move and err < 1e-8, (err, move)  # 10 nT


def test_columns_on_the_axis_are_the_exact_readings_derivatives():
    bench, pts, q, at, pose = _setup()
    prob = _problem(bench, pts, q, at, pose)
    blocks = {b.group: b for b in prob.baseline}
    axis = (pts[:, 0] == 0.0) & (pts[:, 1] == 0.0)
    seen = 0
    for group, names in (("bench", ERROR_NAMES), ("registration", REG_NAMES)):
        blk = blocks[group]
        for k, name in enumerate(names):
            up, dn, pu, pd = at.copy(), at.copy(), pose.copy(), pose.copy()
            if group == "bench":
                up[k] += 1.0
                dn[k] -= 1.0
            else:
                pu[k] += 1.0
                pd[k] -= 1.0
            num = (_reading(bench, pts, q, up, pu) - _reading(bench, pts, q, dn, pd)) / 2.0
            if np.abs(num[axis]).max() < 1e-10:  # a parameter the axis readings do not see
                continue
            col = blk.J[:, :, blk.names.index(name)]
            err = np.abs(col - num)[axis].max()
            assert err < 0.01 * np.abs(num[axis]).max(), (name, err)
            seen += 1
    assert seen >= 10


def test_the_derivatives_are_taken_once_per_map():
    bench, pts, q, at, pose = _setup()
    calls = []

    def counted(p):
        calls.append(len(p))
        return _octupole(p)

    prob = _problem(bench, pts, q, at, pose, reference=counted)
    first = len(calls)
    assert first >= 33  # the value, gradient, Hessian and third derivatives
    again = prob.ctx.rebuild(pose=pose * 0.5, bench_at=at * 0.5)
    again.ctx.rebuild(pose=pose, bench_at=at)
    # each relinearisation reads the field and its gradient at the pose only
    assert len(calls) - first <= 2 * 8, len(calls) - first
    H, T = prob.ctx.rebuild.keywords["hessian"]
    assert H.shape == (len(np.unique(pts, axis=0)), 3, 3, 3) and T.shape[1:] == (3, 3, 3, 3)
