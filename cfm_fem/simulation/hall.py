"""Hall-probe maps of the quadrupole on the reference bench, with concealed effects.

A reading: the probe goes where the HTM chain (:mod:`.bench`, Table II draws, vibration and
reading error) puts it; the magnet sits at its nominal place plus a survey error (20 um, 50
urad; more with ``magnet_misalignment``); each Hall element reads the exact field
(:mod:`.magnet`) at its own position (``sensor_offset`` moves one element; averaged over a
disc with ``sensor_volume_averaging``), turned into the
bench axes by the magnet's rotation; then the probe's own errors: component mixing
(``probe_misalignment``), planar Hall terms, the magnet's temperature coefficient, gains (S_HP,
uniform with 0.15 % std, per element) and offsets, and white noise (7 uT per component). The
probe orientation is calibrated in place: the constant rotation of the carriages is part of that
calibration, so the bench's angular errors act through their lever arms only.

Map coordinates (``x_cmd`` ...) are in the nominal magnet frame: axis travel = map point +
(75, 75, 400) mm (the magnet centre at mid-stroke).
"""

from __future__ import annotations

import numpy as np

from . import bench as B
from . import magnet
from .common import speeds_for, streams, temperature
from .scan import plan

__all__ = ["simulate", "GRIDS", "HALL_NOISE_UT", "map_to_travel"]

HALL_NOISE_UT = 7.0
SURVEY_STD = (20.0, 50.0)  # magnet placement after the survey: um, urad (1 sigma)
GAIN_HALF_WIDTH_PCT = 0.15 * np.sqrt(3.0)  # uniform S_HP with 0.15 % std
#: Map grid (magnet frame, mm): lines in x, y within half the bore radius (the good-field region;
#: nearer the blocks the field bends sharply at the ends), points along z through both ends.
GRIDS = {
    "full": (np.linspace(-4, 4, 6), np.linspace(-4, 4, 6), np.linspace(-300, 300, 26)),
    "small": (np.linspace(-4, 4, 3), np.linspace(-4, 4, 3), np.linspace(-300, 300, 25)),
}
REPS = {"full": 10, "small": 4}
TRAVEL_OFFSET_MM = B.MAGNET_ORIGIN_MM - B.TOOL_MM  # (75, 75, 400)


def map_to_travel(p_mm):
    """Axis travel that brings the probe to map points (nominal bench, magnet at rest), mm."""
    return np.asarray(p_mm, dtype=float) + TRAVEL_OFFSET_MM


def _magnet_pose(rng, extra: dict):
    """Magnet translation (mm) and rotation angles (rad): survey draw plus a concealed error."""
    t = rng.normal(0.0, SURVEY_STD[0], 3)
    r = rng.normal(0.0, SURVEY_STD[1], 3)
    names_t = ("magnet_dx", "magnet_dy", "magnet_dz")
    names_r = ("magnet_rot_x", "magnet_rot_y", "magnet_roll")
    t += [extra.get(k, 0.0) for k in names_t]
    r += [extra.get(k, 0.0) for k in names_r]
    truth = dict(zip(names_t + names_r, np.r_[t, r].tolist(), strict=True))
    return t * 1e-3, r * 1e-6, truth


def _sensitive_points(disc_mm, rot):
    """Points (magnet frame, mm, relative to the element's centre) and weights over which each
    Hall element averages the field: its centre alone, or a thin disc of diameter ``disc_mm``
    in the probe's x-y plane (the elements of a 3-axis chip normal to the magnet axis),
    sampled by Gauss-Legendre in radius (area weight) and 12 azimuths."""
    if not disc_mm:
        return [np.zeros(3)], [1.0]
    r, wr = np.polynomial.legendre.leggauss(4)
    r = 0.25 * disc_mm * (r + 1.0)
    wr = wr * r
    phi = 2.0 * np.pi * np.arange(12) / 12
    pts = [np.array([ri * np.cos(f), ri * np.sin(f), 0.0]) @ rot for ri in r for f in phi]
    w = np.repeat(wr / wr.sum(), len(phi)) / len(phi)
    return pts, list(w)


