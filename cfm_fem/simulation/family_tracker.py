"""Laser-tracker recordings of a family bench, with concealed effects, and the linearised
signatures of those effects on the recording.

The physics is that of :mod:`.tracker` on a bench of :mod:`.benches` (any stack, its own
strokes, tool, vibration and Table II draws) and a scan of :mod:`.scans`: axis travel =
command + backlash + thermal expansion + vibration and reading error; bench errors (plus
position-dependent error functions) through the HTM chain; arm sag; a late reading on the fly;
a slip of the reflector along x from the middle repetition on (``step_event``); tracker
registration and white noise of the configuration's level.
"""

from __future__ import annotations

import numpy as np

from . import bench as B
from . import benches, scans
from .common import reading_streams, temperature

__all__ = ["context", "forward", "truth_params", "signatures", "PARAMS", "PDG_FUNCTIONS"]

REG_STD = (10.0, 10.0)
#: The position-dependent error functions: each of the 18 errors growing linearly (``_u1``) or
#: quadratically (``_u2``) along its own axis's stroke.
PDG_FUNCTIONS = tuple(
    f"{k}_{c}({a})_u{m}" for m in (1, 2) for a in "xyz" for k in ("delta", "eps") for c in "xyz"
)
PARAMS = {
    "thermal_drift": tuple(f"{k}_{c}" for k in ("drift", "scale_drift") for c in "xyz"),
    "reversal": ("backlash_x", "backlash_y", "backlash_z"),
    "reading_delay": ("tau",),
    "position_dependent_geometric": PDG_FUNCTIONS,
    "arm_deflection": ("sag_x", "sag_z"),
    "parameter_bias": B.NAMES,
    "step_event": ("dx_um",),
}


def _centre(cfg):
    return np.array([cfg["bench"]["strokes_mm"][a] for a in "xyz"]) / 2.0


def context(cfg: dict) -> dict:
    """The scan and every random draw of a tracker configuration (from ``cfg['seed']``)."""
    scan = scans.build(cfg["scan"], _centre(cfg))
    n = len(scan.point)
    rng = reading_streams(cfg, ["vib", "noise", "reg", "temp"])
    t_true, t_log = temperature(scan.t_s, rng["temp"])
    return {
        "scan": scan,
        "vib": benches.axis_noise(cfg["bench"], rng["vib"], n),
        "noise": rng["noise"].normal(0.0, cfg["noise_um"] * 1e-3, (n, 3)),
        "reg_t": rng["reg"].normal(0.0, REG_STD[0] * 1e-3, 3),
        "reg_r": rng["reg"].normal(0.0, REG_STD[1] * 1e-6, 3),
        "t_true": t_true,
        "t_log": t_log,
    }


def _sag(u):
    return 16.0 * u**2 * (1.0 - u) ** 2


def forward(cfg: dict, ctx: dict, effects: dict, noisy: bool = True, errors=None):
    """Measured reflector positions (mm, shape (n, 3)).

    ``noisy=False``: the recorded configuration (the bench's errors, the temperatures of the
    recording) without the axes' vibration and reading error and the white noise, which are
    drawn afresh at each reading, and in the bench frame (without the tracker's registration).
    The signatures are taken about it: the registration is one rigid motion of every
    recording, and the reading std is the same along every axis (:func:`noise_std`), so it
    turns each signature and the span of the pose signatures alike and leaves every
    whitened projection, and so every significance, as it is."""
    bench = cfg["bench"]
    scan = ctx["scan"]
    q = scan.q
    stroke = np.array([bench["strokes_mm"][a] for a in "xyz"])
    errs = dict(bench["errors"] if errors is None else errors)
    errs.update(effects.get("parameter_bias", {}))
    dT = ctx["t_true"] - ctx["t_true"][0]
    travel = q.copy()
    rev, th = effects.get("reversal", {}), effects.get("thermal_drift", {})
    for a, c in enumerate("xyz"):
        travel[:, a] += 0.5e-3 * rev.get(f"backlash_{c}", 0.0) * scan.dir[:, a]
        d, s = th.get(f"drift_{c}", 0.0), th.get(f"scale_drift_{c}", 0.0)
        travel[:, a] += dT * (d * 1e-3 + s * 1e-6 * q[:, a])
    if noisy:
        travel = travel + ctx["vib"]
    for key, amp in effects.get("position_dependent_geometric", {}).items():
        name, order = key.rsplit("_u", 1)
        k = "xyz".index(name[-2])
        errs[name] = errs.get(name, 0.0) + amp * (q[:, k] / stroke[k]) ** int(order)
    p = benches.probe_position(travel, errs, bench)
    sag = effects.get("arm_deflection", {})
    u = q / stroke
    p[:, 1] -= 1e-3 * (
        sag.get("sag_x", 0.0) * _sag(u[:, 0]) + sag.get("sag_z", 0.0) * _sag(u[:, 2])
    )
    p = p + scan.v * effects.get("reading_delay", {}).get("tau", 0.0) * 1e-3
    step = effects.get("step_event", {})
    if step:  # a slip of the reflector along x from a repetition on
        p[scan.rep >= step["from_rep"], 0] += 1e-3 * step["dx_um"]
    if not noisy:
        return p
    centre = (q + np.asarray(bench["tool_mm"])).mean(0)
    meas = (p - centre) @ B.rotation(*ctx["reg_r"])[0].T + centre + ctx["reg_t"]
    return meas + ctx["noise"]


