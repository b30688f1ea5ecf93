"""The independent simulator checked against references it did not construct: Maxwell's
equations, a 2-D charge-sheet model of the magnet, closed-form lever arms, the tool's readers."""

from __future__ import annotations

import json

import numpy as np
import pytest

pytest.importorskip("magpylib")

from cfm_fem.simulation import bench as sb  # noqa: E402
from cfm_fem.simulation import hall, magnet, scan, tracker, write_case  # noqa: E402


@pytest.fixture(scope="module")
def probe_points():
    """Points in the bore: body, both ends and field-free space (mm)."""
    rng = np.random.default_rng(5)
    z = np.r_[rng.uniform(-300, 300, 20), -125.0, 125.0, -130.0, 118.0, 0.0]
    xy = rng.uniform(-6, 6, (len(z), 2))
    return np.c_[xy, z]


def test_field_is_div_and_curl_free(probe_points):
    from cfm_fem.workflows.diagnose.problem import field_jacobian

    J = field_jacobian(magnet.field, probe_points, 0.01)  # T/mm
    scale = np.abs(J).max()
    div = np.trace(J, axis1=1, axis2=2)
    curl = np.stack([J[:, 2, 1] - J[:, 1, 2], J[:, 0, 2] - J[:, 2, 0], J[:, 1, 0] - J[:, 0, 1]], -1)
    assert np.abs(div).max() < 1e-5 * scale
    assert np.abs(curl).max() < 1e-5 * scale


def _charge_sheet_field(points_mm):
    """2-D field (T) of the infinitely long block ring from its magnetic surface charges
    sigma = J . n: B = (1 / 2 pi) sum_faces int sigma (r - r') / |r - r'|^2 dl'."""
    t, w = magnet.THICK_MM, 2 * magnet.BORE_MM * np.tan(np.pi / magnet.N_BLOCKS)
    u, wt = np.polynomial.legendre.leggauss(400)
    b = np.zeros((len(points_mm), 2))
    for k in range(magnet.N_BLOCKS):
        phi = 2 * np.pi * k / magnet.N_BLOCKS
        er, et = np.array([np.cos(phi), np.sin(phi)]), np.array([-np.sin(phi), np.cos(phi)])
        c = (magnet.BORE_MM + t / 2) * er
        jloc = magnet.POLARIZATION_T * np.array([np.sin(2 * phi), -np.cos(2 * phi)])
        jv = jloc[0] * er + jloc[1] * et
        for n, half_n, along, half_a in ((er, t, et, w), (et, w, er, t)):
            for sgn in (1.0, -1.0):
                sigma = float(jv @ (sgn * n))
                src = c + sgn * n * half_n / 2 + np.outer(u * half_a / 2, along)
                d = points_mm[:, None, :2] - src[None]
                r2 = np.sum(d**2, -1)
                b += (
                    sigma / (2 * np.pi) * np.einsum("k,pkc->pc", wt * half_a / 2, d / r2[..., None])
                )
    return b


def test_centre_gradient_is_the_design_value_and_the_2d_charge_model():
    h = 0.05
    p = np.array([[h, 0, 0], [-h, 0, 0], [0, h, 0], [0, -h, 0]], float)
    b3 = magnet.field(p)
    g3 = (b3[0, 1] - b3[1, 1]) / (2 * h) * 1e3  # dBy/dx, T/m
    g3b = (b3[2, 0] - b3[3, 0]) / (2 * h) * 1e3  # dBx/dy
    b2 = _charge_sheet_field(p)
    g2 = (b2[0, 1] - b2[1, 1]) / (2 * h) * 1e3
    assert g3 == pytest.approx(g2, rel=1e-3)  # a 250 mm magnet is 2-D at its centre
    assert g3 == pytest.approx(g3b, rel=1e-9)
    assert g3 == pytest.approx(magnet.GRADIENT_T_M, rel=0.01)


