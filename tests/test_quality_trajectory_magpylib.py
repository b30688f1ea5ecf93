"""The dipole trajectory of ``cfm-fem quality --rigidity`` through a magpylib dipole with ends,
written to a map file and read back, against the Lorentz force integrated in the magpylib field
itself (scipy's DOP853, tolerances 1e-11); and the trajectory's U95 against a brute-force
trajectory Monte Carlo (the map measured with the bench's errors, tracked trial by trial)."""

from __future__ import annotations

import numpy as np
import pytest

from cfm_fem.models.field import FieldMap
from cfm_fem.workflows.quality import run_quality

magpy = pytest.importorskip("magpylib")
solve_ivp = pytest.importorskip("scipy.integrate").solve_ivp

#: Two NdFeB poles (mm, T) polarised along +y on either side of the gap: B_y ~ 0.44 T inside.
GAP, POLE_H, POLE_W, POLE_L, BR = 16.0, 20.0, 60.0, 100.0, 1.2
RIGIDITY = 1.5  # T m: about 26 mrad
GX, GY, GZ = np.arange(-8.0, 2.01, 1.0), np.arange(-3.0, 3.01, 1.0), np.arange(-150.0, 150.01, 2.0)


def dipole():
    coll = magpy.Collection()
    for s in (1, -1):
        coll.add(
            magpy.magnet.Cuboid(
                polarization=(0.0, BR, 0.0),
                dimension=(POLE_W * 1e-3, POLE_H * 1e-3, POLE_L * 1e-3),
                position=(0.0, s * (GAP + POLE_H) / 2 * 1e-3, 0.0),
            )
        )
    return coll


def field(coll, p_mm):
    p = np.asarray(p_mm, dtype=float)
    return np.asarray(coll.getB(p.reshape(-1, 3) * 1e-3), dtype=float).reshape(p.shape)


@pytest.fixture(scope="module")
def dipole_map(tmp_path_factory):
    from cfm_fem.io import read_field, write_field

    coll = dipole()
    x, y, z = np.meshgrid(GX, GY, GZ, indexing="ij")
    pts = np.column_stack([x.ravel(), y.ravel(), z.ravel()])
    path = tmp_path_factory.mktemp("quality") / "dipole.csv"
    write_field(path, FieldMap.from_arrays(pts, field(coll, pts)))
    return read_field(path), coll


def reference_orbit(coll, z0, z1):
    """(deflection mrad, sagitta mm, exit (3,) mm) of the orbit integrated in the magpylib field."""
    k = 1.0 / (1000.0 * RIGIDITY)

    def rhs(_s, u):
        t = u[3:]
        return np.concatenate([t, k * np.cross(t, field(coll, u[:3]))])

    def exit_plane(_s, u):
        return u[2] - z1

    exit_plane.terminal = True
    sol = solve_ivp(rhs, (0.0, 3 * (z1 - z0)), [0.0, 0.0, z0, 0.0, 0.0, 1.0], method="DOP853",
                    rtol=1e-11, atol=1e-12, events=exit_plane, dense_output=True)  # fmt: skip
    s1, u1 = sol.t_events[0][0], sol.y_events[0][0]
    t = u1[3:] / np.linalg.norm(u1[3:])
    path = sol.sol(np.linspace(0.0, s1, 20001))[:3].T
    chord = (path[-1] - path[0]) / np.linalg.norm(path[-1] - path[0])
    rel = path - path[0]
    sagitta = np.linalg.norm(rel - np.outer(rel @ chord, chord), axis=1).max()
    return np.arccos(t[2]) * 1e3, sagitta, u1[:3]


