"""U_f under the linear and the harmonic field model against the exact field of the bundled map.

    python scripts/bench_field_models.py                  # 300 nodes per |z| band, 20,000 trials
    python scripts/bench_field_models.py --per-band 100 --trials 5000   # quicker

The bundled map (`meshes/quadrupole.vtu`) is the field of a magpylib permanent-magnet
quadrupole (`scripts/make_default_mesh.py`), so its exact field is known everywhere. For nodes
drawn at random in each |z| band, it prints:

1. U_f of |B| (U_p = 20 and 50 um, mode gauss, ``--outside extrapolate``) from the sweep kernels
   under each field model, against U_f of the exact field with the same standard normals: the
   exact field is its second-order Taylor expansion at the node from central differences of the
   magpylib source (step 0.05 mm; its truncation error at the trials' displacements is checked
   against magpylib itself and printed). Signed median and p90 of |error| per band, and the Monte
   Carlo's own relative standard error of one node's U_f.
2. The time to fit the harmonic model to all 46,051 nodes (kernels compiled).
3. CPU time per trial of both sweep kernels on one thread, same nodes, same trials (the six
   U_p values of the README's sweep, and one U_p value), and of the field at arbitrary points
   (`field_at` of each model, as compare, diagnose and coupled use it).

Needs magpylib (``pip install -e ".[test]"``).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numba
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "scripts"))

import make_default_mesh as source_model  # noqa: E402

from cfm_fem import _kernels  # noqa: E402
from cfm_fem.io import read_field  # noqa: E402
from cfm_fem.models.harmonic import fit_harmonic  # noqa: E402
from cfm_fem.models.mc import symmetric_interval  # noqa: E402
from cfm_fem.models.sweep import SweepConfig  # noqa: E402
from cfm_fem.workflows.sweep.problem import node_keys, prepare_sweep  # noqa: E402

BANDS = [(0, 30), (30, 38), (38, 45), (45, 60), (60, 80), (80, np.inf)]
FD_STEP_MM = 0.05
Z95 = 0.95


def taylor_models(src, points, h=FD_STEP_MM):
    """B, grad B and the Hessian of each component at ``points`` (k, 3) from central differences
    of the exact source: (k, 3), (k, 3, 3) T/mm, (k, 3, 3, 3) T/mm^2."""
    k = len(points)
    e = np.eye(3) * h
    offsets = [np.zeros(3)] + [s * e[i] for i in range(3) for s in (1, -1)]
    offsets += [s1 * e[i] + s2 * e[j] for i in range(3) for j in range(i + 1, 3)
                for s1 in (1, -1) for s2 in (1, -1)]  # fmt: skip
    stencil = np.concatenate([points + o for o in offsets])
    f = source_model.field_T(src, stencil).reshape(len(offsets), k, 3)
    b0 = f[0]
    grad = np.empty((k, 3, 3))
    hess = np.empty((k, 3, 3, 3))
    for i in range(3):
        fp, fm = f[1 + 2 * i], f[2 + 2 * i]
        grad[:, :, i] = (fp - fm) / (2 * h)
        hess[:, :, i, i] = (fp - 2 * b0 + fm) / h**2
    m = 7
    for i in range(3):
        for j in range(i + 1, 3):
            fpp, fpm, fmp, fmm = f[m], f[m + 1], f[m + 2], f[m + 3]
            hess[:, :, i, j] = hess[:, :, j, i] = (fpp - fpm - fmp + fmm) / (4 * h * h)
            m += 4
    return b0, grad, hess


def taylor_field(b0, grad, hess, d):
    """Second-order expansion at displacements d (t, 3) of one node, T."""
    return b0 + d @ grad.T + 0.5 * np.einsum("ta,cab,tb->tc", d, hess, d)


def node_normals(key, seed, n):
    """The standard normals, shape (3, n), the sweep kernels draw for the node of ``key``."""
    skey = _kernels.stream_key(seed, _kernels.STREAM_SWEEP)
    fkey = _kernels.stream_key(seed, _kernels.STREAM_FALLBACK)
    z = np.empty((3, n))
    _kernels.normals_by_index(_kernels.trial_key(skey, key), fkey, 0, n, z, np.empty(n, bool))
    return z


def symmetric_uf(x, p=Z95):
    """U_f of the samples x: the tool's own probabilistically symmetric interval (order
    statistics, JCGM 101 7.7), so that the comparison measures the field model only."""
    lo, hi = symmetric_interval(np.asarray(x), p)
    return max(abs(lo), abs(hi))


def pick_nodes(points, per_band, rng):
    """Nodes drawn at random per |z| band, with the band of each."""
    az = np.abs(points[:, 2])
    nodes, band = [], []
    for b, (lo, hi) in enumerate(BANDS):
        idx = np.flatnonzero((az >= lo) & (az < hi))
        pick = rng.choice(idx, size=min(per_band, len(idx)), replace=False)
        nodes.append(np.sort(pick))
        band.append(np.full(len(pick), b))
    return np.concatenate(nodes), np.concatenate(band)


def accuracy(fm, nodes, band, ups, trials, seed, src, problems):
    """Per band and U_p: median and p90 of the relative U_f error of each model."""
    pts = fm.points[nodes]
    b0, grad, hess = taylor_models(src, pts)
    keys = problems["linear"].keys[nodes]
    exact = np.empty((len(nodes), len(ups)))
    check_pts, check_ref = [], []
    for i in range(len(nodes)):
        z = node_normals(int(keys[i]), seed, trials)
        abs0 = np.linalg.norm(b0[i])
        for k, up in enumerate(ups):
            d = (up * 1e-3) * z.T
            b = taylor_field(b0[i], grad[i], hess[i], d)
            exact[i, k] = symmetric_uf(np.linalg.norm(b, axis=1) - abs0)
            if i % 50 == 0:  # a few trials at the largest U_p: truncation check
                check_pts.append(pts[i] + d[:4])
                check_ref.append(b[:4])
    direct = source_model.field_T(src, np.concatenate(check_pts))
    trunc = np.abs(direct - np.concatenate(check_ref)).max()
    b_ref = fm.b_max
    out = {}
    for name, problem in problems.items():
        stats = problem.run_nodes(nodes)[0]
        uf = np.maximum(np.abs(stats[:, :, 3, 2]), np.abs(stats[:, :, 3, 3]))
        out[name] = uf / exact - 1.0
    return out, trunc, b_ref, exact


def evaluation_cost(fm, fit, nodes, trials, seed):
    """CPU seconds per point of the field at arbitrary points (what compare, diagnose and
    coupled ask of a reference map), one thread: each node's trial points (U_p = 20 um) through
    `LinearInterpolator.field_at` (cell location and interpolation) and `HarmonicFit.field_at`
    (nearest node and its polynomial)."""
    from cfm_fem.models.interpolation import LinearInterpolator

    interp = LinearInterpolator(fm)
    keys = node_keys(fm.points)
    pts = np.concatenate(
        [fm.points[g] + 0.02 * node_normals(int(keys[g]), seed, trials).T for g in nodes]
    )
    interp.field_at(pts[:1000])  # compiled
    fit.field_at(pts[:1000])
    numba.set_num_threads(1)
    cost = {"linear": np.inf, "harmonic": np.inf}
    try:
        for _ in range(3):  # in turn, the fastest of three (see `per_trial_cost`)
            for name, model in (("linear", interp), ("harmonic", fit)):
                t = time.process_time()
                model.field_at(pts)
                cost[name] = min(cost[name], (time.process_time() - t) / len(pts))
    finally:
        numba.set_num_threads(numba.config.NUMBA_NUM_THREADS)
    return cost


def per_trial_cost(problems, nodes, repeat=5):
    """CPU seconds per trial of each model's kernel on one thread: the models run in turn,
    ``repeat`` times, and each keeps its fastest run (on a shared machine another process's
    load inflates a run's CPU time too, and alternating exposes both models to it alike)."""
    numba.set_num_threads(1)
    cost = {name: np.inf for name in problems}
    try:
        for problem in problems.values():
            problem.run_nodes(nodes[:20])  # compiled
        for _ in range(repeat):
            for name, problem in problems.items():
                t = time.process_time()
                problem.run_nodes(nodes)
                dt = (time.process_time() - t) / (len(nodes) * problem.trials)
                cost[name] = min(cost[name], dt)
    finally:
        numba.set_num_threads(numba.config.NUMBA_NUM_THREADS)
    return cost


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--per-band", type=int, default=300)
    ap.add_argument("--trials", type=int, default=20000)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    fm = read_field(ROOT / "meshes" / "quadrupole.vtu")
    src = source_model.build_magnet()
    rng = np.random.default_rng(args.seed)
    nodes, band = pick_nodes(fm.points, args.per_band, rng)
    ups = [20.0, 50.0]

    fit_harmonic(fm.points[:2000], fm.B[:2000])  # compile the fit kernels
    t = time.perf_counter()
    c = time.process_time()
    fit = fit_harmonic(fm.points, fm.B, source=fm.source)
    fit_wall, fit_cpu = time.perf_counter() - t, time.process_time() - c

    problems = {}
    for name in ("linear", "harmonic"):
        cfg = SweepConfig(up_um=ups, trials=args.trials, seed=args.seed, field_model=name,
                          outside="extrapolate")  # fmt: skip
        problems[name] = prepare_sweep(fm, cfg)[1]
    err, trunc, b_ref, exact = accuracy(fm, nodes, band, ups, args.trials, args.seed, src,
                                        problems)  # fmt: skip
    mc = 1.363 / np.sqrt(args.trials)
    print(f"bundled map: {fm.n_nodes} nodes; {len(nodes)} nodes drawn in {len(BANDS)} |z| bands; "
          f"{args.trials} trials, seed {args.seed}, --outside extrapolate")  # fmt: skip
    print(f"exact field: 2nd-order Taylor of the magpylib source (step {FD_STEP_MM} mm); "
          f"largest deviation from magpylib at trial points {trunc:.2e} T "
          f"({trunc / b_ref * 1e4:.2e} units)")  # fmt: skip
    print(f"Monte Carlo relative standard error of one node's U_f: {100 * mc:.2f} %")
    print(f"harmonic fits: {int(fit.use.sum())} nodes, {int((~fit.use).sum())} on the linear "
          f"interpolant; degrees {np.bincount(fit.degree[fit.use]).tolist()}")  # fmt: skip
    head = " ".join(f"{f'{lo:g}-{hi:g}' if np.isfinite(hi) else f'>{lo:g}':>9}" for lo, hi in BANDS)
    for k, up in enumerate(ups):
        print(f"\nU_p = {up:g} um: relative error of U_f(|B|), per |z| band [mm]")
        print(f"{'':24}{head}")
        for name in ("linear", "harmonic"):
            e = err[name][:, k]
            med = [np.median(e[band == b]) for b in range(len(BANDS))]
            p90 = [np.percentile(np.abs(e[band == b]), 90) for b in range(len(BANDS))]
            print(f"{name + ' median':24}" + " ".join(f"{100 * v:+8.2f}%" for v in med))
            print(f"{name + ' p90 |error|':24}" + " ".join(f"{100 * v:8.2f}%" for v in p90))
        h = err["harmonic"][:, k]
        ok_med = all(abs(np.median(h[band == b])) <= 0.005 for b in range(len(BANDS)))
        ok_p90 = all(np.percentile(np.abs(h[band == b]), 90) <= mc for b in range(len(BANDS)))
        verdict = {True: "PASS", False: "FAIL"}
        print(f"harmonic |median| <= 0.5 % in every band: {verdict[ok_med]}; "
              f"p90 within the Monte Carlo's {100 * mc:.2f} %: {verdict[ok_p90]}")  # fmt: skip

    print(f"\nfit of all {fm.n_nodes} nodes: {fit_wall:.2f} s wall, {fit_cpu:.2f} s CPU on "
          f"{numba.get_num_threads()} thread(s) (target <= 10 s)")  # fmt: skip
    for name in ("linear", "harmonic"):
        cfg = SweepConfig(up_um=[0, 10, 20, 30, 40, 50], trials=10000, seed=args.seed,
                          field_model=name)  # fmt: skip
        problems[name] = prepare_sweep(fm, cfg)[1]
    cost = per_trial_cost(problems, nodes)
    print("sweep kernel, CPU time per trial, one thread, U_p = 0:50:10 (6 values), 10,000 "
          "trials, same nodes: " + ", ".join(f"{n} {c * 1e9:.0f} ns" for n, c in cost.items())
          + f"; harmonic / linear = {cost['harmonic'] / cost['linear']:.2f}")  # fmt: skip
    for name in ("linear", "harmonic"):
        cfg = SweepConfig(up_um=[20.0], trials=10000, seed=args.seed, field_model=name)
        problems[name] = prepare_sweep(fm, cfg)[1]
    cost = per_trial_cost(problems, nodes)
    print("sweep kernel, one U_p value (20 um): "
          + ", ".join(f"{n} {c * 1e9:.0f} ns" for n, c in cost.items())
          + f"; harmonic / linear = {cost['harmonic'] / cost['linear']:.2f}")  # fmt: skip
    cost = evaluation_cost(fm, fit, nodes, 1000, args.seed)
    print("field at arbitrary points (field_at, as compare, diagnose and coupled use it), CPU "
          "time per point, one thread: "
          + ", ".join(f"{n} {c * 1e9:.0f} ns" for n, c in cost.items())
          + f"; harmonic / linear = {cost['harmonic'] / cost['linear']:.2f}")  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
