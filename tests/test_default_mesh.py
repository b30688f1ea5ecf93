"""The bundled default field map in meshes/ (made by scripts/make_default_mesh.py).

The expected numbers follow from geometry and magnetostatics, not from the files:
the magnet parameters are read from the generating script (which imports gmsh and
magpylib only inside its functions, so nothing heavy is imported here).
"""

from __future__ import annotations

import importlib.util
import math
from pathlib import Path

import meshio
import numpy as np
import pytest

ROOT = Path(__file__).resolve().parent.parent
MESHES = ROOT / "meshes"
VTU = MESHES / "quadrupole.vtu"
COMSOL = MESHES / "quadrupole_comsol.txt"
OPERA = MESHES / "quadrupole_opera.table"


def _load_script():
    spec = importlib.util.spec_from_file_location(
        "make_default_mesh", ROOT / "scripts" / "make_default_mesh.py"
    )
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


gen = _load_script()
MAG = gen.MAGNET
RADIUS = gen.DEFAULT_RADIUS_MM  # mm
Z_HALF = gen.DEFAULT_Z_HALF_MM  # mm
G2D = gen.gradient_2d_analytic()  # T/mm, infinitely long segmented Halbach quadrupole
COORD_TOL = 10.0**-gen.COORD_DECIMALS  # mm, rounding of the node coordinates


@pytest.fixture(scope="module")
def vtu():
    mesh = meshio.read(VTU)
    assert len(mesh.cells) == 1 and mesh.cells[0].type == "tetra"
    return mesh.points, mesh.cells[0].data, mesh.point_data["B"]


def _volumes(points, tets):
    a, b, c, d = (points[tets[:, i]] for i in range(4))
    return np.einsum("ij,ij->i", np.cross(b - a, c - a), d - a) / 6.0


def _edges(points, tets):
    pairs = [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)]
    return np.stack(
        [np.linalg.norm(points[tets[:, i]] - points[tets[:, j]], axis=1) for i, j in pairs], axis=1
    )


def _fit_linear(points, values):
    """Least squares values ~ c0 + c1 x + c2 y + c3 z; returns (c0, c1, c2, c3) per column."""
    A = np.column_stack([np.ones(len(points)), points])
    coef, *_ = np.linalg.lstsq(A, values, rcond=None)
    return coef


# --------------------------------------------------------------------------------------
# VTU: layout and mesh geometry
# --------------------------------------------------------------------------------------
def test_vtu_layout(vtu):
    points, tets, b = vtu
    n = len(points)
    assert points.shape == (n, 3) and points.dtype == np.float64
    assert tets.ndim == 2 and tets.shape[1] == 4 and np.issubdtype(tets.dtype, np.integer)
    assert b.shape == (n, 3) and b.dtype == np.float64
    assert 40_000 <= n <= 80_000
    assert tets.min() == 0 and tets.max() == n - 1
    assert np.unique(tets).size == n, "every node belongs to a tetrahedron"
    assert (np.sort(tets, axis=1)[:, 1:] != np.sort(tets, axis=1)[:, :-1]).all(), "repeated node"


def test_tetrahedra_positive_and_not_degenerate(vtu):
    points, tets, _ = vtu
    vol = _volumes(points, tets)
    assert (vol > 0).all(), "all tetrahedra positively oriented"
    # shape quality 6 sqrt(2) V / l_rms^3: 1 for a regular tetrahedron, -> 0 for a sliver
    l_rms = np.sqrt((_edges(points, tets) ** 2).mean(axis=1))
    quality = 6.0 * math.sqrt(2.0) * vol / l_rms**3
    assert quality.min() > 0.05


