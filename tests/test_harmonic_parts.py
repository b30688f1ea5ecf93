"""The unrolled harmonic polynomial and the tail statistics of the harmonic sweep."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from cfm_fem import _kernels, testing
from cfm_fem.models.harmonic_basis import field_basis, monomial_exponents, n_basis, n_monomials

ROOT = Path(__file__).resolve().parents[1]
B = _kernels.PART_BLOCK
P = _kernels.PART_PITCH


def test_generated_module_is_the_generators_output():
    run = subprocess.run(
        [sys.executable, str(ROOT / "scripts" / "generate_harmonic_parts.py"), "--check"],
        capture_output=True,
        text=True,
    )
    assert run.returncode == 0, run.stdout + run.stderr


@pytest.mark.parametrize("degree", [2, 5])
def test_parts_match_numpy_monomials_across_blocks(degree):
    """Part q of component c equals the degree-q monomials of u times their coefficients,
    evaluated by numpy, for a trial count that spans several blocks; coefficients beyond the
    node's degree are zero and give zero parts."""
    rng = np.random.default_rng(degree)
    n = 2 * B + 37
    u = rng.normal(size=(3, n)) * 0.7
    exps = monomial_exponents()
    cexp = rng.normal(size=(3, len(exps)))
    cexp[:, n_monomials(degree) :] = 0.0
    mono = np.prod(u.T[:, None, :] ** exps[None], axis=2)  # (n, M)
    parts = np.empty(_kernels.N_SLOTS * P)
    for t0 in range(0, n, B):
        m = min(B, n - t0)
        _kernels.homogeneous_parts(cexp, u, t0, m, parts)
        for q in range(1, 6):
            sel = exps.sum(axis=1) == q
            want = mono[t0 : t0 + m][:, sel] @ cexp[:, sel].T  # (m, 3)
            got = parts.reshape(_kernels.N_SLOTS, P)[3 * (q - 1) : 3 * q, :m].T
            np.testing.assert_allclose(got, want, rtol=1e-13, atol=1e-13 * np.abs(want).max())
            if q > degree:
                assert not got.any()


@pytest.mark.parametrize("degree", [1, 3, 5])
def test_expanded_node_is_the_dense_product_of_basis_and_coefficients(degree):
    """`expand_node` (the basis's non-zero entries only) gives the monomial coefficients of
    the dense product field_basis @ coef, term for term in the order of the basis fields, and
    zero beyond the node's monomials."""
    gmat = field_basis()
    rng = np.random.default_rng(degree)
    coef = rng.normal(size=gmat.shape[2])
    nb_, nm = n_basis(degree), n_monomials(degree)
    want = np.zeros((3, nm))
    for j in range(nb_):  # the dense sum, term by term in j
        want = want + gmat[:, :nm, j] * coef[j]
    out = np.full((3, gmat.shape[1]), np.nan)
    _kernels.expand_node(coef, nb_, _kernels.sparse_basis(gmat), nm, out)
    np.testing.assert_array_equal(out[:, :nm], want)
    start, mono, val = _kernels.sparse_basis(gmat)
    assert len(val) == np.count_nonzero(gmat) and np.all(val != 0.0)


def _tail_case(n, curvature, seed=0, p=0.95, pilot_shift=0.0):
    """Changes x = s (L + k w |w|) of a normal first-order part L and an independent normal w
    (a remainder that reorders the trials), the remainder's exact bound |k| max w^2, and what
    `tail_stats` needs. ``pilot_shift`` moves the leading values of L that place the tails."""
    rng = np.random.default_rng(seed)
    lin = rng.normal(0.3, 2.0, n)
    lin[: _kernels.TAIL_PILOT] += pilot_shift
    w = rng.normal(size=n)
    x = _S * (lin + curvature * w * np.abs(w))
    bound = abs(curvature) * np.max(w**2)
    q = _kernels.coverage_count(n, p)
    z_h = _kernels.tail_quantile_z(n, q)
    bufs = [np.empty(n), np.empty(n, dtype=np.int64)]
    limits = np.empty(4)
    counts = np.empty(4, dtype=np.int64)
    _kernels.gather_tails(lin, n, z_h, n - q, *bufs, limits, counts, np.empty(n))
    return x, q, bound, tuple(bufs), limits, counts


_S = 0.05  # the U_p of `_tail_case`


def _tail_stats(x, q, bound, tails, limits, counts, guide=(np.nan, np.nan)):
    """`tail_stats` of a `_tail_case` with fresh work space: (took, stats, guide after)."""
    n = x.shape[0]
    stats = np.empty(6)
    guide = np.array(guide, dtype=float)
    work = _kernels.radix_work(n)
    took = _kernels.tail_stats(x, n, q, _S, bound, tails, limits, counts, guide, stats,
                               np.empty(n), np.empty(n), _sums(x), work)  # fmt: skip
    return took, stats, guide


