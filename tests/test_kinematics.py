"""HTM chain (eq. 1-10), numba kernels against the numpy reference, streaming Monte Carlo."""

from dataclasses import replace

import numba
import numpy as np
import pytest

from cfm_fem import _kernels as K
from cfm_fem import testing as twins
from cfm_fem.models import kinematics as kin
from cfm_fem.models.bench import ERROR_NAMES, ReadingDelay, error_index
from cfm_fem.models.mc import Pdf, symmetric_interval
from cfm_fem.models.rotations import rotation_zyx


def _rx(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def _ry(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def _rz(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def test_rotation_is_eq4_zyx_product():
    phi, theta, psi = 0.3, -0.7, 1.1
    r = rotation_zyx(phi, theta, psi)
    np.testing.assert_allclose(r, _rz(psi) @ _ry(theta) @ _rx(phi), atol=1e-15)
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-15)
    r_k = np.empty((3, 3))
    K.rotation_zyx_into(phi, theta, psi, r_k)
    np.testing.assert_array_equal(r_k, r)


@pytest.mark.slow
def test_zero_errors_give_zero_error(bench):
    q = bench.grid_points()
    e = kin.probe_errors_for_bench(bench, np.zeros((1, 21)), q)
    assert np.abs(e).max() < 1e-12
    g = kin.kernel_geometry(bench)
    out = np.empty(3)
    K.probe_error_mm(
        np.zeros(21), q[-1], np.zeros(3), g.stack, g.mounts, g.tool, g.strokes, g.profiles, out
    )
    assert np.abs(out).max() < 1e-12


def test_single_errors_have_their_closed_form(bench):
    q = np.array([[150.0, 75.0, 400.0]])
    tool = bench.tool_offset_mm
    p = np.zeros((1, 21))
    # positioning error of X moves the probe along x only
    p[0, error_index("delta_x(x)")] = 1e-3
    np.testing.assert_allclose(
        kin.probe_errors_for_bench(bench, p, q)[0, 0], [1e-3, 0, 0], atol=1e-14
    )
    # yaw of the Z carriage (rotation about y) turns everything above it: E = (R - I) v
    p[:] = 0
    theta = 2e-4
    p[0, error_index("eps_y(z)")] = theta
    v = np.array([q[0, 0], q[0, 1], 0.0]) + tool
    expected = _ry(theta) @ v - v
    np.testing.assert_allclose(kin.probe_errors_for_bench(bench, p, q)[0, 0], expected, atol=1e-13)
    # squareness X-Z: the X travel direction tilts towards +z by alpha
    p[:] = 0
    alpha = 5e-4
    p[0, error_index("alpha_xz")] = alpha
    expected = q[0, 0] * np.array([np.cos(alpha) - 1, 0, np.sin(alpha)])
    np.testing.assert_allclose(kin.probe_errors_for_bench(bench, p, q)[0, 0], expected, atol=1e-13)
    # axis noise enters as a displacement along the (error-free) axes
    dq = np.array([1e-3, -2e-3, 3e-3])
    np.testing.assert_allclose(
        kin.probe_errors_for_bench(bench, np.zeros((1, 21)), q, dq)[0, 0], dq, atol=1e-13
    )


def test_squareness_convention_closes_the_angle():
    for stack in ([2, 0, 1], [0, 1, 2], [1, 2, 0]):
        d = kin.travel_directions(stack, np.array([1e-3, 2e-3, 3e-3]))
        # to first order d_a . d_b = sin(alpha_ab) whatever the stacking order
        assert d[0] @ d[1] == pytest.approx(1e-3, abs=1e-5)
        assert d[0] @ d[2] == pytest.approx(2e-3, abs=1e-5)
        assert d[1] @ d[2] == pytest.approx(3e-3, abs=1e-5)
        np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-15)


def _random_geometry(rng, stack):
    mounts = rng.normal(0, 50, (3, 3))
    tool = rng.normal(0, 300, 3)
    strokes = np.array([150.0, 200.0, 800.0])
    profiles = np.zeros((21, 3))
    profiles[:, 0] = 1.0
    profiles[:18, 1:] = rng.normal(0, 0.5, (18, 2))  # position-dependent errors
    return np.array(stack, dtype=np.int64), mounts, tool, strokes, profiles


@pytest.mark.parametrize("stack", [[2, 0, 1], [0, 1, 2], [1, 0, 2], [2, 1, 0]])
def test_kernel_matches_numpy_reference(stack):
    rng = np.random.default_rng(7)
    stk, mounts, tool, strokes, profiles = _random_geometry(rng, stack)
    # large errors (mrad, 10 um) so that second-order terms of the exact chain matter
    params = np.where(np.arange(21) % 6 < 3, 1e-2, 1e-3) * rng.normal(size=(4, 21))
    params[:, 18:] = rng.normal(0, 1e-3, (4, 3))
    q = rng.uniform(0, 1, (30, 3)) * strokes
    dq = rng.normal(0, 3e-3, (4, 30, 3))
    ref = kin.probe_errors(params, q, dq, stk, mounts, tool, strokes, profiles)
    out = np.empty(3)
    worst = 0.0
    for t in range(4):
        for i in range(30):
            K.probe_error_mm(params[t], q[i], dq[t, i], stk, mounts, tool, strokes, profiles, out)
            worst = max(worst, np.abs(out - ref[t, i]).max())
    assert worst < 1e-12
    assert np.abs(ref).max() > 0.1  # mm: second-order terms (~1e-3 mm) far above 1e-12


@pytest.mark.parametrize("stack", [[2, 0, 1], [1, 2, 0]])
def test_collapsed_trial_terms_match_the_chain(stack):
    rng = np.random.default_rng(8)
    stk, mounts, tool, strokes, _ = _random_geometry(rng, stack)
    profiles = np.ones((21, 1))
    params = 1e-3 * rng.normal(size=(5, 21))
    q = rng.uniform(0, 1, (40, 3)) * strokes
    dq = rng.normal(0, 3e-3, (5, 40, 3))
    terms = np.empty((5, 21))
    K.trial_terms(params, stk, mounts, tool, terms)
    c, g, d = terms[:, None, 0:3], terms[:, None, 3:12], terms[:, None, 12:21]
    e = c + sum(q[None, :, a : a + 1] * g[..., 3 * a : 3 * a + 3] for a in range(3))
    e = e + sum(dq[..., a : a + 1] * d[..., 3 * a : 3 * a + 3] for a in range(3))
    ref = kin.probe_errors(params, q, dq, stk, mounts, tool, strokes, profiles)
    assert np.abs(e - ref).max() < 1e-12


@pytest.mark.slow
def test_the_seam_kernels_are_callable_from_user_njit(bench):
    g = kin.kernel_geometry(bench)
    _, nkey, fkey = kin.geometry._keys(5)
    params = kin.draw_error_sets(bench, 3, seed=5)
    q = bench.grid_points()[:10]

    @numba.njit
    def user_kernel(  # noqa: PLR0917 (the seam kernel's own signature)
        params,
        q,
        sig,
        speed,
        tau_code,
        tau_par,
        stack,
        mounts,
        tool,
        strokes,
        profiles,
        nkey,
        fkey,
        out,
    ):
        dq = np.empty(3)
        e = np.empty(3)
        for t in range(params.shape[0]):
            for i in range(q.shape[0]):
                K.axis_noise_mm(nkey, fkey, t, i, sig, speed, tau_code, tau_par, dq)
                K.probe_error_mm(params[t], q[i], dq, stack, mounts, tool, strokes, profiles, e)
                out[t, i] = e

    out = np.empty((3, 10, 3))
    user_kernel(
        params,
        q,
        g.sig,
        g.speed,
        g.tau_code,
        g.tau_par,
        g.stack,
        g.mounts,
        g.tool,
        g.strokes,
        g.profiles,
        nkey,
        fkey,
        out,
    )
    for t in range(3):
        dq = kin.point_noise(bench, t, range(10), seed=5)
        ref = kin.probe_errors_for_bench(bench, params[t : t + 1], q, dq[None])[0]
        np.testing.assert_allclose(out[t], ref, atol=1e-12)


def test_draw_error_sets_numba_numpy_twins_and_reproducibility(bench):
    a = kin.draw_error_sets(bench, 300, seed=11)
    b = twins.draw_error_sets_numpy(bench, 300, seed=11)
    np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-18)
    np.testing.assert_array_equal(kin.draw_error_sets(bench, 100, seed=11, start=200), a[200:])
    for start in (200, 2**33 + 7):  # a counter past 32 bits: the numpy twin, not numba itself
        np.testing.assert_allclose(
            kin.draw_error_sets(bench, 50, seed=11, start=start),
            twins.draw_error_sets_numpy(bench, 50, seed=11, start=start),
            rtol=1e-12,
            atol=1e-18,
        )
    assert not np.array_equal(kin.draw_error_sets(bench, 300, seed=12), a)
    numba.set_num_threads(1)
    try:
        one = kin.draw_error_sets(bench, 5000, seed=3)
    finally:
        numba.set_num_threads(numba.config.NUMBA_NUM_THREADS)
    np.testing.assert_array_equal(one, kin.draw_error_sets(bench, 5000, seed=3))
    # moments of the Table II PDFs, within 5 standard errors of 5000 draws
    m, s = bench.error_means(), bench.error_stds()
    np.testing.assert_array_less(np.abs(one.mean(0) - m), 5 * s / np.sqrt(5000) + 1e-18)


