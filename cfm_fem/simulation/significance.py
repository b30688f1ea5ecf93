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
"""

from __future__ import annotations

import numpy as np

__all__ = ["whitened", "per_unit", "excess_for"]


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


def excess_for(z_target: float, z_per_unit: float, prior_std: float) -> float:
    """The excess beyond the prior that gives a prior release the significance ``z_target``."""
    s_data = 1.0 / z_per_unit if z_per_unit > 0 else np.inf
    return float(z_target * np.hypot(prior_std, s_data))
