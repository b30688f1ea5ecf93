"""Benchmark the sweep: walk kernel vs scipy, and the million-node run. Prints the figures.

    python scripts/bench_sweep.py ratio              # 100,000 scattered nodes, U_p = 20 um
                                                     # (50, 10,000, then 1,000 per node)
    python scripts/bench_sweep.py big                # 1,000,000 nodes, 10,000 trials, 6 U_p
    python scripts/bench_sweep.py big --nodes 200000 --trials 2000   # smaller, same code path
    python scripts/bench_sweep.py big --outside extrapolate   # surface nodes extrapolated
    python scripts/bench_sweep.py big --notch        # a quadrant removed: non-convex map
    python scripts/bench_sweep.py big --field-model harmonic   # per-node harmonic fits
    python scripts/bench_sweep.py big --field-model harmonic --estimator adaptive
                                                     # and the command line's default estimator
    python scripts/bench_sweep.py trial              # CPU ns per trial, one thread, bundled map

``ratio``: perturbed-interpolation samples per second of the numba kernels against
``scipy.interpolate.LinearNDInterpolator`` on the same map and the same perturbed points, handed
to scipy grouped by node (its fastest order, consecutive queries share a simplex), in one run.
The star kernel (`interpolate_groups`) and scipy run alternately, best of three each. The walk
kernel walks from the node's own cell, then (as the sweep does) from the cell of the
displacement's octant, the octant table of the queried nodes built inside the timing.
Also prints the throughput of the full sweep kernel (random numbers and per-node statistics
included), which is what a user gets, and the memory floor of any kernel with this interface:
the time to read the points and write their values into a fresh array, as scipy returns them,
no interpolation (best of three), against the time that 20x scipy allows.

``trial``: CPU time per trial of the sweep kernel on one thread (8,000 random nodes of the
bundled map, 2,000 trials, 6 U_p values, each trial serving all of them), three repeats.

``big``: the whole sweep as the CLI runs it (mesh, kernel, statistics, VTU/PVD/JSON output) on
an FEM-like map with native tetrahedra; prints wall time and peak resident memory.
"""

from __future__ import annotations

import argparse
import resource
import tempfile
import time

import numba
import numpy as np
import scipy.special
from scipy.interpolate import LinearNDInterpolator

from cfm_fem import FieldMap, _kernels
from cfm_fem.io.sweep_out import write_sweep
from cfm_fem.models.interpolation import interpolate_groups, interpolate_points
from cfm_fem.models.mesh import build_mesh, kuhn_simplices, morton_order
from cfm_fem.models.sweep import SweepConfig
from cfm_fem.workflows.sweep.in_memory import run_sweep


def quadrupole_with_ends(p):
    """Exactly harmonic 3-D test field (T) of a 60 T/m quadrupole whose strength falls as
    cos(q z) to zero at z = +-60 mm (p in mm): B = grad Phi, Phi = a I_2(q r) sin(2 theta)
    cos(q z) / q, q = 2 pi / 240 mm, a = 4 G / q (the modified Bessel equation makes the
    Laplacian of Phi vanish), so the harmonic field model holds at every node."""
    q = 2.0 * np.pi / 240.0
    a = 4.0 * 0.06 / q
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    r = np.hypot(x, y)
    th = np.arctan2(y, x)
    i2 = scipy.special.iv(2, q * r)
    di2 = 0.5 * (scipy.special.iv(1, q * r) + scipy.special.iv(3, q * r))  # I_2'
    with np.errstate(invalid="ignore", divide="ignore"):
        i2_r = np.where(r > 0, i2 / np.where(r > 0, q * r, 1.0), 0.0)
    b_r = a * di2 * np.sin(2 * th) * np.cos(q * z)
    b_t = 2.0 * a * i2_r * np.cos(2 * th) * np.cos(q * z)
    b_z = -a * i2 * np.sin(2 * th) * np.sin(q * z)
    c, s = np.cos(th), np.sin(th)
    return np.c_[b_r * c - b_t * s, b_r * s + b_t * c, b_z]


