"""Each numba kernel against its plain-numpy twin (`cfm_fem.testing`) or scipy."""

import numba
import numpy as np
import pytest
import scipy.spatial

from cfm_fem import FieldMap, _kernels
from cfm_fem import testing as twins
from cfm_fem.models.interpolation import interpolate_points
from cfm_fem.models.mc import coverage_count
from cfm_fem.models.mesh import build_mesh, cell_buckets, exact_search, face_excess


def test_counter_rng_matches_twin_bit_for_bit():
    key = _kernels.stream_key(42, _kernels.STREAM_SWEEP)
    assert int(key) == twins.stream_key(42, twins.STREAM_SWEEP)
    tkey = _kernels.trial_key(key, 7)
    assert int(tkey) == twins.trial_key(int(key), 7)
    for c in (0, 1, 12345, 2**40):
        assert int(_kernels.rng._draw(tkey, c)) == twins.draw(int(tkey), c)


@numba.njit
def _sweep_normals(seed, node, n):  # a user's own @njit code calling the kernels
    key = _kernels.trial_key(_kernels.stream_key(seed, _kernels.STREAM_SWEEP), node)
    fkey = _kernels.stream_key(seed, _kernels.STREAM_FALLBACK)
    out = np.empty((n, 3))
    for t in range(n):
        out[t, 0], out[t, 1], out[t, 2] = _kernels.rng._three_normals(key, fkey, t)
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
        # tail thresholds come from the first values: unrepresentative leading values must
        # only change the path taken, never the result
        np.sort(np.random.default_rng(4).normal(size=3000)),
        np.r_[np.full(600, 0.5), np.random.default_rng(5).normal(size=2400)],
    ],
)
def test_sample_stats_matches_full_sort(sample):
    a = sample.copy()
    out = np.empty(6)
    _kernels.sample_stats(a, len(a), _kernels.coverage_count(len(a), 0.95), out, np.empty(len(a)))
    np.testing.assert_allclose(out, twins.sample_stats(sample), rtol=1e-12, atol=1e-14)


def test_sums_and_tails_one_pass():
    x = np.random.default_rng(6).normal(3.0, 0.2, 4000)
    scratch = np.full(5000, np.nan)
    shift, s1, s2, n_lo, n_hi = _kernels.sums_and_tails(x, len(x), scratch, 5000)
    d = x - x[0]
    assert shift == x[0]
    np.testing.assert_allclose([s1, s2], [d.sum(), (d * d).sum()], rtol=1e-12, atol=1e-12)
    pilot = x[: _kernels.TAIL_PILOT]
    t = pilot.mean() + np.array([-1, 1]) * _kernels.TAIL_SIGMAS * pilot.std(ddof=1)
    # the tails are exactly the values beyond the pilot thresholds, in sample order
    np.testing.assert_array_equal(scratch[:n_lo], x[x <= t[0]])
    np.testing.assert_array_equal(scratch[5000 - n_hi :][::-1], x[x >= t[1]])
    # ~9.7 % of a normal sample each side, within 5 binomial sigmas
    assert abs(n_lo / len(x) - 0.0968) < 5 * np.sqrt(0.0968 * 0.9032 / len(x)) + 0.01
    assert _kernels.sums_and_tails(x, 0, scratch, 0) == (0.0, 0.0, 0.0, 0, 0)


def test_coverage_count_twin():
    # p n exactly or nearly an integer, and p n + 1/2 exactly an integer (p = 0.5, n odd)
    for p in (0.5, 0.6827, 0.9, 0.95, 0.99, 0.9973):
        for n in (*range(2, 1200), 10_000, 10_001, 64_000, 1_000_003):
            assert _kernels.coverage_count(n, p) == coverage_count(n, p), (n, p)


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
    got, cell = interpolate_points(mesh, B, q, start)
    inside = tri.find_simplex(q) >= 0
    np.testing.assert_array_equal(cell >= 0, inside)
    np.testing.assert_allclose(
        got[inside], LinearNDInterpolator(tri, B)(q[inside]), rtol=1e-10, atol=1e-12
    )
    assert np.all(np.isnan(got[~inside]))


def _walk_one_by_one(mesh, q, start):
    """The point-by-point walk (`locate`) the batched one must reproduce."""
    cell = np.empty(len(q), dtype=np.int64)
    bary = np.empty((len(q), 4))
    for i in range(len(q)):
        cell[i] = _kernels.locate(q[i], start[i], mesh.transform, mesh.neighbors, bary[i])
    return cell, bary


def test_batched_walk_takes_the_steps_of_the_point_by_point_walk():
    rng = np.random.default_rng(3)
    pts = rng.uniform(-5, 5, (300, 3))
    mesh = build_mesh(FieldMap.from_arrays(pts, np.zeros((300, 3))))
    # points near nodes, far across the map and outside it; some walks start nowhere
    q = np.r_[pts[rng.integers(0, 300, 1500)] + rng.normal(0, 0.05, (1500, 3)),
              rng.uniform(-7, 7, (1500, 3))]  # fmt: skip
    start = mesh.node_cell[rng.integers(0, 300, len(q))]
    start[::97] = _kernels.OUTSIDE
    n = len(q)
    cur = np.empty(n, dtype=np.int64)
    bary = np.empty((n, 4))
    _kernels.walk_block3(q, 0, n, start, mesh.transform, mesh.neighbors, cur,
                         np.empty(n, dtype=np.int64), bary)  # fmt: skip
    ref_cell, ref_bary = _walk_one_by_one(mesh, q, start)
    np.testing.assert_array_equal(cur, ref_cell)
    assert 0 < (cur == _kernels.OUTSIDE).sum() < n // 2
    inside = cur >= 0
    np.testing.assert_array_equal(bary[inside], ref_bary[inside])  # same sums, same order
    # and a block in the middle of the array reads its own points
    part = np.empty(700, dtype=np.int64)
    _kernels.walk_block3(q, 1000, 700, start[1000:1700], mesh.transform, mesh.neighbors,
                         part, np.empty(700, dtype=np.int64), np.empty((700, 4)))  # fmt: skip
    np.testing.assert_array_equal(part, ref_cell[1000:1700])