def test_field_vanishes_beyond_both_ends():
    p = np.array([[5.0, 5.0, -300.0], [5.0, 5.0, 300.0], [5.0, 5.0, 0.0]])
    b = np.linalg.norm(magnet.field(p), axis=1)
    assert b[2] > 0.3
    assert b[:2].max() < 1e-6  # below the 7 uT Hall noise


def test_chain_with_zero_errors_is_the_identity():
    q = np.random.default_rng(1).uniform(0, 1, (50, 3)) * [150, 150, 800]
    np.testing.assert_array_equal(sb.probe_position(q, {}), q + sb.TOOL_MM)


@pytest.mark.parametrize(
    "name, value, expect",
    [
        # rotation of the Z carriage about x: lever arm from its origin (0, 0, q_z) to the probe
        ("eps_x(z)", 10.0, lambda q: 10e-6 * np.c_[0 * q[:, 0], -500 + 0 * q[:, 0], q[:, 1] - 60]),
        # yaw of the Y carriage about z: lever (0, -60, 500) from its origin
        ("eps_z(y)", 10.0, lambda q: 10e-6 * np.c_[60 + 0 * q[:, 0], 0 * q[:, 0], 0 * q[:, 0]]),
        # X travel leaning towards +z: z grows with x travel
        ("alpha_xz", 20.0, lambda q: np.c_[0 * q[:, 0], 0 * q[:, 0], 20e-6 * q[:, 0]]),
        ("delta_y(x)", 3.0, lambda q: np.tile([0.0, 3e-3, 0.0], (len(q), 1))),
    ],
)
def test_single_error_moves_the_probe_by_its_lever_arm(name, value, expect):
    q = np.random.default_rng(2).uniform(0, 1, (40, 3)) * [150, 150, 800]
    moved = sb.probe_position(q, {name: value}) - (q + sb.TOOL_MM)
    np.testing.assert_allclose(moved, expect(q), atol=1e-7)  # exact rotations: eps^2 terms


def test_table_ii_draws_have_the_stated_moments():
    rng = np.random.default_rng(3)
    d = np.array([list(sb.draw_errors(rng).values()) for _ in range(4000)])
    for k, name in enumerate(sb.NAMES):
        kind, a, b = sb.TABLE_II[name]
        mean, std = ((a + b) / 2, (b - a) / np.sqrt(12)) if kind == "uniform" else (a, b)
        assert abs(d[:, k].mean() - mean) < 5 * std / np.sqrt(len(d))
        assert d[:, k].std() == pytest.approx(std, rel=0.06)


def test_scan_directions_speeds_and_times():
    s = scan.plan([0, 50, 100], [0, 60], [0, 100, 200, 300], [0.0, 10.0, 20.0])
    assert np.all(np.diff(s.t_s) > 0)
    assert np.bincount(s.point).tolist() == [3] * 24
    # stop-and-go: z approached in the line's direction, which alternates (serpentine)
    sg = s.speed == 0
    step = np.diff(s.q[sg, 2])
    same_line = np.abs(step) == 100
    np.testing.assert_array_equal(np.sign(step[same_line]), s.dir[sg, 2][1:][same_line])
    # a standing axis keeps its direction: x and y only change between lines
    moved = np.diff(s.q[:, :2], axis=0) != 0
    kept = np.diff(s.dir[:, :2], axis=0) != 0
    assert not np.any(kept & ~moved)
    assert {-1, 1} <= set(s.dir[:, 0]) and {-1, 1} <= set(s.dir[:, 2])
    fly = s.speed > 0
    assert set(s.speed[fly]) == {10.0, 20.0}
    np.testing.assert_array_equal(s.v[fly, 2], s.dir[fly, 2] * s.speed[fly])
    assert np.all(s.v[:, :2] == 0)
    line = (s.rep == 1) & (s.q[:, 0] == 0) & (s.q[:, 1] == 0)  # constant speed along a line
    dz, dt = np.diff(s.q[line, 2]), np.diff(s.t_s[line])
    np.testing.assert_allclose(np.abs(dz) / dt, 10.0)


