"""GUM-S1 engine against the JCGM 101:2008 worked examples (10**6 trials, vectorised numpy).

Tolerances come from the Monte Carlo numerical uncertainty: the standard deviation of each
result is estimated from 20 sub-runs of the 10**6 values (s / sqrt(20)); published Monte Carlo
values are themselves 10**6-trial results with the same numerical uncertainty, so a difference
is allowed 4 x sqrt(2) standard deviations plus half a unit of the published last digit.
Published values that are exact (analytic) get 4 standard deviations plus the rounding.
"""

import numpy as np
import pytest

from cfm_fem.errors import CfmInputError
from cfm_fem.models.mc import (
    Pdf,
    adaptive_monte_carlo,
    coverage_count,
    draw_inputs,
    gum_linear,
    monte_carlo,
    numerical_tolerance,
    shortest_interval,
    summarize,
    symmetric_interval,
    symmetric_ranks,
    validate_gum,
    variance_shares,
)

M = 10**6


def _numerical_std(values, p, interval="symmetric", parts=20):
    """Standard deviation of (y, u, low, high) of the full run, from ``parts`` sub-runs."""
    stats = []
    for chunk in np.array_split(values, parts):
        s = summarize(chunk, p)
        lo, hi = (s.low, s.high) if interval == "symmetric" else (s.short_low, s.short_high)
        stats.append([s.y, s.u, lo, hi])
    return np.std(stats, axis=0, ddof=1) / np.sqrt(parts)


def _check(got, published, sd, last_digit, mc_reference=True):
    k = 4 * np.sqrt(2) if mc_reference else 4
    tol = k * sd + 0.5 * last_digit
    assert abs(got - published) <= tol, (got, published, tol)


def test_ranks_agree_with_the_sorted_interval():
    x = np.random.default_rng(0).normal(size=1001)
    r_lo, r_hi = symmetric_ranks(1001, 0.95)
    lo, hi = symmetric_interval(x)
    xs = np.sort(x)
    assert (xs[r_lo - 1], xs[r_hi - 1]) == (lo, hi)
    assert r_hi - r_lo == coverage_count(1001, 0.95)


@pytest.mark.parametrize(
    "m, p, q, ranks",
    [
        (1000, 0.95, 950, (25, 975)),  # pM integer, (M - q)/2 integer
        (1001, 0.95, 951, (25, 976)),  # pM = 950.95 -> q = int(pM + 1/2)
        (1021, 0.95, 970, (26, 996)),  # M - q = 51 odd -> r = int((M - q + 1)/2)
        (107, 0.9, 96, (6, 102)),  # pM = 96.3 -> 96, M - q = 11
        (10**4, 0.99, 9900, (50, 9950)),
    ],
)
def test_ranks_follow_jcgm_101_7_7(m, p, q, ranks):
    """q and r written out from JCGM 101 7.7.1-7.7.2 (the worked examples cannot see r +- 1)."""
    assert coverage_count(m, p) == q
    assert symmetric_ranks(m, p) == ranks
    x = np.arange(1.0, m + 1)[::-1]  # value = its 1-based rank after sorting
    assert symmetric_interval(x, p) == ranks
    lo, hi = shortest_interval(x, p)  # equal spacing: every r ties, the first is taken
    assert (lo, hi) == (1.0, 1.0 + q)


def test_9_2_2_sum_of_four_normals():
    pdfs = [Pdf.normal(0.0, 1.0)] * 4
    v = monte_carlo(lambda x: x.sum(axis=1), pdfs, M, seed=1)
    s = summarize(v)
    sd = _numerical_std(v, 0.95)
    # exact: y = 0, u = 2, 95 % interval +-1.96 * 2 = +-3.92
    _check(s.y, 0.0, sd[0], 0.0, mc_reference=False)
    _check(s.u, 2.00, sd[1], 0.01, mc_reference=False)
    _check(s.low, -3.92, sd[2], 0.01, mc_reference=False)
    _check(s.high, 3.92, sd[3], 0.01, mc_reference=False)
    g = gum_linear(lambda x: x.sum(axis=1), pdfs)
    assert g.u == pytest.approx(2.0, rel=1e-9)
    assert validate_gum(*g.interval(0.95), s, ndig=2)["valid"]


def test_9_2_3_sum_of_four_rectangulars():
    pdfs = [Pdf.uniform(-np.sqrt(3), np.sqrt(3))] * 4  # std 1
    v = monte_carlo(lambda x: x.sum(axis=1), pdfs, M, seed=2)
    s = summarize(v)
    sd = _numerical_std(v, 0.95)
    _check(s.u, 2.00, sd[1], 0.01, mc_reference=False)
    _check(s.low, -3.88, sd[2], 0.01)
    _check(s.high, 3.88, sd[3], 0.01)
    lo, hi = gum_linear(lambda x: x.sum(axis=1), pdfs).interval(0.95)
    assert (round(lo, 2), round(hi, 2)) == (-3.92, 3.92)


