"""A randomized family of simulated recordings: every configuration drawn from its seed.

A case of the family is a Hall map or a laser-tracker recording of a drawn configuration:

* the magnet (Hall maps): a dipole, quadrupole, sextupole or octupole (a permanent-magnet ring
  of blocks or current-driven saddle loops) or a solenoid, of drawn bore, length and strength,
  scanned through both ends, through one, or in its body only (:mod:`.magnets`);
* the bench: the carriages stacked in any order, with drawn strokes, tool offset, vibration,
  Table II widths and error draws, survey uncertainty; its bench file (:mod:`.benches`);
* the scan: a grid, on-the-fly lines at several speeds, circles at a radius or a sparse map,
  3 to 10 repetitions (:mod:`.scans`);
* the noise: Hall probe 0.5 to 20 uT, tracker 1 to 8 um (log-uniform);
* the reference given to a Hall diagnosis: the exact field on a grid through the map's points,
  an FEM-like coarser grid, or 2-D harmonics (body-only scans, and the soft-ends case)
  (:mod:`.family_reference`);
* the role: a null (nothing concealed) or one catalogued effect whose size is drawn so that its
  joint significance against its neighbours and nuisances is a drawn 5 to 8 sigma
  (:mod:`.significance`), each reading whitened by its own std and, against a coarse map, by
  the map's error where a cubic reader reads it between its nodes, shared by the point's
  repetitions (:func:`.family_reference.reading_error`).

A size beyond :data:`CAPS` (:data:`PARAM_CAPS`) is drawn again along another direction, then
for another effect; for an effect of :data:`PHYSICAL`, whose cap is the hardware's physical
range (the magnet's temperature coefficient, |beta| <= 2000 ppm/K; the Hall elements' offsets,
|d| <= 1 mm each; the planar Hall coefficients, |k| <= 0.05 /T; the averaging disc, at most
2 mm across; the tracker's thermal drift, its scale drifts |scale_drift| <= 25 ppm/K and its
offset drifts |drift| <= 50 um/K), the case draws another configuration for the same effect
instead, from a seed derived from the case's seed and the attempt (:func:`drawn_case`;
:func:`written_config` gives the configuration a case is written with).

Every label (``strata``), the whole configuration (``config["seed"]``: the seed it was drawn
from), the number of configurations drawn (``attempts``) and the drawn significance
(``sigma_drawn``; ``sigma_noise_only`` without the reference's error and
``reference_error_rms``, uT) go into the truth file, so a case can be replayed from its seed
and role.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from . import benches, magnets, output, scans, significance
from . import family_hall as FH
from . import family_reference as FR
from . import family_tracker as FT

__all__ = [
    "draw_config",
    "drawn_case",
    "written_config",
    "write_family_case",
    "HALL_EFFECTS",
    "TRACKER_EFFECTS",
    "SIGMA_RANGE",
]

SIGMA_RANGE = (5.0, 8.0)
HALL_EFFECTS = (
    "probe_misalignment",
    "sensor_offset",
    "magnet_misalignment",
    "planar_hall",
    "hall_offset_gain",
    "magnet_temperature",
    "fringe_field_3d",
    "sensor_volume_averaging",
)
TRACKER_EFFECTS = (
    "thermal_drift",
    "reversal",
    "reading_delay",
    "position_dependent_geometric",
    "arm_deflection",
    "parameter_bias",
    "step_event",
)
#: Largest plausible size of a parameter (display units); a draw beyond is redrawn (another
#: direction, then another effect; for the effects of :data:`PHYSICAL`, another configuration).
#: :data:`PARAM_CAPS` narrows it for some of an effect's parameters.
CAPS = {
    "probe_misalignment": 50.0,
    # d_i_j, um: a Hall sensor's three elements sit within a millimetre of each other
    "sensor_offset": 1000.0,
    "magnet_misalignment": 3000.0,
    # k_i, 1/T: a Hall element's planar Hall voltage stays within a few % of its Hall voltage
    # at 1 T in the element's plane
    "planar_hall": 0.05,
    "hall_offset_gain": 1000.0,
    # beta, ppm/K: ferrite's -0.19 %/K is the largest remanence coefficient of common magnet
    # materials (NdFeB about -0.12 %/K, SmCo -0.03 %/K)
    "magnet_temperature": 2000.0,
    # disc_mm, mm: the diameter of the disc a Hall element averages the field over; an
    # element's active area is well under a millimetre across, 2 mm with its package
    "sensor_volume_averaging": 2.0,
    # drift_i, um/K (scale_drift_i: PARAM_CAPS)
    "thermal_drift": 50.0,
    "reversal": 100.0,
    "reading_delay": 50.0,
    "position_dependent_geometric": 1000.0,
    "arm_deflection": 200.0,
    "parameter_bias": 2000.0,
    "step_event": 200.0,
}
#: Caps of single parameters (display units), within their effect's :data:`CAPS`.
PARAM_CAPS = {
    # scale_drift_i, ppm/K: an axis's scale grows with temperature as its scale or frame
    # expands, at most aluminium's 23 ppm/K (steel 11.5, glass scales near 0-8)
    **{f"scale_drift_{c}": 25.0 for c in "xyz"},
}
#: Parameters an effect is drawn along (one or two of them at random).
DRAWN = {
    "hall_offset_gain": ("offset_x", "offset_y", "offset_z"),
    "sensor_offset": tuple(f"d_{i}_{j}" for i in "xy" for j in "xyz"),
    "arm_deflection": ("sag_x", "sag_z"),
    "reversal": FT.PARAMS["reversal"],
}
ONE_PARAM = (
    "magnet_misalignment",
    "parameter_bias",
    "position_dependent_geometric",
    "sensor_volume_averaging",
    "magnet_temperature",
    "reading_delay",
)
#: Effects whose cap is a physical range of the hardware: a configuration on which the drawn
#: significance needs more is not a physical one, so the case draws another configuration for
#: the same effect (:func:`_attempt_seed`) rather than conceal another effect.
PHYSICAL = (
    "magnet_temperature",
    "sensor_offset",
    "planar_hall",
    "sensor_volume_averaging",
    "thermal_drift",
)
#: Configurations a case draws at most for an effect of :data:`PHYSICAL`; the last one then
#: conceals the next effect of its fallback list that fits within the caps.
MAX_ATTEMPTS = 20
POSITIVE = ("reversal", "reading_delay", "arm_deflection", "sensor_volume_averaging")
PRIOR_RELEASE = ("magnet_misalignment", "parameter_bias")


def _rng(seed: int, part: int) -> np.random.Generator:
    """The configuration's own streams (apart from the recording's draws of ``streams``)."""
    return np.random.default_rng(np.random.SeedSequence([20261129, int(seed), part]))


def _regime(kind: str, level: float) -> str:
    lo, hi = (2.0, 7.0) if kind == "hall" else (3.0, 5.0)
    return "low" if level < lo else ("high" if level > hi else "mid")


def _magnet(rng) -> dict:
    order = int(rng.integers(0, 5))
    if order == 0:
        return {
            "source": "solenoid",
            "order": 0,
            "bore_mm": float(rng.uniform(15, 40)),
            "length_mm": float(rng.uniform(150, 300)),
            "scale_T": float(rng.uniform(0.05, 1.0)),
        }
    src = "pm" if rng.uniform() < 0.6 else "coil"
    bore = float(rng.uniform(8, 20) if src == "pm" else rng.uniform(10, 30))
    scale = float(rng.uniform(0.2, 1.0) if src == "pm" else rng.uniform(0.05, 0.5))
    return {
        "source": src,
        "order": order,
        "bore_mm": bore,
        "length_mm": float(rng.uniform(100, 300)),
        "scale_T": scale,
    }


def _z_range(rng, spec, ends):
    half, r = 0.5 * spec["length_mm"], spec["bore_mm"]
    k = float(rng.uniform(3.0, 6.0))
    if ends == "both":
        return (-half - k * r, half + k * r)
    if ends == "one":
        return (float(rng.uniform(-0.5, 0.0)) * half, half + k * r)
    return (-(half - 4.0 * r), half - 4.0 * r)


def _hall_config(rng, cfg, size):
    spec = _magnet(rng)
    body_ok = 0.5 * spec["length_mm"] - 4.0 * spec["bore_mm"] >= 20.0
    ends = str(rng.choice(["both", "one", "body"] if body_ok else ["both", "one"]))
    z0, z1 = _z_range(rng, spec, ends)
    half = (0.3 if spec["order"] == 0 else 0.35) * spec["bore_mm"]
    bench = benches.draw_bench(
        rng, (100.0, 100.0, max(600.0, 100.0 * np.ceil((z1 - z0) / 100 + 1)))
    )
    n_reps = int(rng.integers(3, 6) if size == "small" else rng.integers(3, 11))
    kind = str(rng.choice(scans.SCAN_KINDS))
    scan = scans.draw_scan(rng, kind, (half, half), (z0, z1), size, n_reps)
    noise = float(np.exp(rng.uniform(np.log(0.5), np.log(20.0))))
    refs = ["exact", "coarse"] + (["harmonics"] if ends == "body" and spec["order"] else [])
    cfg |= {
        "magnet": spec,
        "bench": bench,
        "scan": scan,
        "noise_uT": noise,
        "reference": str(rng.choice(refs)),
    }
    cfg["strata"] = {
        "magnet": magnets.ORDER_NAMES[spec["order"]],
        "source": spec["source"],
        "ends": ends,
        "bench_stack": bench["stack_label"],
        "scan": kind,
        "noise": _regime("hall", noise),
        "reference": cfg["reference"],
    }


def _tracker_config(rng, cfg, size):
    bench = benches.draw_bench(rng)
    st = bench["strokes_mm"]
    n_reps = int(rng.integers(3, 6) if size == "small" else rng.integers(3, 11))
    kind = str(rng.choice(scans.SCAN_KINDS))
    scan = scans.draw_scan(
        rng, kind, (0.5 * st["x"], 0.5 * st["y"]), (-0.5 * st["z"], 0.5 * st["z"]), size, n_reps
    )
    noise = float(np.exp(rng.uniform(np.log(1.0), np.log(8.0))))
    cfg |= {"magnet": None, "bench": bench, "scan": scan, "noise_um": noise}
    cfg["strata"] = {
        "magnet": "none",
        "source": "none",
        "ends": "none",
        "bench_stack": bench["stack_label"],
        "scan": kind,
        "noise": _regime("tracker", noise),
        "reference": "none",
    }


def draw_config(
    seed: int, size: str = "small", role: str | None = None, kind=None, *, effect=None
) -> dict:
    """The configuration of a family case, all from ``seed``.

    Parameters
    ----------
    seed : int
    size : {'small', 'full'}
        Small: 3 x 3 lines, 13 to 21 planes, 3 to 5 repetitions; full: up to 6 x 6, 21 to 35
        planes, 3 to 10 repetitions.
    role : {'null', 'effect'}, optional
        Drawn from the seed (half each) when not given.
    kind : {'hall', 'tracker'}, optional
        Drawn from the seed (Hall 70 %) when not given.
    effect : str, optional
        The effect of an effect case, in place of the one drawn from the seed (which is
        drawn all the same, so the other draws stay those of the seed); one of
        :func:`effect_pool` of the configuration.

    Returns
    -------
    dict
        ``seed``, ``size``, ``role``, ``kind``, ``magnet``, ``bench``, ``scan``, ``noise_uT`` or
        ``noise_um``, ``reference`` (Hall), ``strata`` (the labels) and ``effect`` (name or
        None; its parameters are drawn by :func:`write_family_case`, which needs the
        signatures).
    """
    if size not in ("small", "full"):
        raise ValueError(f"size must be 'small' or 'full'; found {size!r}")
    rng = _rng(seed, 0)
    draw_role = "null" if rng.uniform() < 0.5 else "effect"
    draw_kind = "hall" if rng.uniform() < 0.7 else "tracker"
    role, kind = role or draw_role, kind or draw_kind
    cfg = {"seed": int(seed), "size": size, "role": role, "kind": kind}
    (_hall_config if kind == "hall" else _tracker_config)(rng, cfg, size)
    cfg["effect"] = None
    if role == "effect":
        pool = effect_pool(cfg)
        drawn = str(rng.choice(pool))
        cfg["effect"] = drawn if effect is None else str(effect)
        if cfg["effect"] not in pool:
            raise ValueError(f"effect {effect!r} is not one of this configuration's {pool}")
        rest = [e for e in pool if e != cfg["effect"]]
        cfg["fallback"] = [str(e) for e in rng.permutation(rest)]
        if cfg["effect"] == "fringe_field_3d":
            cfg["reference"] = cfg["strata"]["reference"] = "harmonics"
    elif role != "null":
        raise ValueError(f"role must be 'null' or 'effect'; found {role!r}")
    return cfg


def effect_pool(cfg: dict) -> list:
    """The effects a configuration can conceal: the catalogue of its kind, less the soft ends
    where there is no 2-D reference or no end scanned, and less the reading delay without an
    on-the-fly repetition."""
    pool = list(HALL_EFFECTS if cfg["kind"] == "hall" else TRACKER_EFFECTS)
    if cfg["kind"] == "hall" and (cfg["magnet"]["order"] == 0 or cfg["strata"]["ends"] == "body"):
        pool.remove("fringe_field_3d")
    if cfg["kind"] == "tracker" and not any(cfg["scan"].get("speeds", [0.0])):
        pool.remove("reading_delay")
    return pool


def _neighbour_names(cfg, effect) -> list:
    """(effect, param) of every nuisance and neighbour signature an effect is told from."""
    hall = cfg["kind"] == "hall"
    names = [("bench", n) for n in benches.B.NAMES]
    if effect != "magnet_misalignment":
        pose = FH.POSE if hall else ("t_x", "t_y", "t_z", "r_x", "r_y", "r_z")
        names += [("pose", p) for p in pose]
    if hall:
        names += [("gain", f"gain_{c}") for c in "xyz"]
        for eff in HALL_EFFECTS:
            if eff in (effect, "fringe_field_3d", "magnet_misalignment"):
                continue
            params = DRAWN.get(eff, FH.PARAMS[eff]) if eff != "sensor_offset" else ()
            names += [(eff, p) for p in params]
        if effect != "sensor_offset":
            names += [("sensor_offset", f"d_{i}_{j}") for i in "xyz" for j in "xyz"]
    else:
        for eff in TRACKER_EFFECTS:
            if eff in (effect, "parameter_bias"):
                continue
            names += [(eff, p) for p in FT.PARAMS[eff]]
    return names


def _relative_offsets(sig: dict) -> None:
    """Element offsets relative to the centroid: a common shift is the registration's."""
    for j in "xyz":
        z = sig.pop(("sensor_offset", f"d_z_{j}"), None)
        if z is None:
            continue
        for i in "xy":
            key = ("sensor_offset", f"d_{i}_{j}")
            if key in sig:
                sig[key] = sig[key] - z


