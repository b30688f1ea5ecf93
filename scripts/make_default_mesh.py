#!/usr/bin/env python
"""Make the bundled default field map in ``meshes/`` (reproducible, deterministic).

    python scripts/make_default_mesh.py            # regenerates everything in meshes/

What it builds
--------------
* A permanent-magnet quadrupole: a 16-segment Halbach ring of NdFeB annular sectors
  (magpylib ``CylinderSegment``), each sector uniformly polarised at ``3*theta_k - pi/2``
  so that the aperture field is a *normal* quadrupole, ``By = G*x``, ``Bx = G*y``, ``G > 0``.
  Every parameter is in ``MAGNET`` below and is repeated in ``meshes/README.md``.
* The aperture region, a cylinder of radius ``--radius`` (below the bore radius) and
  ``|z| <= --z-half`` (1.5 magnet lengths, so the 3-D fringe field at both ends decays
  to ~3e-5 of the central gradient), meshed with linear gmsh tetrahedra, refined near
  the magnet ends where the field changes fastest along z.
* The field B (T) at every node, from magpylib (SI inside magpylib: mm -> m at the call).

Files written to ``--out-dir`` (default: ``meshes/`` next to this script's parent)
-------------------------------------------------------------------------------
* ``quadrupole.vtu``         meshio VTU (binary + zlib): points (n, 3) mm, cells "tetra"
                             (m, 4), point_data "B" (n, 3) float64 T. Default map of the CLI.
* ``quadrupole_comsol.txt``  the same nodes and B as a COMSOL text export (mm, T).
* ``quadrupole_opera.table`` Opera-3D ``.table``: B on a regular grid inside the inscribed
                             box of the aperture (metres, tesla), z varying fastest.
* ``README.md``              what the files are, parameters, counts, sizes, the checks.

The script also checks the physics numerically and prints it (copied into the README):
div B and curl B of a finite-difference stencil at interior points; the central gradient
against the 2-D analytic value; the ironless-magnet theorem ``int G dz = G_2D * L``;
zero field on the axis; the mean-value property of the harmonic field at sampled nodes;
the allowed harmonics of a 16-fold ring; the linear-interpolation error of the mesh.

magpylib caveats handled in ``field_T``: the CylinderSegment formula is unstable within
~0.1 mm of the magnet axis and returns NaN very close to the end-face planes; both are
repaired there (see the docstrings) and verified by the mean-value check.

Determinism: gmsh runs single-threaded with fixed options; nodes are renumbered in a
fixed spatial order; the COMSOL header date is fixed. Same versions -> identical files.
gmsh and magpylib are optional dependencies (``pip install cfm_fem[mesh]``); they are
imported inside the functions that need them so the constants here can be read without.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
from pathlib import Path

import numpy as np

# ---------------------------------------------------------------------------------------
# Magnet (lengths mm, fields T, angles rad). Change here, then regenerate.
# ---------------------------------------------------------------------------------------
MAGNET = {
    "type": "16-segment Halbach permanent-magnet quadrupole (ironless), NdFeB annular sectors",
    "n_segments": 16,  # M, sectors of 360/16 = 22.5 deg, sector k centred at theta_k = 2*pi*k/M
    "order": 2,  # N = 2: quadrupole; sector polarisation angle = (N + 1)*theta_k + phase
    "phase_rad": -math.pi / 2,  # gives a normal quadrupole with G = dBy/dx > 0
    "br_T": 1.2,  # remanence = polarisation J of each sector (magpylib: mu_r = 1)
    "r_inner_mm": 14.0,  # bore radius
    "r_outer_mm": 25.0,
    "length_mm": 80.0,  # magnet from z = -40 mm to z = +40 mm, centred at the origin
}

# Aperture region and mesh defaults (mm)
DEFAULT_RADIUS_MM = 10.0
DEFAULT_Z_HALF_MM = 120.0  # 1.5 * length
DEFAULT_H_END_MM = 0.55  # element size at the magnet end faces, at r = radius
DEFAULT_RADIAL_GRADING = 0.8  # end-face size grows to h_end * (1 + 0.8) on the axis
DEFAULT_H_BODY_MM = 1.4  # element size in the body (field ~ linear in x, y)
DEFAULT_H_FAR_MM = 2.2  # element size far outside the magnet (field < 1e-3 of centre)
DEFAULT_END_WIDTH_MM = 6.0  # half-width of the fine zone around each end face
RAMP_IN = 2.0  # size ramps to h_body over RAMP_IN * end_width towards the centre
RAMP_OUT = 4.0  # and to h_far over RAMP_OUT * end_width outwards
COORD_DECIMALS = 6  # node coordinates rounded to 1e-6 mm (1 nm) so all layouts agree exactly
DEFAULT_GRID = (15, 15, 61)  # Opera grid nx, ny, nz
OPERA_HALF_WIDTH_MM = 7.0  # inscribed square of the r = 10 mm circle is +-7.07 mm

COMSOL_DATE = "Jan 1 2025, 00:00"  # fixed for determinism
R_AXIS_SAFE_MM = 0.25  # below this distance from the axis, see field_T
Z_NUDGE_MM = 1e-3  # see _field_raw_T
FD_STEP_MM = 0.1  # finite-difference step for the div/curl checks (4th-order stencil)


def gradient_2d_analytic(magnet: dict = MAGNET) -> float:
    """Central gradient of the infinitely long segmented Halbach quadrupole, T/mm.

    G = 2 Br (1/r_i - 1/r_o) * sin(3 pi / M) / (3 pi / M): the continuous Halbach
    quadrupole (Halbach 1980) times the fundamental Fourier factor of M uniformly
    polarised annular sectors.
    """
    m, n = magnet["n_segments"], magnet["order"]
    eps = (n + 1) * math.pi / m
    g_cont = 2.0 * magnet["br_T"] * (1.0 / magnet["r_inner_mm"] - 1.0 / magnet["r_outer_mm"])
    return g_cont * math.sin(eps) / eps


# ---------------------------------------------------------------------------------------
# Field
# ---------------------------------------------------------------------------------------
def build_magnet(magnet: dict = MAGNET):
    """magpylib Collection of the M sectors (magpylib works in metres and tesla)."""
    import magpylib as magpy

    m = magnet["n_segments"]
    half_deg = 180.0 / m
    coll = magpy.Collection()
    for k in range(m):
        theta = 2.0 * math.pi * k / m
        alpha = (magnet["order"] + 1) * theta + magnet["phase_rad"]
        br = magnet["br_T"]
        coll.add(
            magpy.magnet.CylinderSegment(
                polarization=(br * math.cos(alpha), br * math.sin(alpha), 0.0),
                dimension=(
                    magnet["r_inner_mm"] * 1e-3,
                    magnet["r_outer_mm"] * 1e-3,
                    magnet["length_mm"] * 1e-3,
                    math.degrees(theta) - half_deg,
                    math.degrees(theta) + half_deg,
                ),
            )
        )
    return coll


def _field_raw_T(source, pts_mm: np.ndarray) -> np.ndarray:
    """magpylib B (T), (n, 3), at pts_mm (mm); non-finite results repaired.

    magpylib's CylinderSegment returns NaN for observers within ~1e-8..1e-7 mm of the
    planes of the end faces (special-case tolerance window, magpylib issue #648). Such
    points get the mean of B at z +- Z_NUDGE_MM (error O(Z_NUDGE^2 d2B/dz2), < 1e-3 units).
    """
    pts_mm = np.asarray(pts_mm, dtype=np.float64).reshape(-1, 3)
    with np.errstate(all="ignore"):
        b = np.asarray(source.getB(pts_mm * 1e-3), dtype=np.float64).reshape(-1, 3)  # mm -> m
        bad = ~np.isfinite(b).all(axis=1)
        if bad.any():
            dz = np.array([0.0, 0.0, Z_NUDGE_MM])
            up = source.getB((pts_mm[bad] + dz) * 1e-3)
            down = source.getB((pts_mm[bad] - dz) * 1e-3)
            b[bad] = 0.5 * (np.reshape(up, (-1, 3)) + np.reshape(down, (-1, 3)))
    return b


def field_T(source, points_mm: np.ndarray, r_safe_mm: float = R_AXIS_SAFE_MM) -> np.ndarray:
    """B (T), shape (n, 3), at ``points_mm`` (mm), shape (n, 3).

    magpylib's CylinderSegment formula is unstable for observers very close to the
    segment axis (here the magnet axis): at r = 1e-3 mm it is off by up to ~1e-2 T, at
    r = 0.01 mm by ~5e-4 T (magpylib issue #606 reports the same for a Halbach octupole).
    For 0 < r < r_safe_mm the field is therefore taken from the quadratic through B on
    the axis (r = 0 is a stable special case) and B at r_safe and 2 r_safe on the same
    ray at the same z; the neglected cubic term is < 1e-6 T here.
    """
    pts = np.asarray(points_mm, dtype=np.float64).reshape(-1, 3)
    b = _field_raw_T(source, pts)
    r = np.hypot(pts[:, 0], pts[:, 1])
    near = (r > 0.0) & (r < r_safe_mm)
    if near.any():
        p, rn = pts[near], r[near]
        u = p[:, :2] / rn[:, None]
        t1, t2 = r_safe_mm, 2.0 * r_safe_mm
        zc = p[:, 2]
        q = np.concatenate([np.c_[0.0 * u, zc], np.c_[u * t1, zc], np.c_[u * t2, zc]])
        b0, b1, b2 = _field_raw_T(source, q).reshape(3, -1, 3)
        # Lagrange weights of the nodes 0, t1, t2 at rn
        w0 = (rn - t1) * (rn - t2) / (t1 * t2)
        w1 = rn * (rn - t2) / (t1 * (t1 - t2))
        w2 = rn * (rn - t1) / (t2 * (t2 - t1))
        b[near] = w0[:, None] * b0 + w1[:, None] * b1 + w2[:, None] * b2
    return b


# ---------------------------------------------------------------------------------------
# Mesh
# ---------------------------------------------------------------------------------------
def mesh_aperture(
    radius,
    z_half,
    h_end,
    h_body,
    h_far,
    end_width,
    magnet_length,
    *,
    radial_grading=DEFAULT_RADIAL_GRADING,
    verbose=False,
):
    """Linear tetrahedral mesh of the cylinder r <= radius, |z| <= z_half (all mm).

    Element size (mm) as a function of the distance d to the nearest magnet end face
    z = +-L/2 and of r: h0(r) = h_end * (1 + radial_grading * (1 - r/radius)) for
    d <= end_width (finest at r = radius, nearest the magnet corners, where the field
    curvature is largest); inside the magnet a linear ramp to ``h_body`` over the next
    ``RAMP_IN*end_width``; outside a linear ramp to ``h_far`` over the next
    ``RAMP_OUT*end_width`` (the fringe field decays over a few bore radii).

    Returns points (n, 3) mm, rounded to ``COORD_DECIMALS``, and positively oriented
    tetrahedra (m, 4) int64; nodes renumbered in a fixed spatial order (z, then y,
    then x) and cells sorted, so the output does not depend on gmsh's numbering.
    """
    import gmsh

    z_end = 0.5 * magnet_length

    def size(dim, tag, x, y, z, lc):  # gmsh size callback, mm
        rho = min(1.0, math.hypot(x, y) / radius)
        h0 = h_end * (1.0 + radial_grading * (1.0 - rho))
        d = abs(abs(z) - z_end)
        if abs(z) < z_end:
            s = min(1.0, max(0.0, (d - end_width) / (RAMP_IN * end_width)))
            return h0 + (h_body - h0) * s
        s = min(1.0, max(0.0, (d - end_width) / (RAMP_OUT * end_width)))
        return h0 + (h_far - h0) * s

    gmsh.initialize(readConfigFiles=False, interruptible=False)
    try:
        gmsh.option.setNumber("General.Verbosity", 5 if verbose else 1)
        gmsh.option.setNumber("General.Terminal", 1 if verbose else 0)
        gmsh.option.setNumber("General.NumThreads", 1)  # determinism
        gmsh.model.add("aperture")
        gmsh.model.occ.addCylinder(0.0, 0.0, -z_half, 0.0, 0.0, 2.0 * z_half, radius)
        gmsh.model.occ.synchronize()
        gmsh.model.mesh.setSizeCallback(size)
        for key, val in {
            "Mesh.MeshSizeFromPoints": 0,
            "Mesh.MeshSizeFromCurvature": 0,
            "Mesh.MeshSizeExtendFromBoundary": 0,
            "Mesh.Algorithm": 6,  # Frontal-Delaunay 2-D
            "Mesh.Algorithm3D": 1,  # Delaunay 3-D
            "Mesh.Optimize": 1,
            "Mesh.ElementOrder": 1,  # linear tetrahedra only
            "Mesh.MaxNumThreads1D": 1,
            "Mesh.MaxNumThreads2D": 1,
            "Mesh.MaxNumThreads3D": 1,
        }.items():
            gmsh.option.setNumber(key, val)
        gmsh.model.mesh.generate(3)
        tags, xyz, _ = gmsh.model.mesh.getNodes()
        _, tet_nodes = gmsh.model.mesh.getElementsByType(4)  # 4 = 4-node tetrahedron
    finally:
        gmsh.finalize()

    tags = tags.astype(np.int64)
    xyz = xyz.reshape(-1, 3)
    lookup = np.full(tags.max() + 1, -1, dtype=np.int64)
    lookup[tags] = np.arange(tags.size)
    tets = lookup[tet_nodes.astype(np.int64)].reshape(-1, 4)

    # keep only nodes used by tetrahedra, renumber in z, y, x order (compresses well)
    used = np.unique(tets)
    pts = np.round(xyz[used], COORD_DECIMALS) + 0.0  # + 0.0 turns -0.0 into 0.0
    order = np.lexsort((pts[:, 0], pts[:, 1], pts[:, 2]))
    new_index = np.empty(tags.size, dtype=np.int64)
    new_index[used[order]] = np.arange(used.size)
    points = pts[order]
    tets = new_index[tets]

    vol = tet_volumes(points, tets)
    neg = vol < 0
    tets[neg] = tets[neg][:, [0, 1, 3, 2]]
    tets = tets[np.lexsort(tets[:, ::-1].T)]  # sort rows, keep orientation within a row
    return points, tets


def tet_volumes(points, tets):
    """Signed volumes (m,) of tetrahedra (m, 4) over points (n, 3)."""
    a, b, c, d = (points[tets[:, i]] for i in range(4))
    return np.einsum("ij,ij->i", np.cross(b - a, c - a), d - a) / 6.0


# ---------------------------------------------------------------------------------------
# Physics checks
# ---------------------------------------------------------------------------------------
def jacobian_fd(source, p_mm, h_mm=FD_STEP_MM):
    """J[i, j] = dB_i/dx_j (T/mm) at p_mm (mm), fourth-order central differences.

    dB/dx ~ (8 (B(x+h) - B(x-h)) - (B(x+2h) - B(x-2h))) / (12 h), truncation O(h^4).
    (h = 0.1 mm: magpylib's sector formulas lose a few digits within ~0.01 mm of the axis,
    so a smaller second-order stencil is worse there.)
    """
    p = np.asarray(p_mm, dtype=np.float64)
    stencil = []
    for j in range(3):
        e = np.zeros(3)
        e[j] = h_mm
        stencil += [p + e, p - e, p + 2 * e, p - 2 * e]
    b = field_T(source, np.array(stencil)).reshape(3, 4, 3)
    d = (8.0 * (b[:, 0] - b[:, 1]) - (b[:, 2] - b[:, 3])) / (12.0 * h_mm)  # d[j, i]
    return d.T


def physics_checks(source, radius, z_half, points, tets, bnodes) -> list[str]:
    """Numerical checks of the field and of the mesh; returns the printed lines."""
    mag = MAGNET
    z_end = 0.5 * mag["length_mm"]
    g2d = gradient_2d_analytic()
    lines = []
    add = lines.append

    add(f"div B and curl B from a 4th-order central-difference stencil (h = {FD_STEP_MM:g} mm):")
    add("  point (mm)                 |grad B| (T/m)  |div B|/|grad B|  |curl B|/|grad B|")
    probes = [
        (0.0, 0.0, 0.0),
        (5.0, 3.0, 0.0),
        (-4.0, 6.0, 20.0),
        (5.0, 3.0, z_end),
        (3.0, -4.0, z_end + 10.0),
        (-2.0, -6.0, -z_end - 5.0),
        (6.0, 6.0, z_end + 40.0),
    ]
    worst = 0.0
    for p in probes:
        jac = jacobian_fd(source, p)
        gn = np.linalg.norm(jac)
        div = abs(np.trace(jac)) / gn
        curl = (
            np.linalg.norm([jac[2, 1] - jac[1, 2], jac[0, 2] - jac[2, 0], jac[1, 0] - jac[0, 1]])
            / gn
        )
        worst = max(worst, div, curl)
        pt = f"({p[0]:6.1f}, {p[1]:6.1f}, {p[2]:6.1f})"
        add(f"  {pt}   {gn * 1e3:14.6g}  {div:16.2e}  {curl:17.2e}")
    add(f"  worst relative residual: {worst:.1e} (0 up to FD truncation and rounding)")

    j0 = jacobian_fd(source, (0.0, 0.0, 0.0))
    g_x, g_y = j0[1, 0], j0[0, 1]
    add("central gradient (T/m):")
    add(f"  dBy/dx at centre (magpylib)                 = {g_x * 1e3:.6f}")
    add(f"  dBx/dy at centre (magpylib)                 = {g_y * 1e3:.6f}")
    add(f"  2-D analytic 2Br(1/ri-1/ro)sinc(3pi/M)      = {g2d * 1e3:.6f}")
    add(f"  ratio centre / 2-D = {g_x / g2d:.5f} (finite length: slightly below 1 expected)")
    add(
        f"  pole-tip field G*r_i = {g_x * mag['r_inner_mm']:.4f} T; dBx/dx = {j0[0, 0] * 1e3:.1e}"
        f" T/m, dBy/dy = {j0[1, 1] * 1e3:.1e} T/m (skew ~ 0)"
    )

    # gradient along z and the ironless-magnet theorem: int G dz = G_2D * L
    z = np.linspace(-z_half, z_half, 2401)
    d = 0.1
    bp = field_T(source, np.c_[np.full_like(z, d), np.zeros_like(z), z])
    bm = field_T(source, np.c_[np.full_like(z, -d), np.zeros_like(z), z])
    gz = (bp[:, 1] - bm[:, 1]) / (2 * d)
    integral = float(np.sum(0.5 * (gz[1:] + gz[:-1]) * np.diff(z)))  # trapezoid, T
    g2d_l = g2d * mag["length_mm"]
    add(f"integrated gradient over |z| <= {z_half:g} mm:")
    add(
        f"  int G dz = {integral:.6f} T; G_2D * L = {g2d_l:.6f} T; ratio = {integral / g2d_l:.6f}"
        " (theorem: 1 for an ironless magnet)"
    )
    gc = gz[z.size // 2]
    for zz in (z_end, z_end + 20.0, z_end + 40.0, z_half):
        add(f"  G(z = {zz:6.1f} mm) / G(0) = {np.interp(zz, z, gz) / gc:.3e}")

    # zero field on the axis, |B| = G(z) r next to it
    b_axis = field_T(source, np.c_[np.zeros_like(z), np.zeros_like(z), z])
    r = np.hypot(points[:, 0], points[:, 1])
    near = (r < 2.0) & (np.abs(points[:, 2]) < z_end - 10.0)
    g_local = np.interp(points[near, 2], z, gz)
    dev = np.abs(np.linalg.norm(bnodes[near], axis=1) / (g_local * r[near]) - 1.0)
    add("field near the axis (quadrupole: B = 0 on x = y = 0, |B| = G(z) r close to it):")
    add(
        f"  max |B| on the axis for |z| <= {z_half:g} mm: {np.abs(b_axis).max():.2e} T"
        f" (scale G*r_i = {gc * mag['r_inner_mm']:.3f} T)"
    )
    add(
        f"  {near.sum()} mesh nodes with r < 2 mm, |z| < {z_end - 10.0:g} mm:"
        f" max | |B| / (G(z) r) - 1 | = {dev.max():.1e}"
    )
    add("  (3-D pseudo-multipoles: order r^2 G''(z) / (8 G(z)) ~ 1e-3 at r = 2 mm)")

    # mean-value property: each component of B is harmonic in the aperture, so B(p)
    # equals the mean over the 6 points p +- h e_j up to O(h^4); catches glitches of the
    # field evaluation anywhere (sampled nodes plus every node close to the axis)
    b_ref = np.linalg.norm(bnodes, axis=1).max()
    idx = np.unique(
        np.r_[np.arange(0, len(points), max(1, len(points) // 1500)), np.flatnonzero(r < 1.0)]
    )
    h = FD_STEP_MM
    nb = np.concatenate([points[idx] + s * h * e for e in np.eye(3) for s in (1.0, -1.0)])
    mean6 = field_T(source, nb).reshape(6, -1, 3).mean(axis=0)
    mv = np.linalg.norm(bnodes[idx] - mean6, axis=1) / b_ref * 1e4
    add(
        f"mean-value property (harmonic B) at {len(idx)} nodes ({(r[idx] < 1.0).sum()} with"
        f" r < 1 mm), h = {h:g} mm:"
    )
    add(f"  max |B(p) - mean of B(p +- h e_j)| = {mv.max():.1e} units of 1e-4 B_ref")
    close = (r > 0) & (r < R_AXIS_SAFE_MM)
    if close.any():
        alt = field_T(source, points[close], r_safe_mm=2 * R_AXIS_SAFE_MM)
        d_alt = np.linalg.norm(bnodes[close] - alt, axis=1).max() / b_ref * 1e4
        add(
            f"  {close.sum()} nodes with r < {R_AXIS_SAFE_MM:g} mm use the on-axis ray fit"
            f" (magpylib unstable there); fit with 2x the radii differs by {d_alt:.1e} units"
        )

    # harmonics at z = 0 on r = radius: allowed n = 2 + k*M only
    nphi = 64
    phi = 2 * np.pi * np.arange(nphi) / nphi
    b = field_T(source, np.c_[radius * np.cos(phi), radius * np.sin(phi), np.zeros(nphi)])
    c = np.fft.fft(b[:, 1] + 1j * b[:, 0]) / nphi  # By + i Bx = sum C_n (z/R)^(n-1)
    main = abs(c[1])
    add(f"harmonics at z = 0, R_ref = {radius:g} mm (units of 1e-4 of B2 = {main:.5f} T):")
    orders = (1, 3, 4, 6, 10, 14, 18)
    add("  " + ", ".join(f"b{n}={abs(c[n - 1]) / main * 1e4:.2g}" for n in orders))
    add("  (16-fold symmetry allows only n = 2, 18, 34, ...)")

    # linear interpolation error of the mesh: at tet centroids (mean of the 4 node
    # values) against magpylib, every k-th tet, in units of 1e-4 of B_ref = max |B|
    sample = tets[:: max(1, len(tets) // 4000)]
    centroids = points[sample].mean(axis=1)
    err = np.linalg.norm(bnodes[sample].mean(axis=1) - field_T(source, centroids), axis=1)
    err_u = err / b_ref * 1e4
    az = np.abs(centroids[:, 2])
    add(
        f"linear interpolation error of the mesh at {len(sample)} tet centroids"
        f" (units of 1e-4 of B_ref = max|B| = {b_ref:.4f} T):"
    )
    add("  |z| range (mm)      n   median     p95     max")
    zones = (
        (0, z_end - 20),
        (z_end - 20, z_end - 10),
        (z_end - 10, z_end + 10),
        (z_end + 10, z_end + 30),
        (z_end + 30, z_half + 1e-9),
    )
    for lo, hi in zones:
        sel = (az >= lo) & (az < hi)
        if sel.any():
            q50, q95 = np.percentile(err_u[sel], [50, 95])
            add(
                f"  {lo:5.0f} - {min(hi, z_half):<5.0f}  {sel.sum():7d}  {q50:7.2f} {q95:7.2f}"
                f" {err_u[sel].max():7.2f}"
            )
    return lines


# ---------------------------------------------------------------------------------------
# Writers (tiny; the package's io.write_field is the general tool)
# ---------------------------------------------------------------------------------------
def _replace(tmp: Path, final: Path) -> None:
    os.replace(tmp, final)


def write_vtu(path: Path, points, tets, b) -> None:
    import meshio

    mesh = meshio.Mesh(points, [("tetra", tets)], point_data={"B": b})
    tmp = path.with_name(path.name + ".tmp")
    meshio.write(tmp, mesh, file_format="vtu", binary=True, compression="zlib")
    _replace(tmp, path)


def write_comsol(path: Path, points, b) -> None:
    """COMSOL 'Export > Data' text layout, mm and T, one row per mesh node."""
    header = [
        ("Model", "cfm_fem_default_quadrupole.mph (scripts/make_default_mesh.py, magpylib field)"),
        ("Version", "COMSOL 6.1.0.252"),
        ("Date", COMSOL_DATE),
        ("Dimension", "3"),
        ("Nodes", str(points.shape[0])),
        ("Expressions", "3"),
        ("Description", "Magnetic flux density"),
        ("Length unit", "mm"),
    ]
    cols = ["X", "Y", "Z", "mf.Bx (T)", "mf.By (T)", "mf.Bz (T)"]
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "w", encoding="ascii", newline="\n") as f:
        for key, val in header:
            f.write(f"% {key + ':':<20}{val}\n")
        f.write("% " + "".join(f"{c:<24}" for c in cols).rstrip() + "\n")
        np.savetxt(f, np.hstack([points, b]), fmt="%.10g", delimiter=" ")
    _replace(tmp, path)


def write_opera(path: Path, x_mm, y_mm, z_mm, b_grid) -> None:
    """Opera-3D .table, metres and tesla, x slowest and z fastest.

    ``b_grid`` has shape (nx, ny, nz, 3). Line 1 lists the point counts in the order of
    real Opera exports: fastest-varying coordinate first, i.e. ``nz ny nx 2`` (see the
    two real files described in meshes/README.md).
    """
    nx, ny, nz = len(x_mm), len(y_mm), len(z_mm)
    X, Y, Z = np.meshgrid(x_mm, y_mm, z_mm, indexing="ij")  # z fastest in C order
    rows = np.column_stack(
        [X.ravel() * 1e-3, Y.ravel() * 1e-3, Z.ravel() * 1e-3, b_grid.reshape(-1, 3)]
    )
    names = ["X [METRE]", "Y [METRE]", "Z [METRE]", "BX [TESLA]", "BY [TESLA]", "BZ [TESLA]"]
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "w", encoding="ascii", newline="\n") as f:
        f.write(f" {nz} {ny} {nx} 2\n")
        for i, name in enumerate(names, start=1):
            f.write(f" {i} {name}\n")
        f.write(" 0\n")
        np.savetxt(f, rows, fmt="% .12E", delimiter=" ")
    _replace(tmp, path)


def write_readme(path: Path, info: dict) -> None:
    """meshes/README.md from the run's numbers (so it is never stale)."""
    m = MAGNET
    nx, ny, nz = info["grid"]
    zh, rad, ew = info["z_half"], info["radius"], info["end_width"]
    half_l = m["length_mm"] / 2
    size = info["size"]
    text = [
        "# meshes/ — bundled default field map",
        "",
        "Everything here is generated by",
        "",
        f"    {info['command']}",
        "",
        "(deterministic: the same gmsh/magpylib/meshio versions give identical files; about",
        "1.5 min on two shared cores). Do not edit by hand: change `scripts/make_default_mesh.py`",
        "and regenerate. Lengths in mm and fields in T unless stated.",
        "",
        "| file | what | size |",
        "|---|---|---|",
        "| `quadrupole.vtu` | default map of the CLI: gmsh linear tetrahedra of the aperture,"
        " point data `B` (n, 3) float64 T, points (n, 3) mm, cells `tetra` (m, 4) int64;"
        f" VTU binary + zlib (meshio) | {size['quadrupole.vtu']} |",
        f"| `quadrupole_comsol.txt` | the same {info['n_nodes']} nodes and B, in the same order,"
        " as a COMSOL 6.1 text export (`% Length unit: mm`, columns"
        f" `X Y Z mf.Bx (T) mf.By (T) mf.Bz (T)`, `%.10g`) | {size['quadrupole_comsol.txt']} |",
        f"| `quadrupole_opera.table` | the same magnet on a regular {nx} x {ny} x {nz} grid"
        f" (x, y in [-{info['half_w']:g}, {info['half_w']:g}] mm, z in [-{zh:g}, {zh:g}] mm)"
        " as an Opera-3D `.table`, metres and tesla, z fastest, x slowest; computed directly"
        f" with magpylib, not interpolated | {size['quadrupole_opera.table']} |",
        "| `README.md` | this file | |",
        "",
        f"Total of the three maps: {info['total_size']}.",
        "",
        "## Magnet",
        "",
        f"{m['type']}, computed with magpylib {info['magpylib']} (`CylinderSegment`: analytic"
        " field of uniformly polarised sectors, mu_r = 1). Frame of the reference bench:",
        "z along the magnet axis, y vertical, x horizontal; the magnet is centred at the origin.",
        "",
        "| parameter | value |",
        "|---|---|",
        f"| segments M | {m['n_segments']} annular sectors of {360 / m['n_segments']:g} deg,"
        " sector k centred at theta_k = 2 pi k / M |",
        "| polarisation direction of sector k | (N + 1) theta_k + phase = 3 theta_k - 90 deg"
        " (normal quadrupole: By = G x, Bx = G y, G > 0) |",
        f"| remanence Br (= polarisation J) | {m['br_T']:g} T (NdFeB) |",
        f"| bore (inner) radius r_i | {m['r_inner_mm']:g} mm |",
        f"| outer radius r_o | {m['r_outer_mm']:g} mm |",
        f"| length L | {m['length_mm']:g} mm, z from -{half_l:g} to +{half_l:g} mm |",
        "| 2-D gradient 2 Br (1/r_i - 1/r_o) sin(3 pi/M) / (3 pi/M) |"
        f" {info['g2d'] * 1e3:.4f} T/m |",
        f"| central gradient of the {m['length_mm']:g} mm magnet (magpylib) |"
        f" {info['g0'] * 1e3:.4f} T/m (pole-tip field {info['g0'] * m['r_inner_mm']:.3f} T) |",
        "",
        "## Mesh",
        "",
        f"Cylinder r <= {rad:g} mm (bore radius {m['r_inner_mm']:g} mm), |z| <= {zh:g} mm"
        " = 1.5 L, so the 3-D fringe field at both ends is included; it decays to ~3e-5",
        f"of the central gradient at the ends of the region. gmsh {info['gmsh']} (OCC cylinder,"
        " Delaunay 3-D, single thread), element order 1 (4-node tetrahedra).",
        "",
        f"Element size h0(r) = {info['h_end']:g} mm x (1 + {info['radial_grading']:g}"
        f" (1 - r / {rad:g} mm)) within {ew:g} mm of the magnet end faces z = +-{half_l:g} mm,",
        "where the field changes fastest along z (finest at the outer radius, nearest the",
        f"magnet corners); it ramps linearly to {info['h_body']:g} mm over the next"
        f" {RAMP_IN * ew:g} mm towards the centre (field",
        f"close to linear in x, y there) and to {info['h_far']:g} mm over the next"
        f" {RAMP_OUT * ew:g} mm outwards (the fringe field is",
        "down to 1e-3 of the central one by |z| = 80 mm). Node coordinates are rounded to"
        f" 1e-{COORD_DECIMALS} mm so",
        "that the VTU and the COMSOL file hold identical nodes; nodes are numbered in (z, y, x)",
        "order and cells are sorted.",
        "",
        f"* nodes: {info['n_nodes']}",
        f"* tetrahedra: {info['n_cells']} (all positively oriented; min volume"
        f" {info['min_vol']:.3g} mm^3)",
        f"* total volume {info['vol']:.2f} mm^3 vs pi r^2 (2 z_half) = {info['vol_exact']:.2f}"
        f" mm^3 (faceting of the circle: {100 * (info['vol'] / info['vol_exact'] - 1):.3f} %)",
        "",
        "The linear interpolation error of the mesh is printed below (field at tet centroids",
        "interpolated from the nodes, against magpylib): a few 1e-4 of B_ref typically and up to",
        "~2e-3 next to the magnet ends. It is a property of this map to keep in mind when",
        "comparing it with positioning-induced field errors (U_p = 10 um at G = 71 T/m is ~1e-3",
        "of B_ref).",
        "",
        "magpylib caveat (handled in the script): its `CylinderSegment` formula is unstable",
        "within ~0.1 mm of the magnet axis (errors up to ~1e-2 T at r = 1e-3 mm, cf. magpylib",
        f"issue #606), so nodes with 0 < r < {R_AXIS_SAFE_MM:g} mm take B from a quadratic along",
        "their ray through the axis value and magpylib at r = 0.25 and 0.5 mm; and it returns",
        "NaN within ~1e-7 mm of the end-face planes, repaired by averaging z +- 1e-3 mm. The",
        "mean-value check below verifies the field at sampled nodes and all nodes near the axis.",
        "",
        "## Files in other layouts",
        "",
        "* COMSOL: header `% Model:`, `% Version: COMSOL 6.1.0.252`,"
        f" `% Date: {COMSOL_DATE}` (fixed for determinism),",
        f"  `% Dimension: 3`, `% Nodes: {info['n_nodes']}`, `% Expressions: 3`,"
        " `% Description: Magnetic flux density`,",
        "  `% Length unit: mm`, the column line, then one row per mesh node in VTU order.",
        f"* Opera: line 1 is `{nz} {ny} {nx} 2`, i.e. the point counts **fastest-varying"
        " coordinate first** (nz ny nx),",
        "  as in the real Opera exports we have seen:"
        " `../shared/data/cctpy/test_opera_field_table.table` has `41 11 21 2`",
        "  for a 21 x 11 x 41 (x, y, z) grid with z fastest, and the cctpy reader's docstring"
        " example `5 461 311 2` has 5 z values.",
        "  Then `1 X [METRE]` ... `6 BZ [TESLA]`, a line `0`, and"
        f" {info['n_grid']} rows `x y z Bx By Bz` (m, T), z fastest, x slowest.",
        "",
        "## Physics checks printed by the script",
        "",
        "```",
        info["checks"],
        "```",
        "",
    ]
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text("\n".join(text), encoding="utf-8")
    _replace(tmp, path)


def _human(nbytes: int) -> str:
    return f"{nbytes / 1e6:.2f} MB" if nbytes >= 1e5 else f"{nbytes / 1e3:.1f} kB"


# ---------------------------------------------------------------------------------------
def main(argv=None) -> int:
    repo = Path(__file__).resolve().parent.parent
    ap = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0],
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    add = ap.add_argument
    add("--out-dir", type=Path, default=repo / "meshes", help="output folder")
    add(
        "--radius",
        type=float,
        default=DEFAULT_RADIUS_MM,
        help="aperture cylinder radius, mm (must be < bore radius)",
    )
    add(
        "--z-half",
        type=float,
        default=DEFAULT_Z_HALF_MM,
        help="the mesh spans -z_half <= z <= z_half, mm",
    )
    add(
        "--h-end",
        type=float,
        default=DEFAULT_H_END_MM,
        help="element size at the magnet end faces at r = radius, mm",
    )
    add(
        "--radial-grading",
        type=float,
        default=DEFAULT_RADIAL_GRADING,
        help="end-zone size is h_end * (1 + g * (1 - r/radius)), g >= 0",
    )
    add(
        "--h-body",
        type=float,
        default=DEFAULT_H_BODY_MM,
        help="element size in the body of the magnet, mm",
    )
    add(
        "--h-far",
        type=float,
        default=DEFAULT_H_FAR_MM,
        help="element size far outside the magnet, mm",
    )
    add(
        "--end-width",
        type=float,
        default=DEFAULT_END_WIDTH_MM,
        help="half-width of the fine zone around each end face, mm",
    )
    add(
        "--grid",
        type=int,
        nargs=3,
        default=list(DEFAULT_GRID),
        metavar=("NX", "NY", "NZ"),
        help="Opera grid points",
    )
    add("--verbose", action="store_true", help="show gmsh output")
    args = ap.parse_args(argv)

    if not 0 < args.radius < MAGNET["r_inner_mm"]:
        ap.error(f"--radius must be in (0, {MAGNET['r_inner_mm']:g}) mm; found {args.radius:g}")
    if args.radial_grading < 0:
        ap.error("--radial-grading must be >= 0")
    if args.h_end <= 0 or args.h_body < args.h_end or args.h_far < args.h_end:
        ap.error("need 0 < --h-end <= --h-body and --h-end <= --h-far")
    if min(args.grid) < 2:
        ap.error("--grid counts must be >= 2")
    half_w = min(OPERA_HALF_WIDTH_MM, args.radius / math.sqrt(2.0))

    import gmsh
    import magpylib
    import meshio

    t0 = time.perf_counter()
    out = args.out_dir
    out.mkdir(parents=True, exist_ok=True)

    print(f"meshing the aperture with gmsh {gmsh.__version__} ...", flush=True)
    points, tets = mesh_aperture(
        args.radius,
        args.z_half,
        args.h_end,
        args.h_body,
        args.h_far,
        args.end_width,
        MAGNET["length_mm"],
        radial_grading=args.radial_grading,
        verbose=args.verbose,
    )
    vol = tet_volumes(points, tets)
    print(f"  {len(points)} nodes, {len(tets)} tetrahedra ({time.perf_counter() - t0:.1f} s)")

    source = build_magnet()
    print(f"field at the nodes with magpylib {magpylib.__version__} ...", flush=True)
    t1 = time.perf_counter()
    b_nodes = field_T(source, points)
    print(f"  done ({time.perf_counter() - t1:.1f} s)")

    nx, ny, nz = args.grid
    xg = np.linspace(-half_w, half_w, nx)
    yg = np.linspace(-half_w, half_w, ny)
    zg = np.linspace(-args.z_half, args.z_half, nz)
    X, Y, Z = np.meshgrid(xg, yg, zg, indexing="ij")
    print(f"field on the {nx}x{ny}x{nz} Opera grid ...", flush=True)
    b_grid = field_T(source, np.column_stack([X.ravel(), Y.ravel(), Z.ravel()]))
    b_grid = b_grid.reshape(nx, ny, nz, 3)

    if not (np.isfinite(b_nodes).all() and np.isfinite(b_grid).all()):
        print("error: non-finite field values", file=sys.stderr)
        return 1

    print("physics checks:")
    checks = physics_checks(source, args.radius, args.z_half, points, tets, b_nodes)
    print("\n".join(checks))

    print(f"writing files to {out} ...", flush=True)
    write_vtu(out / "quadrupole.vtu", points, tets, b_nodes)
    write_comsol(out / "quadrupole_comsol.txt", points, b_nodes)
    write_opera(out / "quadrupole_opera.table", xg, yg, zg, b_grid)

    names = ["quadrupole.vtu", "quadrupole_comsol.txt", "quadrupole_opera.table"]
    sizes = {n: (out / n).stat().st_size for n in names}
    argv = sys.argv[1:] if argv is None else list(argv)
    j0 = jacobian_fd(source, (0.0, 0.0, 0.0))
    info = {
        "command": " ".join(["python scripts/make_default_mesh.py", *argv]),
        "size": {n: _human(s) for n, s in sizes.items()},
        "total_size": _human(sum(sizes.values())),
        "n_nodes": len(points),
        "n_cells": len(tets),
        "grid": (nx, ny, nz),
        "n_grid": nx * ny * nz,
        "half_w": half_w,
        "z_half": args.z_half,
        "radius": args.radius,
        "h_end": args.h_end,
        "h_body": args.h_body,
        "radial_grading": args.radial_grading,
        "h_far": args.h_far,
        "end_width": args.end_width,
        "g2d": gradient_2d_analytic(),
        "g0": j0[1, 0],
        "magpylib": magpylib.__version__,
        "gmsh": gmsh.__version__,
        "min_vol": vol.min(),
        "vol": vol.sum(),
        "vol_exact": math.pi * args.radius**2 * 2 * args.z_half,
        "checks": "\n".join(checks),
    }
    write_readme(out / "README.md", info)
    for n in [*names, "README.md"]:
        print(f"  {n:<24} {_human((out / n).stat().st_size)}")
    print(f"meshio {meshio.__version__}; total {time.perf_counter() - t0:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
