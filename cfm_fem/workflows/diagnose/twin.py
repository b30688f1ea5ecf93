"""Digital twin: tracker recordings and Hall maps from a bench with known errors and effects.

The truth is generated with the exact models (full HTM chain with vibration and reading delay,
the field evaluated at the displaced sensor positions, a 3-D Enge fringe field, box averaging of
the sensitive volume), not with the linearised signatures of
:mod:`cfm_fem.workflows.diagnose.effects`, so the diagnosis is tested against physics, not
against its own equations. Parameters of concealed effects use the names and units of the
catalogue.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ...models.bench import ERROR_NAMES, Bench, MagnetPlacement
from ...models.kinematics.chain import probe_errors_for_bench
from ...models.kinematics.geometry import draw_error_sets
from ...models.recordings import Recording
from .fringe import _fringe_derivatives

__all__ = ["tracker_twin", "hall_twin", "scan_order", "default_hall_points", "fringe_edges"]

UM, URAD = 1e-3, 1e-6


def _reference_bench():
    from ...io.bench_toml import read_reference_bench

    return read_reference_bench()


def scan_order(n_points: int, n_reps: int, q):
    """Row order (rep, point) and approach direction per axis: even reps ascending, odd reps
    descending point index; dir_a = sign of the last non-zero move of axis a.

    Returns
    -------
    rep, pidx : ndarray, shape (n_reps * n_points,)
    dirs : ndarray, shape (n_reps * n_points, 3), int8
    """
    rep, pidx = [], []
    for r in range(n_reps):
        order = np.arange(n_points) if r % 2 == 0 else np.arange(n_points)[::-1]
        rep.append(np.full(n_points, r))
        pidx.append(order)
    rep, pidx = np.concatenate(rep), np.concatenate(pidx)
    qq = q[pidx]
    dirs = np.zeros((len(pidx), 3), dtype=np.int8)
    last = np.ones(3, dtype=np.int8)
    prev = qq[0] - 1.0
    for i in range(len(pidx)):
        mv = np.sign(qq[i] - prev).astype(np.int8)
        last = np.where(mv != 0, mv, last)
        dirs[i] = last
        prev = qq[i]
    return rep, pidx, dirs


def _scan_velocities(q, speed):
    """Velocity at acquisition (mm/s) of the twin's scan: ``speed`` along the largest axis
    move from the previous point (the first row: towards the next one)."""
    d = np.diff(q, axis=0)
    d = np.vstack([d[:1], d])
    axis = np.abs(d).argmax(1)
    vel = np.zeros_like(q)
    rows = np.arange(len(q))
    vel[rows, axis] = np.sign(d[rows, axis]) * speed
    return vel


def _pdg_displacement(bench: Bench, q, amps: dict):
    """Displacement of position-dependent geometric errors {'eps_y(z)_u2': urad, ...}, mm."""
    out = np.zeros((len(q), 3))
    for key, val in amps.items():
        name, order = key.rsplit("_u", 1)
        k = ERROR_NAMES.index(name)
        prof = [0.0] * (int(order) + 1)
        prof[int(order)] = 1.0
        errs = tuple(
            replace(e, profile=tuple(prof)) if j == k else e for j, e in enumerate(bench.errors)
        )
        b2 = replace(bench, errors=errs)
        p = np.zeros((1, 21))
        p[0, k] = val * (URAD if name.startswith("eps") else UM)
        out += probe_errors_for_bench(b2, p, q)[0]
    return out


def tracker_twin(
    seed: int = 0,
    effects: dict | None = None,
    *,
    n_reps: int = 10,
    bench: Bench | None = None,
    tracker_noise_um: float = 5.0,
    speeds=None,
    dt_s: float = 4.0,
    registration: bool = True,
    points=None,
):
    """A laser-tracker recording of the bench with concealed effects.

    Parameters
    ----------
    seed : int
    effects : dict, optional
        ``{effect name: {param: value}}`` in catalogue units, e.g.
        ``{"reversal": {"backlash_z": 12.0}}``, ``{"thermal_drift": {"drift_x": 3.0,
        "scale_drift_z": 2.0}}`` (um/h, ppm/h), ``{"reading_delay": {"tau": 2.0}}`` (ms),
        ``{"position_dependent_geometric": {"eps_y(z)_u2": 30.0}}`` (urad),
        ``{"arm_deflection": {"sag_x": 8.0}}`` (um), ``{"parameter_bias": {"delta_x(x)": 9.0}}``
        (um/urad: the true value, outside its PDF).
    n_reps : int
    bench : Bench, optional (default the reference bench)
    tracker_noise_um : float
        Std of the tracker reading per component.
    speeds : sequence of float, optional
        On-the-fly speeds (mm/s), repetition r at ``speeds[r % len]``; None: stop-and-go.
    dt_s : float
        Time per acquisition (2 s average + move).
    registration : bool
        Apply a random tracker-to-bench transform (20 um, 20 urad).
    points : ndarray (m, 3), optional
        Commanded points (default the bench grid, 936).

    Returns
    -------
    rec : Recording
    truth : dict
        ``errors`` (21, mm/rad), ``effects`` as given, ``registration``.
    """
    effects = {k: dict(v) for k, v in (effects or {}).items()}
    bench = _reference_bench() if bench is None else bench
    rng = np.random.default_rng(seed)
    q_pts = bench.grid_points() if points is None else np.asarray(points, float)
    m = len(q_pts)
    params = draw_error_sets(bench, 1, seed)[0]
    for name, val in effects.get("parameter_bias", {}).items():
        k = ERROR_NAMES.index(name)
        params[k] = val * (URAD if name.startswith(("eps", "alpha")) else UM)
    rep, pidx, dirs = scan_order(m, n_reps, q_pts)
    n = len(pidx)
    q = q_pts[pidx]
    t_s = np.arange(n) * dt_s
    speed = np.zeros(n) if speeds is None else np.asarray(speeds, float)[rep % len(speeds)]
    vel = _scan_velocities(q, speed)
    dq = rng.normal(size=(n, 3)) * bench.noise_std_mm()
    if "reading_delay" in effects:
        dq = dq + effects["reading_delay"]["tau"] * 1e-3 * vel
    E = probe_errors_for_bench(bench, params[None], q, dq[None])[0]
    pdg = effects.get("position_dependent_geometric")
    if pdg:
        E = E + _pdg_displacement(bench, q, pdg)
    if "reversal" in effects:
        for a, c in enumerate("xyz"):
            E[:, a] += 0.5 * effects["reversal"].get(f"backlash_{c}", 0.0) * UM * dirs[:, a]
    if "thermal_drift" in effects:
        d = effects["thermal_drift"]
        th = t_s / 3600.0
        qc = q - q_pts.mean(0)
        for a, c in enumerate("xyz"):
            E[:, a] += th * (
                d.get(f"drift_{c}", 0.0) * UM + d.get(f"scale_drift_{c}", 0.0) * 1e-6 * qc[:, a]
            )
    if "arm_deflection" in effects:
        u = q / bench.strokes_mm
        d = effects["arm_deflection"]
        s = lambda v: 16 * v**2 * (1 - v) ** 2  # noqa: E731
        E[:, 1] -= (d.get("sag_x", 0.0) * s(u[:, 0]) + d.get("sag_z", 0.0) * s(u[:, 2])) * UM
    actual = bench.nominal_probe_mm(q) + E
    reg = {"t_mm": np.zeros(3), "rot_rad": np.zeros(3)}
    if registration:
        from ...models.rotations import rotation_zyx

        reg = {"t_mm": rng.normal(0, 0.02, 3), "rot_rad": rng.normal(0, 20e-6, 3)}
        c = bench.nominal_probe_mm(q_pts).mean(0)
        R = rotation_zyx(*reg["rot_rad"])
        actual = (actual - c) @ R.T + c + reg["t_mm"]
    meas = actual + rng.normal(size=(n, 3)) * tracker_noise_um * UM
    rec = Recording(
        kind="tracker",
        point_id=pidx,
        rep=rep,
        cmd=q,
        meas=meas,
        t_s=t_s,
        dir=dirs,
        speed=speed,
        vel=vel,
        source=f"twin(seed={seed}, effects={effects})",
    )
    return rec, {"errors": params, "effects": effects, "registration": reg}


def default_hall_points():
    """Magnet-frame map: x in [-6, 6] (9), y in [-6, 6] (8), z in [-300, 300] (13) mm: 936."""
    gx, gy, gz = np.linspace(-6, 6, 9), np.linspace(-6, 6, 8), np.linspace(-300, 300, 13)
    return np.stack(np.meshgrid(gx, gy, gz, indexing="ij"), -1).reshape(-1, 3)


def _potential(mp, pts):
    """Scalar potential V with (Bx, By) = grad V of a 2-D multipole (T mm)."""
    c = mp.normal + 1j * mp.skew
    w = (pts[:, 0] + 1j * pts[:, 1]) / mp.r_ref
    F = sum(c[k] * mp.r_ref / (k + 1) * w ** (k + 1) for k in range(c.size))
    return F.imag


def _potential_next_order(mp, pts):
    """W with lap_perp W = V and its gradient (T mm^3, T mm^2): the next order of the 3-D
    potential g V - g'' W of soft ends. A term of degree n of V gives r^2 V_n / (4 (n + 1)).

    Returns
    -------
    ndarray, shape (n, 3)
        W, dW/dx, dW/dy.
    """
    c = mp.normal + 1j * mp.skew
    w = (pts[:, 0] + 1j * pts[:, 1]) / mp.r_ref
    u = sum(c[k] * mp.r_ref / ((k + 1) * (k + 2)) * w ** (k + 1) for k in range(c.size))
    du = sum(c[k] / (k + 2) * w**k for k in range(c.size))  # dU/dx = Im, dU/dy = Re
    r2 = pts[:, 0] ** 2 + pts[:, 1] ** 2
    out = np.empty((len(pts), 3))
    out[:, 0] = 0.25 * r2 * u.imag
    out[:, 1] = 0.5 * pts[:, 0] * u.imag + 0.25 * r2 * du.imag
    out[:, 2] = 0.5 * pts[:, 1] * u.imag + 0.25 * r2 * du.real
    return out


def fringe_edges(params: dict) -> tuple[float, float, float]:
    """(z_entry, z_exit, lambda) in mm, magnet body frame, of the twin's ``fringe_field_3d``:
    catalogue names ``z_entry``, ``z_exit``, ``lambda`` or a centred magnet ``half_length_mm``,
    ``lambda_mm``."""
    lam = float(params.get("lambda", params.get("lambda_mm")))
    if "half_length_mm" in params:
        L = float(params["half_length_mm"])
        return -L, L, lam
    return float(params["z_entry"]), float(params["z_exit"]), lam


def hall_twin(
    seed: int = 0,
    effects: dict | None = None,
    *,
    n_reps: int = 10,
    multipole=None,
    bench: Bench | None = None,
    noise_units: float = 1.0,
    points=None,
    dt_s: float = 4.0,
    reg_std_mm: float = 0.05,
    reg_std_rad: float = 1e-4,
):
    """A Hall map of a 2-D multipole measured on the bench, with concealed effects.

    Parameters
    ----------
    effects : dict, optional
        ``probe_misalignment`` {m_xy, ...: mrad}, ``sensor_offset`` {d_x_y, ...: um},
        ``magnet_misalignment`` {magnet_dx, magnet_dy, magnet_dz: um, magnet_roll,
        magnet_rot_x, magnet_rot_y: urad} (on top of the survey-sized registration),
        ``planar_hall`` {k_x, k_y, k_z: 1/T}, ``hall_offset_gain`` {offset_x: uT, gain_x: %},
        ``magnet_temperature`` {beta: ppm/K}, ``fringe_field_3d`` {z_entry, z_exit,
        lambda: mm} (or a centred {half_length_mm, lambda_mm}): soft ends of the Enge/Fermi
        profile :func:`~cfm_fem.workflows.diagnose.fringe.fringe_profile`, the field the 3-D
        potential g V - g'' W implies (edges in the magnet body frame: the fitted edges also
        carry the magnet's z offset), ``sensor_volume_averaging``
        {a_x, a_y, a_z: mm side of the averaging box}.
    noise_units : float
        Std of the Hall noise per component in units of 1e-4 B_ref.

    Returns
    -------
    rec : Recording
    truth : dict
    context : dict
        ``multipole``, ``bench`` (with the magnet placement used).
    """
    from ...io.harmonics import read_qfdp4
    from ...models.rotations import rotation_zyx

    effects = {k: dict(v) for k, v in (effects or {}).items()}
    mp = read_qfdp4() if multipole is None else multipole
    bench = _reference_bench() if bench is None else bench
    t = np.array([75.0, 75.0, 400.0]) + bench.mounts_mm.sum(0) + bench.tool_offset_mm
    bench = replace(bench, magnet=MagnetPlacement(np.zeros(3), t))
    rng = np.random.default_rng(seed)
    pts = default_hall_points() if points is None else np.asarray(points, float)
    m = len(pts)
    q_pts = bench.axis_positions_for(pts)
    params = draw_error_sets(bench, 1, seed)[0]
    rep, pidx, dirs = scan_order(m, n_reps, q_pts)
    n = len(pidx)
    p = pts[pidx]
    q = q_pts[pidx]
    t_s = np.arange(n) * dt_s
    th = t_s / 3600.0
    temp = 22.0 + 0.4 * np.sin(2 * np.pi * th / 5.0) + 0.05 * th + rng.normal(0, 0.01, n)
    dq = rng.normal(size=(n, 3)) * bench.noise_std_mm()
    E = probe_errors_for_bench(bench, params[None], q, dq[None])[0]
    p_true = p + E @ bench.bench_to_magnet_rotation().T
    # magnet registration: survey-sized + concealed misalignment
    mm = effects.get("magnet_misalignment", {})
    tr = rng.normal(0, reg_std_mm, 3) + np.array([mm.get(f"magnet_d{c}", 0.0) for c in "xyz"]) * UM
    rot = (
        rng.normal(0, reg_std_rad, 3)
        + np.array([mm.get(k, 0.0) for k in ("magnet_rot_x", "magnet_rot_y", "magnet_roll")]) * URAD
    )
    R = rotation_zyx(*rot)
    fr = effects.get("fringe_field_3d")
    if fr:
        fr_edges = fringe_edges(fr)

    def field(x):
        """True field at magnet-frame points x (n, 3) for the displaced, rotated magnet."""
        xl = (x - tr) @ R  # R^T (x - t)
        b = mp.field(xl)
        if fr:  # the gradient of g V - g'' W, to the order in the ends' curvature the model has
            g, dg, d2g, d3g = _fringe_derivatives(xl[:, 2], *fr_edges)
            w3 = _potential_next_order(mp, xl)
            b = b * g[:, None]
            b[:, :2] -= d2g[:, None] * w3[:, 1:]
            b[:, 2] = dg * _potential(mp, xl) - d3g * w3[:, 0]
        return b @ R.T

    va = effects.get("sensor_volume_averaging")
    so = effects.get("sensor_offset", {})
    B = np.empty((n, 3))
    for i, c in enumerate("xyz"):
        d = np.array([so.get(f"d_{c}_{k}", 0.0) for k in "xyz"]) * UM
        xi = p_true + d
        if va:
            nodes, wts = np.polynomial.legendre.leggauss(3)
            acc = np.zeros(n)
            for a, wa in zip(nodes, wts, strict=True):
                for b_, wb in zip(nodes, wts, strict=True):
                    for c_, wc in zip(nodes, wts, strict=True):
                        off = 0.5 * np.array(
                            [a * va.get("a_x", 0), b_ * va.get("a_y", 0), c_ * va.get("a_z", 0)]
                        )
                        acc += wa * wb * wc / 8.0 * field(xi + off)[:, i]
            B[:, i] = acc
        else:
            B[:, i] = field(xi)[:, i]
    if "magnet_temperature" in effects:
        B *= (1 + effects["magnet_temperature"]["beta"] * 1e-6 * (temp - temp[0]))[:, None]
    Bt = B.copy()
    pm = effects.get("probe_misalignment", {})
    for i, ci in enumerate("xyz"):
        for j, cj in enumerate("xyz"):
            if i != j:
                B[:, i] += pm.get(f"m_{ci}{cj}", 0.0) * 1e-3 * Bt[:, j]
    ph = effects.get("planar_hall", {})
    for i, ci in enumerate("xyz"):
        j, k = [a for a in range(3) if a != i]
        B[:, i] += ph.get(f"k_{ci}", 0.0) * Bt[:, j] * Bt[:, k]
    gains = rng.uniform(-1, 1, 3) * 0.15 * np.sqrt(3)  # %: S_HP, uniform with std 0.15 %
    hog = effects.get("hall_offset_gain", {})
    for i, c in enumerate("xyz"):
        g = gains[i] + hog.get(f"gain_{c}", 0.0)
        B[:, i] = B[:, i] * (1 + g * 1e-2) + hog.get(f"offset_{c}", 0.0) * 1e-6
    B += rng.normal(size=(n, 3)) * noise_units * 1e-4 * mp.b_ref
    rec = Recording(
        kind="hall",
        point_id=pidx,
        rep=rep,
        cmd=p,
        B=B,
        t_s=t_s,
        dir=dirs,
        speed=np.zeros(n),
        temp_C=temp,
        source=f"hall twin(seed={seed}, effects={effects})",
    )
    truth = {
        "errors": params,
        "effects": effects,
        "gains_pct": gains,
        "registration": {"t_mm": tr, "rot_rad": rot},
    }
    return rec, truth, {"multipole": mp, "bench": bench}