def test_mesh_fills_the_aperture_cylinder(vtu):
    points, tets, _ = vtu
    r = np.hypot(points[:, 0], points[:, 1])
    tol = COORD_TOL  # node coordinates are rounded to this (mm)
    assert MAG["r_inner_mm"] > RADIUS, "the mesh stays inside the bore"
    assert RADIUS - tol <= r.max() <= RADIUS + tol
    assert np.isclose(points[:, 2].min(), -Z_HALF) and np.isclose(points[:, 2].max(), Z_HALF)

    # conforming: every face is shared by one or two tets, and the faces of one tet lie
    # on the cylinder surface (no cracks or holes inside the volume)
    faces = np.concatenate(
        [tets[:, [0, 1, 2]], tets[:, [0, 1, 3]], tets[:, [0, 2, 3]], tets[:, [1, 2, 3]]]
    )
    uniq, counts = np.unique(np.sort(faces, axis=1), axis=0, return_counts=True)
    assert counts.max() == 2
    outer = uniq[counts == 1]
    on_side = np.abs(r[outer] - RADIUS) <= 2 * tol
    on_cap = np.abs(np.abs(points[outer, 2]) - Z_HALF) <= tol
    assert (on_side.all(axis=1) | on_cap.all(axis=1)).all()

    # volume: all vertices lie in the convex cylinder, so sum <= pi R^2 (2 Z); a side
    # triangle with edges <= l spans an arc theta = 2 asin(l / 2R), so the surface stays
    # at r >= R cos(theta / 2) and the volume >= pi (R^2 - (l/2)^2) (2 Z)
    side = outer[on_side.all(axis=1)]
    l_side = max(
        np.linalg.norm(points[side[:, i]] - points[side[:, j]], axis=1).max()
        for i, j in ((0, 1), (0, 2), (1, 2))
    )
    assert l_side < 0.5 * RADIUS
    vol = _volumes(points, tets).sum()
    exact = math.pi * RADIUS**2 * 2 * Z_HALF
    rounding = 2 * math.pi * RADIUS * 2 * Z_HALF * 2 * tol
    assert exact * (1 - (l_side / (2 * RADIUS)) ** 2) <= vol <= exact + rounding


# --------------------------------------------------------------------------------------
# VTU: the field
# --------------------------------------------------------------------------------------
def test_field_finite_and_of_the_right_size(vtu):
    points, _, b = vtu
    assert np.isfinite(b).all()
    # the largest field is at r = R in the body: G R, with G a little below the 2-D
    # value (finite length) and a small b18 (16 segments); within 1 % of G_2D R
    bmax = np.linalg.norm(b, axis=1).max()
    assert abs(bmax / (G2D * RADIUS) - 1) < 0.01
    # far from the magnet the fringe field has decayed (|z| = 1.5 L)
    far = np.abs(points[:, 2]) > Z_HALF - 5.0
    assert np.linalg.norm(b[far], axis=1).max() < 1e-3 * bmax


def test_field_vanishes_at_the_centre(vtu):
    points, _, b = vtu
    r = np.hypot(points[:, 0], points[:, 1])
    core = (r < 3.0) & (np.abs(points[:, 2]) < 10.0)
    assert core.sum() >= 50
    # a quadrupole is zero on its axis and linear next to it: |B| <= G r, with G(z)
    # below the 2-D value G_2D in a finite magnet
    assert (np.linalg.norm(b[core], axis=1) <= G2D * r[core] * (1 + 1e-4)).all()
    # the linear fit through the nodes near the centre extrapolates to B(0) = 0: the
    # neglected cubic terms (~ G'' r^3 / 8 ~ 2e-4 G * 1 mm at r = 3 mm) are odd in x, y,
    # so with nodes all around the axis they leave an intercept well below 1e-4 G * 1 mm
    near = core & (np.abs(points[:, 2]) < 5.0)
    c0 = _fit_linear(points[near], b[near])[0]
    assert np.abs(c0).max() < 1e-4 * G2D * 1.0


def test_central_gradient_is_a_normal_quadrupole(vtu):
    points, _, b = vtu
    sel = (np.hypot(points[:, 0], points[:, 1]) < 3.0) & (np.abs(points[:, 2]) < 5.0)
    assert sel.sum() >= 50
    coef = _fit_linear(points[sel], b[sel])  # coef[1 + j, i] = dB_i/dx_j, T/mm
    jac = coef[1:].T
    g_x, g_y = jac[1, 0], jac[0, 1]  # dBy/dx, dBx/dy
    # curl B = 0 gives dBy/dx = dBx/dy; the cubic terms within r < 3 mm, |z| < 5 mm
    # (pseudo-multipoles, G'' r^2 / 8 G ~ 5e-5) are symmetric under x <-> y, so they
    # bias both fits alike and leave the difference well below 1e-4
    assert abs(g_x - g_y) < 1e-4 * abs(g_x)
    # normal, not skew: dBx/dx = dBy/dy ~ 0 and nothing depends on z at the centre
    assert abs(jac[0, 0]) < 1e-4 * g_x and abs(jac[1, 1]) < 1e-4 * g_x
    assert np.abs(jac[:, 2]).max() < 1e-3 * g_x
    # div B = 0
    assert abs(np.trace(jac)) < 1e-4 * g_x
    # the 80 mm magnet reaches nearly the 2-D gradient (a few 1e-3 lower), ~71 T/m
    assert 0.98 * G2D < g_x <= G2D * (1 + 1e-4)


