"""Hall-probe maps of a family magnet on a family bench, with concealed effects, and the
linearised signatures of those effects on the map.

The physics is that of :mod:`.hall` with the magnet (:mod:`.magnets`), bench (:mod:`.benches`)
and scan (:mod:`.scans`) of a drawn configuration: the probe goes where the bench's HTM chain
puts it; the magnet sits at its nominal place plus the survey draw (the bench file's survey std)
and any concealed ``magnet_misalignment``; each Hall element reads the exact field at its own
position (``sensor_offset``; averaged over a disc with ``sensor_volume_averaging``), turned into
the bench axes by the magnet's rotation; then mixing, planar Hall terms, the temperature
coefficient, gains and offsets, and white noise of the configuration's level.
"""

from __future__ import annotations

import numpy as np

from . import bench as B
from . import benches, magnets, scans
from .common import reading_streams, temperature

__all__ = [
    "context",
    "forward",
    "truth_params",
    "signatures",
    "magnet_pose",
    "POSE",
    "PARAMS",
    "noise_std",
]

POSE = ("magnet_dx", "magnet_dy", "magnet_dz", "magnet_rot_x", "magnet_rot_y", "magnet_roll")
GAIN_HALF_WIDTH_PCT = 0.15 * np.sqrt(3.0)
#: Parameters of each Hall effect (diagnosis names and units).
PARAMS = {
    "probe_misalignment": tuple(f"m_{i}{j}" for i in "xyz" for j in "xyz" if i != j),
    "sensor_offset": tuple(f"d_{i}_{j}" for i in "xyz" for j in "xyz"),
    "magnet_misalignment": POSE,
    "planar_hall": ("k_x", "k_y", "k_z"),
    "hall_offset_gain": ("offset_x", "offset_y", "offset_z", "gain_x", "gain_y", "gain_z"),
    "magnet_temperature": ("beta",),
    "sensor_volume_averaging": ("disc_mm",),
}


def context(cfg: dict) -> dict:
    """The scan and every random draw of a Hall configuration (from ``cfg['seed']``)."""
    bench = cfg["bench"]
    scan = scans.build(cfg["scan"], benches.travel_offset(bench))
    n = len(scan.point)
    rng = reading_streams(cfg, ["vib", "noise", "survey", "gain", "temp"])
    t_um, r_urad = bench["survey_std"]
    t_true, t_log = temperature(scan.t_s, rng["temp"])
    return {
        "scan": scan,
        "vib": benches.axis_noise(bench, rng["vib"], n),
        "noise": rng["noise"].normal(0.0, cfg["noise_uT"] * 1e-6, (n, 3)),
        "survey": np.r_[rng["survey"].normal(0.0, t_um, 3), rng["survey"].normal(0.0, r_urad, 3)],
        "gains": rng["gain"].uniform(-GAIN_HALF_WIDTH_PCT, GAIN_HALF_WIDTH_PCT, 3),
        "t_true": t_true,
        "t_log": t_log,
    }


def _disc(disc_mm, rot):
    """Points (magnet frame, mm, about the element) and weights of a thin disc of diameter
    ``disc_mm`` in the probe's x-y plane: Gauss-Legendre in radius (2 nodes, area weight) and 6
    azimuths."""
    if not disc_mm:
        return [np.zeros(3)], [1.0]
    r, wr = np.polynomial.legendre.leggauss(2)
    r = 0.25 * disc_mm * (r + 1.0)
    wr = wr * r
    phi = 2.0 * np.pi * np.arange(6) / 6
    pts = [np.array([ri * np.cos(f), ri * np.sin(f), 0.0]) @ rot for ri in r for f in phi]
    return pts, list(np.repeat(wr / wr.sum(), len(phi)) / len(phi))


def magnet_pose(ctx: dict, effects: dict) -> np.ndarray:
    """The magnet's pose as recorded: the survey draw plus any concealed ``magnet_misalignment``
    (the :data:`POSE` parameters: um, urad; shape (6,))."""
    mis = effects.get("magnet_misalignment", {})
    return ctx["survey"] + np.array([mis.get(k, 0.0) for k in POSE])


def element_positions(cfg, ctx, effects, noisy=True, errors=None):
    """Probe positions in the magnet frame and the magnet rotation.

    The magnet is at its recorded pose (:func:`magnet_pose`) whether ``noisy`` or not;
    ``noisy=False`` drops the axes' vibration and reading error alone.

    Returns
    -------
    local : ndarray, shape (n, 3), mm
    rot : ndarray, shape (3, 3)
        Magnet frame to bench axes.
    """
    bench = cfg["bench"]
    scan = ctx["scan"]
    travel = scan.q + (ctx["vib"] if noisy else 0.0)
    probe = benches.probe_position(travel, bench["errors"] if errors is None else errors, bench)
    pose = magnet_pose(ctx, effects)
    rot = B.rotation(*(pose[3:] * 1e-6))[0]
    local = (probe - np.asarray(bench["magnet_mm"]) - pose[:3] * 1e-3) @ rot
    return local, rot