def _draw_effect(cfg, ctx, rng, base, grad, sigmas) -> tuple:
    """The concealed effect's parameters and its significance record.

    Parameters
    ----------
    cfg, ctx : dict
        The configuration and its draws (:func:`.family_hall.context` or
        :func:`.family_tracker.context`); ``cfg["effect"]`` is the effect to conceal.
    rng : numpy.random.Generator
        The stream of the effect's target, parameters and direction.
    base : ndarray, shape (n, 3)
        The noiseless readings of the configuration as recorded (T or mm; for a Hall map the
        magnet at its surveyed pose, :func:`.family_hall.forward`), so the effect is sized on
        the data it is concealed in.
    grad : ndarray, shape (n, 3, 3) or None
        The field gradient (T/mm) of a Hall map (:func:`.family_hall.gradient`).
    sigmas : tuple of ndarray, shape (n, 3)
        The readings' own std (``noise``) and their whitening std with the reference's error
        shared by the readings of each point (``total``, :func:`.significance.shared_error_std`;
        ``noise`` itself without a coarse reference), in the units of ``base``.

    Returns
    -------
    effects : dict or None
        ``{effect: {param: value}}`` (display units), None when no draw fits.
    record : dict
        The target and drawn significance (``sigma_target``, ``sigma_drawn``: against
        ``total``, the reference's error included), ``sigma_noise_only`` (the same values
        against ``noise``), ``kept``, ``z_per_unit`` (against ``total``), ``direction`` and the
        neighbours and nuisances; for a ``magnet_misalignment`` also ``survey_draw`` (the
        survey's draw of its parameter, um or urad) and ``total_departure`` (the survey draw
        plus the concealed value: the recorded pose's departure from the nominal one, which
        the drawn significance sizes). A failed draw holds ``beyond_cap``: whether a direction
        separable from the neighbours needed a size beyond :data:`CAPS` (:data:`PARAM_CAPS`).
    """
    effect = cfg["effect"]
    noise, total = sigmas
    sim = FH if cfg["kind"] == "hall" else FT
    others = _neighbour_names(cfg, effect)
    sig_o = sim.signatures(cfg, ctx, others, base=base, grad=grad)
    if effect != "sensor_offset":
        _relative_offsets(sig_o)
    vec_o = [v for (e, p), v in sig_o.items() if not (effect == "parameter_bias" and e == "bench")]
    target = float(rng.uniform(*SIGMA_RANGE))
    record = {
        "definition": significance.__doc__.split("\n\n")[1].strip(),
        "sigma_target": target,
        "neighbours": sorted({e for e, _ in sig_o if e not in ("bench", "pose", "gain")}),
        "nuisances": sorted({e for e, _ in sig_o if e in ("bench", "pose", "gain")}),
    }
    if effect == "fringe_field_3d":  # against 2-D harmonics: no reference error of a table
        ref = _harmonic_field(cfg, ctx)
        z, kept = significance.per_unit(base - ref, vec_o, noise)
        record |= {"sigma_drawn": z, "sigma_noise_only": z, "kept": kept}
        record["sized"] = "fixed by the magnet"
        return ({effect: {}} if z >= SIGMA_RANGE[0] else None), record
    pool = DRAWN.get(effect, FH.PARAMS.get(effect) or FT.PARAMS.get(effect))
    beyond = False
    for _ in range(8):
        k = min(1 if effect in ONE_PARAM else int(rng.integers(1, 3)), len(pool))
        params = [str(p) for p in rng.choice(pool, k, replace=False)]
        u = rng.normal(size=k)
        u = np.abs(u) if effect in POSITIVE else u
        u /= np.linalg.norm(u)
        sig = sim.signatures(cfg, ctx, [(effect, p) for p in params], base=base, grad=grad)
        s = sum(ui * sig[effect, p] for ui, p in zip(u, params, strict=True))
        vec = vec_o + [v for (e, p), v in sig_o.items() if e == "bench" and p not in params]
        vec = vec if effect == "parameter_bias" else vec_o
        z1, kept = significance.per_unit(s, vec, total)
        if kept < 0.05 or z1 <= 0:
            continue
        values = _amplitudes(cfg, ctx, effect, params, u, z1, target)
        if values is None:
            beyond = True
            continue
        z1_noise = z1 if total is noise else significance.per_unit(s, vec, noise)[0]
        record |= {
            "sigma_drawn": target,
            "sigma_noise_only": _noise_only(cfg, effect, params[0], target, (z1, z1_noise)),
            "kept": kept,
            "z_per_unit": z1,
            "direction": dict(zip(params, u.tolist(), strict=True)),
        }
        if effect == "magnet_misalignment":
            drawn = float(ctx["survey"][FH.POSE.index(params[0])])
            record |= {"survey_draw": drawn, "total_departure": drawn + values[params[0]]}
        return {effect: values}, record
    failed = {"sigma_drawn": None, "sigma_noise_only": None, "kept": None, "beyond_cap": beyond}
    return None, record | failed


