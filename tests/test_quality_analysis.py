"""Field quality of a map (`cfm_fem.models.quality`, `run_quality` without Monte Carlo) against
references built apart from the code: analytic multipoles written with their Cartesian
components, moved and rolled by rotating vectors, and a magpylib Halbach quadrupole and
sextupole integrated on circles."""

from __future__ import annotations

import numpy as np
import pytest

from cfm_fem.errors import CfmInputError
from cfm_fem.models.field import FieldMap
from cfm_fem.models.quality import plan_from_nodes, plan_on_circles
from cfm_fem.workflows.quality import run_quality

R_REF = 5.0


def _grid(half=6.0, step=1.0, z=(-20.0, -10.0, 0.0, 10.0, 20.0)):
    g = np.arange(-half, half + 1e-9, step)
    x, y, zz = np.meshgrid(g, g, np.asarray(z, dtype=float), indexing="ij")
    return np.column_stack([x.ravel(), y.ravel(), zz.ravel()])


def _normal_multipole(x, y, order, strength):
    """B_x, B_y of a normal 2-D multipole of European order 1..4, Cartesian formulas:
    B_y = Re, B_x = Im of strength (x + i y)^(order-1) / R_REF^(order-1)."""
    u, v = x / R_REF, y / R_REF
    by, bx = {
        1: (np.ones_like(u), np.zeros_like(u)),
        2: (u, v),
        3: (u**2 - v**2, 2 * u * v),
        4: (u**3 - 3 * u * v**2, 3 * u**2 * v - v**3),
    }[order]
    return strength * bx, strength * by


def _moved_rolled(points, parts, dx, dy, theta):
    """Field of a magnet made of normal multipoles ``parts`` {order: T at R_REF}, rolled by
    theta about +z and moved by (dx, dy): B(p) = Rot(theta) B0(Rot(-theta) (p - d))."""
    c, s = np.cos(theta), np.sin(theta)
    px, py = points[:, 0] - dx, points[:, 1] - dy
    x0, y0 = c * px + s * py, -s * px + c * py
    bx0 = np.zeros(len(points))
    by0 = np.zeros(len(points))
    for order, strength in parts.items():
        bx, by = _normal_multipole(x0, y0, order, strength)
        bx0 += bx
        by0 += by
    return np.column_stack([c * bx0 - s * by0, s * bx0 + c * by0, np.zeros(len(points))])


def _quality(points, B, **kw):
    fm = FieldMap.from_arrays(points, B, source="analytic")
    return run_quality(fm, R_REF, uncertainty=False, **kw)


def test_pure_quadrupole_moved_and_rolled():
    pts = _grid()
    dx, dy, theta, g = 0.12, -0.07, 3e-3, 0.4
    res = _quality(pts, _moved_rolled(pts, {2: g}, dx, dy, theta))
    assert res.main_order == 2
    # feed-down and roll: F = g e^{-2 i theta} (w - d) / R_REF, so C_2 = g e^{-2 i theta} and
    # C_1 = -C_2 d / R_REF; integrated over the 40 mm of planes
    c2 = g * np.exp(-2j * theta)
    c1 = -c2 * (dx + 1j * dy) / R_REF
    integ = res.nominal.integrated
    assert abs(integ[1] / 40.0 - c2) <= 1e-6 * g
    assert abs(integ[0] / 40.0 - c1) <= 1e-6 * g
    assert np.all(np.abs(integ[2:] / 40.0) <= 1e-6 * g)
    assert res.nominal.centre_mm == pytest.approx([dx, dy], abs=1e-9)
    assert res.nominal.roll_mrad == pytest.approx(theta * 1e3, abs=1e-9)
    assert res.nominal.length_mm == pytest.approx(40.0, abs=1e-9)
    assert res.nominal.b_units[0] == pytest.approx(1e4 * (c1 / abs(c2)).real, abs=1e-6)


def test_mixed_multipole_harmonics_and_sextupole_centre():
    pts = _grid(z=np.linspace(-30, 30, 7))
    parts = {1: 0.002, 2: 0.5, 3: 0.004, 4: -0.001}
    res = _quality(pts, _moved_rolled(pts, parts, 0.0, 0.0, 0.0))
    c = res.nominal.integrated / 60.0
    for n, v in parts.items():
        assert abs(c[n - 1] - v) <= 1e-6 * 0.5
    assert np.all(np.abs(c[4:]) <= 1e-6 * 0.5)
    assert res.nominal.b_units[2] == pytest.approx(1e4 * 0.004 / 0.5, abs=1e-6)
    # a sextupole moved by d: its centre is the point about which the quadrupole term vanishes
    dx, dy = -0.3, 0.21
    res = _quality(pts, _moved_rolled(pts, {3: 0.2}, dx, dy, 0.0))
    assert res.main_order == 3
    assert res.nominal.centre_mm == pytest.approx([dx, dy], abs=1e-9)
    theta = -4e-3
    res = _quality(pts, _moved_rolled(pts, {3: 0.2}, 0.0, 0.0, theta))
    assert res.nominal.roll_mrad == pytest.approx(theta * 1e3, abs=1e-9)


