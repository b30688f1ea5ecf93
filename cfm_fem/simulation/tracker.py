"""Laser-tracker recordings of the reference bench, with concealed effects.

The reflector sits at the probe. A reading is the probe position of the HTM chain
(:mod:`.bench`) at the actual axis travel, seen by the tracker:

* axis travel = command + backlash (``b dir / 2``) + thermal expansion of the screw and frame
  ((T - T0) (d_a + s_a q_a)) + vibration and reading error (N(0, 2.5 um) and N(0, 1 um) per
  axis and reading, paper eq. 10);
* bench errors: Table II draws (one bench per recording), plus any position-dependent error
  function (amplitude x (q / stroke)^k, evaluated at the commanded travel);
* arm sag under the moving load: y -= c 16 u^2 (1 - u)^2 (point load on a simply supported
  beam, u = q / stroke; c the sag at mid-stroke);
* the tracker reads late by tau on the fly: only the moving axis has moved on by v tau;
* a slip: a step of the reflector from a repetition on (not in the catalogue);
* tracker registration to the bench (10 um, 10 urad) and white noise (5 um per coordinate).

Effects are given in the diagnosis' parameter names and units (``effects`` of :func:`simulate`);
the truth is returned in the same names, converted to the diagnosis' conventions where the
physical definition differs (thermal scale about the mean travel).
"""

from __future__ import annotations

import numpy as np

from . import bench as B
from .common import speeds_for, streams, temperature
from .scan import plan

__all__ = ["simulate", "GRIDS", "TRACKER_NOISE_UM"]

TRACKER_NOISE_UM = 5.0
REG_STD = (10.0, 10.0)  # tracker-to-bench registration: um, urad (1 sigma)
#: Commanded travel of the grid lines and points (mm): full = design notes section 5 (936).
GRIDS = {
    "full": (np.linspace(0, 150, 9), np.linspace(0, 150, 8), np.linspace(0, 800, 13)),
    "small": (np.linspace(0, 150, 5), np.linspace(0, 150, 4), np.linspace(0, 800, 7)),
}
REPS = {"full": 10, "small": 4}
STROKE = np.array([B.STROKES_MM[a] for a in "xyz"])


def _sag(u):
    return 16.0 * u**2 * (1.0 - u) ** 2


def _error_functions(errors: dict, pdg: dict, q) -> dict:
    """Bench errors at each reading: constants plus ``{'eps_z(z)_u1': urad, ...}`` profiles."""
    out = dict(errors)
    for key, amp in pdg.items():
        name, order = key.rsplit("_u", 1)
        u = q[:, "xyz".index(name[-2])] / STROKE["xyz".index(name[-2])]
        out[name] = out.get(name, 0.0) + amp * u ** int(order)
    return out


def simulate(seed: int, effects: dict | None = None, size: str = "full", n_reps=None):
    """One tracker recording.

    Parameters
    ----------
    seed : int
    effects : dict, optional
        Concealed effects: name -> {param: value} in the diagnosis' names and units
        (``thermal_drift``: drift_a um/K at zero travel, scale_drift_a ppm/K; ``reversal``:
        backlash_a um; ``reading_delay``: tau ms; ``position_dependent_geometric``: e.g.
        ``eps_z(z)_u1`` urad; ``arm_deflection``: sag_x, sag_z um; ``parameter_bias``: any of the
        21 errors, um or urad, replacing its draw), and ``step_event``: {dx_um, from_rep}.
    size : {'full', 'small'}
    n_reps : int, optional

    Returns
    -------
    columns : dict
        Column name -> ndarray, rows in time order (the CSV contract plus v_x, v_y, v_z).
    truth : dict
    """
    eff = {k: dict(v) for k, v in (effects or {}).items()}
    n_reps = REPS[size] if n_reps is None else int(n_reps)
    rng = streams(seed, ["bench", "vib", "noise", "reg", "temp"])
    scan = plan(*GRIDS[size], speeds_for(n_reps))
    q, n = scan.q, len(scan.point)
    errors = B.draw_errors(rng["bench"])
    errors.update(eff.get("parameter_bias", {}))
    t_true, t_log = temperature(scan.t_s, rng["temp"])
    dT = t_true - t_true[0]

    travel = q.copy()
    rev = eff.get("reversal", {})
    thermal = eff.get("thermal_drift", {})
    for a, c in enumerate("xyz"):
        travel[:, a] += 0.5e-3 * rev.get(f"backlash_{c}", 0.0) * scan.dir[:, a]
        d, s = thermal.get(f"drift_{c}", 0.0), thermal.get(f"scale_drift_{c}", 0.0)
        travel[:, a] += dT * (d * 1e-3 + s * 1e-6 * q[:, a])
    travel += B.axis_noise(rng["vib"], n)
    pdg = eff.get("position_dependent_geometric", {})
    p = B.probe_position(travel, _error_functions(errors, pdg, q))

    sag = eff.get("arm_deflection", {})
    u = q / STROKE
    p[:, 1] -= 1e-3 * sag.get("sag_x", 0.0) * _sag(u[:, 0])
    p[:, 1] -= 1e-3 * sag.get("sag_z", 0.0) * _sag(u[:, 2])
    tau_s = eff.get("reading_delay", {}).get("tau", 0.0) * 1e-3
    p += scan.v * tau_s  # only the moving axis has a velocity
    step = eff.get("step_event", {})
    if step:
        p[scan.rep >= step["from_rep"], 0] += 1e-3 * step["dx_um"]

    reg_t = rng["reg"].normal(0.0, REG_STD[0] * 1e-3, 3)
    reg_r = rng["reg"].normal(0.0, REG_STD[1] * 1e-6, 3)
    centre = (q + B.TOOL_MM).mean(0)
    meas = (p - centre) @ B.rotation(*reg_r)[0].T + centre + reg_t
    meas += rng["noise"].normal(0.0, TRACKER_NOISE_UM * 1e-3, (n, 3))

    cols = {
        "point_id": scan.point, "rep": scan.rep,
        "x_cmd": q[:, 0], "y_cmd": q[:, 1], "z_cmd": q[:, 2],
        "x_meas": meas[:, 0], "y_meas": meas[:, 1], "z_meas": meas[:, 2],
    } | scan.columns(t_log)  # fmt: skip
    params = dict(errors)  # the 21 amplitudes as built (um, urad)
    for name, block in eff.items():
        if name == "thermal_drift":  # diagnosis: scale about the mean travel of the recording
            for a, c in enumerate("xyz"):
                s = block.get(f"scale_drift_{c}", 0.0)
                params[f"drift_{c}"] = block.get(f"drift_{c}", 0.0) + s * 1e-3 * q[:, a].mean()
                params[f"scale_drift_{c}"] = s
        elif name == "step_event":  # diagnosis: the step of the x axis, um
            params["step_x"] = block["dx_um"]
        else:
            params.update(block)
    truth = {
        "kind": "tracker",
        "seed": int(seed),
        "size": size,
        "n_reps": n_reps,
        "effects": eff,
        "params": params,
        "registration": {"t_um": (reg_t * 1e3).tolist(), "rot_urad": (reg_r * 1e6).tolist()},
        "temperature_range_K": float(np.ptp(t_true)),
        "duration_h": float(scan.t_s[-1] / 3600.0),
    }
    return cols, truth