def test_octant_cells_contain_their_corner_and_start_walks_nearby():
    rng = np.random.default_rng(4)
    pts = rng.uniform(-5, 5, (2000, 3))
    B = np.c_[pts[:, 1], pts[:, 0], 0.1 * pts[:, 2]]
    mesh = build_mesh(FieldMap.from_arrays(pts, B))
    eps = 1e-3
    table = _kernels.octant_cells(mesh.coords, mesh.node_cell, mesh.transform, mesh.neighbors, eps)
    signs = np.array([[-1.0 if (o >> a) & 1 else 1.0 for a in range(3)] for o in range(8)])
    corners = (mesh.coords[:, None, :] + eps * signs).reshape(-1, 3)
    found = scipy.spatial.Delaunay(mesh.coords).find_simplex(corners).reshape(-1, 8)
    ref, _ = _walk_one_by_one(mesh, corners, np.repeat(mesh.node_cell, 8))
    want = np.where(ref.reshape(-1, 8) >= 0, ref.reshape(-1, 8), mesh.node_cell[:, None])
    np.testing.assert_array_equal(table, want)
    # every corner inside the map lies in its table cell (barycentric coordinates >= 0)
    ok = found >= 0
    t = mesh.transform[table[ok]]
    lam = np.einsum("kij,kj->ki", t[:, :3], corners.reshape(-1, 8, 3)[ok] - t[:, 3])
    lam = np.c_[lam, 1 - lam.sum(1)]
    assert lam.min() > -1e-9
    # octant_starts picks the row entry of each point's side of its node (numpy twin)
    node = rng.integers(0, len(pts), 5000)
    q = pts[node] + rng.normal(0, 0.01, (5000, 3))
    octant = ((q < pts[node]) * [1, 2, 4]).sum(1)
    start = _kernels.octant_starts(q, node, mesh.coords, table)
    np.testing.assert_array_equal(start, table[node, octant])
    got, cell = interpolate_points(mesh, B, q, start)
    far, far_cell = interpolate_points(mesh, B, q, mesh.node_cell[node])
    np.testing.assert_array_equal(cell, far_cell)  # same cell from either start here
    np.testing.assert_array_equal(got, far)


@pytest.mark.parametrize("outside", ["exclude", "extrapolate"])
def test_gauss_sweep_matches_numpy_twin(outside):
    """Against scipy's interpolant and full sorting; with extrapolation the trials that leave
    the map take the twin node gradient's Taylor expansion (a scattered map: its Delaunay hull
    has flat cells, whose own linear field would extrapolate wildly)."""
    rng = np.random.default_rng(11)
    pts = rng.uniform(0, 4, (60, 3))
    B = np.c_[np.sin(pts[:, 0]) * pts[:, 1], np.cos(pts[:, 2]), pts[:, 0] * 0.3 + 1]
    fm = FieldMap.from_arrays(pts, B)
    mesh = build_mesh(fm, "delaunay")
    up = np.array([0.0, 0.05, 0.4])  # mm: the largest leaves the stars and the map often
    starts = _kernels.octant_cells(
        mesh.coords, mesh.node_cell, mesh.transform, mesh.neighbors, 1e-7
    )
    grad = twins.node_gradients(mesh, B) if outside == "extrapolate" else None
    exit_grad = np.empty((0, 3, 3)) if grad is None else grad  # 3-D: mesh frame = map frame
    stats, n_out, n_lost, _ = _kernels.gauss_sweep(
        np.arange(len(pts)), np.arange(len(pts)), mesh.coords, B, mesh.simplices,
        mesh.transform, mesh.neighbors, starts, np.eye(3), np.ones(3), up, 150, 9, 0.95,
        exit_grad, exact_search(mesh),
    )  # fmt: skip
    ref, ref_out = twins.gauss_sweep(pts, B, up, 150, 9, grad=grad)
    np.testing.assert_array_equal(n_out, ref_out)
    assert n_lost.sum() == 0
    np.testing.assert_allclose(stats, ref, rtol=1e-9, atol=1e-12)
    assert n_out[:, 2].sum() > 0  # the comparison did exercise points leaving the map


def test_block_normals_equal_scalar_generator():
    """The vectorised ziggurat fast path plus its exact redo gives the scalar stream's numbers."""
    key = np.uint64(twins.trial_key(twins.stream_key(3, twins.STREAM_SWEEP), 11))
    fkey = np.uint64(twins.stream_key(3, twins.STREAM_FALLBACK))
    n = 20_000  # ~600 samples take the slow path
    z = np.empty((3, n))
    _kernels.normals_by_index(key, fkey, 5, n, z, np.empty(n, dtype=np.bool_))
    ref = _sweep_normals_from(key, fkey, 5, n)
    np.testing.assert_array_equal(z.T, ref)
    keys = np.array([twins.trial_key(int(key), t) for t in range(500)], dtype=np.uint64)
    zk = np.empty((3, 500))
    _kernels.normals_by_key(keys, fkey, 17, 500, zk, np.empty(500, dtype=np.bool_))
    refk = np.array([_kernels.rng._three_normals(k, fkey, 17) for k in keys])
    np.testing.assert_array_equal(zk.T, refk)