def test_ndtri_matches_scipy():
    from scipy.special import ndtri

    u = np.concatenate([np.logspace(-300, -1, 400), np.linspace(0.01, 0.99, 999)])
    u = np.concatenate([u, 1 - u[(u < 0.5) & (u > 1e-15)]])  # the kernel's u never reaches 1
    mine = np.array([K.ndtri(x) for x in u])
    np.testing.assert_allclose(mine, ndtri(u), rtol=2e-14, atol=1e-15)


def test_normal_generator_is_standard_normal():
    """KS and moments of the counter-based ziggurat, adjacent draws uncorrelated."""
    from scipy import stats

    @numba.njit
    def draw(nkey, fkey, n, out):
        for t in range(n):
            z0, z1, z2 = K.rng._three_normals(K.trial_key(nkey, t), fkey, 17)
            out[t, 0] = z0
            out[t, 1] = z1
            out[t, 2] = z2

    for seed in (0, 2**62 + 1):  # both signs of the boxed key once mattered
        _, nkey, fkey = kin.geometry._keys(seed)
        z = np.empty((200_000, 3))
        draw(nkey, fkey, len(z), z)
        se = 1 / np.sqrt(len(z))
        assert np.all(np.abs(z.mean(0)) < 5 * se)
        assert np.all(np.abs(z.std(0) - 1) < 5 * se / np.sqrt(2))
        for j in range(3):
            assert stats.kstest(z[:, j], "norm").pvalue > 1e-4
        assert abs(np.corrcoef(z[:, 0], z[:, 1])[0, 1]) < 5 * se
        assert abs(np.corrcoef(z[1:, 0], z[:-1, 0])[0, 1]) < 5 * se


