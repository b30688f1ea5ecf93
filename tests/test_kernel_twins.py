"""Kernels that no workflow test pins down, each against its plain-numpy twin (`cfm_fem.testing`).

The kinematics pilot (`pass_pilot`, `fill_values`, `pass_pilot_quantiles`) and its trial keys;
the star searches of the sweep (`star_locate`, `star_find`, `star_recheck`), whose cells a
linear test map cannot tell apart (any cell's linear field is the map's), plus brute-force
checks of what their verdicts promise; the sweep kernels (`gauss_sweep`, `htm_sweep`) on
non-convex meshes with non-linear fields, against a twin that locates every trial in the
mesh's own cells by brute force.
"""

from dataclasses import replace
from functools import cache

import numpy as np
import pytest

from cfm_fem import FieldMap
from cfm_fem import _kernels as K
from cfm_fem import testing as twins
from cfm_fem.io.bench_toml import read_reference_bench
from cfm_fem.models import kinematics as kin
from cfm_fem.models.bench import ReadingDelay, error_index
from cfm_fem.models.interpolation import interpolate_points
from cfm_fem.models.kinematics.chain import probe_errors_for_bench
from cfm_fem.models.kinematics.geometry import draw_error_sets, point_noise
from cfm_fem.models.mc import Pdf
from cfm_fem.models.mesh import build_mesh, exact_search, no_search
from cfm_fem.models.sweep import HTM_PARTS, SweepConfig
from cfm_fem.workflows.sweep.problem import prepare_sweep


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
@pytest.mark.slow
def test_pass_pilot_matches_twin(path):
    """Every sample (E_x, E_y, E_z, |E|) of trials t0 .. t0+n-1 at points keyed by their
    index in the whole grid. The collapsed chain promises the reference path's bits (hot
    path: block normals and the chain in a loop; speed x tau: `axis_noise_mm` per sample);
    the full chain agrees with the numpy HTM chain to rounding (positions ~100 mm, 1e-12 mm)."""
    bench = _bench(path)
    t0, n = 4160, 300
    eng = kin.monte_carlo._Engine(bench, 7, n)
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
    eng = kin.monte_carlo._Engine(bench, 5, n)
    eng.prepare(0, n)
    q = np.ascontiguousarray(bench.grid_points()[::27][:70])
    pidx = np.arange(len(q), dtype=np.int64) * 27
    kth, _ = kin.monte_carlo._pilot_ranks(n, 0.95)
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


@pytest.mark.slow
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


@pytest.mark.slow
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


# ---------------------------------------------------------------------------------------------
# Sweep kernels on non-convex meshes: every trial located in the mesh's own cells
# ---------------------------------------------------------------------------------------------
def _field(p):
    """A non-linear field (T) of p (k, 3): no two triangulations interpolate it alike."""
    x, y, z = p.T
    return np.c_[np.sin(x) * y, np.cos(z) + 0.5 * x * y, 0.3 * x**2 + 1.0]


@cache  # built once per test run (the scattered cylinder's Delaunay takes ~1 s)
def _notched(which, scale=1.0):
    """Non-convex maps (lengths in mm times ``scale``, non-linear fields of the unscaled
    positions) and the nodes to sweep. ``l_grid``: a 7^3 grid of step 0.5 mm with the
    quadrant x > 0, y > 0 removed (Kuhn cells; a re-entrant edge along z), the nodes next to
    the edge. ``cylinder``: scattered nodes of a cylinder (r 3 mm, 8 mm long), a third on its
    mantle, flat hull cells removed (a faceted mantle, not convex at most of its nodes), the
    nodes near the mantle."""
    if which == "l_grid":
        ax = (np.arange(7) - 3) * 0.5
        pts = np.stack(np.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3)
        pts = pts[~((pts[:, 0] > 1e-9) & (pts[:, 1] > 1e-9))]
        nodes = np.flatnonzero((np.abs(pts[:, :2]) <= 0.5 + 1e-9).all(1))
    else:
        rng = np.random.default_rng(5)
        n, m = 420, 140
        r, t = 3 * np.sqrt(rng.uniform(0, 1, n - m)), rng.uniform(0, 2 * np.pi, n - m)
        inner = np.c_[r * np.cos(t), r * np.sin(t), rng.uniform(0, 8, n - m)]
        t = rng.uniform(0, 2 * np.pi, m)
        pts = np.r_[inner, np.c_[3 * np.cos(t), 3 * np.sin(t), rng.uniform(0, 8, m)]]
        nodes = np.flatnonzero((np.hypot(pts[:, 0], pts[:, 1]) > 2.5) & (np.abs(pts[:, 2] - 4) < 2))
    fm = FieldMap.from_arrays(pts * scale, _field(pts))
    mesh = build_mesh(fm, "grid" if which == "l_grid" else "delaunay", "remove")
    assert len(exact_search(mesh)[0]) > 0  # not convex: the exact search is on
    return fm, mesh, nodes