@numba.njit
def _sweep_normals_from(key, fkey, t0, n):
    out = np.empty((n, 3))
    for t in range(n):
        out[t, 0], out[t, 1], out[t, 2] = _kernels.rng._three_normals(key, fkey, t0 + t)
    return out


@pytest.mark.parametrize("d", [2, 3])
def test_direction_bins_invert(d):
    n_bins = _kernels.n_direction_bins(d)
    delta = np.empty(d)
    feasible = 0
    for b in range(n_bins):
        if _kernels.star._bin_centre(b, d, 0.3, delta):
            assert abs(np.abs(delta).sum() - 0.3) < 1e-12
            assert _kernels.direction_bin(delta, d) == b
            feasible += 1
    # 3-D: the bins (i, j) with i + j < levels on each of the 8 faces; 2-D: all of them
    k = _kernels.BIN_LEVELS
    assert feasible == (8 * k * (k + 1) // 2 if d == 3 else n_bins)
    # every random direction falls in a feasible bin
    rng = np.random.default_rng(d)
    for v in rng.normal(size=(2000, d)):
        assert _kernels.star._bin_centre(_kernels.direction_bin(v, d), d, 1.0, delta)


def test_star_tables_locate_like_the_global_walk():
    rng = np.random.default_rng(5)
    pts = rng.uniform(0, 10, (400, 3))
    B = np.c_[np.sin(pts[:, 0]), pts[:, 1] ** 2, pts[:, 2]]
    mesh = build_mesh(FieldMap.from_arrays(pts, B), "delaunay")
    m = _kernels.MAX_STAR
    cells, lmat = np.empty(m, np.int64), np.empty((m, 3, 3))
    dmat, nbr = np.empty((m, 3, 3)), np.empty((m, 3), np.int64)
    lam, bary = np.empty(3), np.empty(4)
    htab = np.full((3, _kernels.STAR_HASH), -1, np.int64)
    checked = 0
    for g in range(0, 400, 7):
        n = _kernels.build_star(g, mesh.node_cell[g], mesh.simplices, mesh.transform,
                                mesh.neighbors, B, cells, lmat, dmat, nbr, htab)  # fmt: skip
        assert n > 0
        # the star is exactly the set of cells incident to g
        assert set(cells[:n]) == set(np.flatnonzero((mesh.simplices == g).any(axis=1)))
        for _ in range(40):
            delta = rng.normal(0, 0.05, 3)
            s, *lam = _kernels.star_locate3(0, lmat, nbr, n, *delta)
            lam = np.array(lam)
            p = mesh.coords[g] + delta
            sg = _kernels.locate(p, mesh.node_cell[g], mesh.transform, mesh.neighbors, bary)
            if s < 0:  # left the star: the global walk ends in a cell not incident to g
                assert sg < 0 or g not in mesh.simplices[sg]
                continue
            checked += 1
            want = (bary[:, None] * B[mesh.simplices[sg]]).sum(0) - B[g]
            np.testing.assert_allclose(dmat[s] @ lam, want, rtol=1e-9, atol=1e-12)
    assert checked > 1000


def test_star_block_pass_places_trials_like_the_walk():
    """`star_errors3` (every trial against every star cell, then walks) gives, bit for bit, the
    errors of walking each trial from its bin's start cell, and lists exactly the other
    trials, with the same reasons."""
    rng = np.random.default_rng(6)
    pts = rng.uniform(0, 10, (300, 3))  # many nodes on the hull: rays that leave the mesh
    B = np.c_[np.sin(pts[:, 0]), pts[:, 1] ** 2, pts[:, 2]]
    mesh = build_mesh(FieldMap.from_arrays(pts, B), "delaunay")
    m, n = _kernels.MAX_STAR, 400
    cells, lmat = np.empty(m, np.int64), np.empty((m, 3, 3))
    dmat, nbr = np.empty((m, 3, 3)), np.empty((m, 3), np.int64)
    htab = np.full((3, _kernels.STAR_HASH), -1, np.int64)
    starts = np.empty(_kernels.n_direction_bins(3), np.int64)
    err, dl, tag = np.full((3, n), np.nan), np.empty((3, n)), np.empty(n)
    rest, code = np.empty(n, np.int64), np.empty(n, np.int64)
    w = np.diag([1.0, 0.5, 2.0])
    counts = {"in": 0, _kernels.LEAVES_MESH: 0, -1: 0}
    for g in range(0, 300, 3):
        k = _kernels.build_star(g, mesh.node_cell[g], mesh.simplices, mesh.transform,
                                mesh.neighbors, B, cells, lmat, dmat, nbr, htab)  # fmt: skip
        smax = rng.choice([0.05, 0.5])  # 0.5: many trials beyond the star
        _kernels.star_bin_starts(lmat, nbr, k, 3, smax, starts)
        z = rng.normal(size=(3, n))
        n_rest = _kernels.star_errors3(z, n, w, smax, lmat, dmat, nbr, k, err, dl, tag, rest,
                                       code)  # fmt: skip
        listed = dict(zip(rest[:n_rest].tolist(), code[:n_rest].tolist(), strict=True))
        assert list(listed) == sorted(listed)
        for t in range(n):
            z0, z1, z2 = z[:, t]  # the kernel's operation order, scalar by scalar
            delta = [smax * (0.0 + w[0, a] * z0 + w[1, a] * z1 + w[2, a] * z2) for a in range(3)]
            b = _kernels.direction_bin(np.array(delta), 3)
            s, *lam = _kernels.star_locate3(starts[b], lmat, nbr, k, *delta)
            if s < 0:
                assert listed.pop(t) == s
                counts[s] += 1
                continue
            assert t not in listed
            want = [0.0 + dmat[s, c, 0] * lam[0] + dmat[s, c, 1] * lam[1] + dmat[s, c, 2] * lam[2]
                    for c in range(3)]  # fmt: skip
            assert np.array_equal(err[:, t], want)
            counts["in"] += 1
        assert not listed
    assert min(counts.values()) > 100, counts


def test_sort_values_matches_numpy():
    rng = np.random.default_rng(8)
    extremes = np.r_[1e-300, 1e300, -1e300, rng.normal(size=100)]
    tail = np.sort(rng.normal(size=10_000))[:1200]  # the shape the sweeps sort
    rng.shuffle(tail)
    outlier = np.r_[rng.normal(size=999), 1e12]  # every other value shares a 16-bit key
    sizes = [rng.normal(size=k) for k in (48, 4096, 4097)]  # either side of the key widths
    for a in (rng.normal(size=5000) ** 3, rng.integers(0, 5, 300).astype(float),
              rng.uniform(size=47), extremes, tail, outlier, -np.abs(rng.normal(size=700)),
              *sizes):  # fmt: skip
        b = a.copy()
        _kernels.sort_values(b)
        np.testing.assert_array_equal(b, np.sort(a))


def test_sort_in_range_matches_numpy():
    """The allocation-free sort of values with known bounds, on bounds wider than the values,
    a range that overflows the key (every value shares one), equal values and short lists;
    one set of work arrays serves lists of any length up to its size."""
    rng = np.random.default_rng(9)
    work = _kernels.radix_work(2000)
    cases = [
        (rng.normal(size=900), -10.0, 10.0),
        (np.r_[-1e308, 1e308, rng.normal(size=200)], -1e308, 1e308),
        (np.full(300, 2.5), 2.5, 2.5),
        (rng.uniform(size=47), 0.0, 1.0),
        (np.sort(rng.normal(size=10_000))[:600], -5.0, 0.0),
    ]
    for a, lo, hi in cases:
        b = a.copy()
        rng.shuffle(b)
        _kernels.sort_in_range(b, lo, hi, work)
        np.testing.assert_array_equal(b, np.sort(a))


def test_abs_b_statistics_on_a_kinked_field():
    """|B| at a node where the field folds (B_x = 0.1 |x|): the component samples are one-sided,
    so their statistics take the exact whole-sample path, which reorders them; |B| must still
    pair the components of the same trial. Checked against the closed form per trial."""
    ax = np.linspace(-2, 2, 5)
    pts = np.stack(np.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3)
    field = lambda p: np.c_[0.1 * np.abs(p[:, 0]), np.ones(len(p)), 0.5 + 0.1 * p[:, 1]]  # noqa: E731
    fm = FieldMap.from_arrays(pts, field(pts))
    mesh = build_mesh(fm, "grid")
    g = int(np.flatnonzero((pts == 0).all(axis=1))[0])
    up = np.array([0.01, 0.02])  # mm, far inside the 1 mm cells
    starts = _kernels.octant_cells(mesh.coords, mesh.node_cell, mesh.transform, mesh.neighbors,
                                   1e-7)  # fmt: skip
    stats, n_out, _, star = _kernels.gauss_sweep(
        np.array([g]), np.array([g]), mesh.coords, fm.B, mesh.simplices, mesh.transform,
        mesh.neighbors, starts, np.eye(3), np.ones(3), up, 4000, 2, 0.95, np.empty((0, 3, 3)),
        exact_search(mesh),
    )  # fmt: skip
    assert star[0] and n_out.sum() == 0
    z = twins.sweep_normals(2, g, 4000)
    for k, s in enumerate(up):
        p = pts[g] + s * z
        err = field(p) - fm.B[g]
        absb = np.linalg.norm(field(p), axis=1) - np.linalg.norm(fm.B[g])
        for c in range(3):
            np.testing.assert_allclose(stats[0, k, c], twins.sample_stats(err[:, c]),
                                       rtol=1e-9, atol=1e-15)  # fmt: skip
        np.testing.assert_allclose(stats[0, k, 3], twins.sample_stats(absb), rtol=1e-7,
                                   atol=1e-15)  # fmt: skip


@pytest.mark.parametrize("planar", [False, True])
def test_node_gradients_match_twin_and_are_exact_on_a_linear_field(planar):
    from cfm_fem.workflows.sweep.problem import node_gradients

    rng = np.random.default_rng(11)
    pts = rng.uniform(-5, 5, (400, 3))
    if planar:  # a tilted plane: gradients come back in the map frame, none along the normal
        pts = np.c_[pts[:, :2], 0.3 * pts[:, 0] - 0.2 * pts[:, 1]]
    G = np.array([[0.02, -0.01, 0.03], [0.005, 0.04, -0.02], [-0.03, 0.01, 0.015]])  # T/mm
    for B in (pts @ G.T + [0.1, -0.2, 0.3], np.sin(pts) * 0.1):
        mesh = build_mesh(FieldMap.from_arrays(pts, B), "delaunay")
        got = node_gradients(mesh, B)
        want = twins.node_gradients(mesh, B)
        # the kernel differences vertex values, the twin sums them: rounding only
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-11 * np.abs(want).max())
    B = pts @ G.T
    got = node_gradients(build_mesh(FieldMap.from_arrays(pts, B), "delaunay"), B)
    if planar:  # the in-plane part of G: G projected on the plane
        nrm = np.array([-0.3, 0.2, 1.0]) / np.linalg.norm([-0.3, 0.2, 1.0])
        G = G @ (np.eye(3) - np.outer(nrm, nrm))
    np.testing.assert_allclose(got, np.broadcast_to(G, got.shape), rtol=1e-9, atol=1e-13)