def noise_std(cfg: dict, ctx: dict) -> np.ndarray:
    """Std of each coordinate (mm, shape (n, 3)): tracker noise plus vibration and reading."""
    b = cfg["bench"]
    s = np.sqrt(cfg["noise_um"] ** 2 + b["vibration_um"] ** 2 + b["reading_um"] ** 2) * 1e-3
    return np.full((len(ctx["scan"].point), 3), s)


def signatures(cfg: dict, ctx: dict, names, base=None, grad=None) -> dict:
    """Change of the noiseless recording per unit of each (effect, param) in ``names`` (mm per
    display unit, shape (n, 3)). ``"pose"``: the tracker registration (t_x, t_y, t_z in um,
    r_x, r_y, r_z in urad about the scan's centre); ``"bench"``: one of the 21 bench errors."""
    base = forward(cfg, ctx, {}, noisy=False) if base is None else base
    centre = (ctx["scan"].q + np.asarray(cfg["bench"]["tool_mm"])).mean(0)
    out = {}
    for eff, p in names:
        if eff == "pose":
            k = "xyz".index(p[-1])
            if p.startswith("t_"):
                s = np.zeros_like(base)
                s[:, k] = 1e-3
            else:
                s = np.cross(np.eye(3)[k], base - centre) * 1e-6
            out[eff, p] = s
        elif eff == "bench" or eff == "parameter_bias":
            e = dict(cfg["bench"]["errors"])
            e[p] += 1.0
            out[eff, p] = forward(cfg, ctx, {}, noisy=False, errors=e) - base
        elif eff == "step_event":
            block = {p: 1.0, "from_rep": step_rep(cfg)}
            out[eff, p] = forward(cfg, ctx, {eff: block}, noisy=False) - base
        else:
            out[eff, p] = forward(cfg, ctx, {eff: {p: 1.0}}, noisy=False) - base
    return out


def step_rep(cfg: dict) -> int:
    """The repetition a concealed slip starts from: the middle one."""
    return int(cfg["scan"]["n_reps"]) // 2


def truth_params(cfg: dict, ctx: dict, effects: dict) -> dict:
    """The parameters a correct diagnosis reports (diagnosis conventions)."""
    params = dict(cfg["bench"]["errors"])
    q = ctx["scan"].q
    for name, block in effects.items():
        if name == "thermal_drift":  # the diagnosis: scale about the mean travel
            for a, c in enumerate("xyz"):
                s = block.get(f"scale_drift_{c}", 0.0)
                params[f"drift_{c}"] = block.get(f"drift_{c}", 0.0) + s * 1e-3 * q[:, a].mean()
                params[f"scale_drift_{c}"] = s
        elif name == "step_event":  # the diagnosis: the step of the x axis, um
            params["step_x"] = block["dx_um"]
        else:
            params.update(block)
    return params
