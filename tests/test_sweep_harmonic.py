"""The sweep under the harmonic field model, against exact fields and across run layouts."""

from __future__ import annotations

import json

import numba
import numpy as np
import pytest

from cfm_fem import testing
from cfm_fem.cli import main
from cfm_fem.models.field import FieldMap
from cfm_fem.models.harmonic import fit_harmonic
from cfm_fem.models.harmonic_basis import field_basis, monomial_exponents
from cfm_fem.models.sweep import SweepConfig, summarize
from cfm_fem.workflows.sweep.in_memory import run_sweep
from cfm_fem.workflows.sweep.problem import prepare_sweep

G, S, C = 0.05, 4e-3, 2e-4  # T/mm, T/mm^2, T/mm^2


def exact_field(p):
    """An exactly harmonic field, written by hand: a quadrupole, a sextupole, a z-dependent
    term grad(z (x^2 + y^2) - 2 z^3 / 3) and a degree-5 term grad Re (x + iy)^6.

    Parameters
    ----------
    p : ndarray, shape (k, 3), mm

    Returns
    -------
    ndarray, shape (k, 3), T
    """
    x, y, z = np.asarray(p, dtype=np.float64).T
    w = (x + 1j * y) / 10.0
    d6 = 6 * w**5 / 10.0 * 1e-2  # d/dx Re(w^6) = Re(6 w^5)/10; d/dy = -Im(6 w^5)/10
    return np.c_[
        G * y + S * (x**2 - y**2) + 2 * C * x * z + d6.real,
        G * x - 2 * S * x * y + 2 * C * y * z - d6.imag,
        C * (x**2 + y**2) - 2 * C * z**2,
    ]


def write_map_csv(fm, path):
    """Write a map as the CSV table the readers take (mm, T); returns the path."""
    rows = np.c_[fm.points, fm.B].tolist()
    path.write_text(
        "x [mm],y [mm],z [mm],Bx [T],By [T],Bz [T]\n"
        + "".join(",".join(map(repr, r)) + "\n" for r in rows)
    )
    return path


def grid_map(n=9, nz=17, half=6.0, half_z=12.0):
    ax = np.linspace(-half, half, n)
    pts = np.stack(np.meshgrid(ax, ax, np.linspace(-half_z, half_z, nz), indexing="ij"), -1)
    pts = pts.reshape(-1, 3)
    return FieldMap.from_arrays(pts, exact_field(pts), source="exact.csv")


def test_the_hand_written_field_is_curl_and_divergence_free():
    rng = np.random.default_rng(3)
    p = rng.uniform(-5, 5, (20, 3))
    h = 1e-4
    jac = np.stack(
        [(exact_field(p + h * e) - exact_field(p - h * e)) / (2 * h) for e in np.eye(3)], -1
    )
    assert np.abs(np.trace(jac, axis1=1, axis2=2)).max() < 1e-9
    assert np.abs(jac - jac.transpose(0, 2, 1)).max() < 1e-9


def _node_keys_by_index(problem, nodes):
    return problem.run_nodes(nodes, keys=nodes)


@pytest.fixture(scope="module")
def exact_case():
    fm = grid_map()
    cfg = SweepConfig(up_um=[0.0, 50.0, 200.0], trials=400, seed=5, field_model="harmonic")
    _, problem, _ = prepare_sweep(fm, cfg)
    lin_cfg = SweepConfig(up_um=[0.0, 50.0, 200.0], trials=400, seed=5, field_model="linear")
    _, lin_problem, _ = prepare_sweep(fm, lin_cfg)
    nodes = np.flatnonzero(np.all(np.abs(fm.points) < [4.0, 4.0, 9.0], axis=1))
    return fm, problem, lin_problem, nodes


