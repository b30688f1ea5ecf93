"""2-D multipole model: analytic fields, Maxwell, feed-down, roll (cfm_fem.models.multipole)."""

from __future__ import annotations

import numpy as np
import pytest

from cfm_fem.errors import CfmInputError
from cfm_fem.models.multipole import Multipole, feed_down, multipole_field, multipole_gradient, roll

R_REF = 10.0  # mm


def _random_multipole(rng, n=12, r_ref=R_REF) -> Multipole:
    """A quadrupole-dominated expansion with random harmonics of a few hundred units."""
    b = rng.normal(0.0, 0.03, n) * 0.07
    a = rng.normal(0.0, 0.03, n) * 0.07
    b[1] = 0.07
    return Multipole(b, a, r_ref, main=2)


def _disc_points(rng, n, radius):
    r = radius * np.sqrt(rng.uniform(0, 1, n))
    t = rng.uniform(0, 2 * np.pi, n)
    return np.column_stack([r * np.cos(t), r * np.sin(t), rng.uniform(-50, 50, n)])


def _rotate_xy(v, angle):
    c, s = np.cos(angle), np.sin(angle)
    out = v.copy()
    out[..., 0] = c * v[..., 0] - s * v[..., 1]
    out[..., 1] = s * v[..., 0] + c * v[..., 1]
    return out


def test_pure_quadrupole_field_and_gradient():
    b2 = 0.0696  # T at R_ref
    g = b2 / R_REF  # T/mm
    m = Multipole([0.0, b2], [0.0, 0.0], R_REF)
    pts = np.array([[1.0, 2.0, 0.0], [-3.0, 0.5, 7.0], [0.0, 0.0, 0.0]])
    B = m.field(pts)
    # B_y + i B_x = B2 (x + i y)/R  ->  B_y = G x, B_x = G y, B_z = 0
    np.testing.assert_allclose(B[:, 0], g * pts[:, 1], rtol=0, atol=1e-16)
    np.testing.assert_allclose(B[:, 1], g * pts[:, 0], rtol=0, atol=1e-16)
    assert np.all(B[:, 2] == 0)
    J = m.gradient(pts)
    expected = np.zeros((3, 3))
    expected[0, 1] = expected[1, 0] = g
    np.testing.assert_allclose(J, np.broadcast_to(expected, J.shape), rtol=0, atol=1e-18)


def test_dipole_is_uniform_and_skew_dipole_is_horizontal():
    m = Multipole([0.5], [0.2], R_REF)
    B = m.field(np.array([[3.0, -4.0, 1.0], [0.0, 0.0, 0.0]]))
    np.testing.assert_allclose(B, [[0.2, 0.5, 0.0]] * 2)
    assert np.all(m.gradient([[1.0, 1.0, 1.0]]) == 0)


def test_gradient_matches_finite_differences_and_is_div_curl_free():
    rng = np.random.default_rng(1)
    m = _random_multipole(rng)
    pts = _disc_points(rng, 50, 0.9 * R_REF)
    h = 1e-4  # mm
    J_fd = np.empty((pts.shape[0], 3, 3))
    for j in range(3):
        e = np.zeros(3)
        e[j] = h
        J_fd[:, :, j] = (m.field(pts + e) - m.field(pts - e)) / (2 * h)
    J = m.gradient(pts)
    scale = np.abs(J).max()
    np.testing.assert_allclose(J_fd, J, rtol=0, atol=1e-7 * scale)
    # div B = 0 and curl B = 0 from the finite differences alone
    div = J_fd[:, 0, 0] + J_fd[:, 1, 1] + J_fd[:, 2, 2]
    curl = np.stack(
        [
            J_fd[:, 2, 1] - J_fd[:, 1, 2],
            J_fd[:, 0, 2] - J_fd[:, 2, 0],
            J_fd[:, 1, 0] - J_fd[:, 0, 1],
        ]
    )
    assert np.abs(div).max() < 1e-7 * scale
    assert np.abs(curl).max() < 1e-7 * scale
    # and exactly in the analytic matrix
    np.testing.assert_allclose(np.trace(J, axis1=1, axis2=2), 0, atol=1e-18)
    np.testing.assert_allclose(J, np.swapaxes(J, 1, 2), rtol=0, atol=0)


