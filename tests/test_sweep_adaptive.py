"""The sweep's adaptive control-variate estimator (the default under the harmonic model):
against plain Monte Carlo of 1e5 trials, and the same numbers whatever the run layout."""

from __future__ import annotations

import json

import numba
import numpy as np
import pytest
from test_sweep_harmonic import grid_map, write_map_csv

from cfm_fem import _kernels
from cfm_fem.cli import main
from cfm_fem.models.harmonic_basis import field_basis, monomial_exponents
from cfm_fem.models.sweep import ADAPTIVE_PLAN, ADAPTIVE_PRECISION, SweepConfig
from cfm_fem.workflows.sweep.in_memory import run_sweep
from cfm_fem.workflows.sweep.problem import prepare_sweep

UP = [0.0, 50.0, 250.0]


def _uf(stats):
    return np.maximum(np.abs(stats[..., 3, 2]), np.abs(stats[..., 3, 3]))


@pytest.fixture(scope="module")
def curved_case():
    fm = grid_map()
    cfg = SweepConfig(up_um=UP, seed=5, field_model="harmonic", estimator="adaptive")
    _, problem, _ = prepare_sweep(fm, cfg)
    assert problem.estimator == "adaptive"
    fit = problem.harmonic
    model = (
        problem.coords, fit.coef, fit.degree, fit.scale, fit.reach_mm,
        np.ascontiguousarray(field_basis()), monomial_exponents(),
    )  # fmt: skip
    inner = np.flatnonzero(np.all(np.abs(fm.points) < [4.0, 4.0, 9.0], axis=1))
    nodes = np.random.default_rng(0).choice(inner, 24, replace=False).astype(np.int64)
    return problem, model, nodes


def test_adaptive_u_f_lies_within_its_precision_of_a_1e5_trial_reference(curved_case):
    """On a field curved enough that U_p = 250 um departs from first order, U_f of the
    adaptive estimator lies within +-1.4 % of plain Monte Carlo of 1e5 trials (independent
    seed) at 95 % of the nodes or more, and so do the other interval ends and the means to a
    small share of the standard deviation; the trial counts stay in the plan's range."""
    problem, model, nodes = curved_case
    keys = problem.keys[nodes]
    args = (model, problem.axis_scale, problem.scales_mm)
    buffers = _kernels.harmonic_cv_buffers(len(problem.scales_mm), 0.95, ADAPTIVE_PLAN)
    st, n_out, _, _, used, _ = _kernels.harmonic_cv_sweep(nodes, keys, *args, 5, 0.95,
                                                          ADAPTIVE_PLAN, buffers)  # fmt: skip
    ref = _kernels.harmonic_gauss_sweep(nodes, keys, *args, 100_000, 11, 0.95, False)[0]
    assert (n_out == 0).all() and (used <= ADAPTIVE_PLAN[1]).all()
    ran = used > 0  # 0: a trial beyond the model's reach, left to the plain Monte Carlo
    assert ran.sum() >= 20 and (used[ran] >= ADAPTIVE_PLAN[0]).all()
    assert np.isnan(st[~ran]).all()
    st, ref = st[ran], ref[ran]
    d = np.abs(_uf(st[:, 1:]) / _uf(ref[:, 1:]) - 1.0)
    assert np.mean(d <= ADAPTIVE_PRECISION) >= 0.95, np.sort(d.ravel())[-5:]
    sd = ref[:, 1:, :, 1]
    for j in (0, 1, 2, 3):  # mean, std, symmetric ends: within 5 % of a std
        assert np.percentile(np.abs(st[:, 1:, :, j] - ref[:, 1:, :, j]) / sd, 95) < 0.05, j
    for j in (4, 5):  # shortest ends: a noisier statistic of both estimators
        assert np.percentile(np.abs(st[:, 1:, :, j] - ref[:, 1:, :, j]) / sd, 95) < 0.15, j
    np.testing.assert_array_equal(st[:, 0], 0.0)
    # the curvature shows at 250 um: the first-order U_f (1.96 sigma) is off there
    lin = 1.959964 * ref[:, 2, 3, 1]
    assert np.median(np.abs(lin / _uf(ref[:, 2]) - 1.0)) > 2 * ADAPTIVE_PRECISION


def test_work_arrays_carried_between_blocks_give_the_same_numbers(curved_case):
    """Nodes run in blocks, each call taking the work arrays the previous one returned (grown
    by its nodes of many trials), give the numbers of one call on all of them, and of calls
    each starting from fresh arrays."""
    problem, model, nodes = curved_case
    keys = problem.keys[nodes]
    args = (model, problem.axis_scale, problem.scales_mm, 5, 0.95, ADAPTIVE_PLAN)

    def fresh():
        return _kernels.harmonic_cv_buffers(len(problem.scales_mm), 0.95, ADAPTIVE_PLAN)

    whole = _kernels.harmonic_cv_sweep(nodes, keys, *args, fresh())
    assert whole[4].max() > 4 * ADAPTIVE_PLAN[0]  # some node grew the arrays
    carried, alone, buffers = [], [], fresh()
    for i0 in range(0, len(nodes), 7):
        sl = slice(i0, i0 + 7)
        *out, buffers = _kernels.harmonic_cv_sweep(nodes[sl], keys[sl], *args, buffers)
        carried.append(out)
        alone.append(_kernels.harmonic_cv_sweep(nodes[sl], keys[sl], *args, fresh())[:5])
    for parts in (carried, alone):
        for k in range(5):
            np.testing.assert_array_equal(np.concatenate([o[k] for o in parts]), whole[k])


