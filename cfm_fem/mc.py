"""GUM Supplement 1 (JCGM 101:2008) machinery shared by every workflow.

Coverage intervals from Monte Carlo samples (section 7.7), the numerical tolerance of a standard
uncertainty (section 7.9.2) and the validation of the GUM uncertainty framework against Monte Carlo
(section 8).
"""

from __future__ import annotations


import numpy as np

__all__ = [
    "coverage_count",
    "symmetric_interval",
    "shortest_interval",
    "numerical_tolerance",
    "gum_validation",
]


def coverage_count(m: int, p: float = 0.95) -> int:
    """Number of sample intervals q spanned by a coverage interval (JCGM 101, 7.7.1).

    q = p*M if that is an integer, else int(p*M + 1/2).
    """
    pm = p * m
    q = round(pm) if abs(pm - round(pm)) < 1e-9 else int(pm + 0.5)
    return int(min(max(q, 1), m - 1))


def symmetric_interval(samples, p: float = 0.95, axis: int = -1, presorted: bool = False):
    """Probabilistically symmetric coverage interval (JCGM 101, 7.7.2).

    Parameters
    ----------
    samples : ndarray, shape (..., M)
        Monte Carlo values along ``axis``.
    p : float
        Coverage probability.

    Returns
    -------
    low, high : ndarray, shape (...)
        The (M-q)/2-th and ((M-q)/2 + q)-th order statistics (1-based; rounded as in 7.7.2).
    """
    y = np.moveaxis(np.asarray(samples, dtype=np.float64), axis, -1)
    if not presorted:
        y = np.sort(y, axis=-1)
    m = y.shape[-1]
    q = coverage_count(m, p)
    r = (m - q) // 2 if (m - q) % 2 == 0 else (m - q + 1) // 2  # 1-based index of the low end
    r = max(r, 1)
    return y[..., r - 1], y[..., r - 1 + q]


def shortest_interval(samples, p: float = 0.95, axis: int = -1, presorted: bool = False):
    """Shortest coverage interval (JCGM 101, 7.7.4).

    Returns
    -------
    low, high : ndarray, shape (...)
        y_(r*) and y_(r*+q), r* minimising y_(r+q) - y_(r) over r = 1..M-q.
    """
    y = np.moveaxis(np.asarray(samples, dtype=np.float64), axis, -1)
    if not presorted:
        y = np.sort(y, axis=-1)
    m = y.shape[-1]
    q = coverage_count(m, p)
    widths = y[..., q:] - y[..., : m - q]
    r = np.argmin(widths, axis=-1)[..., None]
    return np.take_along_axis(y, r, -1)[..., 0], np.take_along_axis(y, r + q, -1)[..., 0]


def numerical_tolerance(u, ndig: int = 2):
    """Numerical tolerance delta of a standard uncertainty (JCGM 101, 7.9.2).

    ``u`` is written as c x 10**l with c an ``ndig``-digit integer; delta = 10**l / 2.
    Zero gives zero.
    """
    u = np.abs(np.asarray(u, dtype=np.float64))
    with np.errstate(divide="ignore"):
        l_exp = np.floor(np.log10(np.where(u > 0, u, 1.0))) - (ndig - 1)
    delta = 0.5 * 10.0**l_exp
    return np.where(u > 0, delta, 0.0)


def gum_validation(y, expanded_u, low, high, delta):
    """Compare the GUM interval y +- U with a Monte Carlo interval [low, high] (JCGM 101, 8.2).

    Returns
    -------
    d_low, d_high : ndarray
        |y - U - low| and |y + U - high|.
    valid : ndarray of bool
        True where both are at most ``delta``.
    """
    y, expanded_u, low, high = (np.asarray(a, dtype=np.float64) for a in (y, expanded_u, low, high))
    d_low = np.abs(y - expanded_u - low)
    d_high = np.abs(y + expanded_u - high)
    return d_low, d_high, (d_low <= delta) & (d_high <= delta)


