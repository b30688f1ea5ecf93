"""Joint significance of a concealed effect against its neighbours, from linearised signatures.

An effect of amplitude ``a`` along a direction of its parameters changes the noiseless
recording by ``a s`` (``s``: its signature, shape (n, 3)). The diagnosis must tell it from the
calibrated model (the registration, the bench errors, the probe's gains) and from the other
effects of the catalogue (its neighbours), each a linear span of signatures. Its joint
significance is the part of ``s / sigma`` that no combination of the others reproduces:

    z(a) = |a| || (I - P) (s / sigma) ||,

``P`` the least-squares projection on the columns ``v / sigma`` of every neighbour and nuisance
signature, ``sigma`` the std of each reading. A prior release (a calibrated parameter beyond its
prior) is significant by how far the data put it beyond the prior: with ``s_data`` = 1 / ||(I -
P) (s / sigma)|| the std with which the data determine it, z = |excess| / sqrt(prior^2 +
s_data^2).

A departure the references cannot describe (the body's 3-D field against its 2-D harmonics) is
judged against the nuisances within their priors: with the columns' amplitudes ``c`` of prior
stds ``p``, z^2 = min_c || s / sigma - A c ||^2 + || c / p ||^2 (:func:`per_unit_prior`).
"""

from __future__ import annotations

import numpy as np

__all__ = ["whitened", "per_unit", "per_unit_prior", "excess_for"]


def whitened(vectors, sigma) -> np.ndarray:
    """Columns ``v / sigma`` flattened, shape (3 n, k)."""
    s = np.asarray(sigma, dtype=float).ravel()
    if not vectors:
        return np.zeros((len(s), 0))
    return np.column_stack([np.asarray(v, dtype=float).ravel() / s for v in vectors])


def per_unit(signal, others, sigma) -> tuple[float, float]:
    """Significance per unit amplitude of ``signal`` against the span of ``others``.

    Parameters
    ----------
    signal : ndarray, shape (n, 3)
        Change of the noiseless recording per unit amplitude.
    others : list of ndarray, shape (n, 3)
        Neighbour and nuisance signatures.
    sigma : ndarray, shape (n, 3)
        Std of each reading, in the units of the signatures.

    Returns
    -------
    z_per_unit : float
        || (I - P) signal / sigma ||.
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
        Std of each reading, in the units of the signatures.
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
    """The excess beyond the prior that gives a prior release the significance ``z_target``."""
    s_data = 1.0 / z_per_unit if z_per_unit > 0 else np.inf
    return float(z_target * np.hypot(prior_std, s_data))
