"""Piecewise-linear interpolation: exact on linear fields, on every kind of mesh."""

import numpy as np
import pytest

from cfm_fem import CfmInputError, FieldMap
from cfm_fem.models.interpolation import LinearInterpolator
from cfm_fem.models.mesh import build_mesh, face_neighbors, kuhn_simplices

G = np.array([[0.3, -0.1, 0.02], [0.05, 0.2, -0.4], [0.0, 0.1, 0.7]])  # T/mm
B0 = np.array([0.1, -0.2, 0.5])


def linear(p):
    return p @ G.T + B0


def grid(nx=5, ny=4, nz=6, h=(1.0, 0.5, 2.0)):
    ax = [np.arange(n) * s for n, s in zip((nx, ny, nz), h, strict=True)]
    return np.stack(np.meshgrid(*ax, indexing="ij"), -1).reshape(-1, 3)


def query_inside(pts, n=500, seed=0):
    lo, hi = pts.min(0), pts.max(0)
    return np.random.default_rng(seed).uniform(lo + 0.01 * (hi - lo), hi - 0.01 * (hi - lo), (n, 3))


@pytest.mark.parametrize("kind", ["delaunay", "grid"])
def test_linear_field_interpolated_exactly(kind):
    pts = grid() if kind == "grid" else np.random.default_rng(1).uniform(0, 5, (300, 3))
    interp = LinearInterpolator(FieldMap.from_arrays(pts, linear(pts)), method=kind)
    assert interp.mesh.kind == kind
    if kind == "grid":
        q = query_inside(pts)
    else:  # random points of random cells (hull slivers are gone: the hull is not the domain)
        rng = np.random.default_rng(2)
        cells = interp.mesh.simplices[rng.integers(0, len(interp.mesh.simplices), 200)]
        w = rng.dirichlet(np.ones(4), 200)
        q = np.einsum("qk,qkd->qd", w, pts[cells])
    B, inside = interp.field_at(q)
    assert inside.all()
    np.testing.assert_allclose(B, linear(q), rtol=1e-12, atol=1e-12)


def test_native_tetra_cells_are_used():
    pts = grid(3, 3, 3, (1, 1, 1))
    order = np.arange(len(pts))
    cells = kuhn_simplices((3, 3, 3), order)
    fm = FieldMap.from_arrays(pts, linear(pts), cells=cells)
    interp = LinearInterpolator(fm)
    assert interp.mesh.kind == "native"
    q = query_inside(pts, 200, 3)
    np.testing.assert_allclose(interp.field_at(q)[0], linear(q), atol=1e-12)


def test_native_cells_keep_gaps_that_delaunay_fills():
    # two separate blocks of cells: the gap between them is not part of the FEM domain
    pts = grid(3, 3, 2, (1, 1, 1))
    cells = kuhn_simplices((3, 3, 2), np.arange(len(pts)))
    pts2 = pts + [0, 0, 3.0]
    fm = FieldMap.from_arrays(
        np.r_[pts, pts2], linear(np.r_[pts, pts2]), cells=np.r_[cells, cells + len(pts)]
    )
    gap = np.array([[1.0, 1.0, 2.0]])
    assert not LinearInterpolator(fm, "native").field_at(gap)[1][0]
    assert LinearInterpolator(fm, "delaunay").field_at(gap)[1][0]


def test_points_outside_are_nan_not_extrapolated():
    pts = grid()
    interp = LinearInterpolator(FieldMap.from_arrays(pts, linear(pts)))
    B, inside = interp.field_at([[-0.5, 0.5, 0.5], [1.0, 0.5, 1.0]])
    assert list(inside) == [False, True]
    assert np.isnan(B[0]).all() and np.isfinite(B[1]).all()


def test_kuhn_triangulation_is_conforming_and_fills_the_box():
    pts = grid(4, 3, 5, (1.0, 2.0, 0.5))
    mesh = build_mesh(FieldMap.from_arrays(pts, linear(pts)), "grid")
    vol = np.abs(1 / np.linalg.det(mesh.transform[:, :3, :]) / 6)
    np.testing.assert_allclose(vol.sum(), 3 * 4 * 2, rtol=1e-12)
    nb = mesh.neighbors
    # every interior face has exactly one partner, and links are symmetric
    for s, j in zip(*np.nonzero(nb >= 0), strict=True):
        assert s in nb[nb[s, j]]
    n_border = (nb < 0).sum()  # 2 triangles per boundary square
    assert n_border == 2 * 2 * (3 * 2 + 3 * 4 + 2 * 4)


