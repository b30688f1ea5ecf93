"""U95 of the field quality in mode htm (`cfm_fem.models.quality.uncertainty`) against a
brute-force Monte Carlo written here from the bench file alone.

The reference reads the bundled bench TOML with `tomllib`, draws its 21 geometric errors,
vibration and reading delay with numpy, composes the HTM chain of the stack (4 x 4 matrices,
rotations Rz Ry Rx, squareness tilting the upper axis of each pair), moves the scan points by
the probe error, evaluates the exact field there and redoes the analysis with its own
least-squares harmonic fit (the centre plane's on the circle r = R_ref by `quality_circle_fit`).
The field: a quadrupole of four magnetic line charges of finite length (closed form, a
potential field with ends), mapped on a 1 mm grid.
"""

from __future__ import annotations

import tomllib
from importlib import resources

import numpy as np
import pytest
from quality_circle_fit import circle_operator

from cfm_fem.models.field import FieldMap
from cfm_fem.models.quality import VECTOR_NAMES
from cfm_fem.workflows.quality import run_quality

R_REF = 5.0  # mm
HALF_XY = 5.0  # mm, the map's grid spans +-HALF_XY
Z_PLANES = np.arange(-44.0, 44.01, 4.0)  # mm
R_CHARGE, L_CHARGE = 20.0, 40.0  # mm: radius and length of the four line charges
STRENGTH = 10.0  # T mm: field of a charge ~ STRENGTH / distance
# a normal quadrupole whose charge at 45 deg is 5 % stronger: its centre leaves the axis
CHARGES = [
    (np.pi / 4 + k * np.pi / 2, -((-1.0) ** k) * (1.05 if k == 0 else 1.0)) for k in range(4)
]


def line_charge_field(p):
    """B (..., 3) T of the four finite line charges at points p (..., 3) mm."""
    b = np.zeros(p.shape)
    z1, z2 = -L_CHARGE / 2, L_CHARGE / 2
    for phi, s in CHARGES:
        dx = p[..., 0] - R_CHARGE * np.cos(phi)
        dy = p[..., 1] - R_CHARGE * np.sin(phi)
        rho2 = dx * dx + dy * dy
        r1 = np.sqrt(rho2 + (p[..., 2] - z1) ** 2)
        r2 = np.sqrt(rho2 + (p[..., 2] - z2) ** 2)
        e_rho = ((p[..., 2] - z1) / r1 - (p[..., 2] - z2) / r2) / rho2  # over rho, times rho
        b[..., 0] += s * STRENGTH * e_rho * dx
        b[..., 1] += s * STRENGTH * e_rho * dy
        b[..., 2] += s * STRENGTH * (1.0 / r2 - 1.0 / r1)
    return b


def grid_map():
    g = np.arange(-HALF_XY, HALF_XY + 0.01, 1.0)
    x, y, z = np.meshgrid(g, g, Z_PLANES, indexing="ij")
    pts = np.column_stack([x.ravel(), y.ravel(), z.ravel()])
    return FieldMap.from_arrays(pts, line_charge_field(pts), source="line charges")


# --------------------------------------------------------------------------- the bench, by hand

UNIT = {"um": 1e-3, "nm": 1e-6, "mm": 1.0, "urad": 1e-6, "mrad": 1e-3, "rad": 1.0}


def read_bench_toml():
    text = resources.files("cfm_fem.data").joinpath("cfm_reference_bench.toml").read_text()
    return tomllib.loads(text)


def draw(spec, rng, m):
    """m values (mm or rad) of one error of the TOML."""
    f = UNIT[spec["unit"]]
    if spec["pdf"] == "uniform":
        return rng.uniform(spec["low"] * f, spec["high"] * f, m)
    if spec["pdf"] == "normal":
        return rng.normal(spec["mean"] * f, spec["std"] * f, m)
    raise AssertionError(f"pdf {spec['pdf']} not handled by the reference")


def rot_zyx(ex, ey, ez):
    """Rz(ez) Ry(ey) Rx(ex), each (m,): (m, 3, 3)."""

    def one(axis, a):
        r = np.zeros(a.shape + (3, 3))
        c, s = np.cos(a), np.sin(a)
        i, j = [(1, 2), (2, 0), (0, 1)][axis]
        r[..., axis, axis] = 1.0
        r[..., i, i], r[..., j, j] = c, c
        r[..., i, j], r[..., j, i] = -s, s
        return r

    return one(2, ez) @ one(1, ey) @ one(0, ex)


def probe_errors(toml, points_magnet, m, rng):
    """Probe error (m, n, 3) mm of m trials at scan points in the magnet frame."""
    frame, magnet = toml["frame"], toml["magnet"]
    assert magnet["rotation_deg"] == [0.0, 0.0, 0.0]  # magnet frame parallel to the bench's
    tool = np.array(frame["tool_offset_mm"])
    mounts = {a: np.array(toml["axes"][a]["mount_offset_mm"]) for a in "xyz"}
    q = points_magnet + np.array(magnet["translation_mm"]) - tool - sum(mounts.values())
    assert np.all((q >= 0) & (q <= [toml["axes"][a]["stroke_mm"] for a in "xyz"]))
    err = {a: {k: draw(v, rng, m) for k, v in toml["errors"][a].items()} for a in "xyz"}
    sq = {k: draw(v, rng, m) for k, v in toml["errors"]["squareness"].items()}
    # travel directions: the upper axis of each pair tilted towards +the lower one
    level = {a: i for i, a in enumerate(frame["stack"])}
    d = {a: np.zeros((m, 3)) + np.eye(3)["xyz".index(a)] for a in "xyz"}
    for a, b in ("xy", "xz", "yz"):
        alpha = sq[f"alpha_{a}{b}"]
        upper, lower = (a, b) if level[a] > level[b] else (b, a)
        d[upper][:, "xyz".index(lower)] += np.tan(alpha)
    for a in "xyz":
        d[a] /= np.linalg.norm(d[a], axis=1, keepdims=True)
    sig = np.hypot(toml["vibration"]["std_um"], toml["reading_delay"]["std_um"]) * 1e-3
    assert toml["reading_delay"]["model"] == "normal"
    n = len(points_magnet)
    v = np.broadcast_to(tool, (m, n, 3)).copy()
    for a in reversed(frame["stack"]):  # P = t1 + R1 (t2 + R2 (t3 + R3 tool))
        e = err[a]
        i = "xyz".index(a)
        travel = q[None, :, i] + rng.normal(0.0, sig, (m, n))
        t = (mounts[a] + np.stack([e["delta_x"], e["delta_y"], e["delta_z"]], 1))[:, None]
        t = t + travel[..., None] * d[a][:, None, :]
        r = rot_zyx(e["eps_x"], e["eps_y"], e["eps_z"])
        v = t + np.einsum("mij,mnj->mni", r, v)
    nominal = q + sum(mounts.values()) + tool
    return v - nominal[None]