def _sums(x):
    """Shift (the first value) and the sums of x - shift and of its square."""
    d = x - x[0]
    return np.array([x[0], d.sum(), (d * d).sum()])


@pytest.mark.parametrize("curvature", [0.0, 0.02, -0.03])
def test_tail_statistics_equal_those_of_the_whole_sample(curvature):
    """Where the remainder bound confines the candidates, the statistics from the tails are
    those of the whole sample (sorted by numpy), to rounding."""
    n = 10_000
    x, q, bound, tails, limits, counts = _tail_case(n, curvature)
    took, stats, guide = _tail_stats(x, q, bound, tails, limits, counts)
    assert took
    want = testing.sample_stats(x)
    np.testing.assert_allclose(stats, want, rtol=1e-12, atol=1e-15)
    h = n - q  # the guide for the next U_p: a little beyond the h-th value of each tail
    ordered = np.sort(x) / _S
    assert ordered[h - 1] <= guide[0] <= ordered[h + h // 16]
    assert ordered[n - h - h // 16] <= guide[1] <= ordered[n - h]


@pytest.mark.parametrize("guide", [(-np.inf, np.inf), (np.inf, -np.inf), (0.0, 0.0), "exact"])
def test_any_guide_gives_the_whole_samples_statistics(guide):
    """The guess of the previous U_p only decides how much is sorted: one far too tight
    (fewer than h values beyond it), one that filters nothing, one across the median and the
    exact h-th values all give the statistics of the whole sample."""
    n = 10_000
    x, q, bound, tails, limits, counts = _tail_case(n, 0.02)
    if guide == "exact":
        ordered = np.sort(x) / _S
        guide = (ordered[n - q - 1], ordered[q])
    took, stats, _ = _tail_stats(x, q, bound, tails, limits, counts, guide)
    assert took
    np.testing.assert_allclose(stats, testing.sample_stats(x), rtol=1e-12, atol=1e-15)


def test_a_nan_change_sends_the_tails_to_the_whole_sample():
    """A NaN among the candidates (a field the model cannot give) is left to `sample_stats`,
    which orders NaN as numpy does."""
    n = 10_000
    x, q, bound, tails, limits, counts = _tail_case(n, 0.02)
    x[np.argmin(x)] = np.nan
    took, _, _ = _tail_stats(x, q, bound, tails, limits, counts)
    assert not took


@pytest.mark.parametrize("shift", [0.3, -0.3])
def test_a_misleading_pilot_still_gives_the_whole_samples_statistics(shift):
    """Leading values 0.15 std above (below) the rest put the pilot's high-tail (low-tail)
    value v where fewer than h values lie beyond it: v is then selected in the gathered tail,
    and the statistics are still those of the whole sample."""
    n = 10_000
    x, q, bound, tails, limits, counts = _tail_case(n, 0.02, pilot_shift=shift)
    assert counts[3 if shift > 0 else 2] == n - q  # the selected v: exactly h values beyond
    took, stats, _ = _tail_stats(x, q, bound, tails, limits, counts)
    assert took
    np.testing.assert_allclose(stats, testing.sample_stats(x), rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize("guide", [None, "near", (-np.inf, np.inf), (np.inf, -np.inf)])
@pytest.mark.parametrize("shape", ["normal", "skewed", "ties"])
def test_whole_sample_statistics_are_those_of_numpy(guide, shape):
    """Where the tails of the first-order part do not confine the changes, the statistics
    come from thresholds on the changes themselves: a previous U_p's guess (close, one that
    keeps everything, one that keeps nothing) or mean -+ z_h std, and `sample_stats` where
    those hold too few values; on a skewed sample and one with ties too, they equal numpy's,
    and the guess returned lies beyond the h-th value."""
    n = 10_000
    rng = np.random.default_rng(11)
    x = {"normal": rng.normal(0.1, 2.0, n), "skewed": rng.gamma(1.5, 1.0, n) ** 2,
         "ties": np.round(rng.normal(size=n), 1)}[shape] * _S  # fmt: skip
    q = _kernels.coverage_count(n, 0.95)
    h = n - q
    ordered = np.sort(x) / _S
    if guide == "near":
        guide = (ordered[h + 3], ordered[n - h - 4])
    g = np.array(guide if guide is not None else (np.nan, np.nan), dtype=float)
    stats = np.empty(6)
    z_h = _kernels.tail_quantile_z(n, q)
    _kernels.whole_sample_stats(x.copy(), n, q, _S, z_h, g, stats, np.empty(n), np.empty(n),
                                _sums(x), _kernels.radix_work(n), np.empty(n))  # fmt: skip
    np.testing.assert_allclose(stats, testing.sample_stats(x), rtol=1e-12, atol=1e-15)
    keeps_nothing = guide is None or guide[0] == -np.inf
    if shape == "skewed" and keeps_nothing:  # none below mean - z_h std: `sample_stats`
        assert np.isnan(g).all()
    else:
        assert ordered[h - 1] <= g[0] and g[1] <= ordered[n - h]


def test_a_loose_bound_refuses_the_tails():
    """A remainder too large for the gathered tails sends the caller to the whole sample."""
    n = 10_000
    x, q, bound, tails, limits, counts = _tail_case(n, 1.0)
    assert not _tail_stats(x, q, bound, tails, limits, counts)[0]


def test_an_understated_bound_would_be_caught_by_the_comparison():
    """The whole-sample comparison above can fail: with a bound far below the true remainder
    (up to +-3 here, L's std is 2) the tails miss order statistics and the result differs
    from numpy's."""
    n = 10_000
    x, q, bound, tails, limits, counts = _tail_case(n, 0.2)
    took, stats, _ = _tail_stats(x, q, 1e-3 * bound, tails, limits, counts)
    assert took
    assert not np.allclose(stats[2:], testing.sample_stats(x)[2:], rtol=1e-12)


def test_point_evaluation_matches_numpy_monomials():
    """`poly_points` (the kernel of `HarmonicFit.field_at`) equals the monomials of each
    point's displacement times its model's coefficients, evaluated by numpy."""
    rng = np.random.default_rng(7)
    exps = monomial_exponents()
    cexp = rng.normal(size=(4, 3, len(exps)))
    which = rng.integers(0, 4, 300).astype(np.int64)
    u = rng.normal(size=(300, 3)) * 0.5
    out = np.empty((300, 3))
    _kernels.poly_points(cexp, which, exps, u, out)
    mono = np.prod(u[:, None, :] ** exps[None], axis=2)
    want = np.einsum("pm,pcm->pc", mono, cexp[which])
    np.testing.assert_allclose(out, want, rtol=1e-13, atol=1e-13 * np.abs(want).max())


def _degree_parts_on_sphere(cexp, u):
    """Part q (1 .. 5) of each component at unit vectors u (n, 3), by numpy: (5, n, 3)."""
    exps = monomial_exponents()
    mono = np.prod(u[:, None, :] ** exps[None], axis=2)
    deg = exps.sum(axis=1)
    return np.stack([mono[:, deg == q] @ cexp[:, deg == q].T for q in range(1, 6)])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_degree_bounds_hold_on_the_sphere_and_the_quadratic_one_is_reached(seed):
    """|part_q,c(u)| <= bound[q - 1, c] on the unit sphere for every degree (50,000 random
    directions, numpy's monomials); the degree-2 bound is the largest |eigenvalue| of the
    quadratic form (numpy's eigvalsh) and no more than the root sum of squares of the
    coefficients, which the others undercut too."""
    rng = np.random.default_rng(seed)
    exps = monomial_exponents()
    cexp = rng.normal(size=(3, len(exps)))
    bound = np.empty((5, 3))
    _kernels.degree_bounds(cexp, exps, _kernels.inverse_multinomials(exps), 5, bound)
    u = rng.normal(size=(50_000, 3))
    u /= np.linalg.norm(u, axis=1)[:, None]
    reached = np.abs(_degree_parts_on_sphere(cexp, u)).max(axis=1)  # (5, 3)
    assert np.all(reached <= bound)
    deg = exps.sum(axis=1)
    for c in range(3):
        a = np.zeros((3, 3))
        for m in np.flatnonzero(deg == 2):
            i, j = np.repeat(np.arange(3), exps[m])
            a[i, j] += cexp[c, m] / (1 if i == j else 2)
            a[j, i] += 0 if i == j else cexp[c, m] / 2
        np.testing.assert_allclose(bound[1, c], np.abs(np.linalg.eigvalsh(a)).max(), rtol=2e-6)
        assert bound[1, c] <= reached[1, c] * 1.01  # reached, up to the directions drawn
    rss = np.array([[np.sqrt((cexp[c, deg == q] ** 2).sum()) for c in range(3)]
                    for q in range(1, 6)])  # fmt: skip
    assert np.all(bound <= rss * (1 + 2e-6))
    assert np.all(bound[2:] < rss[2:])


def test_symmetric_norm_of_degenerate_matrices():
    """The closed form at a multiple of the identity, a rank-one matrix and zero."""
    assert _kernels.symmetric3_norm(-2.0, 0.0, 0.0, -2.0, 0.0, -2.0) == 2.0
    v = np.array([1.0, -2.0, 0.5])
    a = np.outer(v, v)
    got = _kernels.symmetric3_norm(a[0, 0], a[0, 1], a[0, 2], a[1, 1], a[1, 2], a[2, 2])
    np.testing.assert_allclose(got, v @ v, rtol=1e-12)
    assert _kernels.symmetric3_norm(0.0, 0.0, 0.0, 0.0, 0.0, 0.0) == 0.0
