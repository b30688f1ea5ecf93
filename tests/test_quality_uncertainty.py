"""Uncertainty of the field quality (`cfm_fem.models.quality.uncertainty`) against a brute-force
Monte Carlo written here: perturb the scan points, evaluate the exact field, redo the fit."""

from __future__ import annotations

import numba
import numpy as np
import pytest
from quality_circle_fit import circle_operator

from cfm_fem.models.field import FieldMap
from cfm_fem.models.quality import VECTOR_NAMES
from cfm_fem.models.quality.uncertainty import _check
from cfm_fem.workflows.quality import run_quality

R_REF = 5.0
#: Normal quadrupole, sextupole and a skew octupole, T at R_REF.
QUAD, SEXT, SKEW_OCT = 0.5, 0.005, 0.002
Z_PLANES = np.array([-20.0, -10.0, 0.0, 10.0, 20.0])


def exact_field(p):
    """B (n, 3) of the 2-D field, from F = B_y + i B_x as a polynomial in w = (x + i y)/R_REF."""
    w = (p[..., 0] + 1j * p[..., 1]) / R_REF
    f = QUAD * w + SEXT * w**2 + 1j * SKEW_OCT * w**3
    return np.stack([f.imag, f.real, np.zeros_like(f.real)], axis=-1)


@pytest.fixture(scope="module")
def field_map():
    g = np.arange(-5.0, 5.01, 1.0)
    x, y, z = np.meshgrid(g, g, Z_PLANES, indexing="ij")
    pts = np.column_stack([x.ravel(), y.ravel(), z.ravel()])
    return FieldMap.from_arrays(pts, exact_field(pts), source="analytic")


def brute_force(trials, up_mm, seed):
    """Deviations of b1, a1, b3, a4, centre x, y, roll, length of each trial (own analysis)."""
    g = np.arange(-5.0, 5.01, 1.0)
    x, y = np.meshgrid(g, g, indexing="ij")
    keep = np.hypot(x, y) <= 5.0 + 1e-9
    xy = np.column_stack([x[keep], y[keep]])  # the disk the square map covers
    k = len(xy)
    w = (xy[:, 0] + 1j * xy[:, 1]) / 5.0
    pw = w[:, None] ** np.arange(15)
    design = np.vstack([np.hstack([pw.real, -pw.imag]), np.hstack([pw.imag, pw.real])])
    pinv = np.linalg.pinv(design)  # fit at r = 5 mm = R_REF
    wz = np.array([5.0, 10.0, 10.0, 10.0, 5.0])  # trapezoid over the planes
    pts = np.concatenate([np.column_stack([xy, np.full(k, z)]) for z in Z_PLANES])
    on_circle = circle_operator(xy, 5.0, R_REF, 2)  # the quadrupole on r = R_REF, plane z = 0

    def analyse(b):  # b (M, P k, 3) -> (M, 8)
        b = b.reshape(len(b), len(Z_PLANES), k, 3)
        coef = np.concatenate([b[..., 1], b[..., 0]], axis=-1) @ pinv.T
        c = coef[..., :15] + 1j * coef[..., 15:]  # (M, P, 15)
        integ = np.einsum("mpn,p->mn", c, wz)
        rel = 1e4 * integ / np.abs(integ[:, 1:2])
        roll = -np.angle(integ[:, 1]) / 2 * 1e3
        central = np.concatenate([b[:, 2, :, 1], b[:, 2, :, 0]], axis=-1) @ on_circle
        length = np.abs(integ[:, 1]) / (central * np.exp(-1j * np.angle(integ[:, 1]))).real
        # centre: the root d of F(d) = sum C_n (d/R)^(n-1) near -C_1 / C_2 (Newton, 8 steps)
        poly = np.polynomial.polynomial
        u = -integ[:, 0] / integ[:, 1]
        dcoef = integ[:, 1:] * np.arange(1, 15)
        for _ in range(8):
            f = np.array([poly.polyval(ui, ci) for ui, ci in zip(u, integ, strict=True)])
            df = np.array([poly.polyval(ui, ci) for ui, ci in zip(u, dcoef, strict=True)])
            u = u - f / df
        centre = u * R_REF
        return np.column_stack([rel[:, 0].real, rel[:, 0].imag, rel[:, 2].real, rel[:, 3].imag,
                                centre.real, centre.imag, roll, length])  # fmt: skip

    nominal = analyse(exact_field(pts)[None])[0]
    rng = np.random.default_rng(seed)
    disp = rng.normal(0.0, up_mm, (trials, len(pts), 3))
    return analyse(exact_field(pts[None] + disp)) - nominal