def _all_samples(bench, q, trials, seed):
    """Every (trial, point) sample of the kernels: E_x, E_y, E_z, |E|, shape (n, 4, trials)."""
    eng = kin.monte_carlo._Engine(bench, seed, 4096)
    out = np.empty((len(q), 4, trials))
    for a, b in kin.monte_carlo._blocks(0, trials, 4096):
        n = eng.prepare(a, b)
        vals = np.empty((len(q), 4, n))
        eng.pilot(a, n, np.ascontiguousarray(q), np.arange(len(q)), vals)
        out[..., a:b] = vals
    return out


def _check_against_brute_force(bench, q, trials, seed, **kw):
    res = kin.run_kinematics(bench, trials=trials, seed=seed, q_cmd=q, **kw)
    v = _all_samples(bench, q, trials, seed)
    np.testing.assert_allclose(res.mean, v.mean(-1), rtol=1e-9, atol=1e-13)
    np.testing.assert_allclose(res.std, v.std(-1, ddof=1), rtol=1e-7, atol=1e-13)
    lo, hi = symmetric_interval(v, 0.95)
    np.testing.assert_array_equal(res.low, lo)  # exact order statistics
    np.testing.assert_array_equal(res.high, hi)
    return res, v


def test_streaming_statistics_are_exact(bench):
    q = bench.grid_points()[::37]
    _check_against_brute_force(bench, q, 4096 + 517, seed=5)  # a last sub-block of 5 trials
    res, v = _check_against_brute_force(bench, q, 3000, seed=4)
    # the kernel's samples are the exact model with the documented noise
    params = kin.draw_error_sets(bench, 3, seed=4)
    for t in range(3):
        dq = kin.point_noise(bench, t, range(len(q)), seed=4)
        ref = kin.probe_errors_for_bench(bench, params[t : t + 1], q, dq[None])[0]
        np.testing.assert_allclose(v[:, :3, t], ref, atol=1e-12)