def _release_prior(cfg, effect, param) -> tuple[float, float]:
    """The prior (mean, std; display units) of a prior release's parameter: the survey's for
    a ``magnet_misalignment`` (mean 0), the bench error's PDF for a ``parameter_bias``."""
    if effect == "magnet_misalignment":
        return 0.0, _prior_std(cfg, ("pose", param))
    kind, a, b = cfg["bench"]["pdfs"][param]
    return ((a + b) / 2 if kind == "uniform" else a), _prior_std(cfg, ("bench", param))


def _noise_only(cfg, effect, param, target, z_per_unit) -> float:
    """The significance of the drawn effect against the readings' own std alone.

    Parameters
    ----------
    cfg : dict
    effect : str
    param : str
        The first parameter drawn (the one of a prior release).
    target : float
        The drawn significance, with the reference's error.
    z_per_unit : (float, float)
        Significance per display unit along the drawn direction with the reference's error
        and without it.

    Returns
    -------
    float
        ``target`` scaled by the ratio of the two per-unit significances; for a prior release,
        the same excess beyond the prior (:func:`.significance.release_sigma`). Equal to
        ``target`` when the two are equal (no reference error).
    """
    z1, z1_noise = z_per_unit
    if z1_noise == z1:
        return target
    if effect in PRIOR_RELEASE:
        prior = _release_prior(cfg, effect, param)[1]
        excess = significance.excess_for(target, z1, prior)
        return significance.release_sigma(excess, z1_noise, prior)
    return float(target * z1_noise / z1)