def _mass(x):
    m_r, dm_r, rho_a, rho_w, rho_r = x.T
    return (m_r + dm_r) * (1 + (rho_a - 1.2) * (1 / rho_w - 1 / rho_r)) - 100_000.0  # mg


MASS_PDFS = [
    Pdf.normal(100_000.000, 0.050),
    Pdf.normal(1.234, 0.020),
    Pdf.uniform(1.10, 1.30),
    Pdf.uniform(7000.0, 9000.0),
    Pdf.uniform(7950.0, 8050.0),
]


def test_9_3_mass_calibration_and_gum_fails_validation():
    v = monte_carlo(_mass, MASS_PDFS, M, seed=3)
    s = summarize(v)
    sd = _numerical_std(v, 0.95, interval="shortest")
    _check(s.y, 1.2341, sd[0], 1e-4)
    _check(s.u, 0.0754, sd[1], 1e-4)
    _check(s.short_low, 1.0834, sd[2], 1e-4)
    _check(s.short_high, 1.3825, sd[3], 1e-4)
    g = gum_linear(_mass, MASS_PDFS)
    assert round(float(g.y), 4) == 1.2340
    assert round(float(g.u), 4) == 0.0539
    # section 8 with one significant digit of u = 0.08 mg: delta = 0.005 mg, and the GUM fails
    val = validate_gum(*g.interval(0.95), s, ndig=1)
    assert float(val["delta"]) == pytest.approx(0.005)
    assert not val["valid"]
    assert min(val["d_low"], val["d_high"]) > 0.005


def _gauge(x):
    ls, d, d1, d2, alpha_s, theta_bar, delta, d_alpha, d_theta = x.T
    theta = theta_bar + delta
    return ls + d + d1 + d2 - ls * (d_alpha * theta + alpha_s * d_theta) - 50_000_000.0  # nm


GAUGE_PDFS = [
    Pdf.student_t(50_000_623.0, 25.0, 18),  # scale = GUM standard uncertainty, not the std
    Pdf.student_t(215.0, 5.8, 24),
    Pdf.student_t(0.0, 3.9, 5),
    Pdf.student_t(0.0, 6.7, 8),
    Pdf.uniform(9.5e-6, 13.5e-6),
    Pdf.normal(-0.1, 0.2),
    Pdf.arcsine(-0.5, 0.5),
    Pdf.curvilinear_trapezoidal(-1.0e-6, 1.0e-6, 0.1e-6),
    Pdf.curvilinear_trapezoidal(-0.050, 0.050, 0.025),
]


def test_9_5_gauge_block_99_percent():
    v = monte_carlo(_gauge, GAUGE_PDFS, M, seed=5)
    s = summarize(v, 0.99)
    sd = _numerical_std(v, 0.99)
    _check(s.y, 838.0, sd[0], 1.0)
    _check(s.u, 36.0, sd[1], 1.0)
    _check(s.low, 745.0, sd[2], 1.0)
    _check(s.high, 932.0, sd[3], 1.0)

    # the other scale convention (scale = std of the t variable) would give a visibly smaller u
    def as_std(p):
        loc, scale, dof = p.params
        return Pdf.student_t(loc, scale / np.sqrt(dof / (dof - 2)), dof)

    wrong = [as_std(p) if p.kind == "student_t" else p for p in GAUGE_PDFS]
    s_wrong = summarize(monte_carlo(_gauge, wrong, 200_000, seed=6), 0.99)
    assert s.u - s_wrong.u > 10 * sd[1]


# JCGM 100 H.1 (the same gauge block): H.1.3 assigns rectangular PDFs to delta_alpha and
# delta_theta, u = 1e-6/sqrt(3) = 0.58e-6 /degC and 0.05/sqrt(3) = 0.029 degC, and H.1.3.4 /
# H.1.3.6 their reliability, nu = 50 and nu = 2. JCGM 101 9.5 replaces them by the curvilinear
# trapezoids of GAUGE_PDFS (std 0.0300 degC for delta_theta), which moves nu_eff below 16.
GAUGE_H1_PDFS = GAUGE_PDFS[:7] + [Pdf.uniform(-1.0e-6, 1.0e-6), Pdf.uniform(-0.050, 0.050)]
GAUGE_H1_DOF = [None] * 7 + [50, 2]  # _gauge order: ..., d_alpha, d_theta
# GUM standard uncertainties in _gauge order (Student-t inputs: the scale, H.1.3.1-H.1.3.2)
GAUGE_H1_U = [25.0, 5.8, 3.9, 6.7, 4e-6 / np.sqrt(12), 0.2, 0.5 / np.sqrt(2)] + [
    1e-6 / np.sqrt(3),
    0.05 / np.sqrt(3),
]