def test_same_seed_same_recording_and_effects_keep_other_draws():
    a, _ = tracker.simulate(4, size="small")
    b, _ = tracker.simulate(4, size="small")
    c, _ = tracker.simulate(4, {"reversal": {"backlash_z": 4.0}}, size="small")
    for k in a:
        np.testing.assert_array_equal(a[k], b[k])
    dz = (c["z_meas"] - a["z_meas"]) * 1e3
    np.testing.assert_allclose(dz, 2.0 * a["dir_z"], atol=1e-6)  # b dir / 2, nothing else moved


def test_recordings_and_references_parse_with_the_tools_readers(tmp_path):
    from cfm_fem.io import read_field
    from cfm_fem.io.harmonics import read_harmonics
    from cfm_fem.io.recordings import read_hall_map, read_tracker

    t = write_case("reversal", 7, tmp_path, size="small", velocities=False)
    rec = read_tracker(t["recording"])
    cols, _ = tracker.simulate(7, {"reversal": {"backlash_x": 3.0, "backlash_z": 4.0}}, "small")
    np.testing.assert_allclose(rec.meas[:, 2], cols["z_meas"], atol=1e-6)
    np.testing.assert_array_equal(rec.dir[:, 2], cols["dir_z"])
    assert "v_x" not in rec.extra
    truth = json.loads(t["truth"].read_text())
    assert truth["params"]["backlash_z"] == 4.0 and truth["expected"] == "reversal"

    h = write_case("null_hall", 7, tmp_path, size="small")
    rec = read_hall_map(h["recording"])
    assert rec.speed.max() == 20.0 and np.ptp(rec.temp_C) > 0
    fm = read_field(h["reference"])
    i = np.argmin(np.linalg.norm(fm.points - [6.0, 6.0, 125.0], axis=1))
    np.testing.assert_allclose(fm.B[i], magnet.field(fm.points[i : i + 1])[0], atol=1e-9)

    f = write_case("fringe_field_3d", 7, tmp_path, size="small")
    mp = read_harmonics(f["reference"])
    p = np.array([[3.0, -2.0, 0.0], [-5.0, 4.0, 0.0]])
    np.testing.assert_allclose(mp.field(p)[:, :2], magnet.field(p)[:, :2], atol=1e-6)


def test_hall_effects_act_as_their_catalogue_formulas():
    base, tb = hall.simulate(8, size="small")
    eff = {"probe_misalignment": {"m_zx": 0.5}, "planar_hall": {"k_x": 0.01}}
    c, t = hall.simulate(8, eff, size="small")
    bx, by = base["Bx"], base["By"]
    g = 1 + 1e-2 * np.array([tb["params"][f"gain_{a}"] for a in "xyz"])
    # Bz gains 0.5 mrad of Bx (before the gains); Bx gains k By Bz (to the noise of base)
    np.testing.assert_allclose((c["Bz"] - base["Bz"]) / g[2], 0.5e-3 * bx / g[0], atol=3e-8)
    np.testing.assert_allclose((c["Bx"] - bx) / g[0], 0.01 * by * base["Bz"] / g[1] / g[2],
                               atol=1e-7)  # fmt: skip


def test_simulator_imports_no_model_code_of_the_tool():
    import ast
    from pathlib import Path

    import cfm_fem.simulation as pkg

    for path in Path(pkg.__file__).parent.glob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom):
                name = ("." * node.level) + (node.module or "")
                outside = node.level >= 2 or name.startswith("cfm_fem")
                assert not outside or name in ("..errors", "cfm_fem.errors"), (path.name, name)
            elif isinstance(node, ast.Import):
                for alias in node.names:
                    assert not alias.name.startswith("cfm_fem"), (path.name, alias.name)
