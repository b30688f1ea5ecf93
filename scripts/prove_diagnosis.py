"""Blind proof of `cfm-fem diagnose` on twins, at realistic size by default.

1. False-discovery rate over N null datasets (no concealed effect, different seeds, half tracker,
   half Hall map): a dataset is a false discovery when `mismatch` is true or `effects` is not
   empty. Printed with its binomial standard error and the exact (Clopper-Pearson) 95 % upper
   bound.
2. One concealed effect per catalogue entry, plus hard cases: found or not, rank, truth vs
   estimate +- standard uncertainty (and whether |estimate - truth| < 3 u), held-out RMS
   before/after, run time.

Full size: 936 points x 10 repetitions, tracker noise 5 um, Hall noise 1e-4 B_ref.

    NUMBA_NUM_THREADS=1 python scripts/prove_diagnosis.py [--nulls 50] [--small] [--seed 7]
"""

from __future__ import annotations

import os

# the fits are tall-skinny SVDs: a threaded BLAS only loses on a shared machine
for _v in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402
from scipy import stats  # noqa: E402

from cfm_fem.diagnose.effects import averaging_params  # noqa: E402
from cfm_fem.diagnose.problem import hall_problem, tracker_problem  # noqa: E402
from cfm_fem.diagnose.twin import hall_twin, tracker_twin  # noqa: E402
from cfm_fem.diagnose.workflow import diagnose  # noqa: E402
from cfm_fem.io.bench_toml import read_reference_bench  # noqa: E402

BENCH = read_reference_bench()


def _reg(truth, i, scale):
    return truth["registration"]["t_mm" if i < 3 else "rot_rad"][i % 3] * scale


#: Truth of parameters that the tool estimates as a whole (survey draw or S_HP draw of the twin
#: plus the concealed part): name -> function(truth) -> value in display units.
TOTALS = {
    "magnet_dx": lambda t: _reg(t, 0, 1e3),
    "magnet_dy": lambda t: _reg(t, 1, 1e3),
    "magnet_roll": lambda t: _reg(t, 5, 1e6),
    "gain_x": lambda t: t["gains_pct"][0] + t["effects"]["hall_offset_gain"].get("gain_x", 0),
    "z_entry": lambda t: t["effects"]["fringe_field_3d"]["z_entry"] + t["registration"]["t_mm"][2],
    "z_exit": lambda t: t["effects"]["fringe_field_3d"]["z_exit"] + t["registration"]["t_mm"][2],
    "gain_z": lambda t: t["gains_pct"][2] + t["effects"]["hall_offset_gain"].get("gain_z", 0),
}

CASES = [  # (kind, effects, expected name, twin options)
    ("tracker", {"reversal": {"backlash_z": 6.0, "backlash_x": 3.0}}, "reversal", {}),
    ("tracker", {"thermal_drift": {"drift_y": 1.0, "scale_drift_z": 1.5}}, "thermal_drift", {}),
    ("tracker", {"reading_delay": {"tau": 0.3}}, "reading_delay", {"speeds": [10.0, 20.0]}),
    ("tracker", {"arm_deflection": {"sag_z": 5.0}}, "arm_deflection", {}),
    (
        "tracker",
        {"position_dependent_geometric": {"eps_z(z)_u2": 100.0}},
        "position_dependent_geometric",
        {},
    ),
    ("tracker", {"parameter_bias": {"alpha_xy": 200.0}}, "parameter_bias", {}),
    ("hall", {"probe_misalignment": {"m_zx": 0.5, "m_zy": -0.3}}, "probe_misalignment", {}),
    ("hall", {"planar_hall": {"k_z": 0.01}}, "planar_hall", {}),
    ("hall", {"hall_offset_gain": {"offset_z": 20.0, "gain_x": 1.0}}, "hall_offset_gain", {}),
    ("hall", {"magnet_temperature": {"beta": -300.0}}, "magnet_temperature", {}),
    (
        "hall",
        {"magnet_misalignment": {"magnet_dx": 300.0, "magnet_roll": 600.0}},
        "magnet_misalignment",
        {},
    ),
    (
        "hall",
        {"fringe_field_3d": {"z_entry": -250.0, "z_exit": 250.0, "lambda": 30.0}},
        "fringe_field_3d",
        {},
    ),
    ("hall", {"sensor_offset": {"d_y_x": 150.0}}, "sensor_offset (hard: uniform gradient)", {}),
    ("hall", {"hall_offset_gain": {"offset_x": 20.0}}, "hall_offset_gain (hard: in-plane)", {}),
    (
        "hall",
        {"sensor_volume_averaging": {"a_x": 0.15, "a_y": 0.15, "a_z": 0.001}},
        "sensor_volume_averaging (hard: 150 um)",
        {},
    ),
    ("hall", {"magnet_temperature": {"beta": -30.0}}, "magnet_temperature (near limit)", {}),
    (
        "tracker",
        {"reading_delay": {"tau": 0.3}},
        "reading_delay (hard: one speed)",
        {"speeds": [20.0]},
    ),
    ("tracker", {"reversal": {"backlash_z": 1.0}}, "reversal (near limit: 1 um)", {}),
    (
        "tracker",
        {"reversal": {"backlash_z": 5.0}, "thermal_drift": {"drift_x": 1.0}},
        "reversal+thermal_drift",
        {},
    ),
]