def test_feed_down_of_offset_quadrupole_gives_dipole():
    b2, dx, dy = 0.0696, 0.3, -0.2
    b, a = feed_down([0.0, b2], [0.0, 0.0], R_REF, dx, dy)
    # C1' = C2 (dx + i dy)/R: B1 = B2 dx/R, A1 = B2 dy/R; the quadrupole itself is unchanged
    np.testing.assert_allclose(b, [b2 * dx / R_REF, b2], rtol=1e-15)
    np.testing.assert_allclose(a, [b2 * dy / R_REF, 0.0], rtol=0, atol=1e-18)
    # a magnet moved by +dx shows the opposite dipole about the old centre
    moved = Multipole([0.0, b2], [0.0, 0.0], R_REF).moved(dx, dy)
    np.testing.assert_allclose(moved.normal[0], -b2 * dx / R_REF, rtol=1e-15)
    np.testing.assert_allclose(moved.skew[0], -b2 * dy / R_REF, rtol=1e-15)


def test_feed_down_of_sextupole_gives_quadrupole_and_dipole():
    b3, dx = 1e-3, 0.5
    b, a = feed_down([0.0, 0.0, b3], [0.0, 0.0, 0.0], R_REF, dx, 0.0)
    # (w + d)^2 = w^2 + 2 d w + d^2 with d = dx/R
    d = dx / R_REF
    np.testing.assert_allclose(b, [b3 * d**2, 2 * b3 * d, b3], rtol=1e-14)
    np.testing.assert_allclose(a, 0, atol=1e-20)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_shifted_expansion_equals_original_field_at_shifted_points(seed):
    rng = np.random.default_rng(seed)
    m = _random_multipole(rng, n=15)
    dx, dy = rng.uniform(-2, 2, 2)  # mm, up to 0.2 R_ref
    pts = _disc_points(rng, 200, 0.8 * R_REF)
    shift = np.array([dx, dy, 0.0])
    scale = np.abs(m.field(pts + shift)).max()
    np.testing.assert_allclose(
        m.about(dx, dy).field(pts), m.field(pts + shift), rtol=0, atol=1e-12 * scale
    )
    np.testing.assert_allclose(
        m.moved(dx, dy).field(pts), m.field(pts - shift), rtol=0, atol=1e-12 * scale
    )
    # going there and back returns the coefficients
    back = m.about(dx, dy).about(-dx, -dy)
    np.testing.assert_allclose(back.coefficients, m.coefficients, rtol=0, atol=1e-14 * m.b_ref)


@pytest.mark.parametrize("n", [1, 2, 3, 4, 6])
def test_roll_by_pi_over_2n_turns_normal_into_skew(n):
    normal = np.zeros(n)
    normal[n - 1] = 0.05
    b, a = roll(normal, np.zeros(n), np.pi / (2 * n))
    # counter-clockwise by pi/(2n): C_n -> C_n exp(-i pi/2) = -i B_n, i.e. A_n = -B_n
    assert abs(b[n - 1]) < 1e-17
    np.testing.assert_allclose(a[n - 1], -0.05, rtol=1e-15)
    b, a = roll(normal, np.zeros(n), -np.pi / (2 * n))
    np.testing.assert_allclose(a[n - 1], +0.05, rtol=1e-15)


def test_rolled_field_is_the_rotated_field():
    rng = np.random.default_rng(5)
    m = _random_multipole(rng)
    angle = 0.37
    pts = _disc_points(rng, 100, R_REF)
    # B_new(r) = Rot(angle) B_old(Rot(-angle) r)
    expected = _rotate_xy(m.field(_rotate_xy(pts, -angle)), angle)
    np.testing.assert_allclose(m.rolled(angle).field(pts), expected, rtol=0, atol=1e-14)
    assert m.rolled(angle).b_ref == pytest.approx(m.b_ref, rel=1e-14)


