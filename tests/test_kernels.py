"""Each numba kernel against its plain-numpy twin (tests/twins.py) or scipy."""

import numba
import numpy as np
import pytest
import scipy.spatial
import twins

from cfm_fem import FieldMap, _kernels
from cfm_fem.interpolation import build_mesh
from cfm_fem.mc import coverage_count


def test_counter_rng_matches_twin_bit_for_bit():
    key = _kernels.stream_key(42, _kernels.STREAM_SWEEP)
    assert int(key) == twins.stream_key(42, twins.STREAM_SWEEP)
    tkey = _kernels.trial_key(key, 7)
    assert int(tkey) == twins.trial_key(int(key), 7)
    for c in (0, 1, 12345, 2**40):
        assert int(_kernels._draw(tkey, c)) == twins.draw(int(tkey), c)


@numba.njit
def _sweep_normals(seed, node, n):  # a user's own @njit code calling the kernels
    key = _kernels.trial_key(_kernels.stream_key(seed, _kernels.STREAM_SWEEP), node)
    fkey = _kernels.stream_key(seed, _kernels.STREAM_FALLBACK)
    out = np.empty((n, 3))
    for t in range(n):
        out[t, 0], out[t, 1], out[t, 2] = _kernels._three_normals(key, fkey, t)
    return out


def test_sweep_normals_match_twin_and_are_standard_normal():
    z = _sweep_normals(1, 0, 100_000).ravel()
    np.testing.assert_array_equal(z[:3000].reshape(-1, 3), twins.sweep_normals(1, 0, 1000))
    n = len(z)
    # mean ~ N(0, 1/n), variance ~ N(1, 2/n): 4-sigma bounds
    assert abs(z.mean()) < 4 / np.sqrt(n)
    assert abs(z.var() - 1) < 4 * np.sqrt(2 / n)
    # tail probability P(|z| > 1.96) = 0.05 +- 4 sigma of a binomial proportion
    frac = np.mean(np.abs(z) > 1.959963984540054)
    assert abs(frac - 0.05) < 4 * np.sqrt(0.05 * 0.95 / n)
    # different nodes give different, uncorrelated streams
    w = _sweep_normals(1, 1, 100_000).ravel()
    assert abs(np.corrcoef(z, w)[0, 1]) < 4 / np.sqrt(n)


@pytest.mark.parametrize(
    "sample",
    [
        np.random.default_rng(0).normal(size=10_000),
        np.random.default_rng(1).exponential(size=5_001) ** 3,  # heavy tail: fallback path
        np.zeros(300),
        np.random.default_rng(2).integers(0, 3, 1001).astype(float),  # ties
        np.random.default_rng(3).uniform(size=37),
        np.array([1.0, -1.0]),
    ],
)
def test_sample_stats_matches_full_sort(sample):
    a = sample.copy()
    out = np.empty(6)
    _kernels.sample_stats(a, len(a), _kernels.coverage_count(len(a), 0.95), out, np.empty(len(a)))
    np.testing.assert_allclose(out, twins.sample_stats(sample), rtol=1e-12, atol=1e-14)


def test_coverage_count_twin():
    for n in (2, 3, 20, 21, 999, 1000, 10_001):
        assert _kernels.coverage_count(n, 0.95) == coverage_count(n, 0.95)


def test_select_inplace_orders_around_k():
    rng = np.random.default_rng(5)
    for n, k in ((1, 0), (10, 0), (10, 9), (1000, 25), (1000, 974)):
        a = rng.integers(0, 50, n).astype(float)
        b = a.copy()
        _kernels.select_inplace(b, 0, n - 1, k)
        assert b[k] == np.sort(a)[k]
        assert np.all(b[:k] <= b[k]) and np.all(b[k + 1 :] >= b[k])


def test_locate_and_interpolate_match_scipy():
    rng = np.random.default_rng(0)
    pts = rng.uniform(-5, 5, (400, 3))
    B = np.c_[np.sin(pts[:, 0]), pts[:, 1] ** 2, pts[:, 0] * pts[:, 2]]
    mesh = build_mesh(FieldMap.from_arrays(pts, B))
    tri = scipy.spatial.Delaunay(pts)
    from scipy.interpolate import LinearNDInterpolator

    q = rng.uniform(-6, 6, (2000, 3))
    start = mesh.node_cell[rng.integers(0, len(pts), len(q))]
    got, cell = _kernels.interpolate_points(
        q, start, mesh.simplices, mesh.transform, mesh.neighbors, B
    )
    inside = tri.find_simplex(q) >= 0
    np.testing.assert_array_equal(cell >= 0, inside)
    np.testing.assert_allclose(
        got[inside], LinearNDInterpolator(tri, B)(q[inside]), rtol=1e-10, atol=1e-12
    )
    assert np.all(np.isnan(got[~inside]))


def test_gauss_sweep_matches_numpy_twin():
    rng = np.random.default_rng(11)
    pts = rng.uniform(0, 4, (60, 3))
    B = np.c_[np.sin(pts[:, 0]) * pts[:, 1], np.cos(pts[:, 2]), pts[:, 0] * 0.3 + 1]
    fm = FieldMap.from_arrays(pts, B)
    mesh = build_mesh(fm, "delaunay")
    up = np.array([0.0, 0.05, 0.4])  # mm: the largest leaves the stars and the map often
    starts = _kernels.octant_cells(
        mesh.coords, mesh.node_cell, mesh.transform, mesh.neighbors, 1e-7
    )
    stats, n_out, n_lost, _ = _kernels.gauss_sweep(
        np.arange(len(pts)), mesh.coords, B, mesh.simplices, mesh.transform, mesh.neighbors,
        starts, np.eye(3), np.ones(3), up, 150, 9, 0.95, 4,
    )  # fmt: skip
    ref, ref_out = twins.gauss_sweep(pts, B, up, 150, 9)
    np.testing.assert_array_equal(n_out, ref_out)
    assert n_lost.sum() == 0
    np.testing.assert_allclose(stats, ref, rtol=1e-9, atol=1e-12)
    assert n_out[:, 2].sum() > 0  # the comparison did exercise points leaving the map
