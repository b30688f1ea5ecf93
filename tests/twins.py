"""Plain-numpy twins of the numba kernels in cfm_fem._kernels, for tests only (slow, obvious)."""

from __future__ import annotations

import numpy as np
import scipy.spatial

from cfm_fem.mc import coverage_count, shortest_interval, symmetric_interval

M64 = (1 << 64) - 1
GOLDEN = 0x9E3779B97F4A7C15
NODE_GAMMA = 0xD1B54A32D192ED03


def mix64(z: int) -> int:
    z &= M64
    z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) & M64
    z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & M64
    return z ^ (z >> 31)


def stream_key(seed: int, stream: int) -> int:
    return mix64(mix64(seed) + (stream + 1) * NODE_GAMMA)


def uniform_at(key: int, counter: int) -> float:
    return (mix64(key + (counter + 1) * GOLDEN) >> 11) * (1.0 / 9007199254740992.0)


class NormalStream:
    """Marsaglia polar method on the counter-based uniforms, spare kept, as the kernel does."""

    def __init__(self, key: int):
        self.key, self.counter, self.spare = key, 0, None

    def next(self) -> float:
        if self.spare is not None:
            v, self.spare = self.spare, None
            return v
        while True:
            u = 2.0 * uniform_at(self.key, self.counter) - 1.0
            v = 2.0 * uniform_at(self.key, self.counter + 1) - 1.0
            self.counter += 2
            s = u * u + v * v
            if 0.0 < s < 1.0:
                break
        f = np.sqrt(-2.0 * np.log(s) / s)
        self.spare = v * f
        return u * f


def sample_stats(a, p=0.95):
    """mean, std, symmetric low/high, shortest low/high by full sorting (JCGM 101 7.7)."""
    a = np.asarray(a, dtype=np.float64)
    lo, hi = symmetric_interval(a, p)
    slo, shi = shortest_interval(a, p)
    return np.array([a.mean(), a.std(ddof=1), lo, hi, slo, shi])


def gauss_sweep(points, B, up_mm, n_trials, seed, axis=(1.0, 1.0, 1.0), p=0.95):
    """Twin of `cfm_fem._kernels.gauss_sweep` for a 3-D scattered map, using scipy's
    LinearNDInterpolator (Delaunay) and full sorting. Returns stats (n, n_up, 4, 6), n_out."""
    interp = scipy.spatial.Delaunay(points)
    from scipy.interpolate import LinearNDInterpolator

    f = LinearNDInterpolator(interp, B)
    n, n_up = len(points), len(up_mm)
    stats = np.full((n, n_up, 4, 6), np.nan)
    n_out = np.zeros((n, n_up), dtype=np.int64)
    abs0 = np.linalg.norm(B, axis=1)
    for g in range(n):
        rs = NormalStream(stream_key(seed, g))
        z = np.array([[rs.next() for _ in range(3)] for _ in range(n_trials)])
        for k, s in enumerate(up_mm):
            pts = points[g] + s * z * np.asarray(axis)
            Bm = f(pts)
            ok = np.isfinite(Bm[:, 0])
            n_out[g, k] = int((~ok).sum())
            err = Bm[ok] - B[g]
            absb = np.linalg.norm(Bm[ok], axis=1) - abs0[g]
            if ok.sum() >= 2:
                for c in range(3):
                    stats[g, k, c] = sample_stats(err[:, c], p)
                stats[g, k, 3] = sample_stats(absb, p)
    return stats, n_out


def coverage_q(n, p=0.95):
    return coverage_count(n, p)
