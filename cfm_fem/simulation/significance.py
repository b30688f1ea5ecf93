"""Joint significance of a concealed effect against its neighbours, from linearised signatures.

An effect of amplitude ``a`` along a direction of its parameters changes the noiseless recording
by ``a s`` (``s``: its signature, shape (n, 3)); the diagnosis must tell it from the calibrated
model (the registration, the bench errors, the probe's gains), from the other effects of the
catalogue (its neighbours), each a linear span of signatures, and from the reference's own error
where it reads the reference. Its joint significance is the part of ``s / w`` that no
combination of the others reproduces, z(a) = |a| || (I - P) (s / w) ||, with ``P`` the
least-squares projection on the columns ``v / w`` of every neighbour and nuisance signature and
``w`` the whitening std of each reading and component: w^2 = sigma^2 + R_p e_p^2, ``sigma`` the
reading's own std (probe noise, the axes' vibration and reading error through the field
gradient), ``e_p`` the reference's error at the reading's point, shared by its ``R_p`` readings,
so that the mean of a point's repetitions has the variance sigma^2 / R_p + e_p^2 (``e_p`` = 0
for a reference exact at the points, for 2-D harmonics and for tracker recordings;
:func:`shared_error_std`).

A prior release (a calibrated parameter beyond its prior) is significant by how far the data put
it beyond the prior: with ``s_data`` = 1 / ||(I - P) (s / w)|| the std with which the data
determine it, z = |excess| / sqrt(prior^2 + s_data^2).

A departure the references cannot describe (the body's 3-D field against its 2-D harmonics) is
judged against the nuisances within their priors: with the columns' amplitudes ``c`` of prior
stds ``p``, z^2 = min_c || s / w - A c ||^2 + || c / p ||^2 (:func:`per_unit_prior`).

The significance without the reference's error (w = sigma) is the noise-only one; it is never
below the one with it, since a larger std of every reading shrinks every weighted residual.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "whitened",
    "shared_error_std",
    "per_unit",
    "per_unit_prior",
    "excess_for",
    "release_sigma",
]


def whitened(vectors, sigma) -> np.ndarray:
    """Columns ``v / sigma`` flattened, shape (3 n, k), of ``k`` vectors of shape (n, 3)."""
    s = np.asarray(sigma, dtype=float).ravel()
    if not vectors:
        return np.zeros((len(s), 0))
    return np.column_stack([np.asarray(v, dtype=float).ravel() / s for v in vectors])


def shared_error_std(sigma, point, error) -> np.ndarray:
    """Whitening std of each reading with an error shared by every reading of its point.

    A reading of point ``p`` of own std ``sigma`` carries the point's error ``e_p``, the same on
    each of the point's ``R_p`` readings (the reference read between its nodes). Whitening
    each reading by sqrt(sigma^2 + R_p e_p^2) gives the mean of the point's readings the
    variance sigma^2 / R_p + e_p^2 of a signal the same on every repetition, which is what an
    analysis averaging the repetitions faces.

    Parameters
    ----------
    sigma : ndarray, shape (n, 3)
        Std of each reading (T for a Hall map).
    point : ndarray of int, shape (n,)
        The point each reading is taken at (index into ``error``).
    error : ndarray, shape (m, 3)
        The error shared by the readings of each point, in the units of ``sigma``.

    Returns
    -------
    ndarray, shape (n, 3)
        sqrt(sigma^2 + R_p e_p^2) of each reading and component; ``sigma`` itself when
        ``error`` is zero everywhere.
    """
    e = np.asarray(error, dtype=float)
    if not np.any(e):
        return sigma
    point = np.asarray(point, dtype=int)
    reps = np.bincount(point, minlength=len(e))[point]
    return np.sqrt(np.asarray(sigma, dtype=float) ** 2 + reps[:, None] * e[point] ** 2)


def per_unit(signal, others, sigma) -> tuple[float, float]:
    """Significance per unit amplitude of ``signal`` against the span of ``others``.

    Parameters
    ----------
    signal : ndarray, shape (n, 3)
        Change of the noiseless recording per unit amplitude.
    others : list of ndarray, shape (n, 3)
        Neighbour and nuisance signatures.
    sigma : ndarray, shape (n, 3)
        Whitening std of each reading, in the units of the signatures (the reading's own std,
        or :func:`shared_error_std` with the reference's error).

    Returns
    -------
    z_per_unit : float
        || (I - P) signal / sigma ||, per unit amplitude.
    kept : float
        The share of the signal's norm the projection leaves (0: absorbed, 1: orthogonal).
    """
    y = (np.asarray(signal, dtype=float) / sigma).ravel()
    a = whitened(others, sigma)
    r = y
    if a.shape[1]:
        scale = np.linalg.norm(a, axis=0)
        a = a[:, scale > 0] / scale[scale > 0]
        # projection through the eigenvectors of the (unit-diagonal) Gram matrix, the
        # directions the columns do not span (eigenvalue <= 1e-12 of the largest) left out
        lam, vec = np.linalg.eigh(a.T @ a)
        keep = lam > 1e-12 * lam.max()
        u = a @ (vec[:, keep] / np.sqrt(lam[keep]))
        r = y - u @ (u.T @ y)
    norm = float(np.linalg.norm(y))
    z = float(np.linalg.norm(r))
    return z, (z / norm if norm > 0 else 0.0)


def per_unit_prior(signal, others, sigma, prior_std) -> tuple[float, float]:
    """Significance per unit amplitude of ``signal`` against ``others`` of bounded size.

    The amplitude of each column has a Gaussian prior of mean 0 and std ``prior_std`` (its
    display units): least squares augmented with one row ``c_k / prior_k`` per column.

    Parameters
    ----------
    signal : ndarray, shape (n, 3)
        Change of the noiseless recording per unit amplitude.
    others : list of ndarray, shape (n, 3)
        Nuisance signatures, per display unit of their parameter.
    sigma : ndarray, shape (n, 3)
        Whitening std of each reading, in the units of the signatures.
    prior_std : sequence of float, length ``len(others)``
        Prior std of each amplitude (display units; ``inf``: free, as in :func:`per_unit`).

    Returns
    -------
    z_per_unit : float
        sqrt(min_c || signal / sigma - A c ||^2 + || c / prior ||^2).
    kept : float
        ``z_per_unit`` over || signal / sigma ||.
    """
    y = (np.asarray(signal, dtype=float) / sigma).ravel()
    prior = np.asarray(prior_std, dtype=float).ravel()
    a = whitened(others, sigma)
    if a.shape[1] != prior.size:
        raise ValueError(f"{a.shape[1]} signatures but {prior.size} prior stds")
    if np.any(prior <= 0):
        raise ValueError("prior stds must be positive")
    norm = float(np.linalg.norm(y))
    if not a.shape[1]:
        return norm, (1.0 if norm > 0 else 0.0)
    scale = np.linalg.norm(a, axis=0)
    use = scale > 0
    a, prior, scale = a[:, use] / scale[use], prior[use], scale[use]
    # amplitudes in units of the column norms: the prior row of column k is c_k / (p_k s_k)
    rows = np.diag(1.0 / (prior * scale))
    c = np.linalg.lstsq(np.vstack([a, rows]), np.r_[y, np.zeros(len(prior))], rcond=None)[0]
    z = float(np.sqrt(np.sum((y - a @ c) ** 2) + np.sum((rows @ c) ** 2)))
    return z, (z / norm if norm > 0 else 0.0)


def excess_for(z_target: float, z_per_unit: float, prior_std: float) -> float:
    """The excess beyond the prior that gives a prior release the significance ``z_target``.

    Parameters
    ----------
    z_target : float
        The significance wanted.
    z_per_unit : float
        Significance per display unit of the parameter (:func:`per_unit`), 1 / s_data.
    prior_std : float
        The prior's std (display units).

    Returns
    -------
    float
        z_target sqrt(prior^2 + s_data^2), display units.
    """
    s_data = 1.0 / z_per_unit if z_per_unit > 0 else np.inf
    return float(z_target * np.hypot(prior_std, s_data))


def release_sigma(excess: float, z_per_unit: float, prior_std: float) -> float:
    """Significance of a prior release of departure ``excess`` (the inverse of
    :func:`excess_for`): |excess| / sqrt(prior^2 + s_data^2), s_data = 1 / ``z_per_unit``."""
    s_data = 1.0 / z_per_unit if z_per_unit > 0 else np.inf
    return float(abs(excess) / np.hypot(prior_std, s_data))