@pytest.mark.parametrize("outside", ["exclude", "extrapolate"])
@pytest.mark.parametrize("which", ["l_grid", "cylinder"])
def test_gauss_sweep_on_a_non_convex_mesh_matches_a_brute_force_twin(which, outside):
    """`gauss_sweep` against the twin that locates every trial by brute force in the mesh's own
    cells (`twins.mesh_interpolant`), on a non-linear field: the cell a trial lands in matters,
    and so does whether it is in one (a Delaunay of the nodes would fill the notch). The count
    of trials outside exactly, the statistics to rounding. U_p up to a cell height: trials
    leave the star, the map, and cross the notch into the other arm (the exact search places
    them: without it the kernel counts them outside)."""
    fm, mesh, nodes = _notched(which)
    B = fm.B
    up = np.array([0.0, 0.05, 0.5])  # mm
    starts = K.octant_cells(mesh.coords, mesh.node_cell, mesh.transform, mesh.neighbors, 1e-7)
    grad = twins.node_gradients(mesh, B) if outside == "extrapolate" else None
    exit_grad = np.empty((0, 3, 3)) if grad is None else grad  # 3-D: mesh frame = map frame

    def run(search):
        return K.gauss_sweep(nodes, nodes, mesh.coords, B, mesh.simplices, mesh.transform,
                             mesh.neighbors, starts, np.eye(3), np.ones(3), up, 150, 9, 0.95,
                             exit_grad, search)  # fmt: skip

    stats, n_out, n_lost, _ = run(exact_search(mesh))
    interp = twins.mesh_interpolant(mesh, B)
    ref, ref_out = twins.gauss_sweep(mesh.coords, B, up, 150, 9, grad=grad, nodes=nodes,
                                     interp=interp)  # fmt: skip
    np.testing.assert_array_equal(n_out, ref_out)
    assert n_lost.sum() == 0
    np.testing.assert_allclose(stats, ref, rtol=1e-9, atol=1e-12)
    assert (n_out[:, 1:].sum(0) > 0).all()  # trials did leave the map at each U_p
    plain = run(no_search(3))[1]  # every exit taken for a proof, as on a convex mesh
    assert (plain >= n_out).all() and (plain - n_out)[:, 2].sum() > 20, (plain - n_out).sum(0)


