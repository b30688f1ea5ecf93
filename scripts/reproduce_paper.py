"""Reproduce the paper's simulated Table IV, Table V and Fig. 4 and print them beside the paper.

    python scripts/reproduce_paper.py [--trials-kin N] [--trials-coupled N] [--trials-fig4 N]
                                      [--fig4-map meshes/quadrupole.vtu] [--skip-fig4] [--seed S]

Every number printed comes from this run; Monte Carlo figures carry their trial count and a
numerical standard uncertainty (batches) where the engine gives one. Assumptions that decide the
numbers: the geometry of the reference bench (cfm_fem/data/cfm_reference_bench.toml; the paper
gives none): stack Z (800 mm stroke) on the foundation, X (150 mm) on the Z carriage, Y (150 mm)
on the X carriage, probe arm offset (0, -60, 500) mm from the Y carriage, scan grid of
9 x 8 x 13 = 936 points over the strokes; QFDp4 with R_ref = 10 mm (the paper does not state
R_ref), the coupled scan region (transverse grid, 2 mm step, r <= R_ref, z = -100..100 mm), and
B_ref = the main harmonic at R_ref.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from cfm_fem.io import read_field
from cfm_fem.io.bench_toml import read_reference_bench
from cfm_fem.io.harmonics import read_qfdp4
from cfm_fem.io.kinematics_out import PAPER_TABLE_IV
from cfm_fem.models.field_model import PAPER_TABLE_V, FieldModel
from cfm_fem.models.kinematics.monte_carlo import run_kinematics
from cfm_fem.workflows.coupled import field_budget, run_coupled
from cfm_fem.workflows.fig4 import fig4_summary, run_fig4


def table_iv(bench, trials, seed):
    t = time.perf_counter()
    res = run_kinematics(bench, trials=trials, seed=seed)
    print(
        f"\n=== Table IV: probe positioning error E_p [um], {res.n_points} points, {trials} "
        f"trials, seed {seed} ({time.perf_counter() - t:.0f} s)"
    )
    print(
        f"{'axis':6}{'sys':>7}{'std':>7}{'U_p':>7}   {'paper sim sys/std':>18}"
        f"   {'paper exp sys/std':>18}"
    )
    for a in "xyz":
        r, ps, pe = res.pooled[a], PAPER_TABLE_IV["simulation"][a], PAPER_TABLE_IV["experiment"][a]
        print(
            f"{a.upper():6}{r['systematic_um']:7.1f}{r['std_um']:7.1f}{r['U_p_um']:7.1f}   "
            f"{ps['systematic_um']:>12} / {ps['std_um']:<3}   "
            f"{pe['systematic_um']:>12} / {pe['std_um']:<3}"
        )
    print("pooling: RMS over points of the per-point mean (sys) and std; U_p = hypot(sys, std)")


def table_v(bench, trials, seed):
    fm = FieldModel.from_multipole(read_qfdp4())
    print(
        f"\n=== Table V: field error E_f [units of 1e-4 B_ref], B_ref = {fm.b_ref_T} T "
        f"({fm.b_ref_rule}); QFDp4, R_ref = {fm.r_ref_mm:g} mm (assumed); {trials} trials, "
        f"seed {seed}"
    )
    print(
        "region: transverse grid step 2 mm inside r <= R_ref, z = -100, -50, 0, 50, 100 mm "
        "(405 points); S_HP uniform std 0.15 %; pooled over Bx and By"
    )
    print(f"{'':40}{'sys':>8}{'std':>8}{'U_f':>8}   num. u (sys/std/U_f)")
    for align in ("placement", "probe"):
        t = time.perf_counter()
        r = run_coupled(fm, bench, trials=trials, seed=seed, align=align)
        a = r.pooled()["all"]
        print(
            f"{'this run, align=' + align:40}{a['systematic_units']:8.2f}{a['std_units']:8.2f}"
            f"{a['U_f_units']:8.2f}   {a['systematic_num_u']:.2g}/{a['std_num_u']:.2g}/"
            f"{a['U_f_num_u']:.2g}  ({time.perf_counter() - t:.0f} s)"
        )
        fb = field_budget(fm, bench, r.points, trials=min(trials, 20000), seed=seed, align=align)
        for label, key in (
            ("  positioning only", "positioning_only"),
            ("  probe only", "probe_only"),
        ):
            d = fb[key]
            print(
                f"{label:40}{d['systematic_units']:8.2f}{d['std_units']:8.2f}"
                f"{d['U_f_units']:8.2f}   ({fb['trials']} trials)"
            )
        ep = 1e3 * np.sqrt(np.mean(r.ep_mean**2, axis=0)), 1e3 * np.sqrt(np.mean(r.ep_std**2, 0))
        print(
            "  E_p at the scan points [um] sys x/y/z "
            + "/".join(f"{v:.1f}" for v in ep[0])
            + ", std "
            + "/".join(f"{v:.1f}" for v in ep[1])
        )
    for label, key in (("paper, simulated", "simulation"), ("paper, experimental", "experiment")):
        p = PAPER_TABLE_V[key]
        print(f"{label:40}{p['systematic_units']:8.1f}{p['std_units']:8.1f}{p['U_f_units']:8.1f}")


def fig4(path, trials, seed):
    t = time.perf_counter()
    res = run_fig4(read_field(path), [0, 10, 20, 30, 40, 50], trials=trials, seed=seed)
    s = fig4_summary(res)
    print(
        f"\n=== Fig. 4: U_f (95 %) against U_p on {path}, {trials} trials/node, seed {seed}, "
        f"B_ref = {s['b_ref_T']:.6g} T ({s['b_ref_rule']}), {time.perf_counter() - t:.0f} s; "
        f"per-node MC std +-{100 * s['uf_relative_mc_std']:.1f} %"
    )
    print(f"{'U_p um':>7}{'nodes':>7}{'p50':>8}{'p95':>8}{'max':>8}{'law':>8}{'paper':>7}")
    for r in s["table"]:
        paper = "" if r["paper"] is None else f"{r['paper']:g}"
        print(
            f"{r['up_um']:7g}{r['nodes']:7d}{r['p50']:8.1f}{r['p95']:8.1f}{r['max']:8.1f}"
            f"{r['analytic']:8.1f}{paper:>7}"
        )
    print(s["explanation"])


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--trials-kin", type=int, default=100_000)
    p.add_argument("--trials-coupled", type=int, default=100_000)
    p.add_argument("--trials-fig4", type=int, default=2000)
    p.add_argument("--fig4-map", default="meshes/quadrupole.vtu")
    p.add_argument("--skip-fig4", action="store_true")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    bench = read_reference_bench()
    print(f"bench: {bench.name} ({bench.source})")
    table_iv(bench, args.trials_kin, args.seed)
    table_v(bench, args.trials_coupled, args.seed)
    if not args.skip_fig4:
        fig4(args.fig4_map, args.trials_fig4, args.seed)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
