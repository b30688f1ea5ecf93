"""A family of scan plans: grids, on-the-fly lines at several speeds, circles at a radius and
sparse maps, each drawn from a seed and described by a plain dict (written into the truth).

Coordinates of a description are those of the recording: map points (magnet frame, mm) for a
Hall map, axis travel (mm) for a tracker recording; :func:`build` adds the travel offset.

* ``grid``: lines along z through an x-y grid (:func:`.scan.plan`): stop-and-go and on-the-fly
  repetitions, serpentine, both approach directions;
* ``lines``: a few z lines, every repetition on the fly, at two or more speeds;
* ``circle``: ``n_phi`` points on a circle of radius ``radius_mm`` about the axis in each z
  plane, stop-and-go, the sense of rotation reversed every repetition;
* ``sparse``: a random subset of a lattice, stop-and-go, serpentine in z.
"""

from __future__ import annotations

import numpy as np

from .scan import ACQUIRE_S, SETTLE_S, Scan, move_time, plan

__all__ = ["SCAN_KINDS", "draw_scan", "build", "map_points"]

SCAN_KINDS = ("grid", "lines", "circle", "sparse")
SPEEDS = (2.0, 5.0, 10.0, 15.0, 20.0)


def _lin(lo, hi, n):
    return np.round(np.linspace(lo, hi, int(n)), 6).tolist()


def draw_scan(rng, kind: str, xy_half_mm, z_range_mm, size: str, n_reps: int) -> dict:
    """A scan description.

    Parameters
    ----------
    rng : numpy.random.Generator
    kind : str
        One of :data:`SCAN_KINDS`.
    xy_half_mm : (float, float)
        Half extent in x and y about the centre (0 for a Hall map; mid-stroke for a tracker
        recording is added by the caller through ``centre``).
    z_range_mm : (float, float)
    size : {'small', 'full'}
    n_reps : int

    Returns
    -------
    dict
    """
    small = size == "small"
    hx, hy = (float(v) for v in xy_half_mm)
    z0, z1 = (float(v) for v in z_range_mm)
    nz = int(rng.integers(13, 22) if small else rng.integers(21, 36))
    desc = {"kind": kind, "n_reps": int(n_reps), "z": _lin(z0, z1, nz)}
    if kind == "grid":
        n = 3 if small else int(rng.integers(4, 7))
        desc |= {"x": _lin(-hx, hx, n), "y": _lin(-hy, hy, n)}
        cycle = [0.0] + [float(v) for v in rng.choice(SPEEDS, 3, replace=False)]
        if rng.uniform() < 0.3:
            cycle = [0.0]
        desc["speeds"] = [cycle[r % len(cycle)] for r in range(n_reps)]
    elif kind == "lines":
        n = int(rng.integers(2, 4))
        desc |= {"x": _lin(-hx, hx, n), "y": _lin(-hy, hy, 2)}
        sp = [float(v) for v in rng.choice(SPEEDS, 3, replace=False)]
        desc["speeds"] = [sp[r % len(sp)] for r in range(n_reps)]
    elif kind == "circle":
        desc |= {
            "radius_mm": float(rng.uniform(0.5, 1.0) * min(hx, hy)),
            "n_phi": int(rng.choice([6, 8, 12])),
        }
    elif kind == "sparse":
        n = 5 if small else 7
        x, y = _lin(-hx, hx, n), _lin(-hy, hy, n)
        total = n * n * nz
        keep = np.sort(rng.choice(total, int(rng.uniform(0.2, 0.4) * total), replace=False))
        desc |= {"x": x, "y": y, "keep": keep.tolist()}
    else:
        raise ValueError(f"unknown scan kind {kind!r}; expected one of {SCAN_KINDS}")
    return desc


def map_points(desc: dict) -> np.ndarray:
    """The distinct points of a scan (recording coordinates), shape (m, 3), mm, in point_id
    order."""
    z = np.asarray(desc["z"])
    if desc["kind"] == "circle":
        f = 2.0 * np.pi * np.arange(desc["n_phi"]) / desc["n_phi"]
        r = desc["radius_mm"]
        xy = np.stack([r * np.cos(f), r * np.sin(f)], -1)
        return np.array([[*p, zz] for zz in z for p in xy])
    x, y = np.asarray(desc["x"]), np.asarray(desc["y"])
    pts = np.stack(np.meshgrid(x, y, z, indexing="ij"), -1).reshape(-1, 3)
    if desc["kind"] == "sparse":
        pts = pts[np.asarray(desc["keep"], dtype=int)]
    return pts


def _stop_and_go(targets, order_per_rep) -> Scan:
    """Stop-and-go acquisitions of ``targets`` (travel, shape (m, 3)) in the given order per
    repetition; every move is a trapezoidal move of each axis, then settle, then acquire."""
    pos = targets[order_per_rep[0][0]] - 5.0  # homed from below
    last = np.ones(3, dtype=int)
    t = 0.0
    rows = {k: [] for k in ("point", "rep", "q", "t_s", "dir")}
    for r, order in enumerate(order_per_rep):
        for i in order:
            step = targets[i] - pos
            moved = np.abs(step) > 1e-12
            last[moved] = np.sign(step[moved]).astype(int)
            t += float(np.max(move_time(step))) + (SETTLE_S if moved.any() else 0.0)
            pos = targets[i].copy()
            for k, v in zip(
                rows, (i, r, pos.copy(), t + 0.5 * ACQUIRE_S, last.copy()), strict=True
            ):
                rows[k].append(v)
            t += ACQUIRE_S
    n = len(rows["point"])
    return Scan(
        point=np.asarray(rows["point"], dtype=int),
        rep=np.asarray(rows["rep"], dtype=int),
        q=np.asarray(rows["q"], dtype=float),
        t_s=np.asarray(rows["t_s"], dtype=float),
        dir=np.asarray(rows["dir"], dtype=int),
        speed=np.zeros(n),
        v=np.zeros((n, 3)),
    )


def build(desc: dict, offset_mm) -> Scan:
    """The acquisitions of a scan, commanded travel = recording coordinates + ``offset_mm``."""
    off = np.asarray(offset_mm, dtype=float)
    reps = desc["n_reps"]
    if desc["kind"] in ("grid", "lines"):
        g = [np.asarray(desc[c]) + off[k] for k, c in enumerate("xyz")]
        return plan(*g, desc["speeds"])
    pts = map_points(desc) + off
    m = len(pts)
    if desc["kind"] == "circle":
        nphi = desc["n_phi"]
        nz = m // nphi
        orders = []
        for r in range(reps):
            seq = []
            for kz in range(nz):
                ring = np.arange(nphi) if r % 2 == 0 else np.arange(nphi)[::-1]
                seq += list(kz * nphi + np.roll(ring, kz))
            orders.append(seq if r % 2 == 0 else seq[::-1])
        return _stop_and_go(pts, orders)
    # sparse: serpentine in z over the (x, y) columns, reversed every other repetition
    cols = {}
    for i, p in enumerate(pts):
        cols.setdefault((p[0], p[1]), []).append(i)
    seq = []
    for k, key in enumerate(sorted(cols)):
        ids = sorted(cols[key], key=lambda i: pts[i, 2])
        seq += ids if k % 2 == 0 else ids[::-1]
    return _stop_and_go(pts, [seq if r % 2 == 0 else seq[::-1] for r in range(reps)])