def test_adaptive_same_numbers_whatever_threads_and_chunks():
    fm = grid_map(7, 11)
    cfg = SweepConfig(up_um=[10.0, 40.0], seed=2, field_model="harmonic", estimator="adaptive")
    numba.set_num_threads(1)
    try:
        a = run_sweep(fm, cfg).stats
    finally:
        numba.set_num_threads(min(2, numba.config.NUMBA_NUM_THREADS))
    b = run_sweep(fm, SweepConfig(**{**cfg.__dict__, "chunk_nodes": 13})).stats
    np.testing.assert_array_equal(a, b)
    assert np.isfinite(b[:, :, 3]).all()


def test_cli_default_is_adaptive_and_its_pieces_slabs_agree_bit_for_bit(tmp_path):
    fm = grid_map(7, 21)
    f = write_map_csv(fm, tmp_path / "map.csv")
    base = ["sweep", str(f), "--up", "0,30", "--field-model", "harmonic"]
    out = {}
    runs = (("mem", []), ("pieces", ["--pieces", "3"]), ("slabs", ["--slabs", "3"]),
            ("plain", ["--trials", "100"]))  # fmt: skip
    for name, extra in runs:
        assert main([*base, "--out", str(tmp_path / name), *extra]) == 0
        out[name] = json.loads((tmp_path / name / "summary.json").read_text())
    for name in ("pieces", "slabs"):
        assert out[name]["uf_units"] == out["mem"]["uf_units"], name
        assert out[name]["estimator"] == "adaptive", name
    assert out["mem"]["uf_relative_mc_std"] == ADAPTIVE_PLAN[2]
    assert out["plain"]["estimator"] == "plain"
    assert out["plain"]["uf_relative_mc_std"] == pytest.approx(0.1363)


def test_normal_quantile_matches_scipy():
    from scipy.stats import norm

    for p in (0.001, 0.025, 0.5, 0.975, 0.999):
        assert _kernels.normal_quantile(p) == pytest.approx(norm.ppf(p), abs=1e-12)


def _window(xu, x_tails):
    """The trials of ``xu``'s tail windows, as `cv_stats` takes them (`window_trials`)."""
    from cfm_fem._kernels import harmonic_cv as hcv

    lo, hi = np.empty(len(xu), dtype=np.int64), np.empty(len(xu), dtype=np.int64)
    k_lo, k_hi = hcv.window_trials(xu, len(xu), (x_tails[0][-1], x_tails[1][0]), lo, hi)
    return lo, hi, k_lo, k_hi