def test_uniform53_is_never_0_or_1():
    """(k + 1/2) / 2**53 rounds to 1 for the top k alone: the kernel and its twin give the
    largest double below 1 there, and the exact value elsewhere."""
    for h in (0, 1 << 11, 2**64 - 1, 2**64 - 2**11, 2**63, 0x9E3779B97F4A7C15):
        u = _kernels.uniform53(np.uint64(h))
        assert 0.0 < u < 1.0 and u == twins.uniform53(h)
    assert _kernels.uniform53(np.uint64(2**64 - 1)) == np.nextafter(1.0, 0.0)


def _l_shape(n=9, h=0.5, seed=None):
    """A grid map with the quadrant x > 0, y > 0 removed (a re-entrant edge along z), linear
    field; with ``seed``, a scattered node set of the same shape (Delaunay, slivers removed)."""
    ax = (np.arange(n) - n // 2) * h
    pts = np.stack(np.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3)
    if seed is not None:
        pts = pts + np.random.default_rng(seed).uniform(-0.2, 0.2, pts.shape) * h
    pts = pts[~((pts[:, 0] > 1e-9) & (pts[:, 1] > 1e-9))]
    B = pts @ np.array([[0.3, -0.1, 0.02], [0.05, 0.2, -0.4], [0.0, 0.1, 0.7]]).T
    kind = "grid" if seed is None else "delaunay"
    return build_mesh(FieldMap.from_arrays(pts, B + 0.1), kind, "remove"), B + 0.1


@pytest.mark.parametrize("seed", [None, 3])
def test_face_excess_matches_brute_force_over_all_nodes(seed):
    mesh, _ = _l_shape(seed=seed)
    got = face_excess(mesh.coords, mesh.simplices, mesh.transform, mesh.neighbors)
    want = twins.face_excess(mesh)
    np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-12)
    assert (got[mesh.neighbors >= 0] == 0).all()
    if seed is None:  # the notch's faces: the nodes reach 2 mm (4 heights) beyond them
        assert (got > 0).sum() == 2 * 2 * 4 * 8 and got.max() == pytest.approx(4.0)
    ext = np.ptp(mesh.coords, axis=0)
    convex = build_mesh(FieldMap.from_arrays(np.random.default_rng(1).uniform(0, ext, (300, 3)),
                                             np.zeros((300, 3))), "delaunay", "keep")  # fmt: skip
    assert len(exact_search(convex)[0]) == 0  # a convex mesh: nothing to search


