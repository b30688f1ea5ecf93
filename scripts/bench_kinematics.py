"""Performance of the paper-scale kinematics Monte Carlo; prints figures, asserts nothing.

    python scripts/bench_kinematics.py [--trials 1000000] [--numpy-trials 1000] [--threads N]
                                       [--variant reference|profile|speed_tau]

1. the full run: ``run_kinematics`` on the reference bench, 936 points, exact HTM chain,
   vibration and delay drawn per point and trial, exact 95 % intervals (one pass: values counted
   below or kept in windows that narrow as the trials accumulate), wall time per stage;
2. a straightforward numpy implementation of the same model and statistics (vectorised over
   points and a batch of trials: 4x4 HTMs of eq. 2-5, numpy's generator, sorting for the
   intervals), run on a subset of trials and scaled linearly to the full run (sorting grows
   faster than linearly, so the scaled figure favours numpy);
3. the arithmetic lower bound on this machine: the normal variates the model needs (3 per point
   and trial, each generated at least once) at the best measured generator throughput, and the
   floating-point work at a measured vectorised peak; and how close the kernel comes (cpu and
   wall).
"""

from __future__ import annotations

import argparse
import os
import time
from dataclasses import replace

import numba
import numpy as np

from cfm_fem import _kernels as K
from cfm_fem.io.bench_toml import read_reference_bench
from cfm_fem.models import kinematics as kin
from cfm_fem.models.bench import ReadingDelay, error_index
from cfm_fem.models.mc import Pdf, symmetric_interval


def numpy_reference_run(bench, trials, seed=0, batch=50):
    """The same Monte Carlo in plain numpy: returns per-point mean, std, low, high (n, 4)."""
    rng = np.random.default_rng(seed)
    q = bench.grid_points()
    sig = bench.noise_std_mm()
    vals = np.empty((trials, len(q), 4))
    for a in range(0, trials, batch):
        m = min(batch, trials - a)
        params = np.stack([e.pdf.sample(rng, m) for e in bench.errors], axis=-1)
        dq = rng.standard_normal((m, len(q), 3)) * sig
        e = kin.probe_errors_for_bench(bench, params, q, dq)
        vals[a : a + m, :, :3] = e
        vals[a : a + m, :, 3] = np.linalg.norm(e, axis=-1)
    lo, hi = symmetric_interval(vals, 0.95, axis=0)
    return vals.mean(0), vals.std(0, ddof=1), lo, hi


#: The script's own loops are not cached: numba checks only this file's date, so a cached loop
#: would keep the generator inlined from an older `_kernels` module.
_JIT = dict(K.JIT, cache=False)


@numba.njit(**_JIT)
def _normals_loop(nkey, fkey, n, point):
    s = 0.0
    for t in range(n):
        z0, z1, z2 = K.rng._three_normals(K.trial_key(nkey, t), fkey, point)
        s += z0 + z1 + z2
    return s


@numba.njit(**_JIT)
def _hash_loop(keys, reps, point):
    # the two counter hashes of `_zig_fast3` alone (what the generator pays before the ziggurat)
    n = keys.shape[0]
    s = np.uint64(0)
    c = np.uint64(point) * np.uint64(4)
    for _ in range(reps):
        for k in range(n):
            s ^= K.rng._draw(keys[k], c) ^ K.rng._draw(keys[k], c + np.uint64(1))
    return s


@numba.njit(**_JIT)
def _flop_loop(x, y, reps):
    # independent elements in L1: vectorised multiplies and adds (11 flops per element)
    for _ in range(reps):
        for i in range(x.shape[0]):
            v = x[i]
            y[i] = ((((v * 1.0001 + 0.5) * v + 0.25) * v + 0.125) * v + 0.0625) * v + y[i] * 0.5


@numba.njit(**_JIT)
def _block_normals_loop(keys, fkey, reps, point):
    n = keys.shape[0]
    z = np.empty((3, n))
    ok = np.empty(n, dtype=np.bool_)
    s = 0.0
    for r in range(reps):
        K.normals_by_key(keys, fkey, point + r, n, z, ok)
        s += z[0, 0]
    return s