@pytest.mark.slow
def test_windows_narrow_and_stay_exact(bench, monkeypatch):
    q = bench.grid_points()[::37]
    monkeypatch.setattr(
        kin.monte_carlo, "NARROW_FIRST", 4096
    )  # narrowings at 4096, 8192, 16384 trials
    seen = []

    def spy(values, off, cap, fill, below, lo, hi, klo, khi):  # noqa: PLR0917 (narrow's)
        before = (hi - lo).copy()
        narrow(values, off, cap, fill, below, lo, hi, klo, khi)
        seen.append((before, hi - lo, fill.copy(), khi - klo + 1))

    narrow = K.narrow_windows
    monkeypatch.setattr(K, "narrow_windows", spy)
    res, _ = _check_against_brute_force(bench, q, 6 * 4096, seed=3, pilot=1024)
    assert len(seen) == 3
    for before, after, kept, ranks in seen:
        assert np.all(after <= before) and np.mean(after / before) < 0.8
        assert np.all(kept >= ranks)  # at least the ranks that may hold the end
    assert not any("recounted" in n for n in res.notes)
    # ranks that cannot hold the ends: every window loses its end, every point is recounted
    # in two passes, still exact
    monkeypatch.setattr(kin.monte_carlo, "NARROW_SIGMAS", -1e9)
    res, _ = _check_against_brute_force(bench, q, 6 * 4096, seed=3, pilot=1024)
    assert (
        f"{len(q)} point(s) whose window lost its interval end were recounted in two passes"
        in " ".join(res.notes)
    )


def test_a_store_too_large_takes_the_generic_path(bench, monkeypatch):
    """A run whose window store would pass STORE_BYTES counts and regenerates (two passes),
    exact all the same; an adaptive run there keeps the trial count its batches chose."""
    q = bench.grid_points()[::61]
    monkeypatch.setattr(kin.monte_carlo, "STORE_BYTES", 1)
    res, _ = _check_against_brute_force(bench, q, 3000, seed=2)
    assert "second pass that regenerates every sample" in res.interval_method
    ad = kin.run_kinematics(bench, seed=2, q_cmd=q, adaptive_digits=1, max_trials=40_000)
    assert ad.trials == ad.adaptive["batches"] * ad.adaptive["batch_trials"]
    assert "second pass" in ad.interval_method


def test_overflowing_stores_are_recounted_exactly(bench, monkeypatch):
    q = bench.grid_points()[::53]
    monkeypatch.setattr(
        kin.monte_carlo, "_margin", lambda expect: np.ceil(0.5 * np.asarray(expect))
    )
    res, _ = _check_against_brute_force(bench, q, 3 * 4096, seed=6)
    assert f"{len(q)} point(s) whose window lost" in " ".join(res.notes)