# --------------------------------------------------------------------------------------
# COMSOL text layout: the same nodes
# --------------------------------------------------------------------------------------
def test_comsol_export_matches_the_vtu(vtu):
    points, _, b = vtu
    header = {}
    with open(COMSOL, encoding="ascii") as f:
        lines = [next(f) for _ in range(9)]
    for line in lines[:8]:
        assert line.startswith("% ")
        key, _, val = line[2:].partition(":")
        header[key.strip()] = val.strip()
    assert header["Version"] == "COMSOL 6.1.0.252"
    assert header["Dimension"] == "3" and header["Expressions"] == "3"
    assert header["Length unit"] == "mm"
    assert int(header["Nodes"]) == len(points)
    assert lines[8].split()[1:] == ["X", "Y", "Z", "mf.Bx", "(T)", "mf.By", "(T)", "mf.Bz", "(T)"]
    data = np.loadtxt(COMSOL, comments="%")
    assert data.shape == (len(points), 6)
    np.testing.assert_allclose(data[:, :3], points, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(data[:, 3:], b, rtol=1e-9, atol=1e-12)


# --------------------------------------------------------------------------------------
# Opera-3D table: regular grid, metres and tesla
# --------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def opera():
    with open(OPERA, encoding="ascii") as f:
        head = [next(f) for _ in range(8)]
    counts = [int(v) for v in head[0].split()]
    assert len(counts) == 4 and counts[3] == 2
    cols = [line.split(None, 1) for line in head[1:7]]
    assert [c[0] for c in cols] == ["1", "2", "3", "4", "5", "6"]
    assert [c[1].strip() for c in cols] == [
        "X [METRE]",
        "Y [METRE]",
        "Z [METRE]",
        "BX [TESLA]",
        "BY [TESLA]",
        "BZ [TESLA]",
    ]
    assert head[7].strip() == "0"
    data = np.loadtxt(OPERA, skiprows=8)
    return counts[:3], data


def test_opera_grid_layout(opera):
    counts, data = opera
    assert data.shape == (math.prod(counts), 6)
    ux, uy, uz = (np.unique(data[:, i]) for i in range(3))
    # z varies fastest and x slowest; line 1 lists the counts fastest first (nz ny nx),
    # as real Opera exports do
    assert counts == [uz.size, uy.size, ux.size]
    grid = data.reshape(ux.size, uy.size, uz.size, 6)
    assert (np.diff(grid[..., 2], axis=2) > 0).all()
    assert (np.diff(grid[..., 1], axis=1) > 0).all()
    assert (np.diff(grid[..., 0], axis=0) > 0).all()
    # metres: the grid is the inscribed box of the r = 10 mm aperture, |z| <= 1.5 L
    assert np.hypot(ux.max(), uy.max()) <= RADIUS * 1e-3 * (1 + 1e-9)
    assert np.isclose(uz.min(), -Z_HALF * 1e-3) and np.isclose(uz.max(), Z_HALF * 1e-3)
    assert np.isfinite(data).all()


def test_opera_field_is_the_same_quadrupole(opera, vtu):
    counts, data = opera
    nz, ny, nx = counts
    grid = data.reshape(nx, ny, nz, 6)
    x, y, z = grid[:, 0, 0, 0], grid[0, :, 0, 1], grid[0, 0, :, 2]  # m
    jy0 = int(np.argmin(np.abs(y)))
    assert y[jy0] == 0.0
    # mirror symmetry of a normal quadrupole: Bx and Bz are odd in y, so zero at y = 0
    bmax = np.abs(grid[..., 3:]).max()
    assert np.abs(grid[:, jy0, :, 3]).max() < 1e-9 * bmax
    assert np.abs(grid[:, jy0, :, 5]).max() < 1e-9 * bmax
    # gradient G(z) from By(x, 0, z) in T/m; at z = 0 it matches the VTU fit (T/mm * 1e3)
    gz = np.polyfit(x, grid[:, jy0, :, 4], 1)[0]
    points, _, b = vtu
    sel = (np.hypot(points[:, 0], points[:, 1]) < 3.0) & (np.abs(points[:, 2]) < 5.0)
    g_vtu = _fit_linear(points[sel], b[sel])[1, 1] * 1e3
    k0 = int(np.argmin(np.abs(z)))
    assert abs(gz[k0] / g_vtu - 1) < 1e-3
    # ironless magnet: int G dz over all z equals the 2-D gradient times the length
    # (superposition of slices); the fringe beyond |z| = 1.5 L is < 1e-4 of it
    integral = np.sum(0.5 * (gz[1:] + gz[:-1]) * np.diff(z))  # T
    assert abs(integral / (G2D * 1e3 * MAG["length_mm"] * 1e-3) - 1) < 1e-3
    # and the fringe has decayed at the ends of the grid
    assert max(abs(gz[0]), abs(gz[-1])) < 1e-3 * gz[k0]
