"""Kernels that no workflow test pins down, each against its plain-numpy twin (tests/twins.py).

The kinematics pilot (`pass_pilot`, `fill_values`, `pass_pilot_quantiles`) and its trial keys;
the star searches of the sweep (`star_locate`, `star_find`, `star_recheck`), whose cells a
linear test map cannot tell apart (any cell's linear field is the map's), plus brute-force
checks of what their verdicts promise.
"""

from dataclasses import replace

import numpy as np
import pytest
import twins

from cfm_fem import FieldMap
from cfm_fem import _kernels as K
from cfm_fem import kinematics as kin
from cfm_fem.bench import ReadingDelay, error_index
from cfm_fem.interpolation import build_mesh, exact_search
from cfm_fem.io.bench_toml import read_reference_bench
from cfm_fem.mc import Pdf


# ---------------------------------------------------------------------------------------------
# Bench kinematics
# ---------------------------------------------------------------------------------------------
def _bench(path):
    """The reference bench (hot path); with a speed x tau delay (collapsed chain, generic
    noise); or also a position-dependent error (the full HTM chain, `probe_error_mm`)."""
    bench = read_reference_bench()
    if path == "hot":
        return bench
    delay = ReadingDelay("speed_tau", np.zeros(3), np.array([5.0, 0.0, 20.0]), Pdf.uniform(0, 2e-4))
    bench = replace(bench, delay=delay)
    if path == "chain":
        errors = list(bench.errors)
        k = error_index("delta_z(z)")
        errors[k] = replace(errors[k], profile=(0.2, 1.0, -0.5))
        bench = replace(bench, errors=tuple(errors))
    return bench


def _slow_normals(nkey, t0, n, pidx):
    """How many of the (trial, point) samples draw a normal by the ziggurat's slow path."""
    count = 0
    for t in range(t0, t0 + n):
        key = twins.trial_key(int(nkey), t)
        for p in pidx:
            h1, h2 = twins.draw(key, 4 * int(p)), twins.draw(key, 4 * int(p) + 1)
            bits = (h1 & 0xFFFFFFFF, h1 >> 32, h2 & 0xFFFFFFFF)
            layers = ((h2 >> 32) & 1023, (h2 >> 42) & 1023, (h2 >> 52) & 1023)
            count += any(
                abs(twins.int32(b)) >= twins.KN[y] for b, y in zip(bits, layers, strict=True)
            )
    return count


def test_trial_keys_match_twin():
    """Keys of trials t0 .. t0+n-1, a seed whose key has the top bit set included."""
    for seed in (3, 2**62 + 1):
        nkey, _ = kin.noise_keys(seed)
        out = np.zeros(40, dtype=np.uint64)
        K.trial_keys(nkey, 1000, 40, out)
        np.testing.assert_array_equal(out, twins.trial_keys(int(nkey), 1000, 40))
    assert (out >> np.uint64(63)).any()


@pytest.mark.parametrize("path", ["hot", "speed_tau", "chain"])
def test_pass_pilot_matches_twin(path):
    """Every sample (E_x, E_y, E_z, |E|) of trials t0 .. t0+n-1 at points keyed by their
    index in the whole grid. The collapsed chain promises the reference path's bits (hot
    path: block normals and the chain in a loop; speed x tau: `axis_noise_mm` per sample);
    the full chain agrees with the numpy HTM chain to rounding (positions ~100 mm, 1e-12 mm)."""
    bench = _bench(path)
    t0, n = 4160, 300
    eng = kin._Engine(bench, 7, n)
    assert eng.fast == (path == "hot") and eng.g.linear == (path != "chain")
    eng.prepare(t0, t0 + n)
    q = np.ascontiguousarray(bench.grid_points()[::150])
    pidx = np.arange(len(q), dtype=np.int64) * 150
    got = np.empty((len(q), 4, n))
    K.pass_pilot(eng.model, t0, n, q, pidx, got)
    want = twins.kinematics_values(eng.model, t0, n, q, pidx)
    assert _slow_normals(eng.nkey, t0, n, pidx) > 10  # the ziggurat's slow path is in there
    if path == "chain":
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)
        assert np.abs(want[:, :3]).max() > 1e-3  # errors of tens of um: 1e-12 is rounding
    else:
        np.testing.assert_array_equal(got, want)
    # one point alone, into a wider scratch (4, >= n): the same numbers
    ev = np.full((4, n + 5), np.nan)
    K.fill_values(eng.model, t0, n, q, 2, pidx[2], ev)
    np.testing.assert_array_equal(ev[:, :n], got[2])
    assert np.isnan(ev[:, n:]).all()


