"""The local harmonic field model (`cfm_fem.models.harmonic`): its kernel against the numpy
twin, exact and analytic harmonic fields, the bundled map against its magpylib source, the
fallback where Laplace fails, and the same bits whatever the threads, blocks or row order."""

from __future__ import annotations

import meshio
import numba
import numpy as np
import pytest
import scipy.spatial
import scipy.special
from test_default_mesh import VTU, gen

from cfm_fem import _kernels as K
from cfm_fem import testing as twins
from cfm_fem.errors import CfmInputError
from cfm_fem.models import harmonic
from cfm_fem.models.harmonic import fit_harmonic, neighbourhoods
from cfm_fem.models.harmonic_basis import MAX_DEGREE, field_basis, monomial_exponents, n_basis

MU0 = 4e-7 * np.pi  # T m / A


def _cloud(n, half=(10.0, 10.0, 10.0), seed=0):
    """``n`` uniformly scattered nodes in the box |x_i| <= half_i (mm)."""
    return np.random.default_rng(seed).uniform(-1.0, 1.0, (n, 3)) * np.asarray(half)


def _basis_field(points, seed=1, x0=(1.0, -2.0, 0.5), radius=12.0):
    """A sum of the degree <= 5 basis fields with random coefficients (T), about ``x0``."""
    coef = np.random.default_rng(seed).normal(size=n_basis(MAX_DEGREE))
    u = (points - np.asarray(x0)) / radius
    return (twins.harmonic_design(u, MAX_DEGREE) @ coef).reshape(-1, 3)


def _bessel_quadrupole(points, wavelength=40.0, amplitude=1.0):
    """B = grad Phi, Phi = a I_2(q r) cos(2 theta) cos(q z) / q, q = 2 pi / wavelength (T).

    Harmonic: with the modified Bessel equation q^2 I'' + q I' / r - (q^2 + 4 / r^2) I = 0,
    the Laplacian of Phi is q^2 I cos cos - q^2 I cos cos = 0. Near the axis it is a normal
    quadrupole of gradient a q / 4 whose strength varies as cos(q z).
    """
    q = 2.0 * np.pi / wavelength
    x, y, z = points.T
    r = np.hypot(x, y)
    th = np.arctan2(y, x)
    i2 = scipy.special.iv(2, q * r)
    di2 = 0.5 * (scipy.special.iv(1, q * r) + scipy.special.iv(3, q * r))  # I_2'
    b_r = amplitude * di2 * np.cos(2 * th) * np.cos(q * z)
    with np.errstate(invalid="ignore", divide="ignore"):
        b_t = np.where(r > 0, -2.0 * amplitude * i2 / (q * r), 0.0) * np.sin(2 * th) * np.cos(q * z)
    b_z = -amplitude * i2 * np.cos(2 * th) * np.sin(q * z)
    c, s = np.cos(th), np.sin(th)
    return np.c_[b_r * c - b_t * s, b_r * s + b_t * c, b_z]


def _off_node_points(n, half, seed=2):
    """Points between the nodes, away from the box faces by 1 mm."""
    return _cloud(n, np.asarray(half) - 1.0, seed)


# ---------------------------------------------------------------------------------------------
# Kernel against twin
# ---------------------------------------------------------------------------------------------
def _scan_lines(spacing):
    """Hall-probe scan lines along z, 0.1 mm steps, on a 4 x 4 grid of ``spacing`` (mm)."""
    ax = np.arange(4) * spacing
    pts = np.stack(np.meshgrid(ax, ax, np.arange(60) * 0.1, indexing="ij"), -1).reshape(-1, 3)
    return pts - [2.0, 2.0, 3.0]