def test_face_neighbors_of_two_tets():
    cells = np.array([[0, 1, 2, 3], [1, 2, 3, 4]])
    nb = face_neighbors(cells)
    assert nb[0, 0] == 1 and nb[1, 3] == 0 and (nb >= 0).sum() == 2


def test_non_manifold_mesh_is_rejected():
    cells = np.array([[0, 1, 2, 3], [1, 2, 3, 4], [1, 2, 3, 5]])
    with pytest.raises(CfmInputError, match="more than two cells"):
        face_neighbors(cells)


def test_planar_map_is_triangulated_in_its_plane():
    rng = np.random.default_rng(4)
    uv = rng.uniform(-3, 3, (200, 2))
    pts = np.c_[uv[:, 0], np.full(200, 7.5), uv[:, 1]]  # the y = 7.5 mid-plane
    interp = LinearInterpolator(FieldMap.from_arrays(pts, linear(pts)))
    assert interp.mesh.dim == 2 and "out-of-plane" in interp.mesh.description
    q = np.c_[rng.uniform(-1, 1, (50, 2))[:, 0], np.full(50, 7.5), rng.uniform(-1, 1, 50)]
    np.testing.assert_allclose(interp.field_at(q)[0], linear(q), atol=1e-12)


def test_tilted_planar_map():
    rng = np.random.default_rng(6)
    uv = rng.uniform(-3, 3, (150, 2))
    e1, e2 = np.array([1.0, 1.0, 0.0]) / np.sqrt(2), np.array([0.0, 0.0, 1.0])
    pts = uv[:, :1] * e1 + uv[:, 1:] * e2 + [1, 2, 3]
    interp = LinearInterpolator(FieldMap.from_arrays(pts, linear(pts)))
    q = np.array([[0.5, 0.5]]) @ np.c_[e1, e2].T + [1, 2, 3]
    np.testing.assert_allclose(interp.field_at(q)[0], linear(q), atol=1e-12)


@pytest.mark.parametrize(
    "pts, match",
    [
        (np.c_[np.arange(10.0), 2 * np.arange(10.0), np.zeros(10)], "collinear"),
        (np.zeros((2, 3)) + [[0, 0, 0], [1, 0, 0]], "at least"),
    ],
)
def test_degenerate_point_sets_give_clear_errors(pts, match):
    with pytest.raises(CfmInputError, match=match):
        build_mesh(FieldMap.from_arrays(pts, np.ones_like(pts)))


def test_flat_native_cell_is_rejected_with_its_index():
    pts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0.0]])
    cells = np.array([[0, 1, 2, 3], [0, 1, 2, 4]])  # the second lies in z = 0
    with pytest.raises(CfmInputError, match="zero volume.*cell 1"):
        build_mesh(FieldMap.from_arrays(pts, np.ones((5, 3)), cells=cells))


def test_incomplete_grid_leaves_the_missing_region_out():
    # a measured grid with its corner node dropped (placeholder rows): Kuhn cells of the rest
    pts = grid(4, 4, 4, (1, 1, 1))[1:]
    interp = LinearInterpolator(FieldMap.from_arrays(pts, linear(pts)))
    assert interp.mesh.kind == "grid" and "missing" in interp.mesh.notes[0]
    q = query_inside(pts, 400, 8)
    B, inside = interp.field_at(q)
    assert not inside[np.all(q < 1, axis=1)].any()  # the voxel touching the missing node
    assert inside[np.any(q > 1, axis=1)].all()
    np.testing.assert_allclose(B[inside], linear(q[inside]), atol=1e-12)


def test_cospherical_scattered_nodes_get_proper_simplices():
    # a grid turned by 30 degrees is no lattice along x, y, z: Delaunay, where Qhull would make
    # flat simplices of the co-spherical voxel corners
    c, s = np.cos(np.pi / 6), np.sin(np.pi / 6)
    pts = grid(4, 4, 4, (1, 1, 1)) @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]).T
    interp = LinearInterpolator(FieldMap.from_arrays(pts, linear(pts)))
    assert interp.mesh.kind == "delaunay" and np.isfinite(interp.mesh.transform).all()
    assert "jittered" in interp.mesh.notes[0]
    q = pts[10:40] * 0.95 + pts.mean(0) * 0.05
    B, inside = interp.field_at(q)
    assert inside.all()
    # linear fields stay exact up to the jitter of those nodes (1e-6 of the map size, ~4.1 mm
    # here) times the gradient
    np.testing.assert_allclose(B, linear(q), atol=1e-6 * 5 * np.abs(G).sum())