@pytest.mark.parametrize("path", ["hot", "speed_tau"])
def test_pass_pilot_quantiles_match_twin(path):
    """Pilot brackets, min, max (bit for bit) and mean (summation order: n ulps) per point and
    quantity, over more than one point per parallel chunk (70 points, 64 chunks); the lower
    brackets are at or below their order statistic, the upper ones at or above (to rounding)."""
    bench = _bench(path)
    n = 400
    eng = kin._Engine(bench, 5, n)
    eng.prepare(0, n)
    q = np.ascontiguousarray(bench.grid_points()[::27][:70])
    pidx = np.arange(len(q), dtype=np.int64) * 27
    kth, _ = kin._pilot_ranks(n, 0.95)
    got = np.empty((len(q), 4, len(kth) + 1))
    K.pass_pilot_quantiles(eng.model, 0, n, q, pidx, kth, got)
    values = twins.kinematics_values(eng.model, 0, n, q, pidx)
    want = twins.pilot_brackets(values, kth)
    np.testing.assert_array_equal(got[..., :6], want[..., :6])
    bound = n * np.finfo(float).eps * np.abs(values).mean(-1)  # sequential against pairwise
    assert (np.abs(got[..., 6] - want[..., 6]) <= bound).all()
    # conservative up to the rounding of vmin + b * width (the top edge of the last bin may
    # fall an ulp short of the maximum; the windows are padded by 1 % of the bracket)
    srt = np.sort(values, axis=-1)
    ulps = 4 * np.finfo(float).eps * np.abs(srt[..., [0, -1]]).max(-1)
    for j in range(4):
        beyond = got[..., j] - srt[..., kth[j]]
        assert (beyond <= ulps).all() if j % 2 == 0 else (-beyond <= ulps).all()
    assert (got[..., 1] > got[..., 0]).all()  # real brackets, not the degenerate case
    # every value equal (no errors, no noise): every bracket is that value
    model = list(eng.model)
    model[1] = np.zeros_like(model[1])  # terms
    model[3] = np.zeros(3)  # sig
    model[5] = -1  # no delay
    K.pass_pilot_quantiles(tuple(model), 0, n, q, pidx, kth, got)
    np.testing.assert_array_equal(got, 0.0)


# ---------------------------------------------------------------------------------------------
# Stars of the sweep
# ---------------------------------------------------------------------------------------------
def _mesh(which):
    """A convex 3-D Delaunay map, a planar one (d = 2) and an L-shaped scattered map (the
    quadrant x > 0, y > 0 removed, hull slivers removed: not convex). Non-linear fields."""
    rng = np.random.default_rng(3)
    if which == "convex":
        pts = rng.uniform(0, 3, (150, 3))
    elif which == "planar":
        uv = rng.uniform(-3, 3, (150, 2))
        pts = np.c_[uv[:, 0], np.full(150, 7.5), uv[:, 1]]
    else:
        ax = np.arange(-4, 5) * 0.5
        pts = np.stack(np.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3)
        pts = pts + rng.uniform(-0.1, 0.1, pts.shape)
        pts = pts[~((pts[:, 0] > 1e-9) & (pts[:, 1] > 1e-9))]
    B = np.c_[np.sin(pts[:, 0]) * pts[:, 1], np.cos(pts[:, 2]), 0.3 * pts[:, 0] ** 2 + 1.0]
    rule = "keep" if which == "convex" else "remove"
    return build_mesh(FieldMap.from_arrays(pts, B), "delaunay", rule), B


def _star(mesh, B, g):
    """`build_star` tables of node g; checks they list exactly the cells incident to it."""
    d, ms = mesh.dim, K.MAX_STAR
    cells, lmat = np.empty(ms, np.int64), np.empty((ms, d, d))
    dmat, nbr = np.empty((ms, 3, d)), np.empty((ms, d), np.int64)
    htab = np.full((3, K.STAR_HASH), -1, np.int64)
    n_star = K.build_star(g, mesh.node_cell[g], mesh.simplices, mesh.transform, mesh.neighbors,
                          B, cells, lmat, dmat, nbr, htab)  # fmt: skip
    incident = np.flatnonzero((mesh.simplices == g).any(1))
    assert n_star > 0 and np.array_equal(np.sort(cells[:n_star]), incident)
    return n_star, cells[:n_star], lmat, nbr


def _height(mesh, cells):
    """Smallest height of the cells, mm: the scale of displacements that leave a star."""
    d = mesh.dim
    T = mesh.transform[cells, :d]
    grad = np.concatenate([T, -T.sum(axis=1, keepdims=True)], axis=1)
    return 1.0 / np.linalg.norm(grad, axis=2).max()


