"""Blind proof of `cfm-fem diagnose` on twins (issue 5).

1. False-discovery rate over N null datasets (no concealed effect, different seeds): a dataset is
   a false discovery when `mismatch` is true or `effects` is not empty.
2. One concealed effect per catalogue entry (plus hard cases): found or not, rank, truth vs
   estimate, held-out RMS before/after, run time.

    python scripts/prove_diagnosis.py [--nulls 50] [--small]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from cfm_fem.diagnose.problem import hall_problem, tracker_problem
from cfm_fem.diagnose.twin import hall_twin, tracker_twin
from cfm_fem.diagnose.workflow import diagnose
from cfm_fem.io.bench_toml import read_reference_bench

BENCH = read_reference_bench()

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
    ("hall", {"hall_offset_gain": {"offset_z": 20.0, "gain_x": 0.5}}, "hall_offset_gain", {}),
    ("hall", {"magnet_temperature": {"beta": -100.0}}, "magnet_temperature", {}),
    ("hall", {"magnet_misalignment": {"magnet_roll": 600.0}}, "magnet_misalignment", {}),
    (
        "hall",
        {"fringe_field_3d": {"half_length_mm": 250.0, "lambda_mm": 30.0}},
        "fringe_field_3d",
        {},
    ),
    ("hall", {"sensor_offset": {"d_y_x": 150.0}}, "sensor_offset (hard: uniform gradient)", {}),
    (
        "hall",
        {"sensor_volume_averaging": {"a_x": 0.15, "a_y": 0.15, "a_z": 0.001}},
        "sensor_volume_averaging (hard: 150 um)",
        {},
    ),
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


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--nulls", type=int, default=50)
    ap.add_argument("--small", action="store_true", help="140 points x 6 reps (fast)")
    ap.add_argument("--skip-cases", action="store_true")
    a = ap.parse_args(argv)
    false = 0
    t0 = time.perf_counter()
    for i in range(a.nulls):
        kind = "tracker" if i % 2 == 0 else "hall"
        s, _, _ = run(kind, {}, 1000 + i, a.small)
        bad = s["mismatch"] or bool(s["effects"])
        false += bad
        if bad:
            print(
                f"  null {i} ({kind}): mismatch={s['mismatch']} effects="
                f"{[e['name'] for e in s['effects']]} located={s['located'][:2]}"
            )
    rate = false / max(a.nulls, 1)
    ci = 1.96 * np.sqrt(max(rate * (1 - rate), 1e-12) / max(a.nulls, 1))
    print(
        f"false-discovery rate over {a.nulls} null datasets (half tracker, half Hall): "
        f"{false}/{a.nulls} = {100 * rate:.1f} % (+-{100 * ci:.1f} %), "
        f"{time.perf_counter() - t0:.0f} s"
    )
    if a.skip_cases:
        return 0
    print()
    print(
        f"{'concealed effect':44} {'found':6} {'rank':4}  {'truth vs estimate (+-std)':60} "
        f"{'held-out before->after':24} {'s':>5}"
    )
    for kind, eff, expect, kw in CASES:
        s, truth, dt = run(kind, eff, 7, a.small, **kw)
        names = [e["name"] for e in s["effects"]]
        base = expect.split(" ")[0].split("+")
        found = all(b in names for b in base)
        rank = ",".join(str(names.index(b) + 1) if b in names else "-" for b in base)
        parts = []
        for b in base:
            if b in names:
                e = s["effects"][names.index(b)]
                for p, v in eff.get(b, {}).items():
                    if p in e["params"]:
                        parts.append(f"{p} {v:g} vs {e['params'][p]:.3g}+-{e['param_std'][p]:.2g}")
        if not parts and names:
            parts.append("found instead: " + ",".join(names))
        f = s["fit"]
        print(
            f"{expect:44} {'yes' if found else 'no':6} {rank:4}  {'; '.join(parts)[:60]:60} "
            f"{f['cv_rms_before']:.3g}->{f['cv_rms_after']:.3g} {f['unit']:6} {dt:5.1f}"
        )
        if not found:
            adv = [x for x in s["advice"] if "not identifiable" not in x]
            print(f"{'':44} advice: {adv[0][:150] if adv else '-'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