@pytest.mark.slow
def test_trajectory_through_a_magpylib_dipole_map(dipole_map):
    fm, coll = dipole_map
    res = run_quality(fm, 3.0, uncertainty=False, rigidity_Tm=RIGIDITY)
    t = res.summary["trajectory"]
    assert res.main_order == 1
    deflection, sagitta, exit_mm = reference_orbit(coll, GZ[0], GZ[-1])
    print(
        f"deflection {t['deflection_mrad']:.9g} mrad, reference {deflection:.9g} mrad; "
        f"sagitta {t['sagitta_mm']:.9g} mm, reference {sagitta:.9g} mm; exit "
        f"{np.round(t['exit_mm'], 6).tolist()} mm, reference {np.round(exit_mm, 6).tolist()}"
    )
    assert 20.0 < deflection < 30.0 and sagitta > 1.0  # the case is a bend of degrees' order
    assert t["deflection_mrad"] == pytest.approx(deflection, rel=1e-6)
    assert t["deflection_x_mrad"] == pytest.approx(-deflection, rel=1e-6)
    assert t["sagitta_mm"] == pytest.approx(sagitta, abs=1e-4)
    np.testing.assert_allclose(t["exit_mm"], exit_mm, atol=1e-4)
    # the straight-line estimate integrated B_1 / B rho is first order only
    assert t["straight_line_deflection_mrad"] == pytest.approx(deflection, rel=2e-3)


# --------------------------------------------------------------------------- trajectory U95


def trilinear(values, x, y, z):
    """values (M, nx, ny, nz, 3) on the grid SX, SY, GZ at points (M,) each: (M, 3)."""
    out = 0.0
    idx, frac = [], []
    for g, c in ((SX, x), (SY, y), (GZ, z)):
        f = np.clip((c - g[0]) / (g[1] - g[0]), 0.0, len(g) - 1 - 1e-9)
        i = np.floor(f).astype(int)
        idx.append(i)
        frac.append(f - i)
    m = np.arange(values.shape[0])
    for corner in range(8):
        b = [(corner >> k) & 1 for k in range(3)]
        w = np.prod([fr if bk else 1 - fr for fr, bk in zip(frac, b, strict=True)], axis=0)
        out = out + w[:, None] * values[m, idx[0] + b[0], idx[1] + b[1], idx[2] + b[2]]
    return out


def deflections(values, dz=1.0):
    """Deflection (M,) mrad of the orbit from (0, 0, GZ[0]) along +z to GZ[-1] through each of
    M measured maps (trilinear between nodes), RK4 in z: u = (x, y, x', y')."""
    k = 1.0 / (1000.0 * RIGIDITY)

    def rhs(z, u):
        b = trilinear(values, u[:, 0], u[:, 1], np.full(len(u), z))
        d = np.column_stack([u[:, 2], u[:, 3], np.ones(len(u))])
        f = np.cross(d, b)  # (x', y', 1) x B
        n = np.linalg.norm(d, axis=1)
        return np.column_stack([u[:, 2], u[:, 3], k * n * (f[:, 0] - u[:, 2] * f[:, 2]),
                                k * n * (f[:, 1] - u[:, 3] * f[:, 2])])  # fmt: skip

    u = np.zeros((values.shape[0], 4))
    steps = int(round((GZ[-1] - GZ[0]) / dz))
    for j in range(steps):
        z = GZ[0] + j * dz
        k1 = rhs(z, u)
        k2 = rhs(z + dz / 2, u + dz / 2 * k1)
        k3 = rhs(z + dz / 2, u + dz / 2 * k2)
        k4 = rhs(z + dz, u + dz * k3)
        u = u + dz / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    return np.arccos(1.0 / np.sqrt(1.0 + u[:, 2] ** 2 + u[:, 3] ** 2)) * 1e3


#: The nodes around the orbit the brute force measures (it bends towards -x).
SX, SY = np.arange(-6.0, 1.01, 1.0), np.array([-1.0, 0.0, 1.0])