def u95(dev):
    low, high = np.quantile(dev, [0.025, 0.975], axis=0)
    return np.maximum(np.abs(low), np.abs(high))


COLUMNS = ["b1", "a1", "b3", "a4", "centre_x", "centre_y", "roll", "length"]


def test_gauss_u95_matches_brute_force(field_map):
    res = run_quality(field_map, R_REF, up_um=20.0, trials=2000, seed=3, probe="exact",
                      budget=False)  # fmt: skip
    tool = res.mc.u95[[VECTOR_NAMES.index(c) for c in COLUMNS]]
    ref = u95(brute_force(2000, 0.020, seed=99))
    np.testing.assert_allclose(tool, ref, rtol=0.10)
    assert res.mc.trials == 2000 and res.mc.lost == 0
    # feed-down of random displacements: a dipole of tens of units needs U95 well above 0
    assert tool[0] > 0.1


def test_same_numbers_whatever_threads_or_batches(field_map):
    kw = dict(mode="htm", centre_magnet=True, seed=7, probe="table1", budget=False)
    before = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        one = run_quality(field_map, R_REF, trials=40, **kw).mc.deviations
        numba.set_num_threads(min(2, numba.config.NUMBA_NUM_THREADS))
        two = run_quality(field_map, R_REF, trials=40, **kw).mc.deviations
    finally:
        numba.set_num_threads(before)
    np.testing.assert_array_equal(one, two)
    more = run_quality(field_map, R_REF, trials=80, **kw).mc.deviations
    np.testing.assert_array_equal(more[:40], one)
    assert np.all(np.std(one, axis=0)[VECTOR_NAMES.index("centre_x")] > 0)


def test_htm_budget_groups_add_up(field_map):
    res = run_quality(field_map, R_REF, mode="htm", centre_magnet=True, trials=600, seed=2,
                      probe="exact", budget=True, budget_trials=600)  # fmt: skip
    names = [b.label for b in res.budget]
    assert names == ["X axis", "Y axis", "Z axis", "squareness", "vibration and reading delay"]
    for q in ("centre_x", "centre_y", "roll"):
        j = VECTOR_NAMES.index(q)
        total = res.mc.std[j] ** 2
        parts = sum(b.std[j] ** 2 for b in res.budget)
        assert parts == pytest.approx(total, rel=0.25), q
    summary = res.summary
    assert summary["uncertainty"]["budget"]["dominant"]["centre_x"] in names
    assert len(summary["integrated"]["U95_b_n_units"]) == 15


def test_adaptive_criterion():
    rng = np.random.default_rng(0)
    few = [rng.normal(0.0, 3.0, (50, 2)) for _ in range(2)]
    many = [rng.normal(0.0, 3.0, (2000, 2)) for _ in range(30)]
    assert not _check(few, 1)[0]
    conv, spread, delta = _check(many, 1)  # std 3 to one digit: tolerance 0.5
    assert conv and np.all(spread < 0.5) and np.all(delta == 0.5)
    # a wide, skewed column that has not converged holds the rule back, unless it is the one
    # left out (b_N in run_quality_mc)
    mixed = [np.column_stack([v[:, 0], rng.lognormal(0.0, 2.5, 2000)]) for v in many[:4]]
    assert not _check(mixed, 1)[0]
    assert _check(mixed, 1, ignore=1)[0]


def test_adaptive_run_stops_at_the_cap_and_says_so(field_map):
    res = run_quality(field_map, R_REF, up_um=10.0, seed=1, probe="exact", budget=False,
                      batch_trials=100, max_trials=300, digits=2)  # fmt: skip
    mc = res.mc
    assert mc.trials == 300 and mc.batches == 3 and not mc.converged
    assert any("adaptive Monte Carlo stopped at 300 trials" in n for n in res.summary["notes"])
    assert res.summary["uncertainty"]["numerical_tolerance"]["converged"] is False


@pytest.mark.parametrize("model", ["paper", "table1"])
def test_probe_reading_is_the_probe_model(model):
    from cfm_fem.models.probe import HallProbe, apply_probe
    from cfm_fem.models.quality.uncertainty import PROBE_STREAM, _probe_read

    rng = np.random.default_rng(0)
    B = rng.normal(size=(4, 7, 3))
    r = np.linalg.qr(rng.normal(size=(3, 3)))[0]  # bench -> magnet rotation
    probe = HallProbe(model)
    out = _probe_read(probe, B, 5, 3, r)
    for j in range(4):
        draw = probe.sample(
            np.random.default_rng(np.random.SeedSequence(3, spawn_key=(PROBE_STREAM, 5 + j)))
        )
        np.testing.assert_allclose(out[j], apply_probe(B[j] @ r, draw) @ r.T, atol=1e-14)