def test_skew_quadrupole_from_roll_matches_hand_check():
    # normal quadrupole turned by +45 deg: at (1, 1)/sqrt(2) the old field (0, G) at (1, 0) turns
    # into G (-1, 1)/sqrt(2)
    g = 0.07 / R_REF
    m = Multipole([0.0, 0.07], [0.0, 0.0], R_REF).rolled(np.pi / 4)
    s = 1 / np.sqrt(2)
    np.testing.assert_allclose(m.field([[s, s, 0.0]])[0], [-g * s, g * s, 0.0], atol=1e-16)


def test_from_units_matches_tesla_coefficients():
    main_T = 0.0696
    bu = [0.5, 1e4, 2.85e-1, -5.55]
    au = [0.1, 0.0, 1.25, 0.561]
    m = Multipole.from_units(2, main_T, bu, au, R_REF)
    np.testing.assert_allclose(
        m.normal, [0.5e-4 * main_T, main_T, 2.85e-5 * main_T, -5.55e-4 * main_T]
    )
    np.testing.assert_allclose(m.skew, [0.1e-4 * main_T, 0.0, 1.25e-4 * main_T, 0.561e-4 * main_T])
    assert m.main == 2 and m.b_ref == pytest.approx(main_T)
    bu_back, au_back = m.in_units()
    np.testing.assert_allclose(bu_back, bu, rtol=1e-12)
    np.testing.assert_allclose(au_back, au, rtol=1e-12, atol=1e-12)
    # 0 in the main slot means "given by main_T"
    m0 = Multipole.from_units(2, main_T, [0.5, 0.0], [0.1, 0.0], R_REF)
    assert m0.normal[1] == main_T
    with pytest.raises(CfmInputError, match="10000 units"):
        Multipole.from_units(2, main_T, [0.5, 1.0], [0.1, 0.0], R_REF)


def test_shapes_and_batch_equals_single():
    rng = np.random.default_rng(3)
    m = _random_multipole(rng)
    pts = _disc_points(rng, 12, R_REF)
    batch = m.field(pts)
    single = np.array([m.field(p) for p in pts])
    # equal up to rounding (numpy may vectorise the complex products differently)
    np.testing.assert_allclose(batch, single, rtol=1e-15, atol=1e-18)
    assert m.field(pts[:, :2]).shape == (12, 3)
    np.testing.assert_array_equal(m.field(pts[:, :2]), batch)  # z is ignored
    grid = pts.reshape(3, 4, 3)
    assert m.field(grid).shape == (3, 4, 3)
    assert m.gradient(grid).shape == (3, 4, 3, 3)
    np.testing.assert_array_equal(
        multipole_gradient(pts, m.normal, m.skew, m.r_ref), m.gradient(pts)
    )
    with pytest.raises(CfmInputError, match="shape"):
        multipole_field(np.zeros((4, 4)), m.normal, m.skew, R_REF)


def test_rescaled_keeps_the_field():
    rng = np.random.default_rng(4)
    m = _random_multipole(rng)
    pts = _disc_points(rng, 30, R_REF)
    m2 = m.rescaled(17.0)
    assert m2.r_ref == 17.0
    np.testing.assert_allclose(m2.field(pts), m.field(pts), rtol=1e-13, atol=1e-16)


def test_invalid_multipoles_are_rejected():
    with pytest.raises(CfmInputError, match="r_ref"):
        Multipole([0.0, 1.0], [0.0, 0.0], 0.0)
    with pytest.raises(CfmInputError, match="same"):
        Multipole([0.0, 1.0], [0.0], 10.0)
    with pytest.raises(CfmInputError, match="main"):
        Multipole([0.0, 1.0], [0.0, 0.0], 10.0, main=3)
    assert Multipole([1e-6, 1.0, 0.01], [0.0, 0.0, 0.02], 10.0).main == 2  # default: largest
