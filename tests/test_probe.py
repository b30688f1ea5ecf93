"""Hall probe model (Table I): S_HP statistics, exactness when off, non-orthogonality mixing."""

from __future__ import annotations

import numpy as np
import pytest

from cfm_fem.errors import CfmInputError
from cfm_fem.models.probe import HallProbe, ProbeDraws, apply_probe, sample_s_hp, sensing_directions

N = 200_000  # samples for statistical checks
Z = 5.0  # tolerance in standard errors (a false failure ~ 1 in 1.7 million)


def _std_tolerance(sigma, n=N):
    """Standard error of a sample std for a uniform PDF: sigma sqrt((kurtosis - 1)/(4 n)),
    kurtosis 1.8."""
    return sigma * np.sqrt(0.8 / (4 * n))


def test_s_hp_has_mean_one_and_the_stated_std():
    rng = np.random.default_rng(2024)
    s = sample_s_hp(rng, N, std=1.5e-3)
    assert s.shape == (N,)
    assert abs(s.mean() - 1.0) < Z * 1.5e-3 / np.sqrt(N)
    assert abs(s.std(ddof=1) - 1.5e-3) < Z * _std_tolerance(1.5e-3)
    half = np.sqrt(3) * 1.5e-3  # uniform: bounded at +- sqrt(3) std
    assert s.min() >= 1 - half and s.max() <= 1 + half
    assert s.min() < 1 - 0.99 * half and s.max() > 1 + 0.99 * half


def test_paper_model_scales_all_components_by_one_factor():
    probe = HallProbe()  # the paper's S_HP is the default
    assert probe.model == "paper" and probe.instrumental_std == 1.5e-3
    rng = np.random.default_rng(7)
    B = rng.normal(0, 0.05, (N, 3))
    meas = probe.measure(B, rng)
    ratio = meas / B
    np.testing.assert_allclose(ratio[:, 1], ratio[:, 0], rtol=1e-12)
    np.testing.assert_allclose(ratio[:, 2], ratio[:, 0], rtol=1e-12)
    assert abs(ratio[:, 0].std(ddof=1) - 1.5e-3) < Z * _std_tolerance(1.5e-3)


@pytest.mark.parametrize("model", ["paper", "table1"])
def test_probe_with_all_errors_off_is_exact(model):
    probe = HallProbe.exact(model)
    B = np.random.default_rng(1).normal(0, 1, (100, 3))
    np.testing.assert_array_equal(probe.measure(B, 3), B)
    np.testing.assert_array_equal(probe.measure(B, draws=probe.sample(np.random.default_rng(0))), B)


def test_sensing_directions_mix_components_as_documented():
    g = 0.035
    n = sensing_directions(g, 0.0, 0.0)
    # y element tilted towards x by g: a field along x leaks sin(g) into the y channel
    np.testing.assert_allclose(n @ [1.0, 0.0, 0.0], [1.0, np.sin(g), 0.0])
    np.testing.assert_allclose(n @ [0.0, 1.0, 0.0], [0.0, np.cos(g), 0.0])
    np.testing.assert_allclose(n @ [0.0, 0.0, 1.0], [0.0, 0.0, 1.0])
    n = sensing_directions(0.0, 0.02, -0.03)
    np.testing.assert_allclose(n @ [1.0, 0.0, 0.0], [1.0, 0.0, np.sin(0.02)])
    np.testing.assert_allclose(n @ [0.0, 1.0, 0.0], [0.0, 1.0, np.sin(-0.03)])
    # unit rows; x-y and x-z angles are 90 deg minus the tilt
    n = sensing_directions(0.01, 0.02, 0.03)
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, rtol=1e-15)
    np.testing.assert_allclose(np.arccos(n[0] @ n[1]), np.pi / 2 - 0.01, rtol=1e-12)
    np.testing.assert_allclose(np.arccos(n[0] @ n[2]), np.pi / 2 - 0.02, rtol=1e-12)
    np.testing.assert_allclose(np.arccos(n[1] @ n[2]), np.pi / 2 - 0.03, atol=1e-3)
    np.testing.assert_array_equal(sensing_directions(0, 0, 0), np.eye(3))
    assert sensing_directions(np.zeros(4), 0.0, np.zeros((2, 1))).shape == (2, 4, 3, 3)