@pytest.mark.parametrize("case", ["dipole", "current", "lines_1mm", "lines_3mm"])
def test_kernel_matches_twin(case):
    """Degrees and flags equal, coefficients to rounding: a harmonic non-polynomial field; a
    field with curl; scan lines whose neighbourhoods cannot fix every degree (1 mm apart:
    the pivot check lowers the degree; 3 mm: mostly one line, no fit at all)."""
    pts = _scan_lines(float(case[6])) if case.startswith("lines") else _cloud(400, (8.0,) * 3, 3)
    if case == "dipole":  # a point dipole outside the cloud: harmonic, not a polynomial
        d = pts - np.array([0.0, 0.0, 25.0])
        r = np.linalg.norm(d, axis=1)[:, None]
        m = np.array([0.3, -0.2, 1.0]) * 1e4
        B = (3.0 * d * (d @ m)[:, None] / r**2 - m) / r**3
    elif case == "current":  # a current along z through the cloud on a quadrupole: curl != 0
        B = np.c_[0.07 * pts[:, 1] - 0.01 * pts[:, 1], 0.07 * pts[:, 0] + 0.01 * pts[:, 0],
                  1e-3 * pts[:, 2] ** 2]  # fmt: skip
    else:
        B = _bessel_quadrupole(pts)
    idx = np.arange(0, len(pts), 7)
    nbr, scale = neighbourhoods(scipy.spatial.cKDTree(pts), pts, pts[idx], 40)
    args = (pts[idx], scale, nbr, pts, B)
    got = K.harmonic_fit_block(*args, field_basis(5), monomial_exponents(5), 2, 5)
    want = twins.harmonic_fit_twin(*args, 2, 5)
    coef, degree, resid, flag, checks = got
    np.testing.assert_array_equal(degree, want[1])
    np.testing.assert_array_equal(flag, want[3])
    big = np.maximum(np.abs(want[0]).max(axis=1, keepdims=True), 1e-300)
    np.testing.assert_allclose(coef / big, want[0] / big, rtol=0, atol=1e-10)
    floor = 1e-13 * np.abs(B).max()  # rounding of residuals of exact fits
    np.testing.assert_allclose(resid, want[2], rtol=1e-8, atol=floor)
    np.testing.assert_allclose(checks, want[4], rtol=1e-8, atol=floor)
    failed = (flag & K.FIT_FAILED) != 0
    assert np.all(coef[failed] == 0.0) and np.isnan(resid[failed]).all()
    if case == "dipole":
        assert degree.min() >= 4  # the dipole's higher terms show: the fit takes them
    elif case == "current":
        assert np.all(checks[:, K.CHECK_HARMONIC] > 100 * checks[:, K.CHECK_FREE])
    elif case == "lines_1mm":
        assert np.all(flag == K.FIT_CAPPED_PIVOT) and degree.max() < 5
    else:
        assert failed.mean() > 0.5


def _within_reach(fit, q):
    """`HarmonicFit.field_at` at ``q``, checking ``inside`` against the reach rule: the
    nearest node's reach holds the point (a scattered cloud has a few wider gaps)."""
    B, inside = fit.field_at(q)
    d, near = scipy.spatial.cKDTree(fit.centers).query(q)
    np.testing.assert_array_equal(
        inside, np.sqrt(np.sum((q - fit.centers[near]) ** 2, 1)) <= fit.reach_mm[near]
    )
    assert inside.mean() > 0.97 and np.isnan(B[~inside]).all()
    return B, inside


# ---------------------------------------------------------------------------------------------
# Exact and analytic harmonic fields
# ---------------------------------------------------------------------------------------------
def test_degree_5_harmonic_sum_is_reproduced_to_rounding():
    half = (10.0, 10.0, 10.0)
    pts = _cloud(1500, half)
    fit = fit_harmonic(pts, _basis_field(pts))
    assert fit.use.all() and np.all(fit.degree == 5)
    q = _off_node_points(3000, half)
    B, inside = _within_reach(fit, q)
    exact = _basis_field(q[inside])
    err = np.abs(B[inside] - exact).max() / np.abs(exact).max()
    assert err < 1e-12, err  # 6e-14 measured: normal equations with scaled columns suffice
    far = np.array([[0.0, 0.0, 40.0]])
    Bf, inf = fit.field_at(far)
    assert not inf[0] and np.isnan(Bf).all()