def simulate(seed: int, effects: dict | None = None, size: str = "full", n_reps=None):
    """One Hall map.

    Parameters
    ----------
    seed : int
    effects : dict, optional
        Concealed effects: name -> {param: value}, the diagnosis' names and units:
        ``probe_misalignment`` m_ij (mrad), ``sensor_offset`` d_i_j (um: element i moved along
        j), ``magnet_misalignment`` magnet_dx.. (um), magnet_rot_x.. (urad) beyond the survey,
        ``planar_hall`` k_i (1/T), ``hall_offset_gain`` offset_i (uT), gain_i (%, added to the
        S_HP draw), ``magnet_temperature`` beta (ppm/K), ``fringe_field_3d`` (no parameters:
        the recording is the same; the reference lacks the ends), ``sensor_volume_averaging``
        disc_mm (each element averages the field over a thin disc of that diameter in the
        probe's x-y plane).
    size : {'full', 'small'}
    n_reps : int, optional

    Returns
    -------
    columns : dict
        Column name -> ndarray in time order (CSV contract plus v_x, v_y, v_z).
    truth : dict
    """
    eff = {k: dict(v) for k, v in (effects or {}).items()}
    n_reps = REPS[size] if n_reps is None else int(n_reps)
    rng = streams(seed, ["bench", "vib", "noise", "survey", "gain", "temp"])
    gx, gy, gz = GRIDS[size]
    tx, ty, tz = (g + o for g, o in zip((gx, gy, gz), TRAVEL_OFFSET_MM, strict=True))
    scan = plan(tx, ty, tz, speeds_for(n_reps))
    q, n = scan.q, len(scan.point)
    errors = B.draw_errors(rng["bench"])
    travel = q + B.axis_noise(rng["vib"], n)
    probe = B.probe_position(travel, errors)
    t_m, r_m, reg = _magnet_pose(rng["survey"], eff.get("magnet_misalignment", {}))
    rot = B.rotation(*r_m)[0]
    local = (probe - B.MAGNET_ORIGIN_MM - t_m) @ rot  # R^T (P - O): magnet frame

    offs = eff.get("sensor_offset", {})
    disc = eff.get("sensor_volume_averaging", {}).get("disc_mm")
    sens, w_sens = _sensitive_points(disc, rot)
    b = np.empty((n, 3))
    seen = {}  # field at each distinct element position
    for i, c in enumerate("xyz"):  # each element at its own position
        d = tuple(offs.get(f"d_{c}_{j}", 0.0) * 1e-3 for j in "xyz")
        if d not in seen:
            at = local + np.array(d)
            seen[d] = sum(w * magnet.field(at + s) for s, w in zip(sens, w_sens, strict=True))
        b[:, i] = (seen[d] @ rot.T)[:, i]
    t_true, t_log = temperature(scan.t_s, rng["temp"])
    beta = eff.get("magnet_temperature", {}).get("beta", 0.0)
    b *= 1.0 + beta * 1e-6 * (t_true - t_true[0])[:, None]
    mix = eff.get("probe_misalignment", {})
    m = np.array([[mix.get(f"m_{i}{j}", 0.0) for j in "xyz"] for i in "xyz"]) * 1e-3
    k_ph = eff.get("planar_hall", {})
    k = np.array([k_ph.get(f"k_{c}", 0.0) for c in "xyz"])
    planar = k * np.roll(b, -1, axis=1) * np.roll(b, -2, axis=1)  # k_i B_j B_k
    b = b + b @ m.T + planar
    og = eff.get("hall_offset_gain", {})
    gains = rng["gain"].uniform(-GAIN_HALF_WIDTH_PCT, GAIN_HALF_WIDTH_PCT, 3)
    gains += [og.get(f"gain_{c}", 0.0) for c in "xyz"]
    offsets = np.array([og.get(f"offset_{c}", 0.0) for c in "xyz"])
    b = b * (1.0 + 1e-2 * gains) + 1e-6 * offsets
    b += rng["noise"].normal(0.0, HALL_NOISE_UT * 1e-6, (n, 3))

    p_map = q - TRAVEL_OFFSET_MM
    cols = {
        "point_id": scan.point, "rep": scan.rep,
        "x_cmd": p_map[:, 0], "y_cmd": p_map[:, 1], "z_cmd": p_map[:, 2],
        "Bx": b[:, 0], "By": b[:, 1], "Bz": b[:, 2],
    } | scan.columns(t_log)  # fmt: skip
    params = dict(errors) | reg
    params |= {f"gain_{c}": float(g) for c, g in zip("xyz", gains, strict=True)}
    params |= {f"offset_{c}": float(o) for c, o in zip("xyz", offsets, strict=True)}
    for name, block in eff.items():
        if name == "sensor_offset":  # diagnosis: each element from the elements' centroid
            for j in "xyz":
                d = {i: block.get(f"d_{i}_{j}", 0.0) for i in "xyz"}
                mean = sum(d.values()) / 3.0
                params |= {f"d_{i}_{j}": d[i] - mean for i in "xyz"}
        elif name == "sensor_volume_averaging":  # diagnosis: w_j = <d_j^2> / 2, 1e-3 mm^2
            w_xy = (0.5 * block["disc_mm"]) ** 2 / 8.0 * 1e3
            params |= {"dw_xy": 0.0, "dw_z": -w_xy}
        elif name not in ("magnet_misalignment", "hall_offset_gain"):
            params.update(block)
    if "fringe_field_3d" in eff:  # edges in the map frame: they carry the magnet's z offset
        z_in, z_out, lam = magnet.fringe_edges()
        dz = reg["magnet_dz"] * 1e-3
        params |= {"z_entry": z_in + dz, "z_exit": z_out + dz}
        params |= {"lambda": lam, "amplitude": 1.0}
        # each plane's profile values, at the plane's position in the magnet frame
        prof = magnet.profile_derivatives(gz - dz)
        for k, z in enumerate(gz):
            for name, row in zip(("g", "g'", "g''"), prof, strict=True):
                params[f"{name}@{z:g}"] = float(row[k])
    truth = {
        "kind": "hall",
        "seed": int(seed),
        "size": size,
        "n_reps": n_reps,
        "effects": eff,
        "params": params,
        "temperature_range_K": float(np.ptp(t_true)),
        "duration_h": float(scan.t_s[-1] / 3600.0),
        "gradient_T_m": magnet.GRADIENT_T_M,
    }
    return cols, truth