@pytest.mark.parametrize(
    "n, coupling, noise",
    [(1000, 1.0, 1e-3), (4000, 1.0, 0.05), (1000, 0.0, 0.5), (240, 1.0, 1e-3), (240, 1.0, 0.05)],
)
def test_cv_statistics_kernel_matches_its_numpy_twin(n, coupling, noise):
    """`cv_stats` (and the tails of `sample_tails` it takes) against `testing.cv_stats`, on
    errors near their first-order part (the difference estimator) and independent of it (the
    plain figures, whose estimated variance is then the smaller)."""
    from cfm_fem import testing
    from cfm_fem._kernels import harmonic_cv as hcv
    from cfm_fem._kernels.order_stats import _intervals, coverage_count

    rng = np.random.default_rng(n)
    z = rng.standard_normal((2, n))
    s, sig1 = 0.02, 3.0
    xu = sig1 * z[0]
    y = coupling * s * xu + noise * s * sig1 * (z[1] ** 2 - 1.0 + 0.3 * z[0] ** 2)
    q = coverage_count(n, 0.95)
    h = n - q
    work = tuple(np.empty(n) for _ in range(4))
    x_tails = (np.empty(h), np.empty(h))
    x_st = np.empty(6)
    x_st[0], x_st[1] = hcv.sample_tails(xu, n, h, *x_tails, work[2], work[3])
    np.testing.assert_array_equal(x_tails[0], np.sort(xu)[:h])
    np.testing.assert_array_equal(x_tails[1], np.sort(xu)[n - h :])
    _intervals(*x_tails, n, q, x_st)
    out, se = np.empty(6), np.empty(2)
    zq = _kernels.normal_quantile(0.975)
    hcv.cv_stats(y, xu, n, q, s, sig1, zq, x_st, x_tails, _window(xu, x_tails), work, out, se)
    ref_out, ref_se = testing.cv_stats(y, xu, s, sig1)
    np.testing.assert_allclose(out, ref_out, rtol=1e-9, atol=1e-15)
    np.testing.assert_allclose(se, ref_se, rtol=1e-9, atol=1e-18)
    plain = np.sort(y)[h // 2 - 1]  # the plain symmetric low end (h even here)
    assert (out[2] == plain) == (coupling == 0.0)


def test_one_crossing_below_the_spacing_leaves_the_few_trials_error():
    """256 trials whose remainder is far below the spacing of X's order statistics, one trial
    pushed across the low quantile: the standard error of the low end is the few-trials one
    (the remainder's), not the asymptotic one that a single crossing lifts many times over."""
    from cfm_fem._kernels import harmonic_cv as hcv
    from cfm_fem._kernels.order_stats import _intervals, coverage_count

    n, s, sig1 = 256, 0.02, 3.0
    rng = np.random.default_rng(11)
    xu = sig1 * rng.standard_normal(n)
    q = coverage_count(n, 0.95)
    h = n - q
    order = np.argsort(xu)
    r = h // 2 if h % 2 == 0 else (h + 1) // 2
    gap = s * (xu[order[r]] - xu[order[r - 1]])
    e = 1e-3 * gap * rng.standard_normal(n)
    e[order[r]] = -1.5 * gap  # the trial just above X's quantile crosses below Y's
    y = s * xu + e
    work = tuple(np.empty(n) for _ in range(4))
    x_tails = (np.empty(h), np.empty(h))
    x_st = np.empty(6)
    x_st[0], x_st[1] = hcv.sample_tails(xu, n, h, *x_tails, work[2], work[3])
    _intervals(*x_tails, n, q, x_st)
    out, se = np.empty(6), np.empty(2)
    zq = _kernels.normal_quantile(0.975)
    hcv.cv_stats(y, xu, n, q, s, sig1, zq, x_st, x_tails, _window(xu, x_tails), work, out, se)
    y_st = np.empty(6)  # the plain sample figures of Y: its quantiles for the crossings
    y_tails = (np.empty(h), np.empty(h))
    hcv.sample_tails(y, n, h, *y_tails, work[2], work[3])
    _intervals(*y_tails, n, q, y_st)
    c_lo, _, var_lo, _ = hcv._crossings(y, xu, n, s, (y_st[2], y_st[3]), (x_st[2], x_st[3]),
                                        (x_tails[0][h - 1], x_tails[1][0]))  # fmt: skip
    assert c_lo >= 1
    ifx = s * sig1 / (np.exp(-0.5 * zq * zq) / np.sqrt(2.0 * np.pi))
    assert np.sqrt(var_lo) < ifx / n  # the remainder is below the spacing
    asymptotic = np.sqrt(2.0 * c_lo / n * ifx * ifx / n)  # its crossing term alone
    uf = zq * s * sig1
    assert se[0] < 0.25 * asymptotic
    assert se[0] / uf < ADAPTIVE_PLAN[2]  # the node stops at its pilot


@pytest.mark.parametrize("n", [64, 256, 1000])
@pytest.mark.parametrize("coupling", [1.0, 0.3, 0.0])
def test_crossings_from_the_tail_windows_are_those_of_every_trial(n, coupling):
    """The crossing counts and the remainder's window variances taken from X's tail windows
    and Y's tails (O(h) trials) are those of the pass over every trial, to the bit; where a
    tie reaches the edge of Y's tail the windows decline (-1) and the pass is taken."""
    from cfm_fem._kernels import harmonic_cv as hcv
    from cfm_fem._kernels.order_stats import _intervals, coverage_count

    rng = np.random.default_rng(n + int(10 * coupling))
    q = coverage_count(n, 0.95)
    h = n - q
    s = 0.02
    for _ in range(20):
        xu = rng.standard_normal(n)
        y = coupling * s * xu + 0.01 * s * rng.standard_normal(n)
        work = tuple(np.empty(n) for _ in range(4))
        tails = {}
        st = {}
        for name, v in (("x", xu), ("y", y)):
            tails[name] = (np.empty(h), np.empty(h))
            st[name] = np.empty(6)
            hcv.sample_tails(v, n, h, *tails[name], work[2], work[3])
            _intervals(*tails[name], n, q, st[name])
        ends, x_ends = (st["y"][2], st["y"][3]), (st["x"][2], st["x"][3])
        x_win = (tails["x"][0][h - 1], tails["x"][1][0])
        full = hcv._crossings(y, xu, n, s, ends, x_ends, x_win)
        fast = hcv._crossings_in_windows(y, xu, s, ends, x_ends, _window(xu, tails["x"]),
                                         tails["y"], h)  # fmt: skip
        assert fast == full
    r = h // 2 if h % 2 == 0 else (h + 1) // 2
    y[np.argsort(y)[r - 1 : h + 1]] = np.sort(y)[r - 1]  # ties from the low end past the edge
    hcv.sample_tails(y, n, h, *tails["y"], work[2], work[3])
    _intervals(*tails["y"], n, q, st["y"])
    ends = (st["y"][2], st["y"][3])
    fast = hcv._crossings_in_windows(y, xu, s, ends, x_ends, _window(xu, tails["x"]), tails["y"],
                                     h)  # fmt: skip
    assert fast[0] == -1
