"""Coupled Monte Carlo (paper eq. 12-14): exact limits, kernel twin, linear-field identities,
probe-only statistics against closed form, Table V pooling."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from cfm_fem import _kernels as K
from cfm_fem.errors import CfmInputError
from cfm_fem.io.harmonics import read_qfdp4
from cfm_fem.models import kinematics as km
from cfm_fem.models.bench import ReadingDelay
from cfm_fem.models.field import FieldMap
from cfm_fem.models.field_model import FieldModel
from cfm_fem.models.multipole import Multipole
from cfm_fem.models.probe import HallProbe
from cfm_fem.workflows.coupled import (
    centred_on_travel,
    default_region,
    field_budget,
    pool_table_v,
    run_coupled,
)

R_REF = 10.0
B2 = 0.0696  # T at R_ref: gradient G = B2 / R_ref = 6.96e-3 T/mm


def quiet(bench):
    """The bench with no geometric error, vibration or delay."""
    return replace(
        bench.scaled_errors(0.0),
        vibration_std_mm=np.zeros(3),
        delay=ReadingDelay(model="normal", std_mm=np.zeros(3)),
    )


def quad():
    return FieldModel.from_multipole(Multipole([0.0, B2], [0.0, 0.0], R_REF, main=2))


PTS = np.array([[0.0, 0.0, 0.0], [R_REF, 0.0, 0.0], [3.0, -4.0, 50.0], [-6.0, 2.0, -80.0]])


@pytest.mark.slow
def test_kernel_matches_numpy_twin(bench):
    g = km.kernel_geometry(bench)
    nkey, fkey = km.noise_keys(7)
    params = km.draw_error_sets(bench, 16, 7, start=5)
    q = bench.grid_points()[::131]
    pidx = np.arange(len(q), dtype=np.int64) + 3
    out = np.empty((16, len(q), 3))
    K.coupled_probe_errors(params, 5, q, pidx, nkey, fkey, g, out)
    ref = np.stack(
        [
            km.probe_errors_for_bench(
                bench, params[t : t + 1], q, km.point_noise(bench, 5 + t, pidx, 7)
            )[0]
            for t in range(16)
        ]
    )
    np.testing.assert_allclose(out, ref, rtol=0, atol=1e-12)


def test_exact_bench_and_probe_give_zero(bench):
    r = run_coupled(quad(), quiet(bench), PTS, probe=HallProbe.exact(), trials=40, seed=1)
    assert np.all(r.mean == 0) and np.all(r.std == 0) and np.all(r.u95 == 0)
    assert r.pooled()["all"]["U_f_units"] == 0


def test_linear_field_maps_position_error_exactly(bench):
    """Pure quadrupole, exact probe: E_f,y = 1e4 E_x / R_ref and E_f,x = 1e4 E_y / R_ref (mm)."""
    r = run_coupled(quad(), bench, PTS, probe=HallProbe.exact(), trials=400, seed=2)
    scale = 1e4 / R_REF
    np.testing.assert_allclose(r.mean[:, 1], scale * r.ep_mean[:, 0], rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(r.mean[:, 0], scale * r.ep_mean[:, 1], rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(r.std[:, 1], scale * r.ep_std[:, 0], rtol=1e-9)
    np.testing.assert_allclose(r.std[:, 0], scale * r.ep_std[:, 1], rtol=1e-9)
    assert np.all(r.mean[:, 2] == 0)  # 2-D field: B_z = 0
    # the same samples as the kinematics engine at the same commanded positions
    k = km.run_kinematics(bench, trials=400, seed=2, q_cmd=r.q_cmd)
    np.testing.assert_allclose(r.ep_mean, k.mean[:, :3], rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(r.ep_std, k.std[:, :3], rtol=1e-9)


def test_probe_only_matches_closed_form(bench):
    """S_HP uniform, std s: E_f,i = (S - 1) B_i / B_ref, so std = 1e4 s |B_i| / B_ref."""
    m = 4000
    r = run_coupled(quad(), quiet(bench), PTS, trials=m, seed=3)
    B = quad().field(PTS)[0]
    expect = 1e4 * 1.5e-3 * np.abs(B[:, :2]) / B2
    # relative standard error of a sample std of a uniform: sqrt((kurt - 1) / (4 m)), kurt 1.8
    tol = 5 * np.sqrt(0.8 / (4 * m))
    nz = expect > 0
    np.testing.assert_allclose(r.std[:, :2][nz], expect[nz], rtol=tol)
    assert np.all(r.std[:, :2][~nz] == 0)
    assert np.all(np.abs(r.mean[:, :2]) <= 5 * expect / np.sqrt(m) + 1e-12)
    # at (R_ref, 0): By = B_ref, the uniform's 95 % interval is -+0.95 sqrt(3) s
    half = 0.95 * np.sqrt(3) * 15.0
    assert r.low[1, 1] == pytest.approx(-half, rel=0.03)
    assert r.high[1, 1] == pytest.approx(half, rel=0.03)


def test_blocks_and_seed(bench):
    a = run_coupled(quad(), bench, PTS, trials=200, seed=4, block_points=1)
    b = run_coupled(quad(), bench, PTS, trials=200, seed=4, block_points=3)
    for name in ("mean", "std", "low", "high", "batch_mean"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    c = run_coupled(quad(), bench, PTS, trials=200, seed=5)
    assert not np.array_equal(a.mean, c.mean)


def test_align_probe_removes_common_offset(bench):
    b = replace(bench, vibration_std_mm=np.zeros(3), delay=ReadingDelay(std_mm=np.zeros(3)))
    r = run_coupled(quad(), b, PTS, probe=HallProbe.exact(), trials=100, seed=6, align="probe")
    assert np.all(np.abs(r.ep_mean[0]) < 1e-12) and np.all(r.std[0] < 1e-9)
    # elsewhere only the variation of E_p over the region is left: well below a micrometre
    assert np.all(np.abs(r.ep_mean) < 1e-3)


def test_fem_map_of_a_linear_field_agrees_with_the_multipole(bench):
    g = np.linspace(-12.0, 12.0, 7)
    z = np.linspace(-100.0, 100.0, 3)
    x, y, zz = (a.ravel() for a in np.meshgrid(g, g, z, indexing="ij"))
    G = B2 / R_REF
    fm = FieldMap.from_arrays(np.column_stack([x, y, zz]), np.column_stack([G * y, G * x, 0 * x]))
    fem = FieldModel.from_map(fm, b_ref_T=B2)
    assert fem.components == (0, 1, 2)
    pts = PTS[1:]
    a = run_coupled(fem, bench, pts, trials=300, seed=8)
    b = run_coupled(quad(), bench, pts, trials=300, seed=8)
    np.testing.assert_allclose(a.mean, b.mean, atol=1e-7)
    np.testing.assert_allclose(a.std, b.std, atol=1e-7)
    with pytest.raises(CfmInputError, match="outside the field map"):
        run_coupled(fem, bench, [[30.0, 0.0, 0.0]], trials=40)


def test_pool_table_v_by_hand():
    mean = np.array([[3.0, 4.0, 0.0, 1.0], [-3.0, 0.0, 0.0, 1.0]])
    std = np.array([[1.0, 2.0, 0.0, 1.0], [1.0, 2.0, 0.0, 1.0]])
    p = pool_table_v(mean, std, (0, 1))
    assert p["Bx"]["systematic_units"] == pytest.approx(3.0)
    assert p["By"]["systematic_units"] == pytest.approx(np.sqrt(8.0))
    assert p["all"]["systematic_units"] == pytest.approx(np.sqrt((9 + 16 + 9 + 0) / 4))
    assert p["all"]["std_units"] == pytest.approx(np.sqrt((1 + 4 + 1 + 4) / 4))
    assert p["all"]["U_f_units"] == pytest.approx(np.hypot(np.sqrt(8.5), np.sqrt(2.5)))


def test_default_region_and_qfdp4_b_ref():
    pts = default_region(10.0, 2.0, (0.0,))
    assert len(pts) == 81 and np.all(np.hypot(pts[:, 0], pts[:, 1]) <= 10.0 + 1e-9)
    fm = FieldModel.from_multipole(read_qfdp4())
    assert fm.b_ref_T == pytest.approx(0.0696) and fm.r_ref_mm == 10.0


def test_bad_inputs(bench):
    far = replace(bench, magnet=replace(bench.magnet, translation_mm=np.array([0.0, 0.0, 900.0])))
    with pytest.raises(CfmInputError, match="outside the strokes"):
        run_coupled(quad(), far, PTS, trials=40)
    ok = centred_on_travel(far)
    assert not ok.outside_stroke(ok.axis_positions_for(PTS)).any()
    with pytest.raises(CfmInputError, match="align"):
        run_coupled(quad(), bench, PTS, trials=40, align="magnet")
    with pytest.raises(CfmInputError, match="trials"):
        run_coupled(quad(), bench, PTS, trials=5)


def test_cli_default_region_outside_an_off_axis_map_names_the_file(tmp_path, capsys):
    # a map from 0 to 5 mm: the default region (centred on the axis) leaves it
    from cfm_fem.cli import main

    g = np.stack(np.meshgrid(*[np.arange(6.0)] * 3, indexing="ij"), -1).reshape(-1, 3)
    f = tmp_path / "m.csv"
    f.write_text("x [mm],y [mm],z [mm],Bx [T],By [T],Bz [T]\n"
                 + "".join(f"{x},{y},{z},{0.1 * y},{0.1 * x},1\n" for x, y, z in g))  # fmt: skip
    out = tmp_path / "o"
    argv = ["coupled", "--field", str(f), "--trials", "20", "--no-budget", "--out", str(out)]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert f"error: {f}: scan point" in err and "spans x 0..5, y 0..5, z 0..5 mm" in err, err
    assert "the default region is centred on the z axis: set --radius and --z" in err, err
    assert not out.exists()


def test_field_budget_variances_add(bench):
    m = 2000
    fb = field_budget(quad(), bench, PTS[1:], trials=m, seed=9)
    tot = run_coupled(quad(), bench, PTS[1:], trials=m, seed=9).pooled()["all"]
    both = np.hypot(fb["positioning_only"]["std_units"], fb["probe_only"]["std_units"])
    # independent effects, first order: the variances add (sampling noise ~ 1/sqrt(m))
    assert tot["std_units"] == pytest.approx(both, rel=8 / np.sqrt(m))