def peak_rss_bytes() -> float:
    """Peak resident set size of this process, bytes (Linux reports kibibytes)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024.0


def bench_ratio(n_nodes: int, layouts, up_um: float, seed: int = 0):
    """Walk kernel vs scipy on the same map and the same perturbed points, for each
    (nodes queried, samples per node) layout; points are grouped by node for both."""
    rng = np.random.default_rng(seed)
    # scattered nodes in a 20 x 20 x 120 mm aperture box
    pts = rng.uniform([-10, -10, -60], [10, 10, 60], (n_nodes, 3))
    fm = FieldMap.from_arrays(pts, quadrupole_with_ends(pts), source="synthetic scattered map")
    t0 = time.perf_counter()
    mesh = build_mesh(fm, "delaunay")
    t_mesh = time.perf_counter() - t0
    print(
        f"map: {n_nodes} scattered nodes, Delaunay {len(mesh.simplices)} tetrahedra "
        f"({t_mesh:.1f} s); U_p = {up_um:g} um; {numba.get_num_threads()} numba threads"
    )
    tri = LinearNDInterpolator(build_scipy_delaunay(mesh), fm.B)
    # Touch 1 GB once before any timing: on this virtual machine the first touch of memory
    # new to the process can cost a page fault in the host, which a timed run that allocates
    # its output (every kernel here, and scipy) would otherwise pay at random.
    np.ones(1 << 27).sum()
    sigma = up_um * 1e-3
    scipy_rate = None
    for n_query, per_node in layouts:
        nodes = rng.choice(n_nodes, n_query, replace=False)
        nodes = nodes[morton_order(pts[nodes])]  # consecutive nodes are neighbours: scipy's
        # walk starts from the previous point's simplex, so this is its fastest order
        disp = rng.normal(0.0, sigma, (n_query, per_node, 3))
        queries = (pts[nodes, None, :] + disp).reshape(-1, 3)  # grouped by node
        # Points grouped by node, as the sweep draws them: the star's vectorised cone test.
        # The star lists are the map's, made once per map (like scipy's Delaunay set-up); their
        # time is printed, and the ratio with it included.
        group_start = np.arange(n_query + 1) * per_node
        mesh.node_stars()  # loads the compiled kernel: the timing below is the work alone
        mesh._stars = None
        t0 = time.perf_counter()
        mesh.node_stars()
        t_stars = time.perf_counter() - t0
        interpolate_groups(mesh, fm.B, queries[:10], [0, 10], nodes[:1])  # compile
        tri(queries[:10])  # scipy's lazy set-up outside the timing too
        # Best of three each, the star kernel's and scipy's runs alternating: a slow phase of
        # the (virtual) machine then falls on both, not on one.
        t_star = t_scipy = np.inf
        for _ in range(3):
            t0 = time.perf_counter()
            ours_star, walked = interpolate_groups(mesh, fm.B, queries, group_start, nodes)
            t_star = min(t_star, time.perf_counter() - t0)
            del ours_star
            t0 = time.perf_counter()
            ref = tri(queries)
            t_scipy = min(t_scipy, time.perf_counter() - t0)
            del ref
        ours_star, walked = interpolate_groups(mesh, fm.B, queries, group_start, nodes)
        ref = tri(queries)
        start = np.repeat(mesh.node_cell[nodes], per_node)
        interpolate_points(mesh, fm.B, queries[:10], start[:10])  # compile outside timing
        t_ours = np.inf
        for _ in range(3):  # best of three too: the first calls here pay the page faults
            t0 = time.perf_counter()  # of memory new to the process (see above)
            ours, cell = interpolate_points(mesh, fm.B, queries, start)
            t_ours = min(t_ours, time.perf_counter() - t0)
        # As the sweep starts its walks: from the cell of the displacement's octant around the
        # node. The octant table of the queried nodes is built inside the timing.
        which = np.repeat(np.arange(n_query), per_node)
        eps = 1e-7 * float(np.ptp(mesh.coords, axis=0).max())
        sub = (pts[nodes], mesh.node_cell[nodes])
        table = _kernels.octant_cells(*sub, mesh.transform, mesh.neighbors, eps)  # compile
        _kernels.octant_starts(queries[:10], which[:10], pts[nodes], table)
        t_oct = np.inf
        for _ in range(3):
            t0 = time.perf_counter()
            table = _kernels.octant_cells(*sub, mesh.transform, mesh.neighbors, eps)
            t_table = time.perf_counter() - t0
            oct_start = _kernels.octant_starts(queries, which, pts[nodes], table)
            ours_oct, cell_oct = interpolate_points(mesh, fm.B, queries, oct_start)
            dt = time.perf_counter() - t0
            if dt < t_oct:
                t_oct, t_table_best = dt, t_table
        t_table = t_table_best
        inside = cell >= 0
        for c in (cell, cell_oct, np.where(np.isfinite(ours_star[:, 0]), 0, -1)):
            assert np.array_equal(c >= 0, np.isfinite(ref[:, 0])), "kernel and scipy disagree"
        # build_mesh triangulates the nodes moved by 1e-6 of the map size (`delaunay_coords`),
        # scipy the nodes themselves: a few near-degenerate cells of the hull differ, and so
        # does the interpolant there; elsewhere the values agree to rounding
        dev = np.max(
            [np.abs(o[inside] - ref[inside]).max(axis=1) for o in (ours, ours_oct, ours_star)], 0
        )
        err, n_off = dev.max(), int((dev > 1e-12).sum())
        n = len(queries)
        print(f"{n_query} nodes x {per_node} samples per node = {n} points:")
        print(
            f"  numba walk kernel, from the node's cell     : {n / t_ours:10.4g} samples/s "
            f"({t_ours:.3f} s, best of 3) = {t_scipy / t_ours:.1f} x scipy"
        )
        print(
            f"  numba walk kernel, from the octant's cell   : {n / t_oct:10.4g} samples/s "
            f"({t_oct:.3f} s, best of 3, of which {t_table:.3f} s octant table) = "
            f"{t_scipy / t_oct:.1f} x scipy"
        )
        print(
            f"  numba star kernel, points grouped by node   : {n / t_star:10.4g} samples/s "
            f"({t_star:.3f} s, best of 3; {walked} points walked) = {t_scipy / t_star:.1f} x "
            f"scipy; the map's star lists took {t_stars:.3f} s, once per map (included: "
            f"{t_scipy / (t_star + t_stars):.1f} x)"
        )
        print(
            f"  scipy LinearND                              : {n / t_scipy:10.4g} samples/s "
            f"({t_scipy:.3f} s, best of 3)   (max |difference| {err:.2e} T; {n_off} of {n} points "
            f"differ by more than 1e-12 T, in cells where the triangulations differ)"
        )
        t_floor = memory_floor(queries)
        print(
            f"  memory floor (read the points, write their values into a fresh array, no "
            f"interpolation): {t_floor:.3f} s; 20 x scipy leaves {t_scipy / 20:.3f} s"
        )
        scipy_rate = n / t_scipy
    # the full sweep kernel: random numbers, walk and per-node statistics, 1 U_p value
    run_sweep(fem_like_map(2000), SweepConfig(up_um=[up_um], trials=20))  # compile
    per_node = layouts[-1][1]
    t0 = time.perf_counter()
    res = run_sweep(fm, SweepConfig(up_um=[up_um], trials=per_node, seed=1), mesh=mesh)
    t_full = time.perf_counter() - t0
    n = n_nodes * per_node
    print(
        f"full sweep kernel, all {n_nodes} nodes x {per_node} trials: {n / t_full:.4g} "
        f"samples/s incl. random numbers and statistics ({t_full:.1f} s); "
        f"{res.linear_in_up.mean():.3f} of the nodes kept every trial in their own cells"
    )
    print(
        f"  against scipy's rate at {per_node} points per node (interpolation only, no random "
        f"numbers or statistics): {n / t_full / scipy_rate:.1f} x"
    )


def memory_floor(points) -> float:
    """Seconds, best of three, to read ``points`` (k, 3) and write a freshly allocated (k, 3)
    float64 array: what any interpolation kernel that returns the values, as scipy does, spends
    on memory alone (numpy, one thread: two numba threads took the same within 10 % here)."""
    best = np.inf
    for _ in range(3):
        t0 = time.perf_counter()
        out = np.multiply(points, 2.0)
        best = min(best, time.perf_counter() - t0)
        del out
    return best


def build_scipy_delaunay(mesh):
    """scipy's Delaunay object for the same points (LinearNDInterpolator needs it)."""
    from scipy.spatial import Delaunay

    return Delaunay(mesh.coords)