def test_only_co_spherical_nodes_are_moved_and_other_cells_stay_exact():
    # scattered nodes below a lattice block: Delaunay triangulates all nodes moved by 1e-6 of
    # the map size (one triangulation, whatever part of the map), but only the nodes of cells
    # that are flat without the move (the lattice's) keep it: the cells of the others
    # interpolate a linear field exactly (all nodes moved by 1e-5 of the map size before)
    pts = np.r_[np.random.default_rng(4).uniform(0, 5, (400, 3)), grid(4, 4, 4, (1, 1, 1)) + 7]
    fm = FieldMap.from_arrays(pts, linear(pts))
    interp = LinearInterpolator(fm, method="delaunay", hull_slivers="remove")  # flat ones too:
    moved = interp.mesh.tie_nodes  # they would move scattered nodes with collinear lattice ones
    assert moved[400:].all() and not moved[:400].any()
    assert "64 node(s) of co-spherical sets" in interp.mesh.notes[0]
    np.testing.assert_array_equal(interp.mesh.coords[:400], pts[:400])
    cells = interp.mesh.simplices[~moved[interp.mesh.simplices].any(axis=1)]
    rng = np.random.default_rng(5)
    cells = cells[rng.integers(0, len(cells), 300)]
    q = np.einsum("qk,qkd->qd", rng.dirichlet(np.ones(4), 300), pts[cells])
    B, inside = interp.field_at(q)
    assert inside.all()
    np.testing.assert_allclose(B, linear(q), rtol=1e-12, atol=1e-12)


def _random_cube_map(n=3000, seed=1):
    pts = np.random.default_rng(seed).uniform(0, 6, (n, 3))
    return pts, FieldMap.from_arrays(pts, linear(pts))


def test_hull_slivers_removed_only_on_request_and_only_flat_cells_at_the_hull():
    import scipy.spatial

    from cfm_fem.models.mesh import SLIVER_RATIO

    pts, fm = _random_cube_map()
    kept = build_mesh(fm, "delaunay")
    assert len(kept.hull_slivers) == 0
    mesh = build_mesh(fm, "delaunay", "remove")
    gone = mesh.hull_slivers
    assert len(gone) > 0 and len(gone) + len(mesh.simplices) == len(kept.simplices)
    assert any("flat cell(s) on the Delaunay hull removed" in n for n in mesh.notes)
    # every removed cell: circumradius > SLIVER_RATIO x shortest edge, centre outside the hull
    v = pts[gone]
    A = 2.0 * (v[:, 1:] - v[:, :1])
    centre = np.linalg.solve(A, ((v[:, 1:] ** 2).sum(-1) - (v[:, :1] ** 2).sum(-1))[..., None])
    centre = centre[..., 0]
    r = np.linalg.norm(centre - v[:, 0], axis=1)
    edges = [np.linalg.norm(v[:, a] - v[:, b], axis=1) for a in range(4) for b in range(a + 1, 4)]
    assert (r > SLIVER_RATIO * np.min(edges, axis=0)).all()
    hull = scipy.spatial.Delaunay(pts[scipy.spatial.ConvexHull(pts).vertices])
    assert (hull.find_simplex(centre) < 0).all()
    assert (mesh.node_cell >= 0).all()  # no node left without a cell
    # a removed cell is at the hull: it touches the kept mesh's border or the hull itself
    assert np.isin(gone, np.unique(mesh.simplices[(mesh.neighbors < 0).any(axis=1)])).all()


def test_points_next_to_removed_hull_cells_are_found():
    """Removing hull cells makes the border non-convex, and walks from the nearest nodes can be
    blocked by a notch; the cells around the point are then searched (the walks alone miss
    2 of 200 points here)."""
    pts, fm = _random_cube_map(300)
    interp = LinearInterpolator(fm, "delaunay", "remove")
    rng = np.random.default_rng(2)
    cells = interp.mesh.simplices[rng.integers(0, len(interp.mesh.simplices), 200)]
    q = np.einsum("qk,qkd->qd", rng.dirichlet(np.ones(4), 200), pts[cells])
    B, inside = interp.field_at(q)
    assert inside.all()
    np.testing.assert_allclose(B, linear(q), rtol=1e-12, atol=1e-12)
    gone = interp.mesh.hull_slivers
    centre = pts[gone].mean(axis=1)  # inside a removed cell only
    assert not interp.field_at(centre)[1].any()