def measure_peaks():
    """(ns per normal: counter-based ziggurat one at a time and by blocks (the kernels' way),
    numpy's generator) and GFLOP/s, one core."""
    _, nkey, fkey = kin.geometry._keys(0)
    _normals_loop(nkey, fkey, 10, 3)
    n = 2_000_000
    t = time.process_time()
    _normals_loop(nkey, fkey, n, 3)
    ns_scalar = (time.process_time() - t) / (3 * n) * 1e9
    keys = np.empty(4096, dtype=np.uint64)
    K.trial_keys(nkey, 0, 4096, keys)
    _block_normals_loop(keys, fkey, 2, 0)
    reps = n // 4096
    t = time.process_time()
    _block_normals_loop(keys, fkey, reps, 0)
    ns_block = (time.process_time() - t) / (3 * 4096 * reps) * 1e9
    _hash_loop(keys, 1, 0)
    t = time.process_time()
    _hash_loop(keys, reps, 0)
    ns_hash = (time.process_time() - t) / (3 * 4096 * reps) * 1e9
    ns_ours = min(ns_scalar, ns_block)
    rng = np.random.default_rng(0)
    rng.standard_normal(10)
    t = time.process_time()
    rng.standard_normal(6_000_000)
    ns_numpy = (time.process_time() - t) / 6_000_000 * 1e9
    x = np.random.default_rng(1).random(2048)
    y = np.zeros_like(x)
    _flop_loop(x, y, 1)
    reps = 20_000
    t = time.process_time()
    _flop_loop(x, y, reps)
    gflops = 11 * 2048 * reps / (time.process_time() - t) / 1e9
    return ns_ours, ns_scalar, ns_block, ns_hash, ns_numpy, gflops


def numpy_comparison(bench, m, trials, wall_full, npts):
    """Time the numpy implementation on m trials, scale it to ``trials`` and print the ratio."""
    t = time.perf_counter()
    ref = numpy_reference_run(bench, m)
    wall_np = time.perf_counter() - t
    scaled = wall_np * trials / m
    print(
        f"\nnumpy implementation of the same model: {m} trials in {wall_np:.2f} s "
        f"({wall_np / (m * npts) * 1e9:.0f} ns per sample, one thread)"
    )
    ratio = scaled / wall_full
    print(f"  scaled to {trials} trials: {scaled:.0f} s  ->  kernel speed-up {ratio:.0f}x")
    chk = kin.run_kinematics(bench, trials=m, seed=3)
    print(
        f"  (same statistics; numpy {m} trials vs kernel {m} trials, different random streams: "
        f"pooled X std {np.sqrt(np.mean(ref[1][:, 0] ** 2)) * 1e3:.2f} vs "
        f"{chk.pooled['x']['std_um']:.2f} um)"
    )


