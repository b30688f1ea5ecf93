"""Stitch an EMPHATIC fringe scan to the body scan by direct least squares (numpy, scipy).

The fringe scan, placed at the owners' offset (``scripts/diagnose_emphatic.py``), is read at the
body scan's nodes by tensor-product quadratic (three-point Lagrange) interpolation along each
axis, and the body field there is fitted as B_body(q) = B_fringe(q + t) / (1 + g): a translation t
of the magnet between the two scans (a fringe reading at p sees B_body(p - t), the diagnosis'
``magnet_d*``) and one gain g per field component. Body nodes with |x|, |y| <= 10 mm whose
stencil lies in the fringe scan are used. The standard errors are those of the least-squares fit
with the residuals' own variance; each gain has a prior (:data:`GAIN_PRIOR_PCT`, as the
diagnosis' Hall gains), ``--free-gains`` drops it. Independent of ``cfm-fem diagnose``: the
check on its answer.

    python scripts/stitch_emphatic.py [--data ../shared/data/emphatic] [--sides small,large]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from scipy.optimize import least_squares

IN = 25.4
#: The owners' offsets (mm): position in the file minus offset = physical position.
OWNERS_OFFSET_MM = {"small": (-0.144, -0.411, 312.486), "large": (0.375, 0.081, -200.079)}
FILES = {
    "small": "EMPHATIC_smallApertureFringe_cleaned.csv",
    "large": "EMPHATIC_largeApertureFringe_cleaned.csv",
}
BODY = "EMPHATIC_body_scan_5280148.csv"
HALF_WIDTH_MM = 10.0
#: Prior std of each gain, % (a Hall probe's calibration, Table I S_HP of the method's paper):
#: along z a shift of an exponential-like fringe field and a common gain have the same
#: signature, so without it the fit slides along that valley.
GAIN_PRIOR_PCT = 0.15


def read_scan(path: Path, z_column: int):
    """Points (n, 3) mm and field (n, 3) T of a scan: X, Y and the given z column."""
    rows = []
    for line in Path(path).read_text().splitlines():
        if line.startswith("%") or not line.strip():
            continue
        f = line.split(",")
        rows.append([float(f[0]), float(f[1]), float(f[z_column]), *map(float, f[4:7])])
    a = np.array(rows)
    return a[:, :3] * IN, a[:, 3:6]


def _axis_nodes(u, tol: float = 0.05) -> np.ndarray:
    """Distinct coordinates (sorted) of one axis, those closer than ``tol`` mm merged."""
    u = np.sort(u)
    starts = np.r_[True, np.diff(u) > tol]
    return np.array([g.mean() for g in np.split(u, np.flatnonzero(starts)[1:])])


def _lagrange3(nodes, i0, u) -> np.ndarray:
    """Weights (m, 3) of the quadratic through nodes[i0], nodes[i0 + 1], nodes[i0 + 2] at u."""
    x = np.stack([nodes[i0], nodes[i0 + 1], nodes[i0 + 2]], 1)
    w = np.ones((len(u), 3))
    for a in range(3):
        for b in range(3):
            if a != b:
                w[:, a] *= (u - x[:, b]) / (x[:, a] - x[:, b])
    return w


class QuadraticGrid:
    """Tensor-product quadratic interpolation of a scan on a (possibly incomplete) grid.

    Each axis' stencil is the three nodes centred on the nearest one (shifted to stay in the
    grid); where a stencil node is missing (a corner column), the stencils shifted one node
    towards the grid's middle along x, then y, then both are tried; NaN if none is complete.
    """

    def __init__(self, points, B):
        self.axes = [_axis_nodes(points[:, j]) for j in range(3)]
        idx = np.stack([np.abs(points[:, j, None] - self.axes[j]).argmin(1) for j in range(3)], 1)
        shape = tuple(len(a) for a in self.axes)
        self.values = np.full((*shape, 3), np.nan)
        self.values[idx[:, 0], idx[:, 1], idx[:, 2]] = B

    def __call__(self, q) -> np.ndarray:
        q = np.atleast_2d(q)
        out = np.full((len(q), 3), np.nan)
        start = []
        for j in range(3):
            a = self.axes[j]
            near = np.abs(q[:, j, None] - a).argmin(1)
            c = np.clip(near - 1, 0, len(a) - 3)
            inward = np.clip(c + np.where(q[:, j] > a.mean(), -1, 1), 0, len(a) - 3)
            start.append((c, inward))
        inside = np.all([(q[:, j] >= self.axes[j][0]) & (q[:, j] <= self.axes[j][-1])
                         for j in range(3)], axis=0)  # fmt: skip
        for sx, sy in ((0, 0), (1, 0), (0, 1), (1, 1)):
            i0 = (start[0][sx], start[1][sy], start[2][0])
            w = [_lagrange3(self.axes[j], i0[j], q[:, j]) for j in range(3)]
            val = np.zeros((len(q), 3))
            for a in range(3):
                for b in range(3):
                    for c in range(3):
                        v = self.values[i0[0] + a, i0[1] + b, i0[2] + c]
                        val += (w[0][:, a] * w[1][:, b] * w[2][:, c])[:, None] * v
            todo = ~np.isfinite(out).all(1)
            out[todo] = val[todo]
        out[~inside] = np.nan
        return out


def stitch(
    fringe_points,
    fringe_B,
    body_points,
    body_B,
    half_width_mm: float = HALF_WIDTH_MM,
    gain_prior_pct: float | None = GAIN_PRIOR_PCT,
):
    """Translation (um) and gains (%) of the fringe scan against the body scan (module
    docstring).

    Returns
    -------
    dict
        ``shift_um``, ``shift_std_um`` (3,), ``gain_pct``, ``gain_std_pct`` (3,), ``corr``
        (6, 6) correlation matrix (shift then gains), ``rms_units`` (residual rms in units of
        1e-4 max |B_body|) and ``n`` (body nodes used).
    """
    grid = QuadraticGrid(np.asarray(fringe_points, float), np.asarray(fringe_B, float))
    q, Bb = np.asarray(body_points, float), np.asarray(body_B, float)
    keep = (np.abs(q[:, :2]).max(1) <= half_width_mm + 0.5) & np.isfinite(grid(q)).all(1)
    # one node spacing of margin along z so a move never leaves the fringe scan
    dz = np.median(np.diff(grid.axes[2]))
    keep &= (q[:, 2] >= grid.axes[2][0] + 0.5 * dz) & (q[:, 2] <= grid.axes[2][-1] - 0.5 * dz)
    q, Bb = q[keep], Bb[keep]
    units = 1e-4 * float(np.max(np.linalg.norm(body_B, axis=1)))

    def resid(x):
        r = ((Bb - grid(q + x[:3] * 1e-3) / (1.0 + x[3:] * 1e-2)) / units).ravel()
        return r if gain_prior_pct is None else np.r_[r, x[3:] / gain_prior_pct * s_prior]

    s_prior = 1.0
    if gain_prior_pct is not None:  # prior in units of the residuals' own scatter
        free = stitch(fringe_points, fringe_B, body_points, body_B, half_width_mm, None)
        s_prior = free["rms_units"]

    fit = least_squares(resid, np.zeros(6), x_scale=np.r_[np.full(3, 10.0), np.full(3, 0.1)])
    r = fit.fun[: Bb.size]
    s2 = float(r @ r) / (r.size - 6)
    cov = np.linalg.inv(fit.jac.T @ fit.jac) * s2
    std = np.sqrt(np.diag(cov))
    return {
        "shift_um": fit.x[:3],
        "shift_std_um": std[:3],
        "gain_pct": fit.x[3:],
        "gain_std_pct": std[3:],
        "corr": cov / np.outer(std, std),
        "rms_units": float(np.sqrt(np.mean(r**2))),
        "n": int(len(q)),
    }


def _pair(s: dict, what: str):
    """Values and standard errors of ``shift`` (um) or ``gain`` (%) of a `stitch` result."""
    unit = "um" if what == "shift" else "pct"
    return s[f"{what}_{unit}"], s[f"{what}_std_{unit}"]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    here = Path(__file__).resolve().parents[1]
    ap.add_argument("--data", default=str(here.parent / "shared" / "data" / "emphatic"))
    ap.add_argument("--sides", default="small,large")
    ap.add_argument("--free-gains", action="store_true", help="no prior on the gains")
    a = ap.parse_args(argv)
    data = Path(a.data)
    prior = None if a.free_gains else GAIN_PRIOR_PCT
    body_p, body_B = read_scan(data / BODY, 3)  # Zmagnet: the magnet frame
    print("| scan | body nodes | shift um (x, y, z) | gains % (x, y, z) | rms units "
          "| corr(dz, g_z) |")  # fmt: skip
    print("|---|---|---|---|---|---|")
    for side in a.sides.split(","):
        p, B = read_scan(data / FILES[side], 2)  # Z(stage), placed by the owners' offset
        s = stitch(p - np.asarray(OWNERS_OFFSET_MM[side]), B, body_p, body_B, gain_prior_pct=prior)
        sh = ", ".join(f"{v:.1f} +- {e:.1f}" for v, e in zip(*_pair(s, "shift"), strict=True))
        g = ", ".join(f"{v:.3f} +- {e:.3f}" for v, e in zip(*_pair(s, "gain"), strict=True))
        print(f"| {side} aperture | {s['n']} | {sh} | {g} | {s['rms_units']:.3f} "
              f"| {s['corr'][2, 5]:+.3f} |")  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