def test_inside_agrees_with_scipy_around_and_on_the_hull():
    """Points around a scattered map, some on its hull's faces: inside exactly where scipy's
    Delaunay finds a simplex, and the field exact there."""
    import scipy.spatial

    pts, fm = _random_cube_map(300)
    interp = LinearInterpolator(fm, "delaunay")
    rng = np.random.default_rng(5)
    q = rng.uniform(-1.0, 6.0, (2000, 3))
    tri = scipy.spatial.Delaunay(pts)
    faces = tri.convex_hull[rng.integers(0, len(tri.convex_hull), 200)]
    on_face = np.einsum("qk,qkd->qd", rng.dirichlet(np.ones(3), 200), pts[faces])
    B, inside = interp.field_at(np.r_[q, on_face])
    np.testing.assert_array_equal(inside[: len(q)], tri.find_simplex(q) >= 0)
    assert inside[len(q) :].all()
    np.testing.assert_allclose(B[inside], linear(np.r_[q, on_face][inside]), atol=1e-12)
    assert np.isnan(B[~inside]).all()


@pytest.mark.parametrize("d", [2, 3])
def test_barycentric_transforms_invert_each_simplex_as_lapack_does(d):
    """The adjugate inverses and determinants agree with numpy.linalg to rounding; a flat
    simplex gets NaN rows and a zero measure."""
    from cfm_fem.models.mesh import barycentric_transforms

    rng = np.random.default_rng(d)
    coords = rng.normal(size=(60, d)) * np.array([1.0, 1e3, 1e-2][:d])
    simplices = np.array([rng.choice(60, d + 1, replace=False) for _ in range(400)])
    simplices[0, 0] = simplices[0, d]  # the last node repeated: a flat simplex
    T, measure = barycentric_transforms(coords, simplices)
    v = coords[simplices]
    A = np.swapaxes(v[:, :d] - v[:, d][:, None], 1, 2)
    ok = np.arange(len(simplices)) > 0
    inv = np.linalg.inv(A[ok])
    scale = np.abs(inv).max(axis=(1, 2))[:, None, None]
    assert np.all(np.abs(T[ok, :d] - inv) <= 1e-9 * scale)
    factor = 2.0 if d == 2 else 6.0
    np.testing.assert_allclose(measure[ok] * factor, np.linalg.det(A[ok]), rtol=1e-10)
    assert np.isnan(T[0, :d]).all() and measure[0] == 0 and np.array_equal(T[:, d], v[:, d])


@pytest.mark.parametrize("dim", [1, 2, 3, 4])
def test_morton_bits_spread_as_one_bit_at_a_time(dim):
    from cfm_fem.models.mesh import _spread_bits

    bits = 64 // dim
    v = np.random.default_rng(dim).integers(0, 2 ** min(bits, 63), 5000, dtype=np.uint64)
    v[:2] = [0, 2 ** min(bits, 63) - 1]
    expected = np.zeros_like(v)
    for b in range(bits):
        expected |= ((v >> np.uint64(b)) & np.uint64(1)) << np.uint64(dim * b)
    assert np.array_equal(_spread_bits(v, dim), expected)


def test_face_neighbors_of_a_shuffled_mesh_match_across_each_shared_face():
    """Every interior face pairs the two cells that hold it, whatever the cells' node order."""
    pts = grid(6, 5, 4)
    cells = kuhn_simplices((6, 5, 4), np.arange(len(pts)))
    rng = np.random.default_rng(7)
    cells = rng.permuted(cells[rng.permutation(len(cells))], axis=1)
    nb = face_neighbors(cells)
    for c, j in zip(*np.nonzero(nb >= 0), strict=True):
        face = set(np.delete(cells[c], j))
        other = cells[nb[c, j]]
        assert face <= set(other) and c in nb[nb[c, j]]
    squares = 2 * (5 * 4 + 5 * 3 + 4 * 3)  # boundary squares of the 6 x 5 x 4 grid
    assert (nb < 0).sum() == 2 * squares  # two triangles each