def brute_force_trajectory_u95(coll, trials, seed):
    """U95 (mrad) of the deflection through the map the bench measures, trial by trial: every
    node near the orbit read at its place moved by the reference bench (HTM chain of
    `cfm_fem.models.kinematics`, the 21 errors and vibration + delay drawn here with numpy) by
    a probe of the paper's gain (uniform, std 0.15 %), the exact magpylib field there."""
    from cfm_fem.io.bench_toml import read_reference_bench
    from cfm_fem.models.kinematics.chain import probe_errors_for_bench

    bench = read_reference_bench()
    x, y, z = np.meshgrid(SX, SY, GZ, indexing="ij")
    nodes = np.column_stack([x.ravel(), y.ravel(), z.ravel()])
    rng = np.random.default_rng(seed)
    params = np.column_stack([e.pdf.sample(rng, trials) for e in bench.errors])  # mm, rad
    dq = rng.normal(0.0, bench.noise_std_mm(), (trials, len(nodes), 3))
    e = probe_errors_for_bench(bench, params, bench.axis_positions_for(nodes), dq)
    e = e @ bench.bench_to_magnet_rotation().T
    gain = rng.uniform(1 - np.sqrt(3) * 1.5e-3, 1 + np.sqrt(3) * 1.5e-3, trials)
    b = gain[:, None, None] * field(coll, nodes[None] + e)
    shape = (len(SX), len(SY), len(GZ), 3)
    nominal = deflections(field(coll, nodes).reshape((1,) + shape))[0]
    dev = deflections(b.reshape((trials,) + shape)) - nominal
    low, high = np.quantile(dev, [0.025, 0.975])
    return max(-low, high), nominal


@pytest.mark.slow
def test_trajectory_u95_matches_a_brute_force_trajectory_monte_carlo(dipole_map):
    fm, coll = dipole_map
    res = run_quality(fm, 3.0, mode="htm", probe="paper", trials=1000, seed=4, budget=False,
                      rigidity_Tm=RIGIDITY)  # fmt: skip
    t = res.summary["trajectory"]
    ref, nominal = brute_force_trajectory_u95(coll, 300, seed=8)
    print(
        f"U95 of the deflection {t['U95_deflection_mrad']:.4g} mrad, brute force {ref:.4g} "
        f"mrad, of {nominal:.6g} mrad"
    )
    assert nominal == pytest.approx(t["deflection_mrad"], rel=1e-4)  # trilinear, RK4 in z
    assert t["U95_deflection_mrad"] == pytest.approx(ref, rel=0.05)
    assert ref > 1e-3 * nominal  # the probe's gain alone gives 2.5e-3 of it


# --------------------------------------------------------------------------- U95 from positions

#: The map of the position-only check: two node planes beyond the orbit's ends (z = +-100 mm),
#: so that the displaced readings of the nodes the orbit uses stay inside the interpolant.
PZ = np.arange(-104.0, 104.01, 2.0)
#: The nodes whose readings the orbit's interpolation uses (x >= -3 mm; y = 0 and, with zero
#: weight on the orbit's plane y = 0, y = 1 mm).
PX, PY = np.arange(-4.0, 1.01, 1.0), np.array([0.0, 1.0])


def kuhn(values, x, y, z):
    """Piecewise-linear interpolation of values (M, nx, ny, nz, 3) on the grid PX, PY, PZ at
    points (M,) each, on the Kuhn triangulation of each grid cell: the corner, then one step
    along each axis in the order of decreasing fractional coordinate."""
    m = np.arange(values.shape[0])
    corner, frac = [], []
    for g, c in ((PX, x), (PY, y), (PZ, z)):
        f = np.clip((c - g[0]) / (g[1] - g[0]), 0.0, len(g) - 1 - 1e-9)
        corner.append(np.floor(f).astype(int))
        frac.append(f - corner[-1])
    corner, frac = np.stack(corner, 1), np.stack(frac, 1)
    order = np.argsort(-frac, axis=1, kind="stable")
    fs = np.take_along_axis(frac, order, 1)
    w = np.column_stack([1 - fs[:, 0], fs[:, 0] - fs[:, 1], fs[:, 1] - fs[:, 2], fs[:, 2]])
    out = w[:, :1] * values[m, corner[:, 0], corner[:, 1], corner[:, 2]]
    for j in range(3):
        corner[m, order[:, j]] += 1
        out = out + w[:, j + 1 : j + 2] * values[m, corner[:, 0], corner[:, 1], corner[:, 2]]
    return out