def test_analytic_3d_quadrupole_is_reproduced_within_truncation():
    """A normal quadrupole with a cos(q z) strength, by Bessel functions written out here.

    The fit's neighbourhood (radius s ~ 3.7 mm for 1500 nodes in a 20 mm cube) truncates the
    field's Taylor series at degree 5: the relative error is of order (q s)^6 / 6! ~ 5e-5."""
    half = (10.0, 10.0, 10.0)
    pts = _cloud(1500, half, seed=4)
    fit = fit_harmonic(pts, _bessel_quadrupole(pts))
    assert fit.use.all()
    q = _off_node_points(3000, half, seed=5)
    B, inside = _within_reach(fit, q)
    exact = _bessel_quadrupole(q[inside])
    err = np.abs(B[inside] - exact).max() / np.abs(exact).max()
    assert err < 1e-4, err


# ---------------------------------------------------------------------------------------------
# The bundled map against its exact source
# ---------------------------------------------------------------------------------------------
#: Smallest RMS factor (linear error / harmonic error) per slab and part of the aperture, about
#: half the factors these samples give. In the body the 16 magnet segments add harmonics of
#: order 18 and 34 whose period, ~3 mm at r = 8 mm, the 1.4 mm mesh barely samples: there
#: neither model follows them and the harmonic one gains only a factor ~2 between r = 5 mm
#: and the surface cells (where the linear interpolant is worse: factor ~8).
FACTORS = {"body": {"surface": 4.0, "r < 5 mm": 50.0, "5 mm <= r": 1.2},
           "magnet_end": {"surface": 1000.0, "r < 5 mm": 1000.0, "5 mm <= r": 1000.0}}  # fmt: skip


@pytest.mark.parametrize("slab", ["body", "magnet_end"])
def test_bundled_map_beats_the_linear_interpolant(slab):
    """A slab of the bundled map, fitted on its own; at tetrahedron centroids 5 mm or more
    from the slab's cut faces (beyond the neighbourhoods), against magpylib: the linear
    interpolant there is the mean of the four nodes. Cells with a node on the surface
    r = 10 mm are checked apart."""
    pytest.importorskip("magpylib")
    mesh = meshio.read(VTU)
    pts, B, tets = mesh.points, mesh.point_data["B"], mesh.cells_dict["tetra"]
    z0, z1 = (-10.0, 10.0) if slab == "body" else (34.0, 46.0)
    keep = (pts[:, 2] > z0) & (pts[:, 2] < z1)
    fit = fit_harmonic(pts[keep], B[keep])
    assert fit.use.all()
    z = pts[tets, 2]
    cells = tets[((z > z0 + 5.0) & (z < z1 - 5.0)).all(axis=1)]
    on_surface = (np.hypot(pts[cells, 0], pts[cells, 1]) > 9.99).any(axis=1)
    rng = np.random.default_rng(0)  # magpylib takes ~2 ms a point: 300 of each kind
    cells = np.r_[
        rng.choice(cells[on_surface], 300, False), rng.choice(cells[~on_surface], 300, False)
    ]
    centroids = pts[cells].mean(axis=1)
    exact = gen.field_T(gen.build_magnet(), centroids)
    err_lin = np.linalg.norm(B[cells].mean(axis=1) - exact, axis=1)
    harm, inside = fit.field_at(centroids)
    assert inside.all()
    err_harm = np.linalg.norm(harm - exact, axis=1)
    surface = np.arange(len(cells)) < 300
    r = np.hypot(centroids[:, 0], centroids[:, 1])
    parts = {"surface": surface, "r < 5 mm": r < 5.0, "5 mm <= r": ~surface & (r >= 5.0)}
    for name, part in parts.items():
        assert part.sum() > 20
        rms_lin = np.sqrt(np.mean(err_lin[part] ** 2))
        rms_harm = np.sqrt(np.mean(err_harm[part] ** 2))
        assert rms_lin > FACTORS[slab][name] * rms_harm, (name, rms_lin, rms_harm)