def _amplitudes(cfg, ctx, effect, params, u, z1, target):
    """Parameter values of the drawn size (None when beyond :data:`CAPS` or
    :data:`PARAM_CAPS`).

    Parameters
    ----------
    cfg, ctx : dict
        The configuration and its draws (:func:`.family_hall.context` or
        :func:`.family_tracker.context`).
    effect : str
    params : list of str
        The parameters drawn (one for a prior release).
    u : ndarray, shape (len(params),)
        Unit direction of the effect along ``params``.
    z1 : float
        Joint significance per unit amplitude along ``u`` (per display unit), the reference's
        error included.
    target : float
        The drawn significance.

    Returns
    -------
    dict or None
        Value of each parameter (display units). An effect other than a prior release has
        amplitude ``target / z1`` along ``u``. A prior release is sized by its departure from
        the prior's mean, ``significance.excess_for(target, z1, prior)`` of the sign of
        ``u``: a ``parameter_bias`` is the bench error's value ``mean + excess``; a
        ``magnet_misalignment`` is added to the survey draw (``ctx["survey"]``, um or urad)
        in the recorded pose, so its value is the departure less the survey draw and the
        recorded pose departs from the nominal one (the prior's mean, 0) by the excess. The
        cap applies to the concealed value.
    """
    if effect in PRIOR_RELEASE:
        p = params[0]
        mean, prior = _release_prior(cfg, effect, p)
        excess = significance.excess_for(target, z1, prior) * np.sign(u[0])
        if effect == "magnet_misalignment":
            value = float(excess - ctx["survey"][FH.POSE.index(p)])
            return None if abs(value) > CAPS[effect] else {p: value}
        return None if abs(excess) > CAPS[effect] else {p: mean + excess}
    amp = target / z1
    if effect == "sensor_volume_averaging":  # the signature is per mm^2 of disc diameter
        disc = float(np.sqrt(amp))
        return None if disc > CAPS[effect] else {"disc_mm": disc}
    vals = {p: float(amp * ui) for p, ui in zip(params, u, strict=True)}
    if any(abs(v) > PARAM_CAPS.get(p, CAPS[effect]) for p, v in vals.items()):
        return None
    return vals | ({"from_rep": FT.step_rep(cfg)} if effect == "step_event" else {})