@pytest.mark.parametrize("seed", [None, 3])
@pytest.mark.slow
def test_exact_search_finds_the_cell_brute_force_finds(seed):
    """`find_cell` (bucket lists) against every cell; `locate_exact` from a walk blocked by the
    notch gives the brute-force verdict too, where `locate` says outside."""
    mesh, _ = _l_shape(seed=seed)
    search = exact_search(mesh)
    excess, reach, box, dims, bstart, bcells = search
    rng = np.random.default_rng(7)
    q = rng.uniform(mesh.coords.min(0) - 0.3, mesh.coords.max(0) + 0.3, (3000, 3))
    bary = np.empty(4)
    blocked = 0
    for p in q:
        want = twins.find_cell(mesh, p)
        got = _kernels.find_cell(p, mesh.transform, box, dims, bstart, bcells, bary)
        assert got == want
        if got >= 0:
            np.testing.assert_allclose(bary, twins.barycentric_all(mesh, p)[got], atol=1e-12)
        # walks from a node across the notch (x < 0, y > 0 -> x > 0, y < 0)
        start = mesh.node_cell[np.argmin(((mesh.coords - [-1.5, 1.5, p[2]]) ** 2).sum(1))]
        cell = _kernels.locate_exact(p, start, mesh.transform, mesh.neighbors, bary, search)
        assert (cell >= 0) == (want >= 0)
        if cell >= 0:
            assert twins.barycentric_all(mesh, p)[cell].min() >= -_kernels.BARY_EPS
        plain = _kernels.locate(p, start, mesh.transform, mesh.neighbors, bary)
        blocked += plain < 0 <= want
    # the plain walk is blocked by the notch that often (Delaunay fills the notch: only the
    # faces the removed hull slivers leave are not supporting planes there)
    assert blocked > 50 if seed is None else (excess > 0).any()