def forward(cfg: dict, ctx: dict, effects: dict, noisy: bool = True) -> np.ndarray:
    """The readings (T, shape (n, 3)) of a configuration with concealed ``effects``.

    ``noisy=False``: the recorded configuration (the magnet at its surveyed pose, the bench's
    errors, the gains and temperatures of the recording) without what is drawn afresh at each
    reading, the axes' vibration and the white noise: the readings the signatures, the field
    gradient and the noise are taken about."""
    spec = cfg["magnet"]
    local, rot = element_positions(cfg, ctx, effects, noisy)
    offs = effects.get("sensor_offset", {})
    sens, w_sens = _disc(effects.get("sensor_volume_averaging", {}).get("disc_mm"), rot)
    b = np.empty_like(local)
    seen = {}
    for i, c in enumerate("xyz"):
        d = tuple(offs.get(f"d_{c}_{j}", 0.0) * 1e-3 for j in "xyz")
        if d not in seen:
            at = local + np.array(d)
            pts = np.concatenate([at + s for s in sens])
            f = magnets.field(spec, pts).reshape(len(sens), len(at), 3)
            seen[d] = np.tensordot(np.asarray(w_sens), f, axes=1)
        b[:, i] = (seen[d] @ rot.T)[:, i]
    return _probe(cfg, ctx, effects, b, noisy)


def _probe(cfg, ctx, effects, b, noisy):
    """The probe's own errors on the true field ``b`` (bench axes, T)."""
    dt = ctx["t_true"] - ctx["t_true"][0]
    b = b * (1.0 + effects.get("magnet_temperature", {}).get("beta", 0.0) * 1e-6 * dt)[:, None]
    mix = effects.get("probe_misalignment", {})
    m = np.array([[mix.get(f"m_{i}{j}", 0.0) for j in "xyz"] for i in "xyz"]) * 1e-3
    k_ph = effects.get("planar_hall", {})
    k = np.array([k_ph.get(f"k_{c}", 0.0) for c in "xyz"])
    b = b + b @ m.T + k * np.roll(b, -1, axis=1) * np.roll(b, -2, axis=1)
    og = effects.get("hall_offset_gain", {})
    gains = ctx["gains"] + [og.get(f"gain_{c}", 0.0) for c in "xyz"]
    offsets = np.array([og.get(f"offset_{c}", 0.0) for c in "xyz"])
    b = b * (1.0 + 1e-2 * gains) + 1e-6 * offsets
    return b + (ctx["noise"] if noisy else 0.0)


def noise_std(cfg: dict, ctx: dict, grad: np.ndarray) -> np.ndarray:
    """Std of each reading (T, shape (n, 3)): probe noise plus the axes' vibration and reading
    error seen through the field gradient ``grad`` (T/mm, shape (n, 3, 3))."""
    s_pos = np.hypot(cfg["bench"]["vibration_um"], cfg["bench"]["reading_um"]) * 1e-3
    return np.sqrt((cfg["noise_uT"] * 1e-6) ** 2 + s_pos**2 * (grad**2).sum(-1))


def gradient(cfg, ctx, h_mm: float = 0.05) -> np.ndarray:
    """dB_i/dx_j (T/mm, shape (n, 3, 3)), field and displacement along the bench axes, at the
    noiseless reading positions with the magnet at its recorded pose (the configuration the
    vibration and the bench errors move the probe about)."""
    local, rot = element_positions(cfg, ctx, {}, noisy=False)
    g = np.empty((len(local), 3, 3))
    for j in range(3):
        e = np.zeros(3)
        e[j] = h_mm
        g[:, :, j] = (
            magnets.field(cfg["magnet"], local + e) - magnets.field(cfg["magnet"], local - e)
        ) / (2 * h_mm)
    # B_bench = R B(R^T (p - o)): the magnet-frame gradient turned into the bench axes
    return np.einsum("ik,nkl,jl->nij", rot, g, rot)