def _harmonic_field(cfg, ctx):
    """The 2-D harmonics' field (T, shape (n, 3), bench axes, gains applied) at the noiseless
    readings with the magnet at its recorded pose: what the reference gives where the
    recording's field was taken, so that the recording less it is the body's 3-D departure
    alone (the pose, a nuisance the diagnosis fits, is not part of it)."""
    spec = cfg["magnet"]
    r_ref = 0.5 * spec["bore_mm"]
    rows = magnets.harmonics_2d(spec, r_ref, 20)
    local, rot = FH.element_positions(cfg, ctx, {}, noisy=False)
    w = (local[:, 0] + 1j * local[:, 1]) / r_ref
    f = sum((bn + 1j * an) * w ** (int(n) - 1) for n, bn, an in rows)
    b = np.stack([f.imag, f.real, np.zeros(len(w))], -1) @ rot.T
    return b * (1.0 + 1e-2 * ctx["gains"])


def _reference(cfg, ctx, folder: Path, stem: str, tab=None) -> Path:
    """Write the reference file of a Hall case.

    Parameters
    ----------
    cfg : dict
        A Hall configuration; ``cfg["reference"]`` is ``"harmonics"`` (2-D multipoles at half
        the bore radius) or a field table (:data:`.family_reference.TABLE_KINDS`).
    ctx : dict or None
        The configuration's draws (unused: the reference is that of the nominal magnet).
    folder : Path
    stem : str
        The file's name less its suffix.
    tab : tuple, optional
        ``(axes, values)`` of :func:`.family_reference.table`, when already computed.

    Returns
    -------
    Path
        ``<stem>.harmonics.csv`` or ``<stem>.reference.csv`` (nodes in mm, field in T).
    """
    spec = cfg["magnet"]
    if cfg["reference"] == "harmonics":
        r_ref = 0.5 * spec["bore_mm"]
        return output.write_harmonics(
            folder / f"{stem}.harmonics.csv",
            magnets.harmonics_2d(spec, r_ref, 20),
            r_ref,
            [f"2-D multipoles of the simulated {cfg['strata']['magnet']} (z = 0)"],
            main=spec["order"],
        )
    axes, values = FR.table(cfg) if tab is None else tab
    fine = cfg["reference"] == "exact"
    what = "exact field on a grid through the map's points" if fine else "coarse FEM-like grid"
    return output.write_reference_table(
        folder / f"{stem}.reference.csv",
        FR.nodes(axes),
        values.reshape(-1, 3),
        [f"{what}, simulated {cfg['strata']['magnet']}"],
    )