def kuhn_deflections(values, z0, z1, dz=2.0):
    """Deflection (M,) mrad from (0, 0, z0) along +z to z1 through M maps (`kuhn`), RK4 in z."""
    k = 1.0 / (1000.0 * RIGIDITY)

    def rhs(z, u):
        b = kuhn(values, u[:, 0], u[:, 1], np.full(len(u), z))
        d = np.column_stack([u[:, 2], u[:, 3], np.ones(len(u))])
        f = np.cross(d, b)
        n = np.linalg.norm(d, axis=1)
        return np.column_stack([u[:, 2], u[:, 3], k * n * (f[:, 0] - u[:, 2] * f[:, 2]),
                                k * n * (f[:, 1] - u[:, 3] * f[:, 2])])  # fmt: skip

    u = np.zeros((values.shape[0], 4))
    for j in range(int(round((z1 - z0) / dz))):
        z = z0 + j * dz
        k1 = rhs(z, u)
        k2 = rhs(z + dz / 2, u + dz / 2 * k1)
        k3 = rhs(z + dz / 2, u + dz / 2 * k2)
        k4 = rhs(z + dz, u + dz * k3)
        u = u + dz / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    return np.arccos(1.0 / np.sqrt(1.0 + u[:, 2] ** 2 + u[:, 3] ** 2)) * 1e3


def brute_force_position_u95(coll, up_mm, trials, seed, z0, z1, chunk=250):
    """U95 (mrad) of the deflection through the map measured with every node read at its
    place moved by N(0, up^2) per axis (the exact magpylib field there), tracked trial by trial
    through the map's piecewise-linear interpolation; and the nominal deflection."""
    x, y, z = np.meshgrid(PX, PY, PZ, indexing="ij")
    nodes = np.column_stack([x.ravel(), y.ravel(), z.ravel()])
    shape = (len(PX), len(PY), len(PZ), 3)
    nominal = kuhn_deflections(field(coll, nodes).reshape((1,) + shape), z0, z1)[0]
    rng = np.random.default_rng(seed)
    dev = []
    for _ in range(0, trials, chunk):
        b = field(coll, nodes[None] + rng.normal(0.0, up_mm, (chunk, len(nodes), 3)))
        dev.append(kuhn_deflections(b.reshape((chunk,) + shape), z0, z1) - nominal)
    low, high = np.quantile(np.concatenate(dev), [0.025, 0.975])
    return max(-low, high), nominal


@pytest.mark.slow
def test_position_only_deflection_u95_matches_a_brute_force_trajectory_monte_carlo(tmp_path):
    """--up with an exact probe: the orbit sees the reading errors of the nodes around it
    (the linear model between nodes, whose readings the brute force redoes on its own)."""
    from cfm_fem.io import read_field, write_field

    coll = dipole()
    x, y, z = np.meshgrid(GX, GY, PZ, indexing="ij")
    pts = np.column_stack([x.ravel(), y.ravel(), z.ravel()])
    write_field(tmp_path / "dipole.csv", FieldMap.from_arrays(pts, field(coll, pts)))
    res = run_quality(read_field(tmp_path / "dipole.csv"), 3.0, up_um=20.0, probe="exact",
                      trials=1000, seed=2, budget=False, rigidity_Tm=RIGIDITY,
                      field_model="linear", sampling="circles", dz_mm=10.0,
                      n_angles=16, trajectory_step_mm=2.0)  # fmt: skip
    t = res.summary["trajectory"]
    assert t["z_range_mm"] == [-100.0, 100.0] and t["trials"] == 1000
    assert -3.0 < t["exit_mm"][0] < 0.0  # the orbit stays within the cells of PX
    ref, nominal = brute_force_position_u95(coll, 0.020, 1000, 6, -100.0, 100.0)
    scaled = t["deflection_mrad"] * res.mc.u95[-1] / float(res.nominal.main_integral_Tmm)
    print(
        f"U95 of the deflection {t['U95_deflection_mrad']:.4g} mrad, brute force {ref:.4g} "
        f"mrad (the main integral's relative U95 times the deflection: {scaled:.4g} mrad), of "
        f"{nominal:.6g} mrad"
    )
    assert nominal == pytest.approx(t["deflection_mrad"], rel=1e-4)
    assert t["U95_deflection_mrad"] == pytest.approx(ref, rel=0.10)