def test_harmonic_model_gives_the_exact_fields_monte_carlo(exact_case):
    """Same normals (node index as key) through the exact field: the harmonic sweep's
    statistics equal those of the exact field to far below the Monte Carlo noise, and the
    linear interpolant's U_f is visibly off on this curved field."""
    fm, problem, lin_problem, nodes = exact_case
    stats = _node_keys_by_index(problem, nodes)[0]
    lin = _node_keys_by_index(lin_problem, nodes)[0]
    fit = problem.harmonic
    assert fit.use[nodes].all()
    b_exact = fm.B.copy()
    ref, _ = testing.gauss_sweep(
        fm.points, b_exact, [0.0, 0.05, 0.2], 400, 5, nodes=nodes, interp=exact_field
    )
    uf = np.maximum(np.abs(stats[..., 3, 2]), np.abs(stats[..., 3, 3]))
    uf_ref = np.maximum(np.abs(ref[..., 3, 2]), np.abs(ref[..., 3, 3]))
    uf_lin = np.maximum(np.abs(lin[..., 3, 2]), np.abs(lin[..., 3, 3]))
    rel = np.abs(uf[:, 1:] / uf_ref[:, 1:] - 1)
    assert np.median(rel) < 1e-4 and rel.max() < 2e-3
    rel_lin = np.abs(uf_lin[:, 1:] / uf_ref[:, 1:] - 1)
    assert np.median(rel_lin) > 20 * np.median(rel)
    np.testing.assert_array_equal(stats[:, 0], 0.0)


def test_harmonic_kernel_matches_its_numpy_twin(exact_case):
    """Each node's polynomial evaluated by numpy at the trials' displacements, through the
    statistics twin, gives the kernel's numbers to rounding."""
    fm, problem, _, nodes = exact_case
    nodes = nodes[::17]
    stats = _node_keys_by_index(problem, nodes)[0]
    fit = problem.harmonic
    gmat, exps = field_basis(), monomial_exponents()
    for i, g in enumerate(nodes):

        def poly(p, g=g):
            u = (np.asarray(p) - fm.points[g]) / fit.scale[g]
            mono = np.prod(u[:, None, :] ** exps[None], axis=2)
            return np.einsum("pm,cmj,j->pc", mono, gmat, fit.coef[g])

        b = fm.B.copy()
        b[g] = poly(fm.points[g : g + 1])[0]
        ref, n_out = testing.gauss_sweep(
            fm.points, b, [0.0, 0.05, 0.2], 400, 5, nodes=[g], interp=poly
        )
        np.testing.assert_allclose(stats[i], ref[0], rtol=1e-9, atol=1e-15)


def _uf_maps(fm, cfg, **kw):
    res = run_sweep(fm, cfg, **kw)
    return res.uf_units(), res


def test_same_numbers_whatever_threads_and_chunks():
    fm = grid_map(7, 11)
    cfg = SweepConfig(up_um=[10.0, 40.0], trials=200, seed=2, field_model="harmonic")
    numba.set_num_threads(1)
    try:
        a, _ = _uf_maps(fm, cfg)
    finally:
        numba.set_num_threads(min(2, numba.config.NUMBA_NUM_THREADS))
    b, res = _uf_maps(fm, SweepConfig(**{**cfg.__dict__, "chunk_nodes": 13}))
    np.testing.assert_array_equal(a, b)
    fitted = res.field_fit["degree"] > 0
    assert fitted.sum() > 0.9 * len(fitted)
    assert (res.n_outside[fitted] == 0).all()  # surface nodes keep every trial
    assert np.isfinite(b[fitted]).all()


def test_cli_pieces_slabs_and_memory_agree_bit_for_bit(tmp_path):
    fm = grid_map(7, 21)
    f = write_map_csv(fm, tmp_path / "map.csv")
    base = ["sweep", str(f), "--up", "0,30", "--trials", "100", "--field-model", "harmonic"]
    out = {}
    for name, extra in (("mem", []), ("pieces", ["--pieces", "3"]), ("slabs", ["--slabs", "3"])):
        assert main([*base, "--out", str(tmp_path / name), *extra]) == 0
        out[name] = json.loads((tmp_path / name / "summary.json").read_text())
    for name in ("pieces", "slabs"):
        assert out[name]["uf_units"] == out["mem"]["uf_units"], name
        assert out[name]["harmonic"] == out["mem"]["harmonic"], name
        assert out[name]["gum_disagree_nodes"] == out["mem"]["gum_disagree_nodes"], name
    assert out["mem"]["field_model"] == "harmonic"