def test_windows_missed_by_a_tiny_pilot_are_recounted(bench):
    q = bench.grid_points()[::101]
    res, _ = _check_against_brute_force(bench, q, 2000, seed=9, pilot=3, window_slots=8)
    assert any("widened" in n for n in res.notes)


@pytest.mark.slow
def test_generic_path_position_dependent_and_speed_tau(bench, monkeypatch):
    errors = list(bench.errors)
    k = error_index("delta_z(z)")
    errors[k] = replace(errors[k], profile=(0.2, 1.0, -0.5))
    b = replace(
        bench,
        errors=tuple(errors),
        delay=ReadingDelay(
            "speed_tau", np.zeros(3), np.array([0.0, 0.0, 20.0]), Pdf.uniform(0.0, 2e-4)
        ),
    )
    assert not kin.monte_carlo._Engine(b, 0, 16).fast
    q = b.grid_points()[::117]
    res, v = _check_against_brute_force(b, q, 1500, seed=2)
    params = kin.draw_error_sets(b, 2, seed=2)
    for t in range(2):
        dq = kin.point_noise(b, t, range(len(q)), seed=2)
        ref = kin.probe_errors_for_bench(b, params[t : t + 1], q, dq[None])[0]
        np.testing.assert_allclose(v[:, :3, t], ref, atol=1e-12)
    assert "one pass" in res.interval_method
    # the one pass over `fill_values` with its windows narrowing (at 4096, 8192, 16384 trials)
    monkeypatch.setattr(kin.monte_carlo, "NARROW_FIRST", 4096)
    res, _ = _check_against_brute_force(b, q, 6 * 4096, seed=4, pilot=1024)
    assert not any("recounted" in n for n in res.notes)


def test_results_do_not_depend_on_threads(bench):
    q = bench.grid_points()[::29]
    numba.set_num_threads(1)
    try:
        one = kin.run_kinematics(bench, trials=40_000, seed=6, q_cmd=q)  # one narrowing
    finally:
        numba.set_num_threads(numba.config.NUMBA_NUM_THREADS)
    assert numba.get_num_threads() == 2 or numba.config.NUMBA_NUM_THREADS < 2
    two = kin.run_kinematics(bench, trials=40_000, seed=6, q_cmd=q)
    for name in ("mean", "std", "low", "high"):
        np.testing.assert_array_equal(getattr(one, name), getattr(two, name))


def test_a_block_of_points_alone_gives_the_full_runs_numbers(bench):
    """What a Dask worker does: each point's numbers (windows, narrowings, ends) are its own."""
    q = bench.grid_points()[::29]
    full = kin.run_kinematics(bench, trials=40_000, seed=6, q_cmd=q)
    rows = np.array([3, 4, 17, 30])
    part = kin.run_kinematics(bench, trials=40_000, seed=6, q_cmd=q[rows], point_index=rows)
    for name in ("mean", "std", "low", "high"):
        np.testing.assert_array_equal(getattr(part, name), getattr(full, name)[rows])


def test_mc_agrees_with_linearised_model_within_mc_uncertainty(bench):
    m = 20_000
    res = kin.run_kinematics(bench, trials=m, seed=1, exact=False)
    pred = kin.uncertainty_budget(bench)["predicted"]
    for a in "xyz":
        u = res.pooled[a]["std_um"]
        # numerical std: u / sqrt(M) for a mean, ~u / sqrt(2M) for a std (normal-like output)
        assert abs(res.pooled[a]["systematic_um"] - pred[a]["systematic_um"]) < 5 * u / np.sqrt(m)
        assert abs(u - pred[a]["std_um"]) < 5 * u / np.sqrt(2 * m)