def _prior_std(cfg, name) -> float:
    """Prior std (display units) of a nuisance the case's files state: the survey (pose), the
    probe's S_HP gain (%), a bench error's PDF."""
    eff, p = name
    if eff == "pose":
        t_um, r_urad = cfg["bench"]["survey_std"]
        return float(t_um if p.startswith("magnet_d") else r_urad)
    if eff == "gain":
        return float(FH.GAIN_HALF_WIDTH_PCT / np.sqrt(3.0))
    kind, a, b = cfg["bench"]["pdfs"][p]
    return float((b - a) / np.sqrt(12.0) if kind == "uniform" else b)


def _null_harmonics_ok(cfg, ctx, base, grad, sigma) -> float:
    """Significance of the body's own 3-D departure from the 2-D harmonics (a null must have
    none), after the pose, gains and bench errors within their priors.

    The departure, the signatures and ``sigma`` are those of the recorded configuration (the
    magnet at its surveyed pose, the drawn gains and bench errors): each prior bounds how far
    its nuisance may move from the value the recording has to absorb the departure, so the
    recording's own draw of the nuisances within their priors is no departure."""
    names = [("pose", p) for p in FH.POSE] + [("gain", f"gain_{c}") for c in "xyz"]
    names += [("bench", n) for n in benches.B.NAMES]
    sig = FH.signatures(cfg, ctx, names, base=base, grad=grad)
    prior = [_prior_std(cfg, k) for k in sig]
    dep = base - _harmonic_field(cfg, ctx)
    return significance.per_unit_prior(dep, list(sig.values()), sigma, prior)[0]


def _attempt_seed(seed: int, attempt: int) -> int:
    """The seed of a case's configuration at its ``attempt``-th draw (1: the case's seed).

    A later attempt's seed is derived from the case's seed and the attempt (53 bits, so the
    truth's JSON keeps it exact): no other case's configuration is reused.
    """
    if attempt == 1:
        return int(seed)
    state = np.random.SeedSequence([20261129, int(seed), 2, int(attempt)]).generate_state(
        1, np.uint64
    )
    return int(state[0] >> np.uint64(11))


def _conceal(cfg, ctx, rng, base, grad, sigmas, redraw: bool) -> tuple:
    """The concealed effect of an effect case: its own, else the first of its fallback list
    that fits within the caps and is separable (:func:`_draw_effect`).

    Parameters
    ----------
    cfg, ctx, rng, base, grad, sigmas
        As :func:`_draw_effect`.
    redraw : bool
        Whether the case may draw another configuration: then a case's own effect of
        :data:`PHYSICAL` that needs a size beyond its cap is not replaced.

    Returns
    -------
    effects : dict or None
        ``{effect: {param: value}}``, ``{}`` when no effect fits (the case is a null), None
        when the configuration is to be redrawn.
    record : dict
        The significance record, with ``not_separable`` (the effects passed over).
    """
    tried = []
    effects, record = None, {}
    for name in [cfg["effect"], *cfg["fallback"]]:
        cfg["effect"] = name
        effects, record = _draw_effect(cfg, ctx, rng, base, grad, sigmas)
        if effects is not None:
            break
        if redraw and not tried and name in PHYSICAL and record["beyond_cap"]:
            return None, record
        tried.append(name)  # not separable within the caps on this configuration
    if effects is None:
        effects, cfg["effect"] = {}, None
        record["note"] = "no effect separable within the caps: the case is a null"
    record["not_separable"] = tried
    return effects, record