def fem_like_map(n_target: int, seed: int = 0, notch: bool = False) -> FieldMap:
    """Native tetrahedra on a jittered grid filling a 20 x 20 x 120 mm aperture box.

    Kuhn tetrahedra of a grid whose inner nodes are moved by up to 15 % of the spacing: an
    unstructured-looking but valid FEM mesh with cells, like an export with its elements.
    ``notch``: the quadrant x > 0, y > 0 removed (its nodes and every cell touching them): a
    non-convex map with a re-entrant edge along z, where the sweep's exact search runs.
    """
    nx = int(round((n_target / 6) ** (1 / 3)))
    shape = (nx, nx, 6 * nx)
    axes = [
        np.linspace(-10, 10, shape[0]),
        np.linspace(-10, 10, shape[1]),
        np.linspace(-60, 60, shape[2]),
    ]
    pts = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    h = np.array([a[1] - a[0] for a in axes])
    idx = np.stack(np.meshgrid(*[np.arange(s) for s in shape], indexing="ij"), -1).reshape(-1, 3)
    inner = np.all((idx > 0) & (idx < np.array(shape) - 1), axis=1)
    rng = np.random.default_rng(seed)
    pts[inner] += rng.uniform(-0.15, 0.15, (inner.sum(), 3)) * h
    cells = kuhn_simplices(shape, np.arange(len(pts)))
    if notch:
        gone = (pts[:, 0] > 1e-9) & (pts[:, 1] > 1e-9)
        cells = cells[~gone[cells].any(axis=1)]
        keep = np.zeros(len(pts), dtype=bool)
        keep[cells.ravel()] = True
        new = np.cumsum(keep) - 1
        pts, cells = pts[keep], new[cells]
    return FieldMap.from_arrays(
        pts, quadrupole_with_ends(pts), cells=cells, source="synthetic FEM map"
    )