def test_node_reach_matches_twin_and_only_star_cells_come_nearer():
    """The kernel tests only the cells of the buckets nearest to the node and stops at the
    distance found so far; the brute force over every cell gives the same numbers bit for
    bit, at the nodes `exact_search` asks for and at every node (the grid's outer layers)."""
    mesh, _ = _l_shape(seed=3)
    search = exact_search(mesh)
    s_idx, j_idx = np.nonzero(search[0] > 0)  # the nodes of the faces with an excess
    on_face = np.arange(4)[None, :] != j_idx[:, None]
    nodes = np.unique(mesh.simplices[s_idx][on_face])
    assert len(nodes) > 50
    size, cap = _kernels.star_sizes(nodes, mesh.node_cell, mesh.simplices, mesh.neighbors,
                                    mesh.transform)  # fmt: skip
    incident = np.bincount(mesh.simplices.ravel(), minlength=len(mesh.coords))[nodes]
    whole = size == incident
    assert whole.sum() > 50 and not whole.all()
    # the heights over the star are those over every cell of the node where it holds them all
    height = twins.star_height(mesh.transform, mesh.simplices, len(mesh.coords))
    np.testing.assert_array_equal(cap[whole], height[nodes][whole])
    assert (cap[~whole] <= height[nodes][~whole]).all()
    boxes = _kernels.cell_boxes(mesh.coords, mesh.simplices)
    got = _kernels.node_reach(mesh.coords, mesh.simplices, mesh.transform, boxes, *search[2:],
                              nodes, cap)  # fmt: skip
    np.testing.assert_array_equal(got, twins.node_reach(mesh, nodes, cap))
    every = np.arange(len(mesh.coords))
    np.testing.assert_array_equal(
        _kernels.node_reach(mesh.coords, mesh.simplices, mesh.transform, boxes, *search[2:],
                            every, height),
        twins.node_reach(mesh, every, height),
    )  # fmt: skip
    # the search keeps it where the node's cells are face-connected (its star holds them all)
    np.testing.assert_array_equal(np.where(whole, got, 0.0), search[1][nodes])
    assert (got > 0).all() and (got <= cap).all()
    # points nearer to the node than its reach lie in its own cells or in none
    rng = np.random.default_rng(2)
    for g, r in zip(nodes[::10], got[::10], strict=True):
        d = rng.normal(size=(100, 3))
        p = mesh.coords[g] + d / np.linalg.norm(d, axis=1)[:, None] * r * rng.uniform(
            0, 1, (100, 1)
        )
        for x in p:
            c = twins.find_cell(mesh, x)
            assert c < 0 or g in mesh.simplices[c]


def test_convex_faces_give_the_empty_search_bit_for_bit():
    """Search arrays whose excess is all 0 (every border face a supporting plane, as on a
    convex map) give the numbers of the empty search."""
    rng = np.random.default_rng(5)
    pts = rng.uniform(0, 3, (150, 3))
    B = np.c_[np.sin(pts[:, 0]) * pts[:, 1], np.cos(pts[:, 2]), pts[:, 0] * 0.3 + 1]
    mesh = build_mesh(FieldMap.from_arrays(pts, B), "delaunay")
    starts = _kernels.octant_cells(mesh.coords, mesh.node_cell, mesh.transform, mesh.neighbors,
                                   1e-7)  # fmt: skip
    empty = exact_search(mesh)
    assert len(empty[0]) == 0
    zero = (np.zeros_like(mesh.neighbors, dtype=np.float32), np.zeros(len(pts)),
            *cell_buckets(mesh.coords, mesh.simplices))  # fmt: skip
    runs = [
        _kernels.gauss_sweep(
            np.arange(len(pts)),
            np.arange(len(pts)),
            mesh.coords,
            B,
            mesh.simplices,
            mesh.transform,
            mesh.neighbors,
            starts,
            np.eye(3),
            np.ones(3),
            np.array([0.0, 0.05, 0.4]),
            200,
            4,
            0.95,
            np.empty((0, 3, 3)),
            search,
        )  # fmt: skip
        for search in (empty, zero)
    ]
    for a, b in zip(*runs, strict=True):
        np.testing.assert_array_equal(a, b)
    assert runs[0][1][:, 2].sum() > 0  # trials did leave the map