def test_table1_orthogonality_alone_is_uniform_within_35_mrad():
    probe = HallProbe("table1", 0.0, 0.0, 0.0, 0.0, 35e-3)
    meas = probe.measure(np.tile([1.0, 0.0, 0.0], (N, 1)), np.random.default_rng(11))
    assert np.all(meas[:, 0] == 1.0)  # the x element defines the frame
    g_xy = np.arcsin(meas[:, 1])
    g_xz = np.arcsin(meas[:, 2])
    for g in (g_xy, g_xz):
        assert np.abs(g).max() <= 35e-3
        assert abs(g.std(ddof=1) - 35e-3 / np.sqrt(3)) < Z * _std_tolerance(35e-3 / np.sqrt(3))
    assert abs(np.corrcoef(g_xy, g_xz)[0, 1]) < Z / np.sqrt(N)


def test_table1_offset_alone_is_uniform_1_mT():
    probe = HallProbe("table1", 0.0, 0.0, 0.0, 1e-3, 0.0)
    meas = probe.measure(np.zeros((N, 3)), np.random.default_rng(12))
    assert np.abs(meas).max() <= 1e-3
    sigma = 1e-3 / np.sqrt(3)
    np.testing.assert_allclose(meas.std(axis=0, ddof=1), sigma, atol=Z * _std_tolerance(sigma))
    np.testing.assert_allclose(meas.mean(axis=0), 0.0, atol=Z * sigma / np.sqrt(N))


def test_table1_gain_combines_instrumental_tolerance_and_nonlinearity():
    probe = HallProbe("table1", 1.5e-3, 2e-4, 5e-4, 0.0, 0.0)
    draws = probe.sample(np.random.default_rng(13), N)
    assert draws.shape == (N,)
    expected = np.sqrt(1.5e-3**2 + (2e-4**2 + 5e-4**2) / 3)  # 0.1532 %, first order
    std = draws.gain.std(axis=0, ddof=1)
    np.testing.assert_allclose(std, expected, rtol=0.01)
    # the three elements are independent (unlike the paper's single S_HP)
    assert abs(np.corrcoef(draws.gain[:, 0], draws.gain[:, 1])[0, 1]) < Z / np.sqrt(N)
    np.testing.assert_array_equal(draws.offset_T, 0.0)
    np.testing.assert_array_equal(draws.directions, np.broadcast_to(np.eye(3), (N, 3, 3)))


def test_one_probe_for_a_whole_map_broadcasts():
    probe = HallProbe("table1")
    draws = probe.sample(np.random.default_rng(5))  # size () -> one probe
    assert draws.gain.shape == (3,) and draws.directions.shape == (3, 3)
    B = np.random.default_rng(6).normal(0, 0.1, (50, 3))
    meas = probe.measure(B, draws=draws)
    expected = draws.gain * (B @ draws.directions.T) + draws.offset_T
    np.testing.assert_allclose(meas, expected, rtol=1e-14)
    # many trials over many points: draws (m, 1) against B (n, 3) -> (m, n, 3)
    many = probe.sample(np.random.default_rng(5), (4, 1))
    assert apply_probe(B, many).shape == (4, 50, 3)


def test_same_seed_same_numbers_and_switching_a_term_off_keeps_the_others():
    B = np.random.default_rng(0).normal(0, 0.1, (10, 3))
    a = HallProbe("table1").measure(B, 42)
    b = HallProbe("table1").measure(B, np.random.default_rng(42))
    np.testing.assert_array_equal(a, b)
    no_offset = HallProbe("table1", offset_T=0.0)
    d_full = HallProbe("table1").sample(np.random.default_rng(1), 10)
    d_off = no_offset.sample(np.random.default_rng(1), 10)
    np.testing.assert_array_equal(d_full.gain, d_off.gain)
    np.testing.assert_array_equal(d_full.directions, d_off.directions)


def test_bad_arguments():
    probe = HallProbe()
    with pytest.raises(CfmInputError, match="exactly one"):
        probe.measure(np.zeros((2, 3)))
    with pytest.raises(CfmInputError, match="exactly one"):
        probe.measure(np.zeros((2, 3)), 1, draws=probe.sample(np.random.default_rng(1)))
    with pytest.raises(CfmInputError, match="shape"):
        probe.measure(np.zeros((2, 2)), 1)
    with pytest.raises(CfmInputError, match="model"):
        HallProbe("senis")
    with pytest.raises(CfmInputError, match="offset_T"):
        HallProbe("table1", offset_T=-1e-3)
    assert isinstance(probe.sample(np.random.default_rng(0), 3), ProbeDraws)


def test_assumptions_are_stated():
    assert "0.15 %" in HallProbe().assumptions()[0]
    lines = " ".join(HallProbe("table1").assumptions())
    for token in ("0.02 %", "0.05 %", "1 mT", "35 mrad", "0.15 %"):
        assert token in lines