def bench_big(n_nodes: int, trials: int, ups: list[float], out: str | None, outside="exclude",
              notch=False, field_model="linear", estimator="plain"):  # fmt: skip
    t0 = time.perf_counter()
    fm = fem_like_map(n_nodes, notch=notch)
    t_map = time.perf_counter() - t0
    cfg = SweepConfig(up_um=ups, trials=trials, seed=0, outside=outside, field_model=field_model,
                      estimator=estimator)  # fmt: skip
    # compile outside the timing
    small = SweepConfig(up_um=ups, trials=20, outside=outside, field_model=field_model,
                        estimator=estimator)  # fmt: skip
    run_sweep(fem_like_map(2000, notch=notch), small)
    t0 = time.perf_counter()
    res = run_sweep(fm, cfg)
    t_run = time.perf_counter() - t0
    res.mesh = res.mesh.for_output()  # as the command line does before writing
    with tempfile.TemporaryDirectory(dir=out) as tmp:
        t1 = time.perf_counter()
        s = write_sweep(tmp, res, {})
        t_write = time.perf_counter() - t1
    total = t_run + t_write
    print(f"map: {fm.n_nodes} nodes, {len(fm.cells)} native tetrahedra (made in {t_map:.1f} s)"
          + (", quadrant x > 0, y > 0 removed (non-convex)" if notch else ""))  # fmt: skip
    print(f"sweep: {trials} trials per node, U_p = {ups} um, {numba.get_num_threads()} threads, "
          f"--outside {outside}, --field-model {field_model}, estimator {estimator}"
          + (" (trials: where the plain Monte Carlo runs)" if estimator == "adaptive" else "")
          )  # fmt: skip
    if res.field_fit is not None:
        print(f"  nodes on the linear interpolant: {int((res.field_fit['degree'] == 0).sum())}")
    print(f"  mesh + kernel + statistics : {t_run:8.1f} s")
    print(f"  writing {len(ups)} .vtu + pvd + json: {t_write:8.1f} s")
    print(f"  total wall                 : {total:8.1f} s  ({total / 60:.1f} min)")
    peak = peak_rss_bytes()  # both units: "4 GB" can be read either way
    print(f"  peak resident memory       : {peak / 1e9:8.2f} GB ({peak / 2**30:.2f} GiB)")
    if estimator == "plain":  # the adaptive estimator's trials differ from node to node
        print(
            f"  trials per second          : {fm.n_nodes * trials / t_run:.4g} "
            f"(all {len(ups)} U_p values per trial)"
        )
    print(
        f"  U_f p95 per U_p [units]    : "
        f"{[round(v, 2) if v is not None else None for v in s['uf_units']['p95']]}"
    )


