"""Scan plans: the order, timing, approach directions and speeds of every acquisition.

A grid is mapped line by line along z (x slowest, then y, z along the line). Every repetition
visits all lines; even repetitions take them in ascending order, odd ones in descending order, so
x and y are approached from both sides over a recording. Lines run alternately up and down in z
(serpentine), with an overtravel before the first point of each line so that every point of a
line is approached in the line's direction.

A repetition is either stop-and-go (each point reached by a trapezoidal move, then settle, then
acquire; ``speed`` 0) or on the fly (z moves through the line at a constant speed, the
acquisitions triggered at the grid positions; ``speed`` that speed, only z moving).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Scan", "plan", "move_time"]

V_MAX = 20.0  # mm/s, point-to-point moves
ACC = 50.0  # mm/s^2
SETTLE_S = 1.0
ACQUIRE_S = 0.5
OVERTRAVEL_MM = 5.0


@dataclass
class Scan:
    """Acquisitions in time order.

    Attributes
    ----------
    point : ndarray, shape (n,), int
        Index of the grid point (x slowest, z fastest).
    rep : ndarray, shape (n,), int
    q : ndarray, shape (n, 3), mm
        Commanded axis travel at the acquisition.
    t_s : ndarray, shape (n,), s
        Time of the acquisition since the start of the recording.
    dir : ndarray, shape (n, 3), int
        Direction of each axis's own last move (+1, -1); a standing axis keeps it.
    speed : ndarray, shape (n,), mm/s
        Speed of the move at the acquisition (0: stop-and-go).
    v : ndarray, shape (n, 3), mm/s
        Signed axis velocities at the acquisition.
    """

    point: np.ndarray
    rep: np.ndarray
    q: np.ndarray
    t_s: np.ndarray
    dir: np.ndarray
    speed: np.ndarray
    v: np.ndarray

    def columns(self, temp_c) -> dict:
        """The optional recording columns (t_s, dir_*, speed, v_*, temp_C) of these rows."""
        out = {"t_s": self.t_s}
        out |= {f"dir_{c}": self.dir[:, a] for a, c in enumerate("xyz")}
        out["speed"] = self.speed
        out |= {f"v_{c}": self.v[:, a] for a, c in enumerate("xyz")}
        return out | {"temp_C": temp_c}


def move_time(dist_mm, v_max: float = V_MAX, acc: float = ACC) -> np.ndarray:
    """Duration (s) of a trapezoidal (or triangular) move over ``dist_mm`` from rest to rest."""
    d = np.abs(np.asarray(dist_mm, dtype=float))
    tri = 2.0 * np.sqrt(d / acc)
    return np.where(d > v_max**2 / acc, d / v_max + v_max / acc, tri)


class _Axes:
    """Position, last move direction per axis and the clock."""

    def __init__(self, start):
        self.pos = np.asarray(start, dtype=float).copy()
        self.last = np.ones(3, dtype=int)  # homed from below: every axis last moved up
        self.t = 0.0

    def move_to(self, target, settle=SETTLE_S):
        step = np.asarray(target, dtype=float) - self.pos
        moved = np.abs(step) > 1e-12
        self.last[moved] = np.sign(step[moved]).astype(int)
        self.t += float(np.max(move_time(step))) + (settle if moved.any() else 0.0)
        self.pos = np.asarray(target, dtype=float).copy()


def plan(gx, gy, gz, speeds) -> Scan:
    """The acquisitions of a recording.

    Parameters
    ----------
    gx, gy, gz : array_like, mm
        Commanded travel of the grid lines (x, y) and of the points along each line (z).
    speeds : sequence of float, mm/s
        One per repetition: 0 for stop-and-go, else the on-the-fly speed (<= ``V_MAX``).

    Returns
    -------
    Scan
    """
    gx, gy, gz = (np.asarray(g, dtype=float) for g in (gx, gy, gz))
    ny, nz = len(gy), len(gz)
    lines = [(i, j) for i in range(len(gx)) for j in range(ny)]
    ax = _Axes([gx[0], gy[0], gz[0] - OVERTRAVEL_MM])
    rows = {k: [] for k in ("point", "rep", "q", "t_s", "dir", "speed", "v")}

    def record(ip, r, q, t, speed, v):
        for k, val in zip(rows, (ip, r, q, t, ax.last.copy(), speed, v), strict=True):
            rows[k].append(val)

    for r, speed in enumerate(speeds):
        order = lines if r % 2 == 0 else lines[::-1]
        for k, (i, j) in enumerate(order):
            s = 1 if (k + r) % 2 == 0 else -1
            zs = gz if s > 0 else gz[::-1]
            iz = np.arange(nz) if s > 0 else np.arange(nz)[::-1]
            ax.move_to([gx[i], gy[j], zs[0] - s * OVERTRAVEL_MM])
            base = (i * ny + j) * nz
            if speed <= 0:
                for z, m in zip(zs, iz, strict=True):
                    ax.move_to([gx[i], gy[j], z])
                    record(base + m, r, ax.pos.copy(), ax.t + 0.5 * ACQUIRE_S, 0.0, np.zeros(3))
                    ax.t += ACQUIRE_S
                continue
            # on the fly: accelerate over the overtravel, then constant speed through the line
            ax.last[2] = s
            ramp = speed / ACC
            t0 = ax.t + ramp + (OVERTRAVEL_MM - 0.5 * speed * ramp) / speed
            vel = np.array([0.0, 0.0, s * speed])
            for z, m in zip(zs, iz, strict=True):
                t = t0 + abs(z - zs[0]) / speed
                record(base + m, r, np.array([gx[i], gy[j], z]), t, speed, vel)
            ax.t = t0 + abs(zs[-1] - zs[0]) / speed + (t0 - ax.t)  # and the same ramp down
            ax.pos = np.array([gx[i], gy[j], zs[-1] + s * OVERTRAVEL_MM])
    return Scan(
        point=np.asarray(rows["point"], dtype=int),
        rep=np.asarray(rows["rep"], dtype=int),
        q=np.asarray(rows["q"], dtype=float),
        t_s=np.asarray(rows["t_s"], dtype=float),
        dir=np.asarray(rows["dir"], dtype=int),
        speed=np.asarray(rows["speed"], dtype=float),
        v=np.asarray(rows["v"], dtype=float),
    )