def test_circle_plan_matches_node_plan_on_a_2d_field():
    pts = _grid(z=np.linspace(-10, 10, 11))
    parts = {2: 0.3, 3: 0.003}
    B = _moved_rolled(pts, parts, 0.05, 0.02, 1e-3)
    nodes = _quality(pts, B, sampling="nodes")
    circles = _quality(pts, B, sampling="circles", dz_mm=1.0, radius_mm=4.0)
    assert circles.plan.sampling == "circles" and nodes.plan.sampling == "nodes"
    np.testing.assert_allclose(
        circles.nominal.integrated[:6], nodes.nominal.integrated[:6], atol=1e-6 * 0.3 * 20
    )


@pytest.mark.parametrize("sampling", ["nodes", "circles"])
def test_uniform_dipole_has_no_other_harmonic(sampling):
    """A uniform field (a pure dipole, rolled by 2 mrad): no other harmonic beyond 1e-6 of it,
    in the integral and in every plane, whether the map's nodes are fitted or circles are read
    from the local harmonic model between them."""
    pts = _grid(z=np.linspace(-20, 20, 21))
    theta = 2e-3
    res = _quality(pts, _moved_rolled(pts, {1: 0.8}, 0.0, 0.0, theta), sampling=sampling,
                   dz_mm=1.5)  # fmt: skip
    assert res.main_order == 1 and res.plan.sampling == sampling
    c = res.nominal.integrated / (res.plan.z[-1] - res.plan.z[0])
    print(f"{sampling}: other harmonics up to {np.nanmax(np.abs(c[1:])) / 0.8:.2g} of the dipole "
          f"integrated, {np.nanmax(np.abs(res.planes[:, 1:])) / 0.8:.2g} in a plane")  # fmt: skip
    assert abs(c[0] - 0.8 * np.exp(-1j * theta)) <= 1e-6 * 0.8
    fitted = slice(1, res.plan.n_orders)
    assert np.all(np.abs(c[fitted]) <= 1e-6 * 0.8)
    assert np.all(np.abs(res.planes[:, fitted]) <= 1e-6 * 0.8)
    assert res.nominal.roll_mrad == pytest.approx(theta * 1e3, abs=1e-6)
    assert res.nominal.length_mm == pytest.approx(res.plan.z[-1] - res.plan.z[0], rel=1e-9)


def test_plans_refuse_what_they_cannot_fit():
    rng = np.random.default_rng(1)
    cloud = rng.uniform(-5, 5, (400, 3))
    with pytest.raises(CfmInputError, match="z planes"):
        plan_from_nodes(cloud, R_REF)
    off_axis = _grid() + np.array([20.0, 0.0, 0.0])
    with pytest.raises(CfmInputError, match="x = y = 0"):
        plan_from_nodes(off_axis, R_REF)
    with pytest.raises(CfmInputError, match="increasing"):
        plan_on_circles([0.0], 3.0, R_REF)
    # 8 points on a circle fix orders 1..3 only; the others are NaN
    plan = plan_on_circles([0.0, 1.0], 3.0, R_REF, n_angles=8)
    assert plan.n_orders == 3


# --------------------------------------------------------------------------- magpylib

magpy = pytest.importorskip("magpylib")

#: Halbach ring of square blocks: block k at angle theta_k, polarised at (order + 1) theta_k
#: + phase in the magnet frame (16-fold symmetry: allowed harmonics order + 16 j only).
RING = {"blocks": 16, "r_centre": 12.5, "side": 5.0, "length": 41.0, "br": 1.2}


def _halbach(order, dx=0.0, dy=0.0, roll=0.0, phase=-np.pi / 2):
    m = RING["blocks"]
    coll = magpy.Collection()
    for k in range(m):
        th = 2 * np.pi * k / m
        local = (order + 1) * th + phase - th  # polarisation is given in the block's frame
        block = magpy.magnet.Cuboid(
            polarization=(RING["br"] * np.cos(local), RING["br"] * np.sin(local), 0.0),
            dimension=(RING["side"] * 1e-3, RING["side"] * 1e-3, RING["length"] * 1e-3),
            position=(RING["r_centre"] * 1e-3 * np.cos(th), RING["r_centre"] * 1e-3 * np.sin(th),
                      0.0),
        )  # fmt: skip
        block.rotate_from_angax(np.degrees(th), "z", anchor=None)
        coll.add(block)
    coll.rotate_from_angax(np.degrees(roll), "z", anchor=0)
    coll.move((dx * 1e-3, dy * 1e-3, 0.0))
    return coll


def _field(coll, pts_mm):
    return np.asarray(coll.getB(np.asarray(pts_mm) * 1e-3), dtype=float).reshape(-1, 3)