def bench_trial(n_nodes: int, trials: int):
    from pathlib import Path

    from cfm_fem.io import read_field
    from cfm_fem.workflows.sweep.problem import prepare_sweep

    numba.set_num_threads(1)
    fm = read_field(Path(__file__).resolve().parents[1] / "meshes" / "quadrupole.vtu")
    cfg = SweepConfig(up_um=[0, 10, 20, 30, 40, 50], trials=trials, seed=3)
    _, prob, _ = prepare_sweep(fm, cfg)
    nodes = np.sort(np.random.default_rng(0).choice(len(prob.coords), n_nodes, replace=False))
    prob.run_nodes(nodes[:50])  # compile outside the timing
    for _ in range(3):
        t = time.process_time()
        prob.run_nodes(nodes)
        dt = time.process_time() - t
        print(f"{n_nodes} nodes x {trials} trials, 6 U_p, 1 thread: {dt:.2f} s CPU = "
              f"{dt / (n_nodes * trials) * 1e9:.1f} ns per trial")  # fmt: skip


def main():
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("what", choices=["ratio", "big", "trial"])
    ap.add_argument("--nodes", type=int)
    ap.add_argument("--trials", type=int)
    ap.add_argument(
        "--out", help="folder for the temporary outputs of 'big' (default: system temp)"
    )
    ap.add_argument("--outside", choices=["exclude", "extrapolate"], default="exclude",
                    help="'big': what becomes of trials that leave the map")  # fmt: skip
    ap.add_argument(
        "--notch",
        action="store_true",
        help="'big': remove a quadrant (a non-convex map: the exact search runs)",
    )
    ap.add_argument("--field-model", choices=["linear", "harmonic"], default="linear",
                    help="'big': the field model between nodes")  # fmt: skip
    ap.add_argument("--estimator", choices=["plain", "adaptive"], default="plain",
                    help="'big': plain Monte Carlo of --trials per node, or the command line's "
                         "default adaptive estimator (harmonic model; --trials then serves the "
                         "nodes it leaves to the plain Monte Carlo)")  # fmt: skip
    a = ap.parse_args()
    if a.what == "ratio":
        per_node = a.trials or 1000
        n = a.nodes or 100_000
        # 50 points per node on every node; 10,000 (the CLI's default trials) on 500 nodes;
        # then 1,000 on 5,000 nodes, the trials of the full sweep kernel's run that follows
        bench_ratio(n, [(n, 50), (500, 10_000), (5000, per_node)], 20.0)
    elif a.what == "trial":
        bench_trial(a.nodes or 8000, a.trials or 2000)
    else:
        bench_big(
            a.nodes or 1_000_000,
            a.trials or 10_000,
            [0.0, 10.0, 20.0, 30.0, 40.0, 50.0],
            a.out,
            a.outside,
            a.notch,
            a.field_model,
            a.estimator,
        )


if __name__ == "__main__":
    main()