def test_h_1_gauge_block_gum_uncertainty_framework():
    g = gum_linear(_gauge, GAUGE_H1_PDFS, dof=GAUGE_H1_DOF)
    # H.1.6: l = 50.000 838 mm, u_c = 32 nm, nu_eff = 16, t_99(16) = 2.92, U_99 = 93 nm
    assert round(float(g.y)) == 838
    assert round(float(g.u)) == 32
    assert 16.0 <= g.dof < 17.0
    k = g.coverage_factor(0.99)
    assert round(float(k), 2) == 2.92
    lo, hi = g.interval(0.99)
    assert float(hi - g.y) == pytest.approx(float(g.y - lo))
    # the GUM multiplies its rounded figures, U_99 = 2.92 x 32 nm = 93 nm (unrounded 92.5 nm)
    assert round(round(float(k), 2) * round(float(g.u))) == 93
    assert 92.0 < float(hi - g.y) < 93.5

    # Welch-Satterthwaite (GUM eq. G.2b) written out from the sensitivities and the GUM u's
    ci = g.sensitivities * np.array(GAUGE_H1_U)
    uc4 = np.sum(ci**2) ** 2
    ws = ci[0] ** 4 / 18 + ci[1] ** 4 / 24 + ci[2] ** 4 / 5 + ci[3] ** 4 / 8
    assert float(g.u) == pytest.approx(np.sqrt(np.sum(ci**2)), rel=1e-12)
    assert float(g.dof) == pytest.approx(uc4 / (ws + ci[7] ** 4 / 50 + ci[8] ** 4 / 2), rel=1e-12)

    # without the stated reliability of delta_alpha and delta_theta only the Type A terms count
    g_inf = gum_linear(_gauge, GAUGE_H1_PDFS)
    assert float(g_inf.u) == float(g.u)
    assert float(g_inf.dof) == pytest.approx(uc4 / ws, rel=1e-12)
    assert g_inf.dof > 45.0  # 45.6: t_99 = 2.69, U_99 = 85 nm
    assert round(float(g_inf.coverage_factor(0.99)), 2) == 2.69

    # JCGM 101's curvilinear trapezoids: u(delta_theta) = 0.0300 degC, nu_eff 15.8 -> 15
    g_101 = gum_linear(_gauge, GAUGE_PDFS, dof=GAUGE_H1_DOF)
    assert 15.0 <= g_101.dof < 16.0


def test_gum_welch_satterthwaite_sum_of_t_and_normal():
    """Y = X1 + X2, X1 ~ t_4(0, 1) (u = 1, nu = 4), X2 ~ N(0, 1): u_c = sqrt 2,
    nu_eff = 2**2 / (1**4 / 4) = 16, k_95 = t_0.975(16) = 2.120."""
    pdfs = [Pdf.student_t(0.0, 1.0, 4), Pdf.normal(0.0, 1.0)]
    g = gum_linear(lambda x: x.sum(axis=1), pdfs)
    assert float(g.u) == pytest.approx(np.sqrt(2.0), rel=1e-9)
    assert float(g.dof) == pytest.approx(16.0, rel=1e-9)
    np.testing.assert_allclose(g.contributions, [0.5, 0.5], rtol=1e-9)
    assert round(float(g.coverage_factor(0.95)), 3) == 2.120
    lo, hi = g.interval(0.95)
    assert round(float(hi), 3) == round(2.120 * np.sqrt(2.0), 3) == 2.998
    lo, hi = g.interval(0.95, dof=np.inf)  # explicit dof still used as given
    assert round(float(hi), 3) == round(1.960 * np.sqrt(2.0), 3)
    # a stated Type B reliability for X2: 4 / (1/4 + 1/4) = 8
    assert float(gum_linear(lambda x: x.sum(axis=1), pdfs, dof=[None, 4]).dof) == pytest.approx(8)


