"""How many trials a U95 of ``cfm-fem quality`` needs to be known to +-5 %.

    python scripts/quality_trials.py                       # 2 seeds x 20,000 trials
    python scripts/quality_trials.py --seeds 4 --trials 10000 --counts 1000,2000,5000

Runs the Monte Carlo of ``cfm-fem quality --mode htm`` (the reference bench, the paper's probe,
the command's default scan) on ``meshes/quadrupole.vtu`` (R_ref = 10 mm): ``--trials`` trials
for each of ``--seeds`` seeds. Trial t's numbers depend on (seed, t) only, so any N consecutive
trials of a run are an independent Monte Carlo of N trials: U95 at a count N is taken on every
disjoint block of N trials of every seed, and its spread over the blocks is the spread of U95
from one run of N trials.

Printed per quantity: the mean U95 over all trials, the relative standard deviation of U95 over
the blocks at each count (the number of blocks in the header), and the trials for U95 to +-5 %
at 95 %: N (2 s / 0.05)^2 with s^2 N pooled over the counts with 8 blocks or more (s scales as
1 / sqrt(N)). Then the trials at which the command's adaptive rule (batches of 500, the
numerical tolerance of ``--digits``) stops on each seed's trials, replayed on them.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from cfm_fem.io import read_field
from cfm_fem.io.bench_toml import read_reference_bench
from cfm_fem.models.harmonic import fit_harmonic
from cfm_fem.models.mc import symmetric_interval
from cfm_fem.models.probe import HallProbe
from cfm_fem.models.quality import (
    VECTOR_NAMES,
    LocalField,
    Sources,
    analyse,
    fit_planes,
    main_order_of,
    run_quality_mc,
)
from cfm_fem.models.quality.uncertainty import _check
from cfm_fem.workflows.quality import scan_plan

ROOT = Path(__file__).resolve().parents[1]
#: Relative half-width a U95 is asked to within, at 95 %.
TARGET = 0.05


def u95(dev) -> np.ndarray:
    """U95 per column of deviations (M, Q), as `run_quality_mc`."""
    low, high = symmetric_interval(dev, 0.95, axis=0)
    return np.maximum(np.abs(low), np.abs(high))


def adaptive_stop(dev, batch: int, digits: int, main_order: int) -> int | None:
    """Trials at which the adaptive rule stops on these trials (None: not within them)."""
    values = []
    for b in range(0, len(dev) - batch + 1, batch):
        values.append(dev[b : b + batch])
        if _check(values, digits, ignore=main_order - 1)[0]:
            return b + batch
    return None


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--map", default=str(ROOT / "meshes" / "quadrupole.vtu"))
    ap.add_argument("--r-ref", type=float, default=10.0)
    ap.add_argument("--seeds", type=int, default=2, help="seeds 0 .. SEEDS-1")
    ap.add_argument("--trials", type=int, default=20_000, help="trials per seed")
    ap.add_argument("--counts", default="500,1000,2000,5000,10000")
    ap.add_argument("--digits", type=int, default=1)
    ap.add_argument("--json", help="also write the figures to this file")
    args = ap.parse_args(argv)
    counts = sorted(int(c) for c in args.counts.split(","))
    t0 = time.perf_counter()
    fm = read_field(args.map)
    plan, _ = scan_plan(fm, "auto", args.r_ref, None, None, 64, [])
    local = LocalField(fit_harmonic(fm.points, fm.B), plan.points)
    planes = fit_planes(plan, local.B_nominal)
    n_main = main_order_of(np.einsum("pn,p->n", planes, plan.weights_mm))
    nominal = analyse(plan, local.B_nominal, n_main, 0.0).vector()
    src = Sources("htm", bench=read_reference_bench(), probe=HallProbe("paper"))
    devs = []
    for seed in range(args.seeds):
        mc = run_quality_mc(plan, local, src, nominal, n_main, 0.0, seed=seed, trials=args.trials)
        devs.append(mc.deviations)
    seconds = time.perf_counter() - t0
    n_use = min(len(d) for d in devs)
    counts = [c for c in counts if 2 * c <= n_use]
    blocks, rel = [], []
    for c in counts:
        u = np.array([u95(d[b : b + c]) for d in devs for b in range(0, n_use - c + 1, c)])
        blocks.append(len(u))
        with np.errstate(divide="ignore", invalid="ignore"):
            rel.append(u.std(axis=0, ddof=1) / u.mean(axis=0))
    rel = np.array(rel)  # (counts, Q)
    mean = u95(np.concatenate([d[:n_use] for d in devs]))
    many = np.array(blocks) >= 8
    s2n = np.mean(rel[many] ** 2 * np.array(counts)[many, None], axis=0)
    needed = s2n * (2 / TARGET) ** 2
    stops = [adaptive_stop(d, 500, args.digits, n_main) for d in devs]
    print(f"{fm.source}: {len(plan.points)} scan points, {args.seeds} seeds x {n_use} trials, "
          f"{seconds:.0f} s")  # fmt: skip
    head = "".join(f"{f'{c}({b})':>11}" for c, b in zip(counts, blocks, strict=True))
    print("relative std of U95 over blocks of N trials, N(blocks):")
    print(f"{'quantity':<14}{'U95':>11}{head}  trials(+-5 %)")
    finite = np.isfinite(needed)
    for j, name in enumerate(VECTOR_NAMES):
        if not finite[j]:
            continue
        cells = "".join(f"{100 * r:10.1f}%" for r in rel[:, j])
        print(f"{name:<14}{mean[j]:11.4g}{cells}  {needed[j]:10.0f}")
    worst = int(np.nanargmax(needed))
    print(
        f"trials for every U95 to +-{100 * TARGET:g} % at 95 %: {needed[worst]:.0f} "
        f"({VECTOR_NAMES[worst]}); median over the quantities {np.nanmedian(needed):.0f}"
    )
    print(f"adaptive rule (batches of 500, {args.digits} digit(s)) stops at: "
          f"{['beyond ' + str(n_use) if s is None else s for s in stops]}")  # fmt: skip
    if args.json:
        Path(args.json).write_text(json.dumps({
            "map": args.map, "scan_points": len(plan.points), "seeds": args.seeds,
            "trials": n_use, "counts": counts, "blocks": blocks,
            "quantities": list(VECTOR_NAMES), "u95": mean.tolist(), "relative_std": rel.tolist(),
            "trials_for_5_percent": needed.tolist(), "adaptive_stop": stops,
            "seconds": seconds}, indent=1))  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