@pytest.mark.parametrize("which", ["convex", "planar", "l_shape"])
def test_star_locate_matches_twin_walk(which):
    """The walk across the faces that contain g, from random start cells, step for step; on
    the brute-force side: a cell found holds the point, -1 (beyond the star) lies in no star
    cell, and on a convex mesh LEAVES_MESH lies in no cell of the mesh."""
    mesh, B = _mesh(which)
    d = mesh.dim
    rng = np.random.default_rng(1)
    seen = {"cell": 0, "beyond": 0, "leaves": 0}
    lam = np.empty(d)
    for g in rng.choice(len(mesh.coords), 25, replace=False):
        n_star, cells, lmat, nbr = _star(mesh, B, g)
        h = _height(mesh, cells)
        u = rng.normal(size=(30, d))
        deltas = u / np.linalg.norm(u, axis=1)[:, None] * h * rng.uniform(0.05, 4.0, (30, 1))
        for delta in deltas:
            start = int(rng.integers(n_star))
            got = K.star_locate(start, lmat, nbr, n_star, delta, lam)
            want, want_lam = twins.star_locate(start, lmat, nbr, n_star, delta)
            assert got == want
            p = mesh.coords[g] + delta  # mesh (local) coordinates
            bary = twins.barycentric_all(mesh, p)[cells]
            if got >= 0:
                np.testing.assert_array_equal(lam, want_lam)
                assert bary[got].min() >= -1e-9
                seen["cell"] += 1
            elif got == -1:
                assert (bary.min(1) < 1e-9).all()
                seen["beyond"] += 1
            else:
                assert got == K.LEAVES_MESH
                if which == "convex":
                    assert twins.find_cell(mesh, p) < 0
                seen["leaves"] += 1
    assert min(seen.values()) > 20, seen


def test_star_find_matches_brute_force():
    """On the L-shaped map (star_find's use: a non-convex mesh), points around nodes: the first
    star cell holding the point, as every star cell's coordinates say, or OUTSIDE; nearer to g
    than its `node_reach`, OUTSIDE is the brute-force verdict over every cell of the mesh."""
    mesh, B = _mesh("l_shape")
    excess, reach = exact_search(mesh)[:2]
    assert (excess > 0).any()
    rng = np.random.default_rng(2)
    bary, work = np.empty(4), np.empty(3)
    seen = {"cell": 0, "outside": 0, "near_outside": 0}
    nodes = np.r_[rng.choice(np.flatnonzero(reach > 0), 20, replace=False),
                  rng.choice(len(mesh.coords), 10, replace=False)]  # fmt: skip
    for g in nodes:
        n_star, cells, lmat, _ = _star(mesh, B, g)
        h = _height(mesh, cells)
        u = rng.normal(size=(30, 3))
        r = np.where(
            np.arange(30) < 15, reach[g] * rng.uniform(0, 1, 30), h * rng.uniform(0, 3, 30)
        )
        for p in mesh.coords[g] + u / np.linalg.norm(u, axis=1)[:, None] * r[:, None]:
            got = K.star_find(p, g, mesh.coords, mesh.transform, cells, n_star, lmat, work, bary)
            want, want_bary = twins.star_find(mesh, cells, p)
            assert got == want
            if got >= 0:
                np.testing.assert_allclose(bary, want_bary, rtol=0, atol=1e-12)
                seen["cell"] += 1
            else:
                seen["outside"] += 1
                if np.linalg.norm(p - mesh.coords[g]) < reach[g]:
                    assert twins.find_cell(mesh, p) < 0
                    seen["near_outside"] += 1
    assert min(seen.values()) > 20, seen


def test_star_recheck_matches_twin_and_its_proofs_hold():
    """Displacements beyond the reach of nodes whose border faces prove nothing (`star_exact`
    False): the twin's cell, coordinates and proven-outside fractions bit for bit; a cell
    found holds the point, and x_g + r delta lies in no cell of the mesh for r < r_in and
    r > r_out (brute force over every cell)."""
    mesh, B = _mesh("l_shape")
    excess, reach = exact_search(mesh)[:2]
    rng = np.random.default_rng(4)
    lam = np.empty(3)
    seen = {"cell": 0, "r_in": 0, "r_out": 0, "cone": 0}
    fractions = np.linspace(0.02, 3.0, 25)
    nodes = []
    for g in np.flatnonzero(reach > 0):
        n_star, cells = _star(mesh, B, g)[:2]
        if not K.star_exact(g, cells, n_star, mesh.simplices, excess):
            nodes.append(g)
    assert len(nodes) > 20
    for g in rng.choice(nodes, 20, replace=False):
        n_star, cells, lmat, nbr = _star(mesh, B, g)
        u = rng.normal(size=(25, 3))
        deltas = u / np.linalg.norm(u, axis=1)[:, None] * reach[g] * rng.uniform(1, 4, (25, 1))
        for delta in deltas:
            got = K.star_recheck(g, cells, n_star, lmat, nbr, mesh.simplices, excess, reach[g],
                                 delta, lam)  # fmt: skip
            want = twins.star_recheck(g, cells, n_star, lmat, nbr, mesh.simplices, excess,
                                      reach[g], delta)  # fmt: skip
            assert got == want[:3]
            s, r_in, r_out = got
            if s >= 0:
                np.testing.assert_array_equal(lam, want[3])
                assert twins.barycentric_all(mesh, mesh.coords[g] + delta)[cells[s]].min() > -1e-9
                seen["cell"] += 1
                continue
            seen["cone"] += r_in == 0.0
            for r in fractions[(fractions < r_in) | (fractions > r_out)]:
                assert twins.find_cell(mesh, mesh.coords[g] + r * delta) < 0, (g, r, r_in, r_out)
            seen["r_in"] += (fractions < r_in).any()
            seen["r_out"] += (fractions > r_out).any()
    assert min(seen.values()) > 5, seen