def test_gum_dof_edge_cases_and_bad_arguments():
    import warnings

    total = lambda x: x.sum(axis=1)  # noqa: E731
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        g0 = gum_linear(total, [Pdf.constant(1.0), Pdf.constant(2.0)], dof=[3, None])
        assert float(g0.u) == 0.0 and np.isinf(g0.dof)
        assert g0.interval(0.95) == (3.0, 3.0)
        # a zero contribution with finite dof adds nothing
        g1 = gum_linear(total, [Pdf.constant(1.0), Pdf.normal(0.0, 1.0)], dof=[2, None])
        assert np.isinf(g1.dof)
    for bad in ([None], [None, 0], [None, -1.0], [None, np.nan], [None, "5"], [None, True], 5):
        with pytest.raises(CfmInputError, match="gum_linear 'dof'"):
            gum_linear(total, [Pdf.normal(0, 1)] * 2, dof=bad)
    with pytest.raises(CfmInputError, match="Student-t"):
        gum_linear(total, [Pdf.student_t(0, 1, 4), Pdf.normal(0, 1)], dof=[5, None])
    assert float(gum_linear(total, [Pdf.student_t(0, 1, 4)] * 2, dof=[4, None]).dof) == 8


def test_adaptive_procedure_stops_at_the_numerical_tolerance():
    r = adaptive_monte_carlo(lambda x: x.sum(axis=1), [Pdf.normal(0, 1)] * 4, ndig=2, seed=7)
    assert r.converged
    assert np.all(r.two_s <= r.delta)
    assert float(r.delta) == 0.05  # u = 2.0 -> two significant digits -> 10**-1 / 2
    s = r.summary
    assert s.trials == r.batches * r.batch_trials >= 2 * 10**4
    # the result is within the stated tolerance of the exact values
    assert abs(s.u - 2.0) <= r.delta and abs(s.high - 3.92) <= 2 * r.delta


def test_adaptive_stopping_rule_recomputed_from_the_batches():
    """7.9.4 g)-k) written out: batch h uses child h of SeedSequence(seed); s**2 is
    sum (x_r - mean)**2 / (h (h - 1)) for each of y, u, y_low, y_high; stop at the first h >= 2
    where all four 2 s <= delta(u of all h M values). Seed 8 needs several batches."""
    pdfs, m = [Pdf.normal(0, 1)] * 4, 10**4
    r = adaptive_monte_carlo(lambda x: x.sum(axis=1), pdfs, ndig=2, seed=8)
    assert r.converged and r.batch_trials == m and r.batches > 3
    kids = np.random.SeedSequence(8).spawn(r.batches)
    batches = [draw_inputs(pdfs, m, np.random.default_rng(k)).sum(axis=1) for k in kids]
    stats = []
    for h, b in enumerate(batches, start=1):
        s = summarize(b)
        stats.append([s.y, s.u, s.low, s.high])
        if h < 2:
            continue
        x = np.array(stats)
        two_s = 2 * np.sqrt(((x - x.mean(axis=0)) ** 2).sum(axis=0) / (h * (h - 1)))
        delta = numerical_tolerance(np.concatenate(batches[:h]).std(ddof=1), 2)
        assert np.all(two_s <= delta) == (h == r.batches), h  # stops at the first such h
    np.testing.assert_allclose(r.two_s, two_s, rtol=1e-12)
    assert r.summary.trials == r.batches * m
    assert r.summary.high == summarize(np.concatenate(batches)).high


def test_numerical_tolerance_examples():
    # JCGM 101 7.9.2 examples 1-3: u = 0.000 35 g with two and with one digit, u = 2 K
    assert numerical_tolerance(0.00035, 2) == pytest.approx(0.000005)
    assert numerical_tolerance(0.00035, 1) == pytest.approx(0.00005)
    assert numerical_tolerance(2.0, 1) == pytest.approx(0.5)
    assert numerical_tolerance(0.028, 2) == pytest.approx(0.0005)
    assert numerical_tolerance(0.0754, 1) == pytest.approx(0.005)
    assert numerical_tolerance(36.0, 2) == pytest.approx(0.5)
    # c is u rounded to n_dig digits: 0.0996 -> 0.10 = 10 x 10**-2 (not 99.6 x 10**-3)
    assert numerical_tolerance(0.0996, 2) == pytest.approx(0.005)
    assert numerical_tolerance(0.0994, 2) == pytest.approx(0.0005)
    assert numerical_tolerance(0.96, 1) == pytest.approx(0.5)
    np.testing.assert_allclose(numerical_tolerance([9.96, 0.0, 1e-3], 2), [0.5, 0.0, 5e-5])


def test_variance_shares_and_shortest_interval():
    sh = variance_shares(np.array([1.0, 2.0, 0.0]), np.array([3.0, 1.0, 5.0]))
    np.testing.assert_allclose(sh, [9 / 13, 4 / 13, 0.0])
    x = np.random.default_rng(1).exponential(size=200_001)
    lo, hi = shortest_interval(x, 0.95)
    slo, shi = symmetric_interval(x, 0.95)
    assert hi - lo < shi - slo  # skewed: the shortest interval is shorter
    assert lo == pytest.approx(0.0, abs=1e-3)