def _small_points(kind):
    if kind == "tracker":
        g = (np.linspace(0, 150, 5), np.linspace(0, 150, 4), np.linspace(0, 800, 7))
    else:
        g = (np.linspace(-6, 6, 5), np.linspace(-6, 6, 4), np.linspace(-300, 300, 7))
    return np.stack(np.meshgrid(*g, indexing="ij"), -1).reshape(-1, 3)


def run(kind, effects, seed, small, **kw):
    """One twin (tracker: 5 um noise; Hall: 1e-4 B_ref noise) and its diagnosis.

    Returns
    -------
    summary : dict
    truth : dict
    seconds : float
        Twin generation + problem set-up + diagnosis.
    """
    reps = 6 if small else 10
    pts = _small_points(kind) if small else None
    t0 = time.perf_counter()
    if kind == "tracker":
        rec, truth = tracker_twin(
            seed, effects, n_reps=reps, points=pts, dt_s=30.0 if small else 4.0, **kw
        )
        prob = tracker_problem(rec, BENCH)
    else:
        rec, truth, ctx = hall_twin(seed, effects, n_reps=reps, points=pts)
        mp = ctx["multipole"]
        prob = hall_problem(rec, mp.field, mp.b_ref, ctx["bench"])
    s = diagnose(prob).summary
    return s, truth, time.perf_counter() - t0


def false_discovery_rate(n, small, seed0=1000):
    """Run ``n`` null datasets; return (false discoveries, seconds per dataset list)."""
    false, secs = 0, []
    for i in range(n):
        kind = "tracker" if i % 2 == 0 else "hall"
        s, _, dt = run(kind, {}, seed0 + i, small)
        secs.append(dt)
        bad = s["mismatch"] or bool(s["effects"])
        false += bad
        if bad:
            print(
                f"  null {i} ({kind}): mismatch={s['mismatch']} effects="
                f"{[e['name'] for e in s['effects']]} located={s['located'][:2]} "
                f"implausible={[c['name'] for c in s['implausible']]}"
            )
    return false, secs


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--nulls", type=int, default=50)
    ap.add_argument("--small", action="store_true", help="140 points x 6 reps (fast)")
    ap.add_argument("--skip-cases", action="store_true")
    ap.add_argument("--seed", type=int, default=7, help="seed of the concealed-effect twins")
    a = ap.parse_args(argv)
    size = "140 points x 6 reps" if a.small else "936 points x 10 reps"
    print(f"size: {size}; tracker noise 5 um, Hall noise 1e-4 B_ref")
    if a.nulls:
        t0 = time.perf_counter()
        false, secs = false_discovery_rate(a.nulls, a.small)
        n = a.nulls
        rate = false / n
        se = np.sqrt(rate * (1 - rate) / n)
        upper = stats.beta.ppf(0.95, false + 1, n - false) if false < n else 1.0
        print(
            f"false-discovery rate over {n} null datasets (half tracker, half Hall): "
            f"{false}/{n} = {100 * rate:.1f} % (binomial s.e. {100 * se:.1f} %; exact 95 % "
            f"upper bound {100 * upper:.1f} %); {time.perf_counter() - t0:.0f} s, "
            f"{np.mean(secs):.2f} s per dataset"
        )
    if a.skip_cases:
        return 0
    print()
    print(
        f"{'concealed effect':40} {'found':5} {'rank':4}  "
        f"{'truth vs estimate +- u (in 3u?)':70} {'held-out before->after':22} {'s':>5}"
    )
    for kind, eff, expect, kw in CASES:
        s, truth, dt = run(kind, eff, a.seed, a.small, **kw)
        names = [e["name"] for e in s["effects"]]
        base = expect.split(" ")[0].split("+")
        found = all(b in names for b in base)
        rank = ",".join(str(names.index(b) + 1) if b in names else "-" for b in base)
        parts = []
        for b in base:
            if b in names:
                e = s["effects"][names.index(b)]
                items = eff.get(b, {})
                if b == "sensor_volume_averaging":
                    items = averaging_params([items.get(f"a_{c}", 0.0) for c in "xyz"])
                for p, v in items.items():
                    v = TOTALS[p](truth) if p in TOTALS else v
                    if p in e["params"]:
                        est, u = e["params"][p], e["param_std"][p]
                        ok = "yes" if abs(est - v) < 3 * u else "NO"
                        parts.append(f"{p} {v:.4g} vs {est:.4g}+-{u:.2g} ({ok})")
                    else:
                        parts.append(f"{p} {v:.4g}: not estimated")
        if not parts and names:
            parts.append("found instead: " + ",".join(names))
        if not names and s["implausible"]:
            parts.append("implausible: " + ",".join(c["name"] for c in s["implausible"]))
        f = s["fit"]
        print(
            f"{expect:40} {'yes' if found else 'no':5} {rank:4}  {'; '.join(parts)[:70]:70} "
            f"{f['cv_rms_before']:.4g}->{f['cv_rms_after']:.4g} {f['unit']:5} {dt:5.1f}"
        )
        if not found:
            key = base[0]
            cand = {c["name"]: c for c in s["candidates"]}.get(key)
            if cand:
                print(
                    f"{'':40} {key}: {cand['status']}, delta BIC {cand['delta_bic']}, "
                    f"absorbed parameters {cand['absorbed_params'] or 'none'}"
                )
            adv = [x for x in s["advice"] if key in x]
            print(f"{'':40} advice: {adv[0][:160] if adv else '-'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