def _reference(coll, z_half=90.0, dz=0.4, n_theta=64):
    """Integrated C_n at R_REF (T mm), n = 1..16, and the magnetic length (main order from the
    largest), from the field on circles r = R_REF, trapezoid over z, then Fourier."""
    z = np.arange(-z_half, z_half + 1e-9, dz)
    th = 2 * np.pi * np.arange(n_theta) / n_theta
    p = np.stack(np.broadcast_arrays(R_REF * np.cos(th)[None], R_REF * np.sin(th)[None],
                                     z[:, None]), -1).reshape(-1, 3)  # fmt: skip
    b = _field(coll, p).reshape(z.size, n_theta, 3)
    f = b[..., 1] + 1j * b[..., 0]  # (z, theta)
    c_planes = np.fft.fft(f, axis=1)[:, :16] / n_theta  # C_n = mean F e^{-i (n-1) theta}
    w = np.full(z.size, dz)
    w[[0, -1]] = dz / 2
    integ = w @ c_planes
    main = int(np.argmax(np.abs(integ)))
    centre_plane = c_planes[np.argmin(np.abs(z)), main]
    phase = np.exp(-1j * np.angle(integ[main]))
    return integ, abs(integ[main]) / (centre_plane * phase).real


def _ring_nodes():
    """Nodes of the Halbach rings' maps (mm): a 12 x 12 grid of 1 mm over |z| <= 90 mm."""
    g = np.arange(-5.5, 5.51, 1.0)
    x, y, z = np.meshgrid(g, g, np.arange(-90.0, 90.01, 2.0), indexing="ij")
    return np.column_stack([x.ravel(), y.ravel(), z.ravel()])


def _assert_harmonics(res, ref, order):
    """The map's integrated b_n, a_n within 0.05 units of the circles' (main ``order``)."""
    units = 1e4 * ref[:15] / abs(ref[order - 1])
    np.testing.assert_allclose(res.nominal.b_units, units.real, atol=0.05)
    np.testing.assert_allclose(res.nominal.a_units, units.imag, atol=0.05)


@pytest.fixture(scope="module")
def quad_map(tmp_path_factory):
    from cfm_fem.io import read_field, write_field

    dx, dy, roll = 0.05, -0.03, 2e-3
    coll = _halbach(2, dx, dy, roll)
    pts = _ring_nodes()
    path = tmp_path_factory.mktemp("quality") / "halbach_quad.csv"
    write_field(path, FieldMap.from_arrays(pts, _field(coll, pts)))
    return read_field(path), coll, (dx, dy, roll)


def test_magpylib_quadrupole_moved_and_rolled(quad_map):
    fm, coll, (dx, dy, roll) = quad_map
    res = run_quality(fm, R_REF, uncertainty=False)
    ref, ref_length = _reference(coll)
    assert res.main_order == 2
    _assert_harmonics(res, ref, 2)
    assert res.nominal.centre_mm == pytest.approx([dx, dy], abs=1e-3)
    assert res.nominal.roll_mrad == pytest.approx(roll * 1e3, abs=0.01)
    assert res.nominal.length_mm == pytest.approx(ref_length, abs=0.02)


def test_magpylib_sextupole_centre():
    dx, dy = -0.04, 0.06
    coll = _halbach(3, dx, dy)
    pts = _ring_nodes()
    res = _quality(pts, _field(coll, pts))
    ref, ref_length = _reference(coll)
    assert res.main_order == 3
    _assert_harmonics(res, ref, 3)
    assert res.nominal.centre_mm == pytest.approx([dx, dy], abs=1e-3)
    assert res.nominal.length_mm == pytest.approx(ref_length, abs=0.02)


def test_magpylib_dipole_with_ends_rolled():
    """A Halbach dipole with ends rolled by 1.5 mrad: harmonics, roll and magnetic length against
    the field integrated on circles (a dipole's centre has no meaning: no feed-down locates it).
    Its short ends put a pseudo-multipole r^2 d^2B/dz^2 into the centre plane: the dipole there
    is 0.5 % weaker on the circle r = R_ref than on the axis, so the length on the circle (the
    definition) differs by 0.2 mm from the on-axis one, ten times the limit."""
    roll = 1.5e-3
    coll = _halbach(1, roll=roll)
    pts = _ring_nodes()
    res = _quality(pts, _field(coll, pts))
    ref, ref_length = _reference(coll)
    on_axis = abs(ref[0]) / np.hypot(*_field(coll, np.zeros((1, 3)))[0, :2])
    print(f"magnetic length {res.nominal.length_mm:.4f} mm, on the circle r = R_ref "
          f"{ref_length:.4f} mm, on the axis {on_axis:.4f} mm")  # fmt: skip
    assert res.main_order == 1
    _assert_harmonics(res, ref, 1)
    assert res.nominal.roll_mrad == pytest.approx(roll * 1e3, abs=0.01)
    assert on_axis - ref_length > 0.1  # the case tells the definitions apart
    assert res.nominal.length_mm == pytest.approx(ref_length, abs=0.02)