def _reference_error(cfg: dict) -> tuple:
    """The coarse reference table of a Hall case and its reading error at the map's points.

    Returns
    -------
    table : tuple or None
        ``(axes, values)`` of :func:`.family_reference.table` for a coarse reference (the
        file's nodes and values), else None.
    error : ndarray, shape (m, 3) or (1, 3), T
        :func:`.family_reference.reading_error` at each of the map's points; zeros of shape
        (1, 3) for another reference or a tracker recording.
    """
    if cfg["kind"] != "hall" or cfg["reference"] != "coarse":
        return None, np.zeros((1, 3))
    tab = FR.table(cfg)
    return tab, FR.reading_error(cfg, tab)


def _sized_case(cfg: dict, redraw: bool) -> dict | None:
    """The draws of a configuration and its concealed effect, sized on them.

    Parameters
    ----------
    cfg : dict
        A configuration (:func:`draw_config`) with its ``replica``.
    redraw : bool
        Whether the case may draw another configuration (:func:`_conceal`).

    Returns
    -------
    dict or None
        ``cfg`` (its ``effect`` and ``reference`` as concealed and written), ``ctx``,
        ``effects``, ``record`` (the significance record, with ``reference_error_rms``: the
        rms over the map's points of the reference's reading error of each component, uT,
        zero but for a coarse table) and ``table`` (the coarse reference table, else None).
        None when the configuration cannot carry its effect within the effect's physical
        range.
    """
    hall = cfg["kind"] == "hall"
    sim = FH if hall else FT
    ctx = sim.context(cfg)
    base = sim.forward(cfg, ctx, {}, noisy=False)
    grad = FH.gradient(cfg, ctx) if hall else None
    sigma = FH.noise_std(cfg, ctx, grad) if hall else FT.noise_std(cfg, ctx)
    tab, error = _reference_error(cfg)
    total = significance.shared_error_std(sigma, ctx["scan"].point, error)
    effects, record = {}, None
    if cfg["effect"]:
        rng = _rng(cfg["seed"], 1)
        effects, record = _conceal(cfg, ctx, rng, base, grad, (sigma, total), redraw)
        if effects is None:
            return None
        # the soft ends are judged against the 2-D harmonics, which have no table's error
        soft_ends = cfg["effect"] == "fringe_field_3d"
        record["reference_error_rms"] = FR.error_rms_uT(np.zeros((1, 3)) if soft_ends else error)
        if soft_ends:
            cfg["reference"] = cfg["strata"]["reference"] = "harmonics"
        elif (
            cfg.get("reference") == "harmonics"
            and _null_harmonics_ok(cfg, ctx, base, grad, sigma) > 1
        ):
            cfg["reference"] = cfg["strata"]["reference"] = "exact"
    elif hall and cfg["reference"] == "harmonics":
        z = _null_harmonics_ok(cfg, ctx, base, grad, sigma)
        if z > 1.0:
            cfg["reference"] = cfg["strata"]["reference"] = "exact"
        record = {"body_vs_2d_sigma": z}
    return {"cfg": cfg, "ctx": ctx, "effects": effects, "record": record, "table": tab}


def drawn_case(seed: int, size: str, role, kind, replica: int, effect=None) -> dict:
    """A case's configuration, draws and concealed effect, from its seed.

    The first attempt is the configuration of ``seed`` (:func:`draw_config`). When the
    case's effect is one of :data:`PHYSICAL` and its drawn significance needs a size beyond
    the effect's cap on that configuration, the configuration is not a physical one: attempt
    k draws the configuration of :func:`_attempt_seed` (seed, k) with the same role, kind and
    effect, up to :data:`MAX_ATTEMPTS` (the last one conceals a fallback effect instead).

    Returns
    -------
    dict
        As :func:`_sized_case`, with ``attempts`` (1: the seed's own configuration).
    """
    cfg = draw_config(seed, size, role, kind, effect=effect)
    effect = cfg["effect"]
    for attempt in range(1, MAX_ATTEMPTS + 1):
        if attempt > 1:
            cfg = draw_config(
                _attempt_seed(seed, attempt), size, cfg["role"], cfg["kind"], effect=effect
            )
        cfg["replica"] = int(replica)
        case = _sized_case(cfg, redraw=attempt < MAX_ATTEMPTS)
        if case is not None:
            return case | {"attempts": attempt}
    raise AssertionError("the last attempt conceals a fallback effect")  # not reached