# ---------------------------------------------------------------------------------------------
# Fallback
# ---------------------------------------------------------------------------------------------
def _conductor_field(points, radius=6.0, current_density=3e6, background=True):
    """A round conductor along z (uniform J, A/m^2) in the Bessel quadrupole: inside,
    B = mu0 J r / 2 phi-hat (curl B = mu0 J); outside, mu0 J R^2 / (2 r) phi-hat (T, mm)."""
    x, y = points[:, 0], points[:, 1]
    r2 = x * x + y * y
    k = MU0 * current_density / 2.0 * 1e-3  # T/mm
    f = k * np.where(r2 < radius**2, 1.0, radius**2 / np.maximum(r2, 1e-300))
    b = np.c_[-y * f, x * f, 0.0 * f]
    return b + _bessel_quadrupole(points, amplitude=0.3) if background else b


def test_current_in_the_neighbourhood_triggers_the_fallback():
    half = (15.0, 15.0, 8.0)
    pts = _cloud(3000, half, seed=6)
    fit = fit_harmonic(pts, _conductor_field(pts))
    r = np.hypot(pts[:, 0], pts[:, 1])
    inside = r + fit.scale < 6.0
    outside = r - fit.scale > 6.0
    assert inside.sum() > 30 and outside.sum() > 500
    assert not fit.use[inside].any()
    assert fit.use[outside].all()
    # the model then reports no field where only fallback nodes are near
    B, ok = fit.field_at(np.zeros((1, 3)))
    assert not ok[0] and np.isnan(B).all()
    # the same map without the current: no fallback anywhere
    clean = fit_harmonic(pts, _bessel_quadrupole(pts, amplitude=0.3))
    assert clean.use.all()
    assert "linear interpolant" in fit.fallback_rule


def test_field_jump_at_a_surface_triggers_the_fallback():
    """A jump of 0.01 T in the tangential field across the plane z = 0 (a current sheet, as
    at the surface of iron): the nodes whose neighbourhood it cuts near the middle fall back;
    the nodes whose neighbourhood lies on one side do not."""
    pts = _cloud(3000, (10.0, 10.0, 10.0), seed=11)
    B = _bessel_quadrupole(pts, amplitude=0.3)
    B[pts[:, 2] > 0, 0] += 0.01
    fit = fit_harmonic(pts, B)
    depth = np.abs(pts[:, 2]) / fit.scale
    assert (depth < 0.25).sum() > 100 and (depth > 1).sum() > 1000
    assert not fit.use[depth < 0.25].any()
    assert fit.use[depth > 1].all()


def test_pure_conductor_field_falls_back():
    pts = _cloud(600, (4.0, 4.0, 4.0), seed=7)
    fit = fit_harmonic(pts, _conductor_field(pts, background=False))
    assert not fit.use.any()


# ---------------------------------------------------------------------------------------------
# Same bits whatever the threads, blocks and row order
# ---------------------------------------------------------------------------------------------
def _grid(n=11, h=0.7):
    ax = (np.arange(n) - (n - 1) / 2) * h
    return np.stack(np.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3)


FIELDS = ("coef", "degree", "residual_T", "scale", "reach_mm", "use", "centers")


@pytest.mark.parametrize("layout", ["scattered", "grid"])
def test_same_bits_whatever_threads_blocks_and_row_order(layout, monkeypatch):
    pts = _cloud(1200, (6.0, 6.0, 6.0), seed=8) if layout == "scattered" else _grid()
    B = _bessel_quadrupole(pts)
    ref = fit_harmonic(pts, B)
    perm = np.random.default_rng(9).permutation(len(pts))
    default = numba.get_num_threads()
    runs = []
    try:
        numba.set_num_threads(1)
        runs.append((fit_harmonic(pts, B), None))
        numba.set_num_threads(default)
        monkeypatch.setattr(harmonic, "_FIT_BLOCK", 7)
        monkeypatch.setattr(harmonic, "_QUERY_CHUNK", 100)
        runs.append((fit_harmonic(pts, B), None))
        runs.append((fit_harmonic(pts[perm], B[perm]), perm))
    finally:
        numba.set_num_threads(default)
    for fit, order in runs:
        for name in FIELDS:
            want = getattr(ref, name)
            np.testing.assert_array_equal(
                getattr(fit, name), want if order is None else want[order]
            )
    # off-node points, and cell centres of the grid (equidistant from 8 nodes)
    q = np.r_[_off_node_points(500, (6.0, 6.0, 6.0)), pts[::7] + 0.35]
    np.testing.assert_array_equal(runs[-1][0].field_at(q)[0], ref.field_at(q)[0])