# --------------------------------------------------------------------------- planes 4 mm apart

GZ4 = np.arange(-150.0, 150.01, 4.0)


@pytest.fixture(scope="module")
def coarse_map():
    """The dipole's map with planes 4 mm apart: its nodes' harmonic models (40 neighbours,
    mostly in their own plane) reach about 2 mm, less than half the planes' spacing."""
    coll = dipole()
    x, y, z = np.meshgrid(GX, GY, GZ4, indexing="ij")
    pts = np.column_stack([x.ravel(), y.ravel(), z.ravel()])
    return FieldMap.from_arrays(pts, field(coll, pts), source="dipole 4 mm"), coll


@pytest.mark.slow
def test_trajectory_runs_through_a_map_of_planes_4_mm_apart(coarse_map):
    fm, coll = coarse_map
    res = run_quality(fm, 3.0, uncertainty=False, rigidity_Tm=RIGIDITY)
    t = res.summary["trajectory"]
    deflection, _, exit_mm = reference_orbit(coll, GZ4[0], GZ4[-1])
    linear, reads = t["linear_reads"]
    print(f"deflection {t['deflection_mrad']:.7g} mrad, reference {deflection:.7g} mrad; "
          f"{linear} of {reads} field readings from the linear interpolant")  # fmt: skip
    assert t["z_range_mm"] == [-150.0, 150.0]
    assert t["exit_mm"][2] == pytest.approx(150.0, abs=1e-9)
    assert 0 < linear < reads
    assert any("linear interpolant" in n for n in res.summary["notes"])
    assert t["deflection_mrad"] == pytest.approx(deflection, rel=5e-4)


@pytest.mark.slow
def test_deflection_response_matches_the_orbit_through_a_refitted_map():
    """The first-order map from node reading errors to the deflection (`orbit_response`)
    against the map read with errors (20 um per axis and node), its harmonic model fitted anew
    and the orbit tracked, on a map of the orbit's surroundings with planes 2 mm apart. The
    refit chooses each node's degree anew (most nodes change it), the first order keeps them:
    limit 20 %."""
    from cfm_fem.models.harmonic import fit_harmonic
    from cfm_fem.models.quality.orbit_mc import OrbitField, _harmonic_maps, orbit_response
    from cfm_fem.models.quality.trajectory import track

    coll = dipole()
    x, y, z = np.meshgrid(np.arange(-5.0, 1.01), np.arange(-2.0, 2.01), GZ, indexing="ij")
    pts = np.column_stack([x.ravel(), y.ravel(), z.ravel()])
    fm = FieldMap.from_arrays(pts, field(coll, pts))
    nominal = OrbitField(fit_harmonic(pts, fm.B), fm)
    t = track(nominal.field_at, RIGIDITY, GZ[0], GZ[-1])
    resp = orbit_response(nominal, t)
    # the response is linear in the readings: the nominal readings give the nominal fits
    maps, nbr = _harmonic_maps(nominal.fit, resp.nodes[:50])
    coef = np.einsum("gbq,gq->gb", maps, fm.B[nbr].reshape(50, -1))
    np.testing.assert_allclose(coef, nominal.fit.coef[resp.nodes[:50]], atol=1e-12)
    rng = np.random.default_rng(3)
    for _ in range(2):
        b = field(coll, pts + rng.normal(0.0, 0.020, pts.shape))
        direction = resp.exit_tangent + resp.matrix @ (b - fm.B)[resp.nodes].ravel()
        predicted = np.arccos(direction[2] / np.linalg.norm(direction)) * 1e3
        redone = track(OrbitField(fit_harmonic(pts, b), FieldMap.from_arrays(pts, b)).field_at,
                       RIGIDITY, GZ[0], GZ[-1])  # fmt: skip
        change = redone["deflection_mrad"] - t["deflection_mrad"]
        first_order = predicted - t["deflection_mrad"]
        print(f"deflection change {change:.4e} mrad, first order {first_order:.4e} mrad")
        assert abs(change) > 1e-4  # the errors move the deflection
        assert first_order == pytest.approx(change, rel=0.20)