def test_mc_spread_shrinks_as_one_over_sqrt_n(bench):
    from scipy import stats

    q = bench.grid_points()[::311]
    n_seeds = 40
    spread = []
    for m in (150, 600):
        vals = [
            kin.run_kinematics(bench, trials=m, seed=s, q_cmd=q, exact=False).pooled["x"]["std_um"]
            for s in range(n_seeds)
        ]
        spread.append(np.std(vals, ddof=1))
    # 4x the trials must halve the spread; the band is the 99.9 % range of the ratio of two
    # sample standard deviations (F distribution with n_seeds - 1 degrees of freedom each)
    f_lo, f_hi = stats.f.ppf([0.0005, 0.9995], n_seeds - 1, n_seeds - 1)
    assert 2 * np.sqrt(f_lo) < spread[0] / spread[1] < 2 * np.sqrt(f_hi)


def test_budget_shares_sum_to_one_and_design_meets_target(bench):
    bud = kin.uncertainty_budget(bench)
    for key in ("var_share", "up_share"):
        for a in "xyz":
            assert sum(r[key][a] for r in bud["rows"]) == pytest.approx(1.0, abs=1e-12)
    assert len(bud["rows"]) == len(ERROR_NAMES) + 1
    target = np.array([0.018, 0.013, 0.014])
    d = kin.design_tolerances(bench, target)
    assert np.all(np.array(d["up_after_plan_um"]) <= 1e3 * target * (1 + 1e-9))
    assert np.all(np.array(d["up_at_common_um"]) <= 1e3 * target * (1 + 1e-9))
    for r in d["rows"]:
        if r["factor"] is not None and np.isfinite(r["factor"]):
            assert r["up_at_factor_um"] is not None
    # a loose target: every error may be loosened (factor > 1)
    loose = kin.design_tolerances(bench, [1.0, 1.0, 1.0])
    assert all(r["factor"] is None or r["factor"] > 1 for r in loose["rows"])
    assert loose["plan"] == []


def test_up_share_is_an_elasticity_and_negative_where_the_mean_opposes(bench):
    """What the budget's columns are (README, `cfm-fem kinematics`/`tolerance` headers):
    var_share a share of u^2 in [0, 1]; up_share = (1/2) d ln U_p^2 / d ln s_k, negative for
    eps_y(z) on Z (its mean opposes the total systematic error): tightening it raises U_p."""
    lm = kin.linear_model(bench)
    var_share, up_share = lm.shares()
    assert np.all((var_share >= 0) & (var_share <= 1))
    up2 = lm.pooled()[2] ** 2
    h = 1e-6
    for k in range(len(bench.errors)):
        s = np.ones(len(bench.errors))
        s[k] = 1 + h
        hi = lm.pooled(s)[2] ** 2
        s[k] = 1 - h
        lo = lm.pooled(s)[2] ** 2
        np.testing.assert_allclose(up_share[:, k], (hi - lo) / (2 * h) / (2 * up2), atol=1e-8)
    k = error_index("eps_y(z)")
    assert up_share[2, k] < -0.01  # Z axis
    s = np.ones(len(bench.errors))
    s[k] = 0.99
    assert lm.pooled(s)[2][2] > lm.pooled()[2][2]
    mean = lm.b.sum(-1)
    assert np.mean(lm.b[:, 2, k] * mean[:, 2]) < 0  # the mean part is what makes it negative


def test_adaptive_run_stops_at_the_numerical_tolerance(bench):
    q = bench.grid_points()[::113]
    res = kin.run_kinematics(bench, seed=3, q_cmd=q, adaptive_digits=2, exact=False)
    a = res.adaptive
    assert a["batches"] >= 2 and res.trials == a["batches"] * a["batch_trials"]
    assert a["converged"]  # u ~ 13 um: delta = 0.5 um, reached after two batches of 12288
    assert np.all(np.array(a["two_s_um"]) <= np.repeat(a["delta_um"], 3))
    assert kin.noise_keys(3) == kin.geometry._keys(3)[1:]


