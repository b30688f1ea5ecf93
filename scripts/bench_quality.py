"""Time ``cfm-fem quality --mode htm`` on the bundled map, step by step.

    python scripts/bench_quality.py                      # defaults of the command
    python scripts/bench_quality.py --max-trials 2000    # a shorter adaptive run

Runs the steps of `cfm_fem.workflows.quality.run_quality` one by one on
``meshes/quadrupole.vtu`` (R_ref = 10 mm, the reference bench, the paper's probe) and prints the
wall time of each: reading the map, fitting the local harmonic model, the circle sampling, the
Monte Carlo of the whole bench and the budget (one run per error group), with the trial counts,
the scan points and numba's thread count. The kernels are compiled beforehand (on a tiny map),
so compilation is not counted.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numba
import numpy as np

from cfm_fem.io import read_field
from cfm_fem.io.bench_toml import read_reference_bench
from cfm_fem.models.field import FieldMap
from cfm_fem.models.harmonic import fit_harmonic
from cfm_fem.models.probe import HallProbe
from cfm_fem.models.quality import (
    LocalField,
    Sources,
    analyse,
    budget_groups,
    fit_planes,
    main_order_of,
    run_quality_mc,
)
from cfm_fem.workflows.quality import run_quality, scan_plan

ROOT = Path(__file__).resolve().parents[1]


def _warm() -> None:
    """Compile the kernels on a tiny map."""
    g = np.arange(-3.0, 3.01, 1.0)
    x, y, z = np.meshgrid(g, g, np.arange(-3.0, 3.01, 1.0), indexing="ij")
    pts = np.column_stack([x.ravel(), y.ravel(), z.ravel()])
    B = np.column_stack([0.1 * pts[:, 1], 0.1 * pts[:, 0], np.zeros(len(pts))])
    run_quality(FieldMap.from_arrays(pts, B), 3.0, mode="htm", centre_magnet=True, trials=20,
                budget_trials=20)  # fmt: skip


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--map", default=str(ROOT / "meshes" / "quadrupole.vtu"))
    ap.add_argument("--r-ref", type=float, default=10.0)
    ap.add_argument("--max-trials", type=int, default=20_000)
    ap.add_argument("--budget-trials", type=int, default=200)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    _warm()
    times = {}
    t = time.perf_counter()
    fm = read_field(args.map)
    times["read_s"] = time.perf_counter() - t
    t = time.perf_counter()
    fit = fit_harmonic(fm.points, fm.B)
    times["harmonic_fit_s"] = time.perf_counter() - t
    t = time.perf_counter()
    plan, _ = scan_plan(fm, "auto", args.r_ref, None, None, 64, [])
    local = LocalField(fit, plan.points)
    planes = fit_planes(plan, local.B_nominal)
    n_main = main_order_of(np.einsum("pn,p->n", planes, plan.weights_mm))
    nominal = analyse(plan, local.B_nominal, n_main, 0.0).vector()
    times["sampling_s"] = time.perf_counter() - t
    src = Sources("htm", bench=read_reference_bench(), probe=HallProbe("paper"))
    t = time.perf_counter()
    mc = run_quality_mc(plan, local, src, nominal, n_main, 0.0, seed=args.seed,
                        max_trials=args.max_trials)  # fmt: skip
    times["monte_carlo_s"] = time.perf_counter() - t
    t = time.perf_counter()
    groups = [run_quality_mc(plan, local, g, nominal, n_main, 0.0, seed=args.seed,
                             trials=args.budget_trials) for g in budget_groups(src)]  # fmt: skip
    times["budget_s"] = time.perf_counter() - t
    times["total_s"] = sum(times.values())
    out = {
        "map": args.map, "nodes": fm.n_nodes, "scan_points": len(plan.points),
        "planes": plan.n_planes, "threads": numba.get_num_threads(),
        "trials": mc.trials, "converged": mc.converged, "budget_groups": len(groups),
        "budget_trials": args.budget_trials,
        **{k: round(v, 2) for k, v in times.items()},
    }  # fmt: skip
    print(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