def bench_variant(name):
    """The reference bench, or it with delta_z(z) position dependent (profile 0.2 + u - 0.5 u^2:
    the full HTM chain per sample) or with a speed x tau reading delay (20 mm/s along z, tau
    uniform on [0, 0.2] ms): the benches off the hand-vectorised path."""
    bench = read_reference_bench()
    if name == "profile":
        errors = list(bench.errors)
        k = error_index("delta_z(z)")
        errors[k] = replace(errors[k], profile=(0.2, 1.0, -0.5))
        bench = replace(bench, errors=tuple(errors))
    elif name == "speed_tau":
        delay = ReadingDelay("speed_tau", np.zeros(3), np.array([0.0, 0.0, 20.0]),
                             Pdf.uniform(0.0, 2e-4))  # fmt: skip
        bench = replace(bench, delay=delay)
    return bench


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=1_000_000)
    ap.add_argument("--numpy-trials", type=int, default=1000)
    ap.add_argument("--threads", type=int, default=numba.config.NUMBA_NUM_THREADS)
    ap.add_argument("--variant", choices=["reference", "profile", "speed_tau"],
                    default="reference", help="bench (`bench_variant`)")  # fmt: skip
    args = ap.parse_args()
    numba.set_num_threads(args.threads)
    bench = bench_variant(args.variant)
    print(f"bench: {args.variant}")
    npts = len(bench.grid_points())
    pairs = args.trials * npts
    print(
        f"machine: {os.cpu_count()} CPUs, numba threads {numba.get_num_threads()}, "
        f"load average {os.getloadavg()[0]:.2f}"
    )

    t = time.perf_counter()
    kin.run_kinematics(bench, trials=200_000, seed=1)  # compile (cached) and warm up, narrowing
    print(f"warm-up (compile or load from cache): {time.perf_counter() - t:.1f} s")

    t = time.perf_counter()
    c = time.process_time()
    full = kin.run_kinematics(bench, trials=args.trials, seed=0)
    wall_full = time.perf_counter() - t
    cpu_full = time.process_time() - c
    print(
        f"\nfull run, exact intervals: {args.trials} trials x {npts} points = {pairs:.3g} samples"
    )
    print(
        f"  wall {wall_full:.2f} s (cpu {cpu_full:.1f} s); stages: "
        + ", ".join(f"{k} {v:.2f}" for k, v in full.seconds.items())
    )
    print(f"  {wall_full / pairs * 1e9:.2f} ns wall per (trial, point) sample")
    for note in full.notes:
        print(f"  note: {note}")
    for a in "xyz":
        p = full.pooled[a]
        print(
            f"  {a.upper()}: systematic {p['systematic_um']:.2f} um, std {p['std_um']:.2f} um, "
            f"U_p {p['U_p_um']:.2f} um"
        )

    m = args.numpy_trials
    if args.variant == "speed_tau" or m < 2:  # the numpy twin draws normal noise only
        print("\nnumpy implementation: skipped (--numpy-trials < 2, or a speed x tau delay)")
    else:
        numpy_comparison(bench, m, args.trials, wall_full, npts)

    ns_ours, ns_scalar, ns_block, ns_hash, ns_numpy, gflops = measure_peaks()
    cores = numba.get_num_threads()
    # every sample needs its 3 normals at least once, whatever the statistics algorithm
    normals = 3 * pairs
    best = min(ns_ours, ns_numpy)
    cpu_rng = normals * best * 1e-9
    flops = 40 * pairs  # 18 multiply-adds (36 flops), |E| (6): per sample, once
    cpu_flop = flops / (gflops * 1e9)
    cpu_bound = max(cpu_rng, cpu_flop)
    print("\narithmetic lower bound on this machine (each sample generated once):")
    print(f"  normal variates: 3 per sample, {normals:.3g}; measured {ns_block:.2f} ns each "
          f"(counter-based ziggurat by blocks of 4096, fast path vectorised), {ns_scalar:.2f} ns "
          f"one at a time, numpy's generator {ns_numpy:.2f} ns")  # fmt: skip
    print(
        f"    of the block generator's {ns_block:.2f} ns: {ns_hash:.2f} ns the counter hashes "
        "(SplitMix64, 2 per 3 normals), the rest the ziggurat (tables, test, slow-path redo)"
    )
    print(f"  -> {cpu_rng:.1f} cpu-s at {best:.2f} ns per normal")
    print(f"  floating point: ~{flops:.3g} flops at a measured {gflops:.1f} GFLOP/s per core "
          f"(vectorised) -> {cpu_flop:.1f} cpu-s")  # fmt: skip
    print(f"  bound {cpu_bound:.1f} cpu-s = {cpu_bound / cores:.2f} s wall on {cores} cores")
    print(f"  the run used {cpu_full:.1f} cpu-s ({cpu_full / cpu_bound:.1f}x the bound) and "
          f"{wall_full:.2f} s wall ({wall_full / (cpu_bound / cores):.1f}x)")  # fmt: skip
    if cpu_full < 1.5 * wall_full:
        print(
            f"  note: cpu {cpu_full:.1f} s for {wall_full:.1f} s wall: the {cores} threads did "
            "not get their cores (other load on the machine); the wall figures are inflated"
        )


if __name__ == "__main__":
    main()