@pytest.mark.parametrize("n", [50, 100, 3000, 6000])
def test_sort_values_with_nan_is_numpys(n):
    """A NaN (a trial that met a slab's halo sentinel) must not index the counting arrays."""
    a = np.random.default_rng(n).normal(size=n)
    a[:: n // 10] = np.nan
    b = a.copy()
    _kernels.sort_values(b)
    np.testing.assert_array_equal(b, np.sort(a))


def _faceted_cylinder(n=700, seed=5):
    """Scattered nodes of a cylinder (r 3 mm, 12 mm long), a third on its mantle: the flat
    hull cells removed, the mantle is a faceted surface that is not convex at most of its
    nodes (few stars are; most have free faces and cells reaching beyond other faces)."""
    rng = np.random.default_rng(seed)
    m = n // 3
    r, t = 3 * np.sqrt(rng.uniform(0, 1, n - m)), rng.uniform(0, 2 * np.pi, n - m)
    inner = np.c_[r * np.cos(t), r * np.sin(t), rng.uniform(0, 12, n - m)]
    t = rng.uniform(0, 2 * np.pi, m)
    pts = np.r_[inner, np.c_[3 * np.cos(t), 3 * np.sin(t), rng.uniform(0, 12, m)]]
    B = np.c_[pts[:, 1], pts[:, 0], 0 * pts[:, 2]]
    return build_mesh(FieldMap.from_arrays(pts, B), "delaunay", "remove"), B


@pytest.mark.parametrize("which", ["l_shape", "cylinder"])
@pytest.mark.slow
def test_star_exit_verdicts_match_brute_force(which):
    """Trials the star walk finds leaving the star at a node whose border faces are no proof
    (`star_exact` False), within the node's reach: `star_exit` says outside (LEAVES_MESH) only
    where no cell of the mesh holds x_g + r delta for any r in (0, 1]; a star cell only where
    that cell holds x_g + delta. Exercises both proofs: the free faces (no star cell beyond
    their plane) and the cones of the cells that reach beyond a border plane."""
    mesh, B = _l_shape(seed=3) if which == "l_shape" else _faceted_cylinder()
    excess, reach = exact_search(mesh)[:2]
    d, ms = 3, _kernels.MAX_STAR
    cells, lmat = np.empty(ms, np.int64), np.empty((ms, d, d))
    dmat, nbr = np.empty((ms, 3, d)), np.empty((ms, d), np.int64)
    htab = np.full((3, _kernels.STAR_HASH), -1, np.int64)
    cand, free = np.empty(ms, np.int64), np.empty((2, ms * d), np.int64)
    lam = np.empty(d)
    rng = np.random.default_rng(7)
    seen = dict(free_face=0, cone_cells=0, outside=0, in_star=0, walk=0)
    for g in np.flatnonzero(reach > 0)[:60]:
        n_star = _kernels.build_star(g, mesh.node_cell[g], mesh.simplices, mesh.transform,
                                     mesh.neighbors, B, cells, lmat, dmat, nbr, htab)  # fmt: skip
        if n_star <= 0 or _kernels.star_exact(g, cells, n_star, mesh.simplices, excess):
            continue
        n_cand, n_free = _kernels.star_behind(g, mesh.coords, cells, n_star, lmat, nbr,
                                              mesh.simplices, cand, free)  # fmt: skip
        seen["free_face"] += n_free > 0
        seen["cone_cells"] += n_cand > 0
        u = rng.normal(size=(60, 3))
        deltas = u / np.linalg.norm(u, axis=1)[:, None] * reach[g] * rng.uniform(0.05, 1, (60, 1))
        for delta in deltas:
            s = _kernels.star_locate3(0, lmat, nbr, n_star, *delta)[0]
            if s != _kernels.LEAVES_MESH:
                continue
            got = _kernels.star_exit(lmat, reach[g], cand, n_cand, free, n_free, delta, lam)[0]
            if got == _kernels.LEAVES_MESH:
                seen["outside"] += 1
                for r in (0.05, 0.3, 1.0):
                    assert twins.find_cell(mesh, mesh.coords[g] + r * delta) < 0
            elif got >= 0:
                seen["in_star"] += 1
                bary = twins.barycentric_all(mesh, mesh.coords[g] + delta)[cells[got]]
                assert bary.min() >= -_kernels.BARY_EPS
            else:
                assert got == -1  # in a cell's cone, beyond it: the global walk decides
                seen["walk"] += 1
    assert seen["free_face"] > 5 and seen["outside"] > 100, seen
    if which == "l_shape":  # the re-entrant edge: stars whose other arm holds trials
        assert seen["cone_cells"] > 5 and seen["in_star"] + seen["walk"] > 0, seen


def test_bucket_lists_match_twin():
    """The bucket grid of the exact search, counted and filled by the kernel, is the numpy
    twin's (every entry listed and sorted) entry for entry, on boxes spanning several buckets
    per axis (3-D and planar)."""
    rng = np.random.default_rng(4)
    for dims in (np.array([5, 3, 7]), np.array([6, 4])):
        d = len(dims)
        box = np.stack([rng.uniform(-1, 1, d), dims / rng.uniform(1, 3, d)])  # corner, 1/mm
        lo = box[0] + rng.uniform(-0.1, 1.0, (400, d)) * dims / box[1]  # some beyond the grid
        boxes = np.stack([lo, lo + rng.uniform(0, 0.5, (400, d)) * dims / box[1]], axis=1)
        i0, span = twins.padded_ranges(boxes, box, dims)
        assert (span > 1).any(axis=0).all() and (span == 1).any()
        assert _kernels.bucket_entries(boxes, box, dims) == np.prod(span, axis=1).sum()
        for got, want in zip(_kernels.bucket_lists(boxes, box, dims),
                             twins.bucket_lists(i0, span, dims), strict=True):  # fmt: skip
            np.testing.assert_array_equal(got, want)


@pytest.mark.parametrize("which", ["l_grid", "l_scatter", "planar", "coarsened"])
def test_cell_buckets_match_twin_bit_for_bit(which):
    """`cell_buckets` (boxes, padded extent and lists by kernels) gives the numpy code's grid
    and lists exactly, including the coarser grids taken when boxes span many buckets."""
    kw = {}
    if which == "planar":
        uv = np.random.default_rng(2).uniform(-3, 3, (300, 2))
        pts = np.c_[uv[:, 0], np.full(300, 7.5), uv[:, 1]]
        mesh = build_mesh(FieldMap.from_arrays(pts, pts + 1), "delaunay", "remove")
        assert mesh.dim == 2
    else:
        mesh = _l_shape(seed=None if which == "l_grid" else 3)[0]
    if which == "coarsened":
        kw = dict(per_bucket=0.05, max_entries=3.0)
    v = mesh.coords[mesh.simplices]
    boxes = _kernels.cell_boxes(mesh.coords, mesh.simplices)
    np.testing.assert_array_equal(boxes, np.stack([v.min(1), v.max(1)], axis=1))
    got = cell_buckets(mesh.coords, mesh.simplices, **kw)
    want = twins.cell_buckets(mesh.coords, mesh.simplices, **kw)
    for a, b in zip(got, want, strict=True):
        assert a.dtype == b.dtype
        np.testing.assert_array_equal(a, b)
    assert got[2][-1] == len(got[3]) >= len(mesh.simplices)
    if which == "coarsened":  # the first grid held too many entries: a coarser one was taken
        n_first = twins.cell_buckets(mesh.coords, mesh.simplices, 0.05, np.inf)[1].prod()
        assert got[1].prod() < n_first


def test_kernels_cached_tells_a_cold_cache_from_a_warm_one(tmp_path, monkeypatch):
    """The first-run note of the commands relies on reading numba's cache index (a new
    module's cache is cold: numba writes it beside the source, in tmp_path)."""
    import importlib
    import sys

    (tmp_path / "tiny_kernel.py").write_text(
        "import numba\n\n@numba.njit(cache=True)\ndef twice(x):\n    return 2 * x\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    sys.modules.pop("tiny_kernel", None)
    mod = importlib.import_module("tiny_kernel")
    assert not _kernels.kernels_cached(mod.twice)
    assert mod.twice(3) == 6
    assert _kernels.kernels_cached(mod.twice)


_CALLER = (
    "import numba\nfrom callee import g\n\n@numba.njit(cache=True)\ndef f():\n    return g()\n"
)
_CALLEE = "import numba\n\n@numba.njit(cache=True)\ndef g():\n    return {}\n"


def test_a_changed_callee_reaches_a_cached_caller_only_through_the_digest(tmp_path):
    """numba checks a cached kernel against its own file only: after an edit to the module of
    a function it calls, it still runs the old code. `drop_stale_cache` (run on import of the
    kernels) compiles it anew; with unchanged sources, and after a first run into an empty
    folder, it keeps the cache."""
    import shutil
    import subprocess
    import sys

    (tmp_path / "caller.py").write_text(_CALLER)
    sources = [tmp_path / "caller.py", tmp_path / "callee.py"]
    cache = tmp_path / "__pycache__"
    guard = (
        "from cfm_fem._kernels.options import drop_stale_cache; "
        f"drop_stale_cache({str(cache)!r}, {[str(p) for p in sources]!r}); "
    )

    def run(value, guarded):
        callee = tmp_path / "callee.py"
        if not callee.exists() or callee.read_text() != _CALLEE.format(value):
            callee.write_text(_CALLEE.format(value))  # a new stamp only for new code
        code = (guard if guarded else "") + "from caller import f; print(f())"
        out = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True,
                             text=True, check=True)  # fmt: skip
        return int(out.stdout)

    assert run(1, guarded=False) == 1
    assert run(2, guarded=False) == 1  # numba's cache alone: the stale caller
    assert run(2, guarded=True) == 2
    stamp = (cache / "cfm_fem_kernels.sha256").read_text()
    files = sorted(p.name for p in cache.glob("*.nb[ic]"))
    assert files and run(2, guarded=True) == 2  # unchanged: the cache is kept
    assert sorted(p.name for p in cache.glob("*.nb[ic]")) == files
    assert (cache / "cfm_fem_kernels.sha256").read_text() == stamp
    assert run(3, guarded=True) == 3
    shutil.rmtree(cache)  # a first run: compiled once, then loaded
    assert run(3, guarded=True) == 3
    written = {p.name: p.stat().st_mtime_ns for p in cache.glob("*.nb[ic]")}
    assert written and run(3, guarded=True) == 3
    assert {p.name: p.stat().st_mtime_ns for p in cache.glob("*.nb[ic]")} == written


def _cycling(mesh, every=5):
    """``mesh.neighbors`` with every ``every``-th interior cell's faces leading back to itself:
    a walk that enters such a cell without ``p`` in it goes round in it until ``MAX_WALK``, as
    a walk that cycles on a non-Delaunay mesh does (none turned up in 2,000 random 2-D and 400
    3-D non-Delaunay meshes tried, so the cycle is made by hand)."""
    nb = mesh.neighbors.copy()
    inner = np.flatnonzero((nb >= 0).all(1))[::every]
    nb[inner] = inner[:, None]
    return nb, inner


@pytest.mark.parametrize("kind", ["convex", "buckets", "notch"])
def test_a_walk_that_cycles_is_settled_by_the_exact_search(kind):
    """A walk that fails (`WALK_FAILED`, from `locate` or `locate_exact`) left the sweep
    kernels a trial they counted as lost (the node then had no U_f). `settle_walk` finds the
    cell: by the bucket lists where the mesh has them (non-convex, or all-zero excess), by
    testing every cell where it has none (convex) - the brute-force twin's cell in both
    cases (`tests/test_sweep.py` runs the kernels on such walks)."""
    if kind == "notch":
        mesh, _ = _l_shape(seed=3)
        search = exact_search(mesh)
        assert len(search[0]) > 0
    else:
        pts = np.random.default_rng(2).uniform(0, 4, (300, 3))
        mesh = build_mesh(FieldMap.from_arrays(pts, np.zeros((300, 3))), "delaunay", "keep")
        search = exact_search(mesh)
        assert len(search[0]) == 0  # convex
        if kind == "buckets":
            search = (np.zeros_like(mesh.neighbors, dtype=np.float32), np.zeros(300),
                      *cell_buckets(mesh.coords, mesh.simplices))  # fmt: skip
    nb, _ = _cycling(mesh)
    rng = np.random.default_rng(8)
    lo, hi = mesh.coords.min(0), mesh.coords.max(0)
    q = rng.uniform(lo - 0.1 * (hi - lo), hi + 0.1 * (hi - lo), (600, 3))
    starts = rng.integers(0, len(mesh.simplices), len(q))
    bary = np.empty(4)
    failed = 0
    for p, start in zip(q, starts, strict=True):
        want = twins.find_cell(mesh, p)
        got = _kernels.settle_walk(p, mesh.transform, search, bary)
        assert got == want
        if got >= 0:
            np.testing.assert_allclose(bary, twins.barycentric_all(mesh, p)[got], atol=1e-12)
        cell = _kernels.locate_exact(p, start, mesh.transform, nb, bary, search)
        if cell == _kernels.WALK_FAILED:  # as the sweep kernels settle it
            failed += 1
            cell = _kernels.settle_walk(p, mesh.transform, search, bary)
            assert cell == want
        else:
            assert (cell >= 0) == (want >= 0)
        if cell >= 0:
            np.testing.assert_allclose(bary, twins.barycentric_all(mesh, p)[cell], atol=1e-12)
    assert failed > 50  # the walk did cycle that often
