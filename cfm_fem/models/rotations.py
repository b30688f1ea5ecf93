"""Rotation matrices and homogeneous transformation matrices (paper eq. 2 and 4)."""

from __future__ import annotations

import numpy as np


def rotation_zyx(phi, theta, psi) -> np.ndarray:
    """Rotation matrix of paper eq. 4: R = Rz(psi) Ry(theta) Rx(phi).

    Parameters
    ----------
    phi, theta, psi : float or ndarray, shape (...), rad
        Rotations about x, y and z.

    Returns
    -------
    ndarray, shape (..., 3, 3)
    """
    phi, theta, psi = np.broadcast_arrays(
        *(np.asarray(a, dtype=np.float64) for a in (phi, theta, psi))
    )
    cf, sf = np.cos(phi), np.sin(phi)
    ct, st = np.cos(theta), np.sin(theta)
    cp, sp = np.cos(psi), np.sin(psi)
    r = np.empty(phi.shape + (3, 3))
    r[..., 0, 0] = cp * ct
    r[..., 0, 1] = cp * sf * st - cf * sp
    r[..., 0, 2] = sf * sp + cf * cp * st
    r[..., 1, 0] = ct * sp
    r[..., 1, 1] = cf * cp + sf * sp * st
    r[..., 1, 2] = cf * sp * st - cp * sf
    r[..., 2, 0] = -st
    r[..., 2, 1] = ct * sf
    r[..., 2, 2] = cf * ct
    return r


def htm(rotation, translation) -> np.ndarray:
    """Homogeneous transformation matrix of eq. 2.

    Parameters
    ----------
    rotation : ndarray, shape (..., 3, 3)
    translation : ndarray, shape (..., 3), mm

    Returns
    -------
    ndarray, shape (..., 4, 4)
    """
    rotation = np.asarray(rotation, dtype=np.float64)
    translation = np.asarray(translation, dtype=np.float64)
    shape = np.broadcast_shapes(rotation.shape[:-2], translation.shape[:-1])
    m = np.zeros(shape + (4, 4))
    m[..., :3, :3] = rotation
    m[..., :3, 3] = translation
    m[..., 3, 3] = 1.0
    return m