# --------------------------------------------------------------------------- the analysis, by hand


def analyse(b, xy, n_orders):
    """Deviation columns of VECTOR_NAMES (without the main integral) of readings b (M, P k, 3)."""
    k = len(xy)
    w = (xy[:, 0] + 1j * xy[:, 1]) / HALF_XY
    pw = w[:, None] ** np.arange(n_orders)
    design = np.vstack([np.hstack([pw.real, -pw.imag]), np.hstack([pw.imag, pw.real])])
    pinv = np.linalg.pinv(design) * np.tile((R_REF / HALF_XY) ** np.arange(n_orders), 2)[:, None]
    b = b.reshape(len(b), len(Z_PLANES), k, 3)
    coef = np.concatenate([b[..., 1], b[..., 0]], axis=-1) @ pinv.T
    c = coef[..., :n_orders] + 1j * coef[..., n_orders:]  # (M, P, N) at R_REF
    wz = np.full(len(Z_PLANES), 4.0)
    wz[[0, -1]] = 2.0
    integ = np.einsum("mpn,p->mn", c, wz)
    main = integ[:, 1]
    rel = np.full((len(b), 15), np.nan + 0j)
    rel[:, :n_orders] = 1e4 * integ / np.abs(main)[:, None]
    roll = -np.angle(main) / 2 * 1e3
    mid = b[:, len(Z_PLANES) // 2]  # the plane z = 0: its quadrupole on the circle r = R_REF
    centre_plane = np.concatenate([mid[..., 1], mid[..., 0]], axis=-1) @ circle_operator(
        xy, HALF_XY, R_REF, 2
    )
    length = np.abs(main) / (centre_plane * np.exp(-1j * np.angle(main))).real
    # centre: root of F(u) = sum_n C_n u^(n-1), u = d / R_REF, by Newton from -C_1 / C_2
    u = -integ[:, 0] / main
    powers = np.arange(n_orders)
    for _ in range(20):
        f = np.sum(integ * u[:, None] ** powers, axis=1)
        df = np.sum(integ[:, 1:] * powers[1:] * u[:, None] ** (powers[1:] - 1), axis=1)
        u = u - f / df
    d = u * R_REF
    return np.column_stack([rel.real, rel.imag, d.real, d.imag, roll, length])


def u95(dev):
    low, high = np.quantile(dev, [0.025, 0.975], axis=0)
    return np.maximum(np.abs(low), np.abs(high))


def brute_force(trials, n_orders, seed, chunk=250):
    toml = read_bench_toml()
    g = np.arange(-HALF_XY, HALF_XY + 0.01, 1.0)
    x, y = np.meshgrid(g, g, indexing="ij")
    keep = np.hypot(x, y) <= HALF_XY + 1e-9
    xy = np.column_stack([x[keep], y[keep]])
    pts = np.concatenate([np.column_stack([xy, np.full(len(xy), z)]) for z in Z_PLANES])
    nominal = analyse(line_charge_field(pts)[None], xy, n_orders)[0]
    rng = np.random.default_rng(seed)
    out = []
    for t0 in range(0, trials, chunk):
        e = probe_errors(toml, pts, min(chunk, trials - t0), rng)
        out.append(analyse(line_charge_field(pts[None] + e), xy, n_orders) - nominal)
    return np.concatenate(out)


NAMES = VECTOR_NAMES[:-1]  # all but the main integral (the probe is exact here)


@pytest.mark.slow
def test_htm_u95_matches_brute_force():
    trials = 5000
    res = run_quality(grid_map(), R_REF, mode="htm", trials=trials, seed=5, probe="exact",
                      budget=False)  # fmt: skip
    assert res.plan.r_fit_mm == HALF_XY and res.main_order == 2 and res.mc.lost == 0
    n_orders = res.plan.n_orders
    ref = u95(brute_force(trials, n_orders, seed=11))
    tool = res.mc.u95[: len(NAMES)]
    fitted = [i for i, nm in enumerate(NAMES) if nm[0] not in "ab" or int(nm[1:]) <= n_orders]
    ratio = tool[fitted] / ref[fitted]
    bad = {
        NAMES[i]: round(float(r), 3)
        for i, r in zip(fitted, ratio, strict=True)
        if abs(r - 1) > 0.10
    }
    print(
        "U95 tool / brute force:",
        {NAMES[i]: round(float(r), 3) for i, r in zip(fitted, ratio, strict=True)},
    )
    assert not bad, bad
    # the bench's errors matter: the centre moves by micrometres
    assert tool[NAMES.index("centre_x")] > 1e-3
