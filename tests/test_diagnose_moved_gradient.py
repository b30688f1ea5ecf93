"""A Hall map's Jacobian and vibration lever are the field's gradient where the bench errors put
the probe.

On a sextupole's axis the gradient at the nominal point vanishes; a move of tens of um by the
bench errors gives it a gradient H d, through which the readings there see the errors, the
magnet's offset and the axes' vibration. The columns of `hall_problem` linearised at the errors
``at`` are checked against central differences of the exact reading B(p - t + d(theta)).
"""

from __future__ import annotations

import numpy as np
from hall_exact import exact_problem, exact_reading

from cfm_fem.models.bench import ERROR_NAMES
from cfm_fem.workflows.diagnose.problem import (
    REG_NAMES,
    bench_move,
    moved_gradient,
    posed_field,
)
from cfm_fem.workflows.inputs import choose_bench

G_SEXT = 0.1  # T/mm^2


def _sextupole(p):
    """B_y + i B_x = g(z) (x + i y)^2, g growing slowly along z (a 3-D field), T (p in mm)."""
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    g = G_SEXT * (1.0 + z / 200.0)
    bz = G_SEXT / 200.0 * (x * x * y - y**3 / 3.0)
    return np.stack([2.0 * g * x * y, g * (x * x - y * y), bz], -1)


def _setup():
    bench = choose_bench(None)[0]
    z = np.linspace(-40.0, 40.0, 5)
    pts = np.array([[x, y, zz] for x, y in ((0.0, 0.0), (2.0, 0.0), (0.0, -3.0)) for zz in z])
    q = bench.axis_positions_for(pts)
    assert not np.any(bench.outside_stroke(q))
    # errors of tens of urad on levers of hundreds of mm: moves of tens of um
    at = np.zeros(len(ERROR_NAMES))
    for k, name in enumerate(ERROR_NAMES):
        at[k] = 40.0 if name.startswith(("eps", "alpha")) else 5.0
        at[k] *= (-1.0) ** k
    pose = np.array([20.0, -15.0, 0.0, 30.0, -20.0, 10.0])  # um, urad
    return bench, pts, q, at, pose


def _reading(bench, pts, q, theta, pose):
    return exact_reading(_sextupole, bench, pts, q, theta, pose)


def _problem(bench, pts, q, at, pose):
    return exact_problem(_sextupole, _sextupole, 0.1, bench, pts, q, at, pose)


def test_bench_and_registration_columns_are_the_exact_readings_derivatives():
    bench, pts, q, at, pose = _setup()
    prob = _problem(bench, pts, q, at, pose)
    blocks = {b.group: b for b in prob.baseline}
    seen = 0
    axis = (pts[:, 0] == 0.0) & (pts[:, 1] == 0.0)
    # the gradient at the nominal points: the columns it would give miss the axis readings'
    old = np.einsum("nij,njp->nip", prob.ctx.G, prob.ctx.bench_disp)
    for group, names, step in (("bench", ERROR_NAMES, 1.0), ("registration", REG_NAMES, 1.0)):
        blk = blocks[group]
        for k, name in enumerate(names):
            up, dn = at.copy(), at.copy()
            pu, pd = pose.copy(), pose.copy()
            if group == "bench":
                up[k] += step
                dn[k] -= step
            else:
                pu[k] += step
                pd[k] -= step
            num = (_reading(bench, pts, q, up, pu) - _reading(bench, pts, q, dn, pd)) / (2 * step)
            col = blk.J[:, :, blk.names.index(name)]
            scale = np.abs(num).max()
            if scale < 1e-9:  # an error or rotation this scan does not see
                continue
            err = np.abs(col - num)[axis].max()
            # the axis readings see the move only through H d
            tol = max(0.01 * np.abs(num[axis]).max(), 1e-8)  # T per um or urad: 0.01 uT
            assert err < tol, (name, err, scale)
            if group == "bench" and np.abs(num[axis]).max() > 1e-6:
                seen += 1
                assert np.abs(old[..., k] - num)[axis].max() > 10 * tol, name
    assert seen >= 10  # errors the axis readings see through H d
    # the vibration's lever is that same gradient
    G_num = np.empty((len(pts), 3, 3))
    moved = pts + bench_move(bench, q, at)
    for j in range(3):
        e = np.zeros(3)
        e[j] = 1e-3
        f = posed_field(_sextupole, pose)
        G_num[:, :, j] = (f(moved + e) - f(moved - e)) / 2e-3
    R = bench.bench_to_magnet_rotation()
    want = np.einsum("nij,jk->nik", G_num, R)
    tol = 1e-5 * np.abs(want).max()
    assert np.abs(prob.ctx.lever - want).max() < tol
    nominal = np.einsum("nij,jk->nik", prob.ctx.G, R)
    assert np.abs(nominal - want)[axis].max() > 100 * tol


def test_moved_gradient_without_a_hessian_is_the_gradient():
    bench, pts, q, at, _ = _setup()
    G = np.random.default_rng(0).normal(size=(len(pts), 3, 3))
    assert moved_gradient(bench, q, at, G, None) is G