def test_grid_ties_are_broken_by_coordinates():
    """On a cubic grid the 40th neighbour lies in a shell of 24 equidistant nodes: the
    neighbourhood takes them in (distance, x, y, z) order, the same from any row order."""
    pts = _grid(7, 1.0)
    tree = scipy.spatial.cKDTree(pts)
    centre = np.flatnonzero(np.all(pts == 0.0, axis=1))
    nbr, scale = neighbourhoods(tree, pts, pts[centre], 40)
    d2 = np.sum(pts[nbr[0]] ** 2, axis=1)
    assert scale[0] == np.sqrt(5.0) and np.all(np.diff(d2) >= 0)
    shell = pts[nbr[0][d2 == 5.0]]
    all_shell = pts[np.sum(pts**2, axis=1) == 5.0]
    want = all_shell[np.lexsort(all_shell.T[::-1])][: len(shell)]
    np.testing.assert_array_equal(shell, want)


# ---------------------------------------------------------------------------------------------
# Bad input
# ---------------------------------------------------------------------------------------------
def test_planar_or_tiny_maps_are_refused():
    flat = _cloud(200, (5.0, 5.0, 0.0))
    with pytest.raises(CfmInputError, match="3-D map.*one plane") as info:
        fit_harmonic(flat, np.ones_like(flat), source="flat.txt")
    assert str(info.value).startswith("flat.txt")
    tiny = _cloud(12)
    with pytest.raises(CfmInputError, match="at least 20 nodes"):
        fit_harmonic(tiny, np.ones_like(tiny))
    pts = _cloud(100)
    with pytest.raises(CfmInputError, match="k must be"):
        fit_harmonic(pts, np.ones_like(pts), k=5)
    with pytest.raises(CfmInputError, match="degrees"):
        fit_harmonic(pts, np.ones_like(pts), min_degree=1)


@pytest.mark.parametrize("layout", ["grid", "cloud"])
def test_neighbour_order_kernel_is_its_twin_bit_for_bit(layout):
    """`canonical_neighbours` orders candidates as its numpy twin `_canonical` does, to the
    bit: squared distances, then x, y, z on the ties of a grid's shells."""
    if layout == "grid":
        ax = np.arange(-4.0, 5.0) * 0.7
        pts = np.stack(np.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3)
    else:
        pts = _cloud(600)
    centres = pts[::5]
    _, cand = scipy.spatial.cKDTree(pts).query(centres, 48)
    cand = np.ascontiguousarray(cand[:, ::-1])  # the kernel must sort, not keep the order
    nbr, d2 = K.canonical_neighbours(pts, centres, cand)
    want_nbr, want_d2 = harmonic._canonical(pts, centres, cand)
    np.testing.assert_array_equal(nbr, want_nbr)
    np.testing.assert_array_equal(d2, want_d2)


def test_fit_kernels_allocate_by_np_empty_alone():
    """The fit's module allocates with np.empty only: numba compiles each of np.zeros,
    np.full and np.ones (and np.empty again for the dtype they pass it) as a function of its
    own, CPU time of the first run after an install (docs/performance.md)."""
    import ast
    import inspect

    from cfm_fem._kernels import harmonic_fit

    tree = ast.parse(inspect.getsource(harmonic_fit))
    others = {"zeros", "full", "ones", "zeros_like", "full_like", "ones_like"}
    calls = [
        (node.lineno, node.func.attr)
        for node in ast.walk(tree)
        if isinstance(node, ast.Call)
        and isinstance(node.func, ast.Attribute)
        and isinstance(node.func.value, ast.Name)
        and node.func.value.id == "np"
        and node.func.attr in others
    ]
    assert calls == []