@pytest.mark.parametrize(
    "which, path, outside", [("l_grid", "hot", "exclude"), ("cylinder", "chain", "extrapolate")]
)
def test_htm_sweep_on_a_non_convex_mesh_matches_a_brute_force_twin(which, path, outside):
    """`htm_sweep` (every column of mode htm) against the numpy HTM chain and the brute-force
    twin of the mesh's own cells, on the non-convex maps shrunk to cells of 20-30 um, the size
    of the reference bench's probe errors (mean ~15 um, std ~14 um): trials cross cells, leave
    the map, cross the notch; a non-linear field, so the cell matters. The collapsed chain and
    the full chain (`_bench`); trials outside left out, or extrapolated with the node
    gradients the sweep uses. Counts outside exactly, statistics to rounding (probe errors
    agree to ~1e-13 mm). Trials the walk puts outside but that lie in the mesh are placed by
    `locate_exact` (both maps) or, nearer to their node than its reach, by `star_find`
    (the cylinder's faceted mantle)."""
    n, seed = 120, 5
    fm, mesh, nodes = _notched(which, 0.04)
    bench = _bench(path)
    cfg = SweepConfig(trials=n, seed=seed, mode="htm", bench=bench, outside=outside)
    _, problem, _ = prepare_sweep(fm, cfg, mesh)
    stats, n_out, n_lost = problem.run_nodes(nodes)[:3]
    assert n_lost.sum() == 0
    q = bench.axis_positions_for(fm.points[nodes])
    params = draw_error_sets(bench, n, seed)
    keys = twins.node_keys(fm.points[nodes])  # the nodes' random-stream keys
    dq = np.stack([point_noise(bench, t, keys, seed) for t in range(n)])  # (n, k, 3)
    rot = bench.bench_to_magnet_rotation()
    interp = twins.mesh_interpolant(mesh, fm.B)
    grad = problem.exit_grad if outside == "extrapolate" else None
    reach = problem.search[1]
    placed = {"star_find": 0, "locate_exact": 0}
    for j, (geo, noise) in enumerate(HTM_PARTS.values()):
        dm = probe_errors_for_bench(bench, params * geo, q, dq * noise) @ rot.T  # map frame
        for i, g in enumerate(nodes):
            p = mesh.coords[g] + dm[:, i]
            gg = None if grad is None else grad[g]
            want, want_out = twins.error_stats(interp(p), fm.B[g], dm[:, i], gg)
            assert n_out[i, j] == want_out, (g, j)
            # probe errors to ~1e-13 mm (axis positions ~100 mm), fields ~50 T/mm: 1e-10 T
            np.testing.assert_allclose(stats[i, j], want, rtol=1e-9, atol=1e-10)
            # in the mesh, but outside by the plain walk from the kernel's start cells
            octant = ((dm[:, i] < 0) * [1, 2, 4]).sum(1)
            walk = interpolate_points(mesh, fm.B, p, problem.start_cells[g, octant])[1]
            found = (twins.locate_all(mesh, p)[0] >= 0) & (walk == K.OUTSIDE)
            near = np.linalg.norm(dm[:, i], axis=1) < reach[g]
            placed["star_find"] += (found & near).sum()
            placed["locate_exact"] += (found & ~near).sum()
    assert (n_out.sum(0) > 0).all()  # trials did leave the map in every column
    assert placed["locate_exact"] > 20 and (which == "l_grid" or placed["star_find"] > 20), placed
    plain = replace(problem, search=None).run_nodes(nodes)[1]  # every exit taken for a proof
    assert (plain >= n_out).all()
    assert (plain - n_out).sum() == sum(placed.values()), (plain - n_out).sum(0)


@pytest.mark.parametrize("mode", ["gauss", "htm"])
def test_a_node_listed_twice_gets_the_same_numbers_twice(mode):
    """A node whose star is built twice in one kernel call (`_star_slot`'s hash table holds
    entries of other nodes) gets its whole star both times. Every node listed twice in a row,
    on the faceted cylinder: the numbers of the nodes listed once, bit for bit."""
    scale, cfg = (1.0, SweepConfig(up_um=[50.0, 500.0], trials=120, seed=5))
    if mode == "htm":
        scale, cfg = (0.04, SweepConfig(trials=120, seed=5, mode="htm", bench=_bench("chain")))
    fm, mesh, nodes = _notched("cylinder", scale)
    _, problem, _ = prepare_sweep(fm, cfg, mesh)
    once = problem.run_nodes(nodes)
    twice = problem.run_nodes(np.repeat(nodes, 2))
    for a, b in zip(once, twice, strict=True):
        np.testing.assert_array_equal(b[0::2], a)
        np.testing.assert_array_equal(b[1::2], a)
    # the star tables themselves: built twice on one table, the same star
    d, ms = 3, K.MAX_STAR
    htab = np.full((3, K.STAR_HASH), -1, np.int64)
    for g in nodes[:10]:
        tables = []
        for _ in range(2):
            cells, lmat = np.empty(ms, np.int64), np.empty((ms, d, d))
            dmat, nbr = np.empty((ms, 3, d)), np.empty((ms, d), np.int64)
            n_star = K.build_star(g, mesh.node_cell[g], mesh.simplices, mesh.transform,
                                  mesh.neighbors, fm.B, cells, lmat, dmat, nbr, htab)  # fmt: skip
            tables.append((n_star, cells[:n_star], lmat[:n_star], dmat[:n_star], nbr[:n_star]))
        assert tables[0][0] > 1
        for x, y in zip(*tables, strict=True):
            np.testing.assert_array_equal(x, y)
