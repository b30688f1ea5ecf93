"""The soft-end model's pieces against closed forms: the layers of the 3-D potential, the
profile's derivatives, how many layers a plane's points separate, the Fermi summary."""

from __future__ import annotations

import math

import numpy as np

from cfm_fem.workflows.diagnose import fringe

G, H = 0.055, 3e-5  # T/mm, T/mm^2: a quadrupole and a sextupole


def _field_2d(q):
    """grad V of V = G x y + H (x^3 - 3 x y^2) / 3 (harmonic)."""
    x, y = q[:, 0], q[:, 1]
    return np.stack([G * y + H * (x * x - y * y), G * x - 2 * H * x * y, 0 * x], -1)


def _layer_exact(p, k):
    """U_k of a harmonic V_n of degree n: r^2k V_n n! / (4^k k! (n + k)!)."""
    x, y = p[:, 0], p[:, 1]
    r2k = (x * x + y * y) ** k
    c = 1.0 / (4**k * math.factorial(k))
    quad = G * x * y * 2 / math.factorial(2 + k)
    sext = H * (x**3 - 3 * x * y * y) / 3 * 6 / math.factorial(3 + k)
    return c * r2k * (quad + sext)


def test_potential_layers_are_the_closed_form_of_solid_harmonics():
    p = np.random.default_rng(1).uniform(-5, 5, (40, 3))
    layers = fringe.potential_layers(_field_2d, p, layers=4)
    for k in range(1, 5):
        exact = _layer_exact(p, k)
        assert np.abs(layers[k - 1, :, 0] - exact).max() < 1e-12 * np.abs(exact).max()
        for a in range(2):  # the gradients, against differences of the closed form
            e = np.zeros(3)
            e[a] = 1e-4
            fd = (_layer_exact(p + e, k) - _layer_exact(p - e, k)) / 2e-4
            assert np.abs(layers[k - 1, :, 1 + a] - fd).max() < 1e-7 * np.abs(fd).max()


def test_each_layer_is_the_transverse_laplacian_of_the_next():
    p = np.random.default_rng(2).uniform(-4, 4, (30, 3))
    h = 2e-3
    for k in range(1, 4):
        lap = -4.0 * _layer_exact(p, k + 1)
        for a in range(2):
            e = np.zeros(3)
            e[a] = h
            lap += _layer_exact(p + e, k + 1) + _layer_exact(p - e, k + 1)
        lap /= h * h
        target = fringe.potential_layers(_field_2d, p, layers=k)[k - 1, :, 0]
        assert np.abs(lap - target).max() < 1e-5 * np.abs(target).max()


def test_layer_hessians_match_the_closed_form():
    p = np.random.default_rng(3).uniform(-4, 4, (20, 3))
    hess = fringe._layer_hessians(_field_2d, p)
    h = 1e-3
    for k in range(1, 5):
        for a in range(2):
            for b in range(2):
                ea, eb = np.zeros(3), np.zeros(3)
                ea[a], eb[b] = h, h
                fd = (
                    _layer_exact(p + ea + eb, k)
                    - _layer_exact(p + ea - eb, k)
                    - _layer_exact(p - ea + eb, k)
                    + _layer_exact(p - ea - eb, k)
                ) / (4 * h * h)
                scale = np.abs(fd).max() + 1e-30
                assert np.abs(hess[k - 1, :, a, b] - fd).max() < 1e-5 * scale


def test_profile_derivatives_match_differences_and_the_leading_orders():
    z = np.linspace(-140.0, 140.0, 57)
    d = fringe.fringe_derivatives(z, -125.0, 124.0, 3.7, 6)
    lead = fringe._fringe_derivatives(z, -125.0, 124.0, 3.7)
    for m in range(4):
        assert np.allclose(d[m], lead[m], rtol=1e-12, atol=1e-15)
    h = 1e-3
    up = fringe.fringe_derivatives(z + h, -125.0, 124.0, 3.7, 6)
    down = fringe.fringe_derivatives(z - h, -125.0, 124.0, 3.7, 6)
    for m in range(6):
        fd = (up[m] - down[m]) / (2 * h)
        assert np.abs(fd - d[m + 1]).max() < 1e-6 * np.abs(d[m + 1]).max()


def _plane(n_side):
    xs = np.linspace(-4, 4, n_side)
    x, y = (a.ravel() for a in np.meshgrid(xs, xs, indexing="ij"))
    return np.stack([x, y, np.full_like(x, 132.0)], -1)


def _quadrupole(q):
    return np.stack([G * q[:, 1], G * q[:, 0], 0 * q[:, 0]], -1)


def test_a_six_by_six_plane_separates_four_layers_and_three_by_three_one():
    # a pure quadrupole read on a 3 x 3 grid: V = G x y vanishes on the axes, so B_z sees one
    # radius and only the first layer separates; 6 x 6 points have six radii
    for n_side, want in ((6, 4), (3, 1)):
        p = _plane(n_side)
        U = fringe.potential_layers(_quadrupole, p)
        V = G * p[:, 0] * p[:, 1]
        cols = fringe._plane_columns(_quadrupole(p), V, U, np.arange(len(p)), 4)
        assert fringe._plane_layers(cols) == want


def test_fermi_summary_recovers_a_fermi_profile_from_its_plane_values():
    th = (-124.8, 125.3, 3.9)
    z = np.array([-180.0, -156, -132, -108, -84, 84, 108, 132, 156, 180])
    d = fringe.fringe_derivatives(z, *th, 2)
    obs, values, std = [], [], []
    for j, zj in enumerate(z):
        for m in range(3):
            obs.append((zj, m, len(values)))
            values.append(d[m, j])
            std.append(1e-5 * 10.0 ** (-m))
    cov = np.diag(np.square(std))
    got = fringe._fermi_summary(obs, np.array(values), cov, (-126.0, 126.0, 4.5))
    for name, true in zip(("z_entry", "z_exit", "lambda"), th, strict=True):
        value, sd, unit = got[name]
        assert unit == "mm" and abs(value - true) < 1e-6 and sd < 1e-2


def test_truncation_bias_is_what_a_short_fit_of_the_full_series_gets_wrong():
    # a plane of 3 x 3 points next to an edge: the field of four layers with the Fermi
    # profile's derivatives, fitted with the first layer only (and the B_z constant)
    th, a, z = (-125.0, 125.0, 3.7), 1.0, 126.0
    p = _plane(3)
    p[:, 2] = z
    U = fringe.potential_layers(_quadrupole, p)
    V = G * p[:, 0] * p[:, 1]
    cols = fringe._plane_columns(_quadrupole(p), V, U, np.arange(len(p)), 4)
    d = fringe.fringe_derivatives(np.array([z]), *th, 7)[:, 0]
    field = cols.reshape(-1, 8) @ d
    fitted = np.concatenate([cols[..., :2], np.zeros((len(p), 3, 1))], axis=-1)
    fitted[:, 2, 2] = 1.0
    short = np.linalg.lstsq(fitted.reshape(-1, 3), field, rcond=None)[0]
    bias = fringe._truncation_bias(fitted, cols[..., 2:], z, th, a)
    assert np.allclose(short[:2] - d[:2], bias[:2], rtol=1e-9, atol=1e-15)
    assert abs(bias[1]) > 1e-3 * abs(d[1])  # the short fit is visibly off at the edge