def test_degenerate_constant_bench(bench):
    """Constant errors, no noise: every trial gives the same error, std 0, a point interval."""
    errors = tuple(replace(e, pdf=Pdf.constant(1e-6 * (k + 1))) for k, e in enumerate(bench.errors))
    b = replace(
        bench,
        errors=errors,
        vibration_std_mm=np.zeros(3),
        delay=ReadingDelay("normal", np.zeros(3)),
    )
    q = b.grid_points()[::200]
    res = kin.run_kinematics(b, trials=50, seed=0, q_cmd=q)
    ref = kin.probe_errors_for_bench(b, b.error_means()[None], q)[0]
    np.testing.assert_allclose(res.mean[:, :3], ref, atol=1e-15)
    assert np.all(res.std < 1e-15)
    np.testing.assert_array_equal(res.low, res.high)
    np.testing.assert_allclose(res.low[:, :3], ref, atol=1e-15)


def test_budget_share_equals_variance_removed_by_fixing_the_error(bench):
    """First-order Sobol index by brute force: fix eps_y(z) at its mean and rerun the MC."""
    k = error_index("eps_y(z)")
    share = next(r for r in kin.uncertainty_budget(bench)["rows"] if r["name"] == "eps_y(z)")
    share = share["var_share"]["x"]
    errors = list(bench.errors)
    errors[k] = replace(errors[k], pdf=Pdf.constant(errors[k].pdf.mean))
    fixed = replace(bench, errors=tuple(errors))
    q = bench.grid_points()[::47]
    m = 20_000
    u_all = kin.run_kinematics(bench, trials=m, seed=8, q_cmd=q, exact=False).pooled["x"]["std_um"]
    u_fix = kin.run_kinematics(fixed, trials=m, seed=8, q_cmd=q, exact=False).pooled["x"]["std_um"]
    removed = 1 - (u_fix / u_all) ** 2
    # each u^2 has a relative MC std of about sqrt(2 / M); the two runs share no draws of eps_y(z)
    assert share == pytest.approx(removed, abs=5 * 2 * np.sqrt(2 / m))
    assert share > 0.3