def test_mode_htm_under_the_harmonic_model_is_close_to_linear_where_the_field_is_flat():
    ax = np.linspace(-10, 10, 11)
    pts = np.stack(np.meshgrid(ax, ax, np.linspace(-20, 20, 11), indexing="ij"), -1)
    pts = pts.reshape(-1, 3) + [0.0, 0.0, 0.0]
    B = np.c_[G * pts[:, 1], G * pts[:, 0], np.full(len(pts), 0.2)]  # linear: both exact
    fm = FieldMap.from_arrays(pts, B, source="lin.csv")
    res = {}
    for model in ("linear", "harmonic"):
        cfg = SweepConfig(trials=200, seed=1, mode="htm", field_model=model, outside="extrapolate")
        res[model] = run_sweep(fm, cfg)
    inner = np.all(np.abs(pts) < [6, 6, 15], axis=1)
    a, b = res["linear"].uf_units()[inner], res["harmonic"].uf_units()[inner]
    ok = np.isfinite(a) & np.isfinite(b)
    assert ok.sum() > 10
    np.testing.assert_allclose(b[ok], a[ok], rtol=1e-6)
    assert res["harmonic"].field_fit["degree"].min() >= 2


def test_planar_map_refused_for_the_harmonic_model(tmp_path, capsys):
    ax = np.linspace(-5, 5, 6)
    pts = np.stack(np.meshgrid(ax, ax, [0.0], indexing="ij"), -1).reshape(-1, 3)
    f = tmp_path / "plane.csv"
    rows = np.c_[pts, exact_field(pts)].tolist()
    f.write_text(
        "x [mm],y [mm],z [mm],Bx [T],By [T],Bz [T]\n"
        + "".join(",".join(map(repr, r)) + "\n" for r in rows)
    )
    rc = main(["sweep", str(f), "--field-model", "harmonic", "--out", str(tmp_path / "o")])
    assert rc == 2
    err = capsys.readouterr().err
    assert "3-D map" in err and "Traceback" not in err
    assert not (tmp_path / "o" / "summary.json").exists()


def test_default_field_model_is_harmonic_on_a_volume_and_linear_on_a_plane(tmp_path, capsys):
    """With no --field-model, a 3-D map runs under the harmonic fits and a planar map under the
    linear interpolant, with a note saying why; the summary names the model that served."""
    vol = tmp_path / "volume.csv"
    pts = grid_map().points
    vol.write_text(
        "x [mm],y [mm],z [mm],Bx [T],By [T],Bz [T]\n"
        + "".join(",".join(map(repr, r)) + "\n" for r in np.c_[pts, exact_field(pts)].tolist())
    )
    args = ["--up", "0,20", "--trials", "200"]
    assert main(["sweep", str(vol), *args, "--out", str(tmp_path / "v")]) == 0
    summary = json.loads((tmp_path / "v" / "summary.json").read_text())
    assert summary["field_model"] == "harmonic"
    assert summary["harmonic"]["linear_fallback_nodes"] < len(pts)
    assert "harmonic fit per node" in capsys.readouterr().out

    ax = np.linspace(-5, 5, 6)
    flat = np.stack(np.meshgrid(ax, ax, [0.0], indexing="ij"), -1).reshape(-1, 3)
    plane = tmp_path / "plane.csv"
    plane.write_text(
        "x [mm],y [mm],z [mm],Bx [T],By [T],Bz [T]\n"
        + "".join(",".join(map(repr, r)) + "\n" for r in np.c_[flat, exact_field(flat)].tolist())
    )
    assert main(["sweep", str(plane), *args, "--out", str(tmp_path / "p")]) == 0
    summary = json.loads((tmp_path / "p" / "summary.json").read_text())
    assert summary["field_model"] == "linear"
    assert any("planar map" in n for n in summary["notes"])
    out = capsys.readouterr().out
    assert "linear interpolant at every node" in out


def test_default_field_model_matches_an_explicit_harmonic_run():
    fm = grid_map()
    runs = [
        run_sweep(fm, SweepConfig(up_um=[20.0], trials=200, seed=3, **kw))
        for kw in ({}, {"field_model": "harmonic"})
    ]
    assert np.array_equal(runs[0].stats, runs[1].stats, equal_nan=True)


def conductor_field(p, centre=(3.0, 0.0), radius=2.0, k=0.01):
    """A quadrupole plus the field of a straight conductor along z of uniform current density
    (k = mu0 J / 2, T/mm): curl B != 0 inside the conductor, so Laplace's equation fails there."""
    x, y, z = np.asarray(p, dtype=np.float64).T
    dx, dy = x - centre[0], y - centre[1]
    r2 = dx**2 + dy**2
    scale = np.where(r2 < radius**2, 1.0, radius**2 / np.maximum(r2, 1e-300))
    return np.c_[G * y - k * dy * scale, G * x + k * dx * scale, np.zeros_like(x)]


