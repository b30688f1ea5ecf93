"""Axis velocities at acquisition, recorded or inferred from the scan.

A reading delay displaces the probe along the velocity it had when the reading was taken, so
only the axes moving at that instant carry it. Recordings may give the signed velocities
(``v_x, v_y, v_z``); otherwise they are inferred from the commanded positions in acquisition
order, ``t_s`` and ``speed``: on the fly, the probe passes through a point along the straight
move that joins it to a neighbouring reading of the same scan line, so the velocity is ``speed``
along that move. The approach directions (``dir_*``) say nothing about motion at acquisition (a
standing axis keeps the direction of its last move) and are not used here.
"""

from __future__ import annotations

import numpy as np

__all__ = ["axis_velocities"]

#: Relative tolerance when comparing the apparent speed of a move (distance / time) with the
#: recorded speed, and when calling a move single-axis.
_SPEED_TOL = 0.3
_AXIS_TOL = 1e-6


def _single_axis(delta):
    """Axis index of a move along one axis only, -1 otherwise; delta shape (n, 3), mm."""
    a = np.abs(delta)
    big = a.max(1)
    axis = a.argmax(1)
    others = a.sum(1) - big
    ok = (big > 0) & (others <= _AXIS_TOL * np.maximum(big, 1e-300))
    return np.where(ok, axis, -1)


def axis_velocities(cmd, speed, t_s=None, vel=None, order=None):
    """Signed axis velocities at acquisition, mm/s.

    Parameters
    ----------
    cmd : ndarray, shape (n, 3), mm
        Commanded axis positions.
    speed : ndarray, shape (n,), mm/s, or None
        Speed of the move at acquisition (0: stop-and-go). None: no motion known.
    t_s : ndarray, shape (n,), s, optional
        Acquisition times; they give the acquisition order and tell the neighbour on the same
        scan line (its distance over the time step matches ``speed``).
    vel : ndarray, shape (n, 3), mm/s, optional
        Recorded velocities: returned as they are.
    order : ndarray, shape (n,), int, optional
        Acquisition order when ``t_s`` is absent (default: row order).

    Returns
    -------
    vel : ndarray, shape (n, 3), mm/s, or None
        None when neither velocities nor speeds are known.
    source : str
        ``'recorded'``, ``'inferred'`` or ``'none'``.
    """
    if vel is not None:
        return np.asarray(vel, dtype=np.float64), "recorded"
    if speed is None:
        return None, "none"
    cmd = np.asarray(cmd, dtype=np.float64)
    speed = np.asarray(speed, dtype=np.float64)
    n = len(cmd)
    out = np.zeros((n, 3))
    moving = speed > 0
    if not moving.any() or n < 2:
        return out, "inferred"
    if order is None:
        order = np.argsort(t_s, kind="stable") if t_s is not None else np.arange(n)
    c = cmd[order]
    sp = speed[order]
    step = np.diff(c, axis=0)  # move from row k to row k + 1 (acquisition order)
    axis = _single_axis(step)
    same_speed = np.isclose(sp[1:], sp[:-1], rtol=1e-6)
    line = (axis >= 0) & same_speed
    if t_s is not None:
        dt = np.diff(np.asarray(t_s, dtype=np.float64)[order])
        dist = np.abs(step).max(1)
        with np.errstate(divide="ignore", invalid="ignore"):
            apparent = dist / dt
        line &= np.abs(apparent - sp[1:]) <= _SPEED_TOL * np.maximum(sp[1:], 1e-300)
    else:
        # without times, the scan axis is the axis of most single-axis moves
        counts = np.bincount(axis[axis >= 0], minlength=3)
        line &= axis == int(np.argmax(counts))
    # each reading takes the move to its next reading on the line, else the move from its
    # previous one (the last reading of a line)
    nxt = np.r_[line, False]
    prv = np.r_[False, line]
    vo = np.zeros((n, 3))
    for k in np.flatnonzero(moving[order]):
        if nxt[k]:
            d = step[k]
        elif prv[k]:
            d = step[k - 1]
        else:
            continue
        a = int(np.argmax(np.abs(d)))
        vo[k, a] = np.sign(d[a]) * sp[k]
    out[order] = vo
    return out, "inferred"