def test_one_pass_kernels_match_numpy(bench):
    """The fused hot-path pass (sub-blocks, vectorised sums, slow-path samples redone, values
    kept in their windows) against the plain values of the same samples; then the narrowing
    and the selection of the ends against numpy."""
    q = np.ascontiguousarray(bench.grid_points()[::41])
    npts = len(q)
    pidx = np.arange(npts) * 41
    eng = kin.monte_carlo._Engine(bench, 11, 4096)
    assert eng.fast
    n = eng.prepare(0, 3000)
    vals = np.empty((npts, 4, n))
    eng.pilot(0, n, q, pidx, vals)
    lo = np.ascontiguousarray(np.quantile(vals, [0.01, 0.90], axis=-1).transpose(1, 2, 0))
    hi = np.ascontiguousarray(np.quantile(vals, [0.05, 0.99], axis=-1).transpose(1, 2, 0))
    shift = np.ascontiguousarray(vals[..., :50].mean(-1))
    acc = np.zeros((npts, 4, 2))
    below = np.zeros((npts, 4, 2), np.int64)
    store = kin.monte_carlo._Store(npts, 200)
    eng.keep(0, n, q, pidx, shift=shift, lo=lo, hi=hi, acc=acc, below=below, store=store)
    d = vals - shift[..., None]
    np.testing.assert_allclose(acc[..., 0], d.sum(-1), rtol=1e-11, atol=1e-15)
    np.testing.assert_allclose(acc[..., 1], (d * d).sum(-1), rtol=1e-11, atol=1e-15)
    inside = (vals[..., None, :] >= lo[..., None]) & (vals[..., None, :] <= hi[..., None])
    np.testing.assert_array_equal(below, (vals[..., None, :] < lo[..., None]).sum(-1))
    np.testing.assert_array_equal(store.fill, inside.sum(-1))
    assert store.fill.min() > 20 and store.fill.max() > store.cap.max()  # some overflowed
    for i, c, e in np.ndindex(npts, 4, 2):
        f = store.fill[i, c, e]
        if f <= store.cap[i, c, e]:
            got = store.values[store.off[i, c, e] : store.off[i, c, e] + f]
            np.testing.assert_array_equal(np.sort(got), np.sort(vals[i, c][inside[i, c, e]]))

    # narrowing keeps the ranks asked for (1-based among the n samples) and counts the rest
    ok = store.fill <= store.cap
    klo = np.clip(below + 5, 1, None)
    khi = below + np.maximum(store.fill - 5, 1)
    old_lo, old_hi, old_fill = lo.copy(), hi.copy(), store.fill.copy()
    flat = [x.reshape(-1) for x in (store.values, store.off, store.cap, store.fill, below)]
    K.narrow_windows(*flat, lo.reshape(-1), hi.reshape(-1), klo.ravel(), khi.ravel())
    srt = np.sort(vals, -1)
    for i, c, e in np.ndindex(npts, 4, 2):
        if not ok[i, c, e]:  # overflowed: left alone
            assert store.fill[i, c, e] == old_fill[i, c, e] and lo[i, c, e] == old_lo[i, c, e]
            continue
        assert old_lo[i, c, e] <= lo[i, c, e] <= srt[i, c, klo[i, c, e] - 1]
        assert srt[i, c, khi[i, c, e] - 1] <= hi[i, c, e] <= old_hi[i, c, e]
        v = vals[i, c]
        assert below[i, c, e] == np.count_nonzero(v < lo[i, c, e])
        kept = v[(v >= lo[i, c, e]) & (v <= hi[i, c, e])]
        got = store.values[store.off[i, c, e] : store.off[i, c, e] + store.fill[i, c, e]]
        np.testing.assert_array_equal(np.sort(got), np.sort(kept))
    # the ends: the order statistics of the ranks asked for, NaN where not held
    rank = np.clip(below + 3, 1, n)
    ends = np.empty((npts, 4, 2))
    values, off, cap, fill, below_flat = flat
    K.select_ends(values, off, fill, cap, below_flat, lo.ravel(), hi.ravel(), rank.ravel(),
                  ends.reshape(-1))  # fmt: skip
    want = np.take_along_axis(srt[:, :, None, :], rank[..., None] - 1, -1)[..., 0]
    np.testing.assert_array_equal(ends[ok], want[ok])
    assert np.isnan(ends[~ok]).all()


@pytest.mark.parametrize(
    "seed, message",
    [
        (-1, "--seed must be in [0, 2**63); got -1"),
        (2**63, "--seed must be in [0, 2**63); got 9223372036854775808"),
        (True, "--seed must be an integer in [0, 2**63); got True"),
        (1.0, "--seed must be an integer in [0, 2**63); got 1.0"),
    ],
    ids=["negative", "too_large", "bool", "float"],
)
def test_kinematics_seeds_follow_the_one_seed_rule(bench, seed, message):
    """kinematics kept its own seed check (another message, and True taken as seed 1); it is
    `cfm_fem.errors.check_seed` now, as every command and the sweep API."""
    from cfm_fem.errors import CfmInputError

    with pytest.raises(CfmInputError) as info:
        kin.draw_error_sets(bench, 2, seed)
    assert str(info.value) == message
    with pytest.raises(CfmInputError, match=r"^--seed must be"):
        kin.noise_keys(seed)


def test_kinematics_stream_keys_of_valid_seeds_are_unchanged():
    """The seed check changed; the keys (hence every number) of valid seeds did not."""
    expected = {
        0: (14347448314117563705, 8500450509414873753, 17593686279737627579),
        12345: (9998596017203915950, 15630863903320480134, 14432981579369329159),
        2**63 - 1: (4357909079089423242, 10249593929634935389, 17363596703774052514),
    }
    for seed, keys in expected.items():
        for s in (seed, np.int64(seed)):
            got = kin.geometry._keys(s)
            assert all(isinstance(k, np.uint64) for k in got)
            assert tuple(int(k) for k in got) == keys