def test_nodes_where_laplace_fails_keep_the_linear_interpolant():
    ax = np.linspace(-6, 6, 13)
    pts = np.stack(np.meshgrid(ax, ax, np.linspace(-6, 6, 13), indexing="ij"), -1).reshape(-1, 3)
    fm = FieldMap.from_arrays(pts, conductor_field(pts), source="conductor.csv")
    cfg = SweepConfig(up_um=[20.0], trials=200, seed=4, field_model="harmonic")
    res = run_sweep(fm, cfg)
    lin = run_sweep(fm, SweepConfig(up_um=[20.0], trials=200, seed=4))
    fallback = res.field_fit["degree"] == 0
    inside = np.hypot(pts[:, 0] - 3.0, pts[:, 1]) < 2.0
    assert fallback[inside & (np.abs(pts[:, 2]) < 5)].all()
    far = np.hypot(pts[:, 0] - 3.0, pts[:, 1]) > 6.0
    assert not fallback[far & (np.abs(pts) < 5).all(axis=1)].any()
    np.testing.assert_array_equal(res.stats[fallback], lin.stats[fallback])
    s = summarize(res)
    h = s["harmonic"]
    assert h["linear_fallback_nodes"] == int(fallback.sum())
    box = h["linear_fallback_box_mm"]
    assert box["min"][0] <= 1.0 and box["max"][0] >= 5.0
    assert "curl" in h["fallback_rule"]


def test_compare_and_diagnose_take_a_harmonic_reference_map(tmp_path):
    """A Hall map recorded between the nodes of a reference map, read under both models: the
    harmonic one is named in the outputs, and its residual is the smaller one."""
    fm = grid_map(9, 17)
    ref = tmp_path / "ref.csv"
    rows = np.c_[fm.points, fm.B].tolist()
    ref.write_text(
        "x [mm],y [mm],z [mm],Bx [T],By [T],Bz [T]\n"
        + "".join(",".join(map(repr, r)) + "\n" for r in rows)
    )
    rng = np.random.default_rng(8)
    pts = rng.uniform([-4, -4, -9], [4, 4, 9], (40, 3))
    lines = []
    for i, p in enumerate(pts):
        for rep in range(3):
            b = exact_field(p[None])[0] + rng.normal(0, 7e-6, 3)
            lines.append(",".join(map(repr, [i, rep, *p.tolist(), *b.tolist()])) + "\n")
    rec = tmp_path / "hall.csv"
    rec.write_text("point_id,rep,x_cmd,y_cmd,z_cmd,Bx,By,Bz\n" + "".join(lines))
    rms = {}
    for model in ("linear", "harmonic"):
        out = tmp_path / f"cmp_{model}"
        argv = ["compare", "--hall-map", str(rec), "--reference", str(ref), "--trials", "100",
                "--field-model", model, "--out", str(out)]  # fmt: skip
        assert main(argv) == 0
        doc = json.loads((out / "compare.json").read_text())
        assert ("harmonic fit" in doc["reference"]) == (model == "harmonic")
        out = tmp_path / f"diag_{model}"
        argv = ["diagnose", "--hall-map", str(rec), "--reference", str(ref), "--no-report",
                "--field-model", model, "--out", str(out)]  # fmt: skip
        assert main(argv) == 0
        diag = json.loads((out / "diagnosis.json").read_text())
        rms[model] = diag["fit"]["rms_before"]
        if model == "harmonic":  # the recording is the reference's field plus noise
            assert not diag["mismatch"] and diag["fit"]["chi2_dof_before"] < 2.0
    assert rms["harmonic"] < 0.1 * rms["linear"]


def test_a_harmonic_field_keeps_its_model_on_the_grids_edges():
    """On a 12 mm grid of the hand-written field (its degree-5 term is strongest at the
    corners) the one-sided neighbourhoods of the edges lift the degree-2 curl ratio above 3;
    their chosen fits beat the unconstrained quadratic, so no node falls back."""
    fm = grid_map(7, 21)
    fit = fit_harmonic(fm.points, fm.B)
    assert fit.use.all()