def written_config(seed: int, size: str = "small", role=None, kind=None, effect=None) -> dict:
    """The configuration a case is written with (:func:`write_family_case`, the truth's
    ``config``), with its ``attempts``.

    It is :func:`draw_config` of the seed but where the case's own draws change it: an effect
    case whose effect is one of :data:`PHYSICAL` and needs a size beyond its range on the
    seed's configuration is written on another one (:func:`drawn_case`); an effect the
    configuration cannot carry is replaced by one of its fallback list (``effect``; the soft
    ends then bring their 2-D harmonics); a reference of 2-D harmonics from which the body
    departs by more than 1 sigma is replaced by the exact one.

    Cost: a null without a reference of 2-D harmonics takes :func:`draw_config` alone
    (about 1 ms); any other case is sized as :func:`write_family_case` sizes it (its
    signatures and significance: a fraction of a second per configuration at ``size``
    ``'small'``, several seconds at ``'full'``).

    Parameters
    ----------
    seed, size, role, kind, effect
        As :func:`write_family_case`.

    Returns
    -------
    dict
        The configuration (:func:`draw_config`, with ``replica`` 0) as written, and
        ``attempts`` (1: the seed's own configuration).
    """
    cfg = draw_config(seed, size, role, kind, effect=effect)
    if cfg["role"] == "null" and cfg.get("reference") != "harmonics":
        return cfg | {"replica": 0, "attempts": 1}
    case = drawn_case(seed, size, cfg["role"], cfg["kind"], 0, effect)
    return case["cfg"] | {"attempts": case["attempts"]}


def write_family_case(
    seed: int, folder, size: str = "small", role=None, kind=None, replica: int = 0, effect=None
) -> dict:
    """Simulate one family case and write its recording, truth, reference and bench file.

    Parameters
    ----------
    seed : int
        The case's seed: its configuration (:func:`draw_config`), or, when the case's effect
        needs a size beyond its physical range there, a configuration drawn from the seed and
        an attempt counter (:func:`drawn_case`; the truth's ``attempts`` and
        ``config["seed"]``).
    folder : str or Path
    size : {'small', 'full'}
    role : {'null', 'effect'}, optional
    kind : {'hall', 'tracker'}, optional
    replica : int
        k > 0 writes the same case with the readings' noise drawn afresh
        (:func:`.common.reading_streams`); its files are named ``family_<seed>_r<k>``.
    effect : str, optional
        The effect to conceal instead of the seed's own draw (:func:`draw_config`), the
        seed's other draws kept.

    Returns
    -------
    dict
        ``recording``, ``truth``, ``reference`` (None for a tracker recording) and ``bench``
        paths, ``kind``, ``expected`` (the effect or None) and the ``args`` of
        ``cfm-fem diagnose`` (less ``--out``), as :func:`.cases.write_case`.
    """
    case = drawn_case(seed, size, role, kind, replica, effect)
    cfg, ctx, effects = case["cfg"], case["ctx"], case["effects"]
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    hall = cfg["kind"] == "hall"
    sim = FH if hall else FT
    cols = _columns(cfg, ctx, sim.forward(cfg, ctx, effects))
    stem = f"family_{seed}" + (f"_r{replica}" if replica else "")
    expected = cfg["effect"]
    truth = {
        "case": f"family_{cfg['kind']}",
        "seed": int(seed),
        "replica": int(replica),
        "attempts": case["attempts"],
        "kind": cfg["kind"],
        "role": cfg["role"],
        "expected": expected,
        "effects": effects,
        "params": sim.truth_params(cfg, ctx, effects),
        "strata": cfg["strata"],
        "significance": case["record"],
        "config": cfg,
        "size": size,
        "n_reps": cfg["scan"]["n_reps"],
        "n_readings": len(ctx["scan"].point),
        "temperature_range_K": float(np.ptp(ctx["t_true"])),
        "duration_h": float(ctx["scan"].t_s[-1] / 3600.0),
    }
    rec = output.write_csv(
        folder / f"{stem}.csv", cols, [f"simulated family {cfg['kind']} recording, seed {seed}"]
    )
    tru = output.write_json(folder / f"{stem}.truth.json", truth)
    bench = output.write_text(
        folder / f"{stem}.bench.toml",
        benches.bench_toml(cfg["bench"], comment=f"family case {seed}"),
    )
    ref = _reference(cfg, ctx, folder, stem, case["table"]) if hall else None
    args = ["--hall-map", str(rec), "--reference", str(ref)] if hall else ["--tracker", str(rec)]
    return {
        "recording": rec,
        "truth": tru,
        "reference": ref,
        "bench": bench,
        "kind": cfg["kind"],
        "expected": expected,
        "args": [*args, "--bench", str(bench)],
    }


def _columns(cfg, ctx, values) -> dict:
    scan = ctx["scan"]
    if cfg["kind"] == "hall":
        p = scan.q - benches.travel_offset(cfg["bench"])
        head = {
            "point_id": scan.point,
            "rep": scan.rep,
            "x_cmd": p[:, 0],
            "y_cmd": p[:, 1],
            "z_cmd": p[:, 2],
            "Bx": values[:, 0],
            "By": values[:, 1],
            "Bz": values[:, 2],
        }
    else:
        q = scan.q
        head = {
            "point_id": scan.point,
            "rep": scan.rep,
            "x_cmd": q[:, 0],
            "y_cmd": q[:, 1],
            "z_cmd": q[:, 2],
            "x_meas": values[:, 0],
            "y_meas": values[:, 1],
            "z_meas": values[:, 2],
        }
    return head | scan.columns(ctx["t_log"])