def signatures(cfg: dict, ctx: dict, names, base=None, grad=None) -> dict:
    """Linearised signatures: for each (effect, param) in ``names`` the change of the noiseless
    readings per unit of the parameter (T per display unit, shape (n, 3)).

    Every signature is taken about the recorded configuration (``base``, the noiseless readings
    of :func:`forward`, and ``grad``, :func:`gradient`): a pose step is added to the surveyed
    pose, the probe's errors act on the field at the recorded pose. Effect ``"pose"``: the
    registration (the 6 :data:`POSE` parameters); ``"gain"``: the calibrated gains (%);
    ``"bench"``: one of the 21 bench errors, through the field gradient; ``sensor_offset``: an
    element moved along the magnet's axes, through the field gradient."""
    base = forward(cfg, ctx, {}, noisy=False) if base is None else base
    out = {}
    for eff, p in names:
        if eff in ("pose", "magnet_misalignment"):
            step = 1.0 if p.startswith("magnet_d") else 10.0
            plus = forward(cfg, ctx, {"magnet_misalignment": {p: step}}, noisy=False)
            out[eff, p] = (plus - base) / step
        elif eff == "gain":
            out[eff, p] = base * 1e-2 * np.eye(3)["xyz".index(p[-1])]
        elif eff == "bench":
            e = dict(cfg["bench"]["errors"])
            e[p] = e[p] + 1.0
            bench = cfg["bench"]
            dp = benches.probe_position(ctx["scan"].q, e, bench) - benches.probe_position(
                ctx["scan"].q, bench["errors"], bench
            )
            out[eff, p] = np.einsum("nij,nj->ni", grad, dp)
        elif eff == "sensor_offset":
            i, j = "xyz".index(p[2]), "xyz".index(p[4])
            s = np.zeros_like(base)
            s[:, i] = (grad @ _rotation(ctx))[:, i, j] * 1e-3
            out[eff, p] = s
        elif eff == "sensor_volume_averaging":  # per unit of disc_mm^2 at 2 mm
            plus = forward(cfg, ctx, {eff: {"disc_mm": 2.0}}, noisy=False)
            out[eff, p] = (plus - base) / 4.0
        else:
            step = {
                "probe_misalignment": 1.0,
                "planar_hall": 1e-3,
                "hall_offset_gain": 1.0,
                "magnet_temperature": 100.0,
            }[eff]
            plus = _probe(cfg, ctx, {eff: {p: step}}, _raw(cfg, ctx, base), noisy=False)
            out[eff, p] = (plus - base) / step
    return out


def _rotation(ctx):
    """The magnet's recorded rotation (magnet frame to bench axes), shape (3, 3)."""
    return B.rotation(*(magnet_pose(ctx, {})[3:] * 1e-6))[0]


def _raw(cfg, ctx, base):
    """The true field behind noiseless readings ``base`` (the calibrated gains undone)."""
    return base / (1.0 + 1e-2 * ctx["gains"])


def truth_params(cfg: dict, ctx: dict, effects: dict) -> dict:
    """The parameters a correct diagnosis reports (diagnosis conventions)."""
    params = dict(cfg["bench"]["errors"])
    params |= dict(zip(POSE, magnet_pose(ctx, effects).tolist(), strict=True))
    og = effects.get("hall_offset_gain", {})
    for c, g in zip("xyz", ctx["gains"], strict=True):
        params[f"gain_{c}"] = float(g + og.get(f"gain_{c}", 0.0))
        params[f"offset_{c}"] = float(og.get(f"offset_{c}", 0.0))
    for name, block in effects.items():
        if name == "sensor_offset":
            for j in "xyz":
                d = {i: block.get(f"d_{i}_{j}", 0.0) for i in "xyz"}
                mean = sum(d.values()) / 3.0
                params |= {f"d_{i}_{j}": d[i] - mean for i in "xyz"}
        elif name == "sensor_volume_averaging":
            params |= {"dw_xy": 0.0, "dw_z": -((0.5 * block["disc_mm"]) ** 2) / 8.0 * 1e3}
        elif name == "fringe_field_3d":
            spec = cfg["magnet"]
            z_in, z_out, lam = magnets.fringe_edges(spec)
            dz = params["magnet_dz"] * 1e-3
            params |= {"z_entry": z_in + dz, "z_exit": z_out + dz, "lambda": lam, "amplitude": 1.0}
            gz = np.unique(np.round(scans.map_points(cfg["scan"])[:, 2], 6))
            prof = magnets.profile_derivatives(spec, gz - dz)
            for k, z in enumerate(gz):
                for nm, row in zip(("g", "g'", "g''"), prof, strict=True):
                    params[f"{nm}@{z:g}"] = float(row[k])
        elif name not in ("magnet_misalignment", "hall_offset_gain"):
            params.update(block)
    return params
